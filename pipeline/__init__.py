"""imupipe pipeline: order, config, sinks and the command line."""
