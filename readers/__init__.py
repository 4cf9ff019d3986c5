"""imupipe readers: log formats into the common table."""
