"""The rig file's layout and writing: records, meta, content checksum, the atomic save.

A rig file is one ``.npz`` (no pickles) with a format version and a content checksum.
This module reads nothing and imports no engine class: a ``Rig`` is read by attribute,
through the ``SavedRig`` protocol below, so ``Rig.save``, ``Rig.to_bytes`` and
``Rig.checksum`` use it without an import cycle, type-only imports included; reading a file
back into a ``Rig`` is ``facecast.rig.rigfile``.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path
from typing import Any, BinaryIO, Protocol

import numpy as np

__all__ = [
    "DEFAULT_MAX_BYTES",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "SavedModel",
    "SavedRig",
    "content_checksum",
    "rig_to_bytes",
    "save_rig",
    "write_rig",
]

FORMAT_NAME = "facecast-rig"
FORMAT_VERSION = 1
# A rig file larger than this once unpacked is refused before any array is read.
DEFAULT_MAX_BYTES = 4 << 30

REQUIRED_RECORDS = (
    "source_neutral",
    "mean",
    "features",
    "params",
    "linear_coeffs",
    "radial_coeffs",
    "alpha",
    "blend_basis",
    "target_faces",
)
MODEL_RECORDS = (
    "source_neutral",
    "mean",
    "features",
    "params",
    "linear_coeffs",
    "radial_coeffs",
    "alpha",
    "input_matrix",
    "input_offset",
)
OPTIONAL_RECORDS = (
    "feature_indices",
    "stable_points",
    "preview_vertices",
    "preview_faces",
    "calibration",
    "input_matrix",
    "input_offset",
)


class SavedModel(Protocol):
    """What a rig file holds of one weight model (``facecast.rig.weight_model.WeightModel`` is one)."""

    @property
    def kernel(self) -> str: ...
    @property
    def clamp(self) -> str | None: ...
    @property
    def ridge(self) -> float: ...
    @property
    def sparsity_penalty(self) -> float: ...
    @property
    def source_neutral(self) -> np.ndarray: ...
    @property
    def mean(self) -> np.ndarray: ...
    @property
    def features(self) -> np.ndarray: ...
    @property
    def params(self) -> np.ndarray: ...
    @property
    def linear_coeffs(self) -> np.ndarray: ...
    @property
    def radial_coeffs(self) -> np.ndarray: ...
    @property
    def alpha(self) -> np.ndarray: ...
    @property
    def input_matrix(self) -> np.ndarray | None: ...
    @property
    def input_offset(self) -> np.ndarray | None: ...


class SavedRig(Protocol):
    """What a rig file holds of a rig (``facecast.rig.Rig`` is one), read by attribute."""

    @property
    def names(self) -> tuple[str, ...]: ...
    @property
    def model(self) -> SavedModel: ...
    @property
    def models(self) -> tuple[SavedModel, ...]: ...
    @property
    def blend_basis(self) -> np.ndarray: ...
    @property
    def target_faces(self) -> np.ndarray: ...
    @property
    def feature_indices(self) -> np.ndarray | None: ...
    @property
    def stable_points(self) -> np.ndarray | None: ...
    @property
    def source_preview(self) -> tuple[np.ndarray, np.ndarray] | None: ...
    @property
    def calibration(self) -> np.ndarray | None: ...
    @property
    def align_scale(self) -> bool: ...
    @property
    def fit_report(self) -> dict[str, Any]: ...
    @property
    def regions(self) -> tuple[tuple[str, np.ndarray], ...] | None: ...


def _model_arrays(model: SavedModel, prefix: str) -> dict[str, np.ndarray]:
    values = {key: getattr(model, key) for key in MODEL_RECORDS}
    return {prefix + k: v for k, v in values.items() if v is not None}


def _arrays(rig: SavedRig) -> dict[str, np.ndarray]:
    model = rig.model
    arrays = {
        "source_neutral": model.source_neutral,
        "mean": model.mean,
        "features": model.features,
        "params": model.params,
        "linear_coeffs": model.linear_coeffs,
        "radial_coeffs": model.radial_coeffs,
        "alpha": model.alpha,
        "blend_basis": rig.blend_basis,
        "target_faces": rig.target_faces,
    }
    optional = {
        "feature_indices": rig.feature_indices,
        "stable_points": rig.stable_points,
        "preview_vertices": None if rig.source_preview is None else rig.source_preview[0],
        "preview_faces": None if rig.source_preview is None else rig.source_preview[1],
        "calibration": rig.calibration,
        "input_matrix": model.input_matrix,
        "input_offset": model.input_offset,
    }
    arrays.update({k: v for k, v in optional.items() if v is not None})
    # Region rigs: the models after the first, prefixed r1., r2., ...
    for r, extra in enumerate(rig.models[1:], start=1):
        arrays.update(_model_arrays(extra, f"r{r}."))
    return {k: np.ascontiguousarray(v) for k, v in arrays.items()}


def _meta(rig: SavedRig) -> dict[str, Any]:
    meta = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "names": list(rig.names),
        "kernel": rig.model.kernel,
        "clamp": rig.model.clamp,
        "ridge": [m.ridge for m in rig.models],
        "align_scale": rig.align_scale,
        "fit_report": rig.fit_report or {},
        "regions": None
        if rig.regions is None
        else [{"name": name, "columns": columns.tolist()} for name, columns in rig.regions],
    }
    penalties = [m.sparsity_penalty for m in rig.models]
    if any(penalties):
        # Written only when set; files without it (all that older facecast wrote) read as
        # 0, the plain projection they were made with, so the format version stays 1.
        meta["sparsity_penalty"] = penalties
    return meta


def checksum_of(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(meta, sort_keys=True, allow_nan=True).encode())
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"|{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.data)  # its bytes as they lie (each is C-contiguous): no copy
    return h.hexdigest()


def content_checksum(rig: SavedRig) -> str:
    return checksum_of(_meta(rig), _arrays(rig))


def write_rig(rig: SavedRig, file: BinaryIO) -> None:
    """Write the rig's file to an open binary file (seekable), array by array: numpy puts
    each into the zip in chunks, so no copy of the rig is made in memory (a 1 M-vertex
    rig's basis is 60 MB; ``rig_to_bytes`` made it twice more)."""
    meta = _meta(rig)
    arrays = _arrays(rig)
    meta_with_sum = dict(meta, checksum=checksum_of(meta, arrays))
    # allow_pickle=False: no record is an object array (and given, the flag cannot be taken
    # for one of ``arrays`` by mypy, as numpy's stub types **kwds).
    np.savez(
        file,
        allow_pickle=False,
        meta=np.frombuffer(json.dumps(meta_with_sum).encode(), dtype=np.uint8),
        **arrays,
    )


def rig_to_bytes(rig: SavedRig) -> bytes:
    """The rig's file as bytes (``write_rig`` into memory)."""
    buffer = io.BytesIO()
    write_rig(rig, buffer)
    return buffer.getvalue()


def save_rig(rig: SavedRig, path: str | os.PathLike[str]) -> None:
    """Write atomically: a temporary file beside ``path``, fsynced, then renamed over it."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write_rig(rig, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
