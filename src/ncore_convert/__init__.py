"""ncore-convert: public autonomous-driving datasets to NVIDIA NCore V4."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ncore-convert")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"
