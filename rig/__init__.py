"""facecast.rig: the numeric engine (example sets, fitting, evaluation, mesh and rig files).

Pure numpy/scipy plus mesh-format libraries; it imports nothing from protocol, server
or client, and does no networking.
"""

from .errors import ExampleSetError, FitError, InputError, RigError, RigFileError
from .examples import ExampleSet

__all__ = [
    "ExampleSet",
    "ExampleSetError",
    "FitError",
    "InputError",
    "RigError",
    "RigFileError",
]
