"""The rig file read back: a ``Rig`` from bytes or a path, every record validated.

A file that is truncated, tampered with or of an unknown version gives ``RigFileError``,
never a crash or a silently wrong rig. The layout and the writer are
``facecast.rig.io.rigformat``; its writing names are re-exported here.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import RigFileError
from .io.rigformat import (
    DEFAULT_MAX_BYTES,
    FORMAT_NAME,
    FORMAT_VERSION,
    MODEL_RECORDS,
    OPTIONAL_RECORDS,
    REQUIRED_RECORDS,
    checksum_of,
    rig_to_bytes,
    save_rig,
)
from .npy_reads import NPY_READS
from .radial import KERNELS
from .rig import Rig, WeightModel

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "load_rig",
    "rig_from_bytes",
    "rig_to_bytes",
    "save_rig",
]


def load_rig(path: str | os.PathLike[str], *, max_bytes: int = DEFAULT_MAX_BYTES) -> Rig:
    """Read a rig file written by ``Rig.save``."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RigFileError(f"{path}: no such rig file", code="not_found") from None
    except IsADirectoryError:
        raise RigFileError(f"{path}: is a directory, not a rig file") from None
    return rig_from_bytes(data, source=str(path), max_bytes=max_bytes)


def rig_from_bytes(data: bytes, *, source: str = "rig", max_bytes: int = DEFAULT_MAX_BYTES) -> Rig:
    """Parse rig file bytes, verifying format, version, sizes and checksum.

    A character file (glTF, GLB, VRM) given where a rig is expected is told how to become
    one (``character_not_rig``): it is uploaded as a character or fitted first.
    """
    if data[:4] == b"glTF" or (data.lstrip()[:1] == b"{" and b'"asset"' in data[:4096]):
        raise RigFileError(
            f"{source}: is a character file (glTF/GLB/VRM), not a fitted rig: upload it as a "
            "character (`facecast rigs put URL ID FILE`, PUT /v1/characters/{id}) or fit it "
            "first (`facecast fit FILE -o RIG`)",
            code="character_not_rig",
        )
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            total = sum(info.file_size for info in archive.infolist())
            if total > max_bytes:
                raise RigFileError(
                    f"{source}: unpacks to {total} bytes, over the limit of {max_bytes}",
                    code="rig_too_large",
                )
        with NPY_READS, np.load(io.BytesIO(data), allow_pickle=False) as npz:
            contents = {name: npz[name] for name in npz.files}
    except RigFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise RigFileError(
            f"{source}: not a facecast rig file, or truncated ({type(exc).__name__}: {exc})"
        ) from None
    if "meta" not in contents:
        raise RigFileError(f"{source}: not a facecast rig file (no meta record)")
    try:
        meta = json.loads(contents.pop("meta").tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError, ValueError) as exc:
        raise RigFileError(f"{source}: unreadable meta record ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise RigFileError(f"{source}: not a facecast rig file")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise RigFileError(
            f"{source}: rig file format version {version!r} is not supported (this facecast "
            f"reads version {FORMAT_VERSION}); refit the rig or upgrade facecast",
            code="unsupported_version",
        )
    missing = [k for k in REQUIRED_RECORDS if k not in contents]
    if missing:
        raise RigFileError(f"{source}: rig file lacks {', '.join(missing)}")
    unknown = {
        k
        for k in set(contents) - set(REQUIRED_RECORDS) - set(OPTIONAL_RECORDS)
        if not k.startswith("r")
    }
    unknown |= {
        k for k in contents if k[:1] == "r" and "." in k and k.split(".", 1)[1] not in MODEL_RECORDS
    }
    if unknown:
        raise RigFileError(f"{source}: rig file has unknown records {sorted(unknown)}")
    stored = meta.pop("checksum", None)
    if stored != checksum_of(meta, contents):
        raise RigFileError(
            f"{source}: checksum mismatch: the rig file was modified or corrupted",
            code="checksum_mismatch",
        )
    _check_finite(contents, source)
    try:
        return _build(meta, contents)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise RigFileError(f"{source}: inconsistent rig file ({exc})") from None


def _check_finite(arrays: dict[str, np.ndarray], source: str) -> None:
    """Refuse NaN or Inf in any float record: they would stream as NaN vertices or weights.

    The checksum proves only that the file is as written, not that its writer was sane
    (anyone can write a file with a valid checksum), so the values are checked too.
    """
    for name in sorted(arrays):
        values = arrays[name]
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            raise RigFileError(
                f"{source}: record {name!r} holds NaN or Inf; a rig file must be finite",
                code="rig_not_finite",
            )


