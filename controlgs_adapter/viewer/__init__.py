"""``controlgs view``: an interactive comparison in the browser of what the headset shows for the
backbone without and with supersampling and for ControlGS (and a run's ablations) at any run-time
state. :class:`ViewerSession` renders, :func:`make_server` serves the page on the loopback
interface; ``docs/how-to/viewer.md`` describes the page."""

from .server import STATIC_FILES, ViewerServer, make_server
from .session import OPTICS_MODES, STAGES, Superseded, ViewerSession, ViewState, parse_state

__all__ = ["ViewerSession", "ViewState", "parse_state", "Superseded", "STAGES", "OPTICS_MODES", "ViewerServer",
           "make_server", "STATIC_FILES"]
