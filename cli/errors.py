"""The exceptions of the ``facecast`` command and its tools; importing it loads nothing heavy.

Commands import `CommandError` from here at module level (``main`` catches it), so no
command reaches back into ``facecast.cli.main``. The tree (the root is
``facecast.errors.FacecastError``)::

    CommandError                          "command_failed"   printed as ``facecast CMD:
                                                             error: ...``, exit status 2
    RenderError(ValueError)               "bad_render_input" bad input to the renderer;
                                                             an instance's code may be finer
    TrackerUnavailable(RuntimeError)      "tracker_unavailable"  mediapipe/OpenCV missing
    TrackerPacketError(ValueError)        "bad_tracker_packet"   facecast.cli.bridges.tracker
    ├── LiveLinkPacketError               "bad_livelink_packet"  ...bridges.livelink
    └── FacialMocapPacketError            "bad_ifacialmocap_packet"  ...bridges.ifacialmocap
"""

from __future__ import annotations

from facecast.errors import FacecastError

__all__ = ["CommandError", "RenderError", "TrackerUnavailable"]


class CommandError(FacecastError):
    """A user-facing failure of a command: printed as ``facecast: error: ...``, exit 2."""

    code: str = "command_failed"


class RenderError(FacecastError, ValueError):
    """Bad input to the renderer; ``code`` is a stable machine-readable string."""

    code: str = "bad_render_input"

    def __init__(self, message: str, *, code: str = "bad_render_input") -> None:
        super().__init__(message)
        self.code = code


class TrackerUnavailable(FacecastError, RuntimeError):
    """mediapipe or OpenCV is not installed (the ``facecast[perform]`` extra)."""

    code: str = "tracker_unavailable"