def _build(meta: dict[str, Any], a: dict[str, np.ndarray]) -> Rig:
    names = tuple(str(n) for n in meta["names"])
    m = len(names)
    basis = a["blend_basis"]
    if basis.ndim != 2 or basis.shape[0] != m or basis.shape[1] % 3 or basis.dtype != np.float32:
        raise ValueError(f"blend_basis has shape {basis.shape} {basis.dtype}")
    v = basis.shape[1] // 3
    faces = a["target_faces"]
    if (
        faces.ndim != 2
        or faces.shape[1] != 3
        or (faces.size and (faces.min() < 0 or faces.max() >= v))
    ):
        raise ValueError("target_faces out of range")
    models = [_build_model(meta, a, "", 0)]
    regions: tuple[tuple[str, np.ndarray], ...] | None = None
    if meta.get("regions"):
        named: list[tuple[str, np.ndarray]] = []
        for r, region in enumerate(meta["regions"]):
            columns = np.asarray(region["columns"], dtype=np.int64)
            if r:
                models.append(_build_model(meta, a, f"r{r}.", r))
            if columns.ndim != 1 or (columns.size and (columns.min() < 1 or columns.max() >= m)):
                raise ValueError(f"region {region['name']!r} has columns out of range")
            if columns.size != models[r].params.shape[0] - 1:
                raise ValueError(f"region {region['name']!r} has {columns.size} columns")
            named.append((str(region["name"]), columns))
        regions = tuple(named)
    elif models[0].params.shape[0] != m:
        raise ValueError(f"{models[0].params.shape[0]} examples in the model for {m} names")
    preview = None
    if "preview_vertices" in a and "preview_faces" in a:
        preview = (a["preview_vertices"], a["preview_faces"])
    return Rig(
        names=names,
        model=tuple(models),
        target_neutral=np.ascontiguousarray(basis[0].reshape(v, 3)),
        blend_basis=np.ascontiguousarray(basis),
        target_faces=faces.astype(np.int32),
        feature_indices=a.get("feature_indices"),
        source_preview=preview,
        stable_points=a.get("stable_points"),
        align_scale=bool(meta.get("align_scale", False)),
        report=meta.get("fit_report", {}),
        calibration=a.get("calibration"),
        regions=regions,
    )


def _build_model(
    meta: dict[str, Any], a: dict[str, np.ndarray], prefix: str, index: int
) -> WeightModel:
    k = a[prefix + "source_neutral"].shape[0]
    n = a[prefix + "features"].shape[0]
    m = a[prefix + "params"].shape[0]
    shapes = {
        "source_neutral": (k, 3),
        "mean": (3 * k,),
        "features": (n, 3 * k),
        "params": (m, n),
        "linear_coeffs": (n + 1, m),
        "radial_coeffs": (m, m),
        "alpha": (m,),
    }
    for key, shape in shapes.items():
        if a[prefix + key].shape != shape:
            raise ValueError(f"{prefix}{key} has shape {a[prefix + key].shape}, expected {shape}")
    if not (a[prefix + "alpha"] > 0).all():
        raise ValueError(f"{prefix}alpha must be > 0")
    ridge = float(meta.get("ridge", [0.0] * (index + 1))[index])
    if not np.isfinite(ridge) or ridge < 0:
        raise ValueError(f"ridge must be a finite number >= 0, got {ridge}")
    clamp = meta.get("clamp")
    if clamp not in (None, "nonneg", "unit"):
        raise ValueError(f"unknown clamp mode {clamp!r}")
    if str(meta["kernel"]) not in KERNELS:
        raise ValueError(f"unknown kernel {meta['kernel']!r}")
    return WeightModel(
        kernel=str(meta["kernel"]),
        source_neutral=a[prefix + "source_neutral"],
        mean=a[prefix + "mean"],
        features=a[prefix + "features"],
        params=a[prefix + "params"],
        linear_coeffs=a[prefix + "linear_coeffs"],
        radial_coeffs=a[prefix + "radial_coeffs"],
        alpha=a[prefix + "alpha"],
        clamp=clamp,
        ridge=ridge,
        sparsity_penalty=_penalty(meta, index),
        input_matrix=a.get(prefix + "input_matrix"),
        input_offset=a.get(prefix + "input_offset"),
    )


def _penalty(meta: dict[str, Any], index: int) -> float:
    penalty = float(meta.get("sparsity_penalty", [0.0] * (index + 1))[index])
    if not np.isfinite(penalty) or penalty < 0:
        raise ValueError(f"sparsity_penalty must be a finite number >= 0, got {penalty}")
    return penalty
