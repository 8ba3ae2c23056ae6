"""Exceptions of the numeric engine; every one carries a stable code.

The tree (the root is ``facecast.errors.FacecastError``)::

    RigError(code, message)            any failure of the engine
    ├── ExampleSetError(RigError, ValueError)   bad example data (files, shapes, NaN, pairing)
    ├── FitError(RigError, ValueError)          examples that cannot be fitted (collapsed, singular)
    ├── RigFileError(RigError, ValueError)      unreadable, truncated, tampered or unknown-version rig file
    ├── InputError(RigError, ValueError)        bad runtime input to a fitted rig (shape, NaN/Inf)
    ├── MeshError(RigError, ValueError)         a mesh deformation transfer cannot use (not a
    │                                           manifold triangle/quad mesh, degenerate triangles)
    ├── MarkerError(RigError, ValueError)       correspondence markers out of range, repeated or too few
    └── CorrespondenceError(RigError, ValueError)  the source cannot be fitted onto the target
                                                (diverged, far apart, no triangle pairs)
"""

from __future__ import annotations

from facecast.errors import FacecastError


class RigError(FacecastError):
    """Base of the engine's errors; ``code`` is a stable machine-readable string."""

    code: str = "rig_error"

    def __init__(self, message: str, *, code: str | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code

    @property
    def message(self) -> str:
        return str(self.args[0]) if self.args else ""


class ExampleSetError(RigError, ValueError):
    code = "bad_example_set"


class FitError(RigError, ValueError):
    code = "fit_failed"


class RigFileError(RigError, ValueError):
    code = "bad_rig_file"


class InputError(RigError, ValueError):
    code = "bad_input"


class MeshError(RigError, ValueError):
    code = "bad_target_mesh"


class MarkerError(RigError, ValueError):
    code = "bad_markers"


class CorrespondenceError(RigError, ValueError):
    code = "correspondence_failed"
