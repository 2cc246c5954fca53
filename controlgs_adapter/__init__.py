"""controlgs-adapter: make neural-Gaussian renderers aware of the XR display/optics path (ControlGS)."""

from ._version import __version__
from .hookspecs import hookimpl
from .state import Camera, RuntimeState

__all__ = ["__version__", "hookimpl", "Camera", "RuntimeState"]
