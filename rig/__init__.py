"""facecast.rig: the numeric engine (example sets, fitting, evaluation, mesh and rig files).

Pure numpy/scipy plus mesh-format libraries; it imports nothing from protocol, server
or client, and does no networking.
"""

from .errors import ExampleSetError, FitError, InputError, RigError, RigFileError
from .examples import ExampleSet
from .fit import FitReport, IdentifiabilityWarning, fit
from .kernels import KERNELS
from .pose import align_points, similarity_transform
from .regions import Region, fit_regions, split_masks
from .rig import Rig
from .rigfile import load_rig, rig_from_bytes

__all__ = [
    "KERNELS",
    "ExampleSet",
    "ExampleSetError",
    "FitError",
    "FitReport",
    "IdentifiabilityWarning",
    "InputError",
    "Region",
    "Rig",
    "RigError",
    "RigFileError",
    "align_points",
    "fit",
    "fit_regions",
    "load_rig",
    "rig_from_bytes",
    "similarity_transform",
    "split_masks",
]
