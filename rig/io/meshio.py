"""Reading and writing Wavefront OBJ meshes and K x 3 point files (.npy, .csv).

Keeps the file's vertex order exactly (feature-point indices refer to it) and reports
every bad file as an ``ExampleSetError`` naming it; it knows nothing of example sets.
"""

from __future__ import annotations

import io
import os
import re
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import ExampleSetError
from ..npy_reads import NPY_READS

__all__ = [
    "format_faces",
    "format_obj",
    "points_to_csv",
    "read_obj",
    "read_obj_vertices",
    "read_points",
    "write_obj",
]

# trimesh's OBJ loader (process=False, maintain_order=True) drops vertices that no face
# references once the file has `vt` lines, which silently shifts feature-point indices;
# this small parser keeps every `v` line, in order, and ignores vt/vn entirely.


def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ExampleSetError(f"{path}: file not found", code="missing_file") from None
    except IsADirectoryError:
        raise ExampleSetError(
            f"{path}: is a folder, expected a file", code="missing_file"
        ) from None
    except OSError as exc:
        raise ExampleSetError(
            f"{path}: cannot read ({exc.strerror})", code="missing_file"
        ) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        # OBJ exporters write 8-bit names in comments and groups; numbers are ASCII.
        return data.decode("latin-1")


def read_obj(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read vertices and faces of a Wavefront OBJ file, in the file's vertex order.

    Polygons are fan-triangulated ((a, b, c, d) -> (a, b, c), (a, c, d)); texture and
    normal indices (``f 1/2/3``) are ignored, as are vt, vn, groups and materials.
    Negative (relative) indices are resolved.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    vertices : (V, 3) float64
    faces : (F, 3) int64
        0-based; (0, 3) for a point cloud.

    Raises
    ------
    ExampleSetError
        Missing file, a line that does not parse, a face index out of range, NaN/Inf
        coordinates (with the line number), or no vertices at all.
    """
    path = Path(path)
    text = _read_text(path)
    fast = _parse_obj_fast(text, with_faces=True)
    if fast is not None:
        return fast
    return _parse_obj_checked(path, text)


def read_obj_vertices(path: str | os.PathLike[str]) -> np.ndarray:
    """Only the (V, 3) float64 vertices of an OBJ, skipping the faces when it can.

    For animation frames and example meshes whose topology comes from elsewhere: about
    twice as fast as ``read_obj``. Errors as ``read_obj``.
    """
    path = Path(path)
    text = _read_text(path)
    fast = _parse_obj_fast(text, with_faces=False)
    if fast is not None:
        return fast[0]
    return _parse_obj_checked(path, text)[0]


_INDENTED_OR_TABBED = re.compile(r"^[ \t]+[vf][ \t]|^[vf]\t", re.MULTILINE)
_CORNER_TAIL = re.compile(r"/\S*")


def _parse_obj_fast(text: str, *, with_faces: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """Vectorised parse of a well-formed OBJ; None hands anything unusual to the checked path.

    The checked path takes twice as long on a 26k-vertex head, and it is the one that
    finds the line number of an error, so this one only has to recognise trouble.
    """
    if _INDENTED_OR_TABBED.search(text):
        return None
    first_face = 0 if text.startswith("f ") else text.find("\nf ")
    if first_face >= 0 and text.rfind("\nv ") > first_face:
        return None  # vertices after faces: let the checked path resolve indices in order
    lines = text.splitlines()
    vertex_text = [line[2:] for line in lines if line.startswith("v ")]
    face_text = [line[2:] for line in lines if line.startswith("f ")] if with_faces else []
    if not vertex_text:
        return None
    try:
        flat = np.array(" ".join(vertex_text).split(), dtype=np.float64)
        if flat.size != 3 * len(vertex_text) or not np.isfinite(flat).all():
            return None
        vertices = flat.reshape(-1, 3)
        if not face_text:
            return vertices, np.zeros((0, 3), dtype=np.int64)
        corners = _CORNER_TAIL.sub("", "\n".join(face_text)).splitlines()
        sizes = np.fromiter((len(c.split()) for c in corners), dtype=np.int64, count=len(corners))
        ids = np.array(" ".join(corners).split(), dtype=np.int64) - 1
    except ValueError:
        return None
    if sizes.min() < 3 or ids.size != sizes.sum() or ids.min() < 0 or ids.max() >= len(vertices):
        return None
    # Fan triangulation (a, b, c, d) -> (a, b, c), (a, c, d) of all polygons at once.
    per_polygon = sizes - 2
    starts = np.cumsum(sizes) - sizes
    polygon = np.repeat(np.arange(sizes.size), per_polygon)
    k = np.arange(per_polygon.sum()) - np.repeat(np.cumsum(per_polygon) - per_polygon, per_polygon)
    first = starts[polygon]
    faces = np.stack([ids[first], ids[first + k + 1], ids[first + k + 2]], axis=1)
    return vertices, faces


def _parse_obj_checked(path: Path, text: str) -> tuple[np.ndarray, np.ndarray]:
    """Line-by-line parse that names the line of the first problem."""
    vertex_rows: list[list[str]] = []
    vertex_lines: list[int] = []
    faces: list[tuple[int, int, int]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line or line[0] not in "vf \t":
            continue
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise ExampleSetError(
                    f"{path}, line {number}: vertex needs 3 coordinates", code="bad_mesh"
                )
            vertex_rows.append(parts[1:4])
            vertex_lines.append(number)
        elif key == "f":
            corners = parts[1:]
            if len(corners) < 3:
                raise ExampleSetError(
                    f"{path}, line {number}: face needs at least 3 vertices", code="bad_mesh"
                )
            try:
                ids = [int(c.split("/", 1)[0]) for c in corners]
            except ValueError:
                raise ExampleSetError(
                    f"{path}, line {number}: cannot parse face {line.strip()!r}", code="bad_mesh"
                ) from None
            count = len(vertex_rows)
            resolved = []
            for i in ids:
                j = i - 1 if i > 0 else count + i
                if i == 0 or not 0 <= j < count:
                    raise ExampleSetError(
                        f"{path}, line {number}: face index {i} out of range "
                        f"({count} vertices defined so far)",
                        code="bad_mesh",
                    )
                resolved.append(j)
            first = resolved[0]
            faces.extend((first, resolved[k], resolved[k + 1]) for k in range(1, len(resolved) - 1))
    if not vertex_rows:
        raise ExampleSetError(f"{path}: no vertices (not an OBJ mesh?)", code="bad_mesh")
    try:
        vertices = np.array(vertex_rows, dtype=np.float64)
    except ValueError:
        for row, number in zip(vertex_rows, vertex_lines, strict=True):
            try:
                [float(x) for x in row]
            except ValueError:
                raise ExampleSetError(
                    f"{path}, line {number}: cannot parse vertex {' '.join(row)!r}",
                    code="bad_mesh",
                ) from None
        raise
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        bad_line = vertex_lines[int(np.flatnonzero(~finite)[0])]
        raise ExampleSetError(f"{path}, line {bad_line}: NaN or Inf coordinate", code="non_finite")
    face_array = np.array(faces, dtype=np.int64).reshape(-1, 3)
    return vertices, face_array


def format_obj(vertices: np.ndarray, faces_text: str = "", *, precision: int = 9) -> str:
    """OBJ text for one mesh; ``faces_text`` from ``format_faces`` so frames reuse it.

    One C-level ``%`` over the whole array instead of a Python loop per vertex.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    row = f"v %.{precision}g %.{precision}g %.{precision}g\n"
    return (row * v.shape[0]) % tuple(v.ravel().tolist()) + faces_text


def format_faces(faces: np.ndarray) -> str:
    """The ``f`` lines (1-based) of an OBJ file for (F, 3) 0-based triangles."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3) + 1
    return ("f %d %d %d\n" * f.shape[0]) % tuple(f.ravel().tolist())


def write_obj(path: str | os.PathLike[str], vertices: npt.ArrayLike, faces: npt.ArrayLike) -> None:
    """Write an OBJ with one ``v`` line per vertex (in order) and one ``f`` per triangle.

    Parameters
    ----------
    path : path-like
    vertices : (V, 3) float
        Written with 17 significant digits for float64 (exact round trip) and 9 for
        float32.
    faces : (F, 3) int
        0-based triangles.
    """
    v = np.asarray(vertices)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ExampleSetError(f"{path}: expected vertices of shape (V, 3), got {v.shape}")
    f = np.asarray(faces)
    if f.size and (f.ndim != 2 or f.shape[1] != 3):
        raise ExampleSetError(f"{path}: expected faces of shape (F, 3), got {f.shape}")
    precision = 9 if v.dtype == np.float32 else 17
    text = "# facecast\n" + format_obj(v, format_faces(f), precision=precision)
    Path(path).write_text(text, encoding="ascii")


def read_points(path: str | os.PathLike[str]) -> np.ndarray:
    """Read K x 3 feature points from ``.npy`` or ``.csv``.

    CSV: comma-separated, three numbers a line, an optional header line first, blank
    lines and ``#`` comments allowed.

    Returns
    -------
    (K, 3) float64

    Raises
    ------
    ExampleSetError
        Missing file, unknown extension, unparsable content, not 3 columns, no points,
        NaN/Inf (with the CSV line number).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        points = _read_npy(path)
    elif suffix == ".csv":
        points = _read_csv(path)
    else:
        raise ExampleSetError(
            f"{path}: unknown point file type {suffix!r} (expected .npy or .csv)",
            code="bad_points",
        )
    if points.shape[0] < 1:
        raise ExampleSetError(f"{path}: no points", code="bad_points")
    return points


def _read_npy(path: Path) -> np.ndarray:
    try:
        with NPY_READS, path.open("rb") as handle:
            array = np.load(handle, allow_pickle=False)
    except FileNotFoundError:
        raise ExampleSetError(f"{path}: file not found", code="missing_file") from None
    except (OSError, ValueError, EOFError) as exc:
        raise ExampleSetError(
            f"{path}: not a readable .npy file ({exc})", code="bad_points"
        ) from None
    if not isinstance(array, np.ndarray) or array.ndim != 2 or array.shape[1] != 3:
        shape = getattr(array, "shape", None)
        raise ExampleSetError(f"{path}: expected shape (K, 3), got {shape}", code="bad_points")
    if not np.issubdtype(array.dtype, np.number) or np.iscomplexobj(array):
        raise ExampleSetError(
            f"{path}: expected real numbers, got {array.dtype}", code="bad_points"
        )
    points = array.astype(np.float64)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise ExampleSetError(f"{path}: NaN or Inf in point {row}", code="non_finite")
    return points


def _read_csv(path: Path) -> np.ndarray:
    text = _read_text(path)
    rows: list[list[float]] = []
    seen_data = False
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split(",")]
        try:
            values = [float(c) for c in cells]
        except ValueError:
            if not seen_data and not rows:
                seen_data = True  # the one header line allowed before the data
                continue
            raise ExampleSetError(
                f"{path}, line {number}: cannot parse {raw.strip()!r} as numbers",
                code="bad_points",
            ) from None
        seen_data = True
        if len(values) != 3:
            raise ExampleSetError(
                f"{path}, line {number}: expected 3 columns (x, y, z), got {len(values)}",
                code="bad_points",
            )
        if not all(np.isfinite(values)):
            raise ExampleSetError(
                f"{path}, line {number}: NaN or Inf coordinate", code="non_finite"
            )
        rows.append(values)
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def points_to_csv(points: np.ndarray) -> str:
    """CSV text (header ``x,y,z``) for (K, 3) points, readable by ``read_points``."""
    buffer = io.StringIO()
    np.savetxt(
        buffer,
        np.asarray(points, dtype=np.float64),
        delimiter=",",
        fmt="%.17g",
        header="x,y,z",
        comments="",
    )
    return buffer.getvalue()
