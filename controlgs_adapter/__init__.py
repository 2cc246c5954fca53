"""controlgs-adapter: make neural-Gaussian renderers aware of the XR display/optics path (ControlGS)."""

from ._version import __version__
from .hookspecs import hookimpl
from .state import Camera, RuntimeState
from .controlgs import ControlGS
from .schedules import DisplaySchedule, FoveationSchedule, LensSchedule, ResampleSchedule, StrengthSchedule

__all__ = ["__version__", "hookimpl", "Camera", "RuntimeState"]
__all__ += ["ControlGS", "StrengthSchedule", "LensSchedule", "ResampleSchedule", "DisplaySchedule", "FoveationSchedule"]
