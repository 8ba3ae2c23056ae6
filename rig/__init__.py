"""facecast.rig: the numeric engine (example sets, fitting, evaluation, mesh and rig files).

Pure numpy/scipy plus mesh-format libraries; it imports nothing from protocol, server
or client, and does no networking.
"""

from .characters.loaders import load_example_set
from .errors import ExampleSetError, FitError, InputError, RigError, RigFileError
from .examples import ExampleSet
from .fit import FitReport, IdentifiabilityWarning, fit, refit_noise
from .io.gltf import export_glb, read_glb_morph_targets
from .io.meshio import read_obj, read_obj_vertices, read_points, write_obj
from .noise import estimate_noise
from .pose import align_points, similarity_transform
from .radial import KERNELS
from .regions import Region, fit_regions, split_masks
from .rig import Rig
from .rigfile import load_rig, rig_from_bytes
from .smoothing import SMOOTHING_CHOICES, SmoothedTake, smooth_take
from .sources.animation import SourceAnimation, write_clone_output
from .sources.loading import load_source_animation

__all__ = [
    "KERNELS",
    "SMOOTHING_CHOICES",
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
    "SmoothedTake",
    "SourceAnimation",
    "align_points",
    "estimate_noise",
    "export_glb",
    "fit",
    "fit_regions",
    "load_example_set",
    "load_rig",
    "load_source_animation",
    "read_glb_morph_targets",
    "read_obj",
    "read_obj_vertices",
    "read_points",
    "refit_noise",
    "rig_from_bytes",
    "similarity_transform",
    "smooth_take",
    "split_masks",
    "write_clone_output",
    "write_obj",
]
