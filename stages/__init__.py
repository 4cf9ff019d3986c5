"""imupipe stages: the calibration math."""
