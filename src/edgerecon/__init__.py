"""edgerecon: latency-optimised multi-view 3D reconstruction of dynamic scenes on edge devices."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("edgerecon")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
