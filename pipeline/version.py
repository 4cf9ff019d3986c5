"""The installed imupipe version."""

from importlib.metadata import PackageNotFoundError, version

try:
    VERSION = version("imupipe")
except PackageNotFoundError:  # running from a source tree that is not installed
    VERSION = "0+unknown"
