"""Numeric arrays on the wire: one {dtype, shape, data} map per array (PROTOCOL.md §4).

Converts between numpy arrays and that map, validating every part on the way in;
it knows nothing about messages and never copies array data more than once.
"""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np

from facecast.protocol.errors import ErrorCode, ProtocolError

#: Wire dtype names and the little-endian numpy dtypes they stand for.
WIRE_DTYPES: Final[dict[str, np.dtype[Any]]] = {
    "f16": np.dtype("<f2"),
    "f32": np.dtype("<f4"),
    "f64": np.dtype("<f8"),
}
_NAME_BY_ITEMSIZE: Final = {2: "f16", 4: "f32", 8: "f64"}
#: float16 arrays with more values than this are checked by their exponent bits (below).
_F16_BITS_CHECK_MIN = 256
#: float32/64 arrays with at most this many values are first checked by a dot product.
_DOT_CHECK_MAX = 4096
_F16_NEGATIVE_NON_FINITE: Final = 0xFC00
_F16_EXPONENT_ALL_ONES: Final = 0x7C00


def all_finite(array: np.ndarray) -> bool:
    """Whether ``array`` (any shape, float16/32/64) holds no NaN and no infinity.

    numpy's ``isfinite`` has no vectorised loop for float16 (~2 ns a value: 150 us for an
    ICT vertices result); its bits tell in ~0.1 ns a value: a float16 is Inf or NaN
    exactly when its exponent bits are all ones (0x7C00 and up with the sign bit off). float32
    and float64 keep ``isfinite``, which numpy vectorises (a bit mask is slower there).
    Small arrays too: below a few hundred values the call overhead is all there is.
    """
    if array.dtype.itemsize == 2:
        if array.size > _F16_BITS_CHECK_MIN:
            # Two reductions and no temporary (a masked copy is one more pass over a
            # result's bytes): as uint16 the negative Inf/NaN are those >= 0xFC00 (the
            # negative finite ones lie below), as int16 the positive ones >= 0x7C00.
            bits = np.ascontiguousarray(array).view(np.uint16)
            return (
                int(bits.max()) < _F16_NEGATIVE_NON_FINITE
                and int(bits.view(np.int16).max()) < _F16_EXPONENT_ALL_ONES
            )
    elif array.size <= _DOT_CHECK_MAX and math.isfinite(np.vdot(array, array)):
        # A frame's points: one BLAS dot (0.5 us) instead of isfinite + all (1.2 us). A
        # NaN or infinity makes the sum of squares NaN or +inf (squares cannot cancel);
        # a finite sum proves every value finite. Not finite (maybe only an overflow of
        # huge values): the exact check below decides.
        return True
    return bool(np.isfinite(array).all())


def check_result_finite(values: np.ndarray, where: str, seq: int | None) -> None:
    """Raise RESULT_NOT_FINITE unless a result's array is finite in its own dtype (§4).

    For senders: finite input can still give values that overflow the negotiated dtype
    (float16 ends at 65504), and no peer may send NaN or infinity. The frame gets this
    error instead of a result; the session goes on.
    """
    if not all_finite(values):
        raise ProtocolError(
            ErrorCode.RESULT_NOT_FINITE,
            f"{where} is not finite in {values.dtype} (an overflow: points far from the "
            "rig's neutral, or a dtype too small for the result); no result for this frame",
            seq=seq,
        )


def wire_dtype_name(dtype: np.dtype[Any]) -> str:
    """The wire name ("f16", "f32", "f64") of a floating numpy dtype."""
    dtype = np.dtype(dtype)
    name = _NAME_BY_ITEMSIZE.get(dtype.itemsize) if dtype.kind == "f" else None
    if name is None:
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY, f"only float16/32/64 arrays can be sent, got {dtype}"
        )
    return name


def array_to_wire(array: np.ndarray) -> dict[str, Any]:
    """The wire map of ``array``: {"dtype": name, "shape": [...], "data": bytes-like}.

    ``data`` is a memoryview of ``array`` itself when it is already little-endian and
    C-contiguous (the usual case), so msgpack copies the bytes once, straight into its
    output buffer.
    """
    name = wire_dtype_name(array.dtype)
    wire = WIRE_DTYPES[name]
    if array.dtype != wire or not array.flags.c_contiguous:
        array = np.ascontiguousarray(array, dtype=wire)
    return {"dtype": name, "shape": list(array.shape), "data": array.data}


def _bad_shape(where: str, trailing: tuple[int, ...], shape: Any) -> ProtocolError:
    expected = f"[N, {', '.join(map(str, trailing))}]" if trailing else "[N]"
    return ProtocolError(
        ErrorCode.INVALID_ARRAY, f"{where}.shape must be {expected}, got {shape!r}"
    )


def array_from_wire(
    obj: Any, where: str, *, trailing: tuple[int, ...], max_rows: int
) -> np.ndarray:
    """Validate a wire array map and view its bytes as an array.

    Parameters
    ----------
    obj : Any
        The decoded msgpack value of the array field.
    where : str
        Field name for error messages, e.g. ``"frame.points"``.
    trailing : tuple of int
        Required shape after the first axis: ``(3,)`` for points and vertices, ``()``
        for weights.
    max_rows : int
        Largest first axis accepted (``Limits.max_points`` etc.).

    Returns
    -------
    (N, *trailing) array, read-only, in the wire dtype
        A zero-copy view of the message's bytes.
    """
    if type(obj) is not dict:
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY, f"{where} must be a map with dtype, shape and data"
        )
    name = obj.get("dtype")
    dtype = WIRE_DTYPES.get(name) if type(name) is str else None
    if dtype is None:
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY,
            f"{where}.dtype must be one of {list(WIRE_DTYPES)}, got {name!r}",
        )
    shape = obj.get("shape")
    if type(shape) is not list or len(shape) != 1 + len(trailing):
        raise _bad_shape(where, trailing, shape)
    for n in shape:
        # type(), not ==: 3.0 == 3 and True == 1, but neither is a msgpack int.
        if type(n) is not int or n < 0:
            raise _bad_shape(where, trailing, shape)
    rows = shape[0]
    if len(trailing) and tuple(shape[1:]) != trailing:
        raise _bad_shape(where, trailing, shape)
    if rows > max_rows:
        raise ProtocolError(
            ErrorCode.MESSAGE_TOO_LARGE, f"{where} has {rows} rows, more than the limit {max_rows}"
        )
    if rows == 0:
        raise ProtocolError(ErrorCode.INVALID_ARRAY, f"{where} must not be empty")
    data = obj.get("data")
    if type(data) is not bytes:
        raise ProtocolError(ErrorCode.INVALID_ARRAY, f"{where}.data must be bin")
    count = rows
    for n in trailing:
        count *= n
    if count * dtype.itemsize != len(data):
        raise ProtocolError(
            ErrorCode.INVALID_ARRAY,
            f"{where}.data has {len(data)} bytes, shape {shape} of {name} needs "
            f"{count * dtype.itemsize}",
        )
    # One constructor call instead of frombuffer + reshape: the same read-only view.
    array = np.ndarray(shape, dtype, data)
    if not all_finite(array):
        raise ProtocolError(ErrorCode.NON_FINITE, f"{where} contains NaN or infinity")
    return array
