"""The finiteness check of wire arrays (``arrays.all_finite``) against ``np.isfinite``.

The float16 bit test must agree with numpy for every one of the 65536 float16 patterns, at
any position and array size; float32/float64 for any bits, NaN payloads included; and a
non-finite value anywhere in a decoded array must give NON_FINITE.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.protocol import ErrorCode, ProtocolError, array_from_wire
from facecast.protocol.arrays import all_finite

ALL_F16 = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16)
SIZES = [3, 257]


@pytest.mark.parametrize("size", SIZES)
def test_every_float16_pattern_agrees_with_isfinite_at_any_size(size):
    # Each pattern alone among finite values, at a position that moves with the pattern.
    array = np.full(size, 1.5, np.float16)
    verdicts = np.empty(ALL_F16.size, bool)

    for bits in range(ALL_F16.size):
        where = bits % size
        array[where] = ALL_F16[bits]
        verdicts[bits] = all_finite(array)
        array[where] = 1.5

    np.testing.assert_array_equal(verdicts, np.isfinite(ALL_F16))


def test_whole_float16_range_is_non_finite_and_its_finite_part_is_finite():
    finite_part = ALL_F16[np.isfinite(ALL_F16)]

    assert not all_finite(ALL_F16)
    assert all_finite(finite_part)
    assert finite_part.size == 2 * 0x7C00


@pytest.mark.parametrize("dtype", [np.uint32, np.uint64], ids=["f32", "f64"])
def test_random_float32_and_float64_patterns_agree_with_isfinite(dtype):
    rng = np.random.default_rng(7)
    info = np.iinfo(dtype)
    patterns = rng.integers(0, info.max, size=(4000, 5), dtype=dtype, endpoint=True)
    # Force a share of Inf/NaN exponents, with random payloads and signs.
    exponent = dtype(0x7F800000 if dtype is np.uint32 else 0x7FF0000000000000)
    patterns[::3, 2] |= exponent
    rows = patterns.view(np.float32 if dtype is np.uint32 else np.float64)

    verdicts = [all_finite(row) for row in rows]

    np.testing.assert_array_equal(verdicts, np.isfinite(rows).all(axis=1))


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=600),
    st.sampled_from(["f16", "shape"]),
)
def test_any_float16_array_agrees_with_isfinite(patterns, layout):
    array = np.array(patterns, np.uint16).view(np.float16)
    if layout == "shape" and array.size % 3 == 0:
        array = array.reshape(-1, 3)

    assert all_finite(array) == bool(np.isfinite(array).all())


@pytest.mark.parametrize("name", ["f16", "f32", "f64"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_large_wire_array_with_one_non_finite_value_is_refused(name, bad):
    dtype = {"f16": "<f2", "f32": "<f4", "f64": "<f8"}[name]
    values = np.zeros((1000, 3), dtype)
    values[777, 1] = bad
    wire = {"dtype": name, "shape": [1000, 3], "data": values.tobytes()}

    with pytest.raises(ProtocolError) as error:
        array_from_wire(wire, "result.vertices", trailing=(3,), max_rows=1000)

    assert error.value.code == ErrorCode.NON_FINITE


def test_large_finite_float16_wire_array_is_accepted_unchanged():
    values = np.linspace(-65504, 65504, 3000, dtype=np.float16).reshape(1000, 3)
    wire = {"dtype": "f16", "shape": [1000, 3], "data": values.tobytes()}

    array = array_from_wire(wire, "result.vertices", trailing=(3,), max_rows=1000)

    np.testing.assert_array_equal(array, values)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_small_array_of_finite_values_whose_squares_overflow_is_finite(dtype):
    huge = np.full((20, 3), np.finfo(dtype).max, dtype)
    assert all_finite(huge)
    huge[7, 1] = -np.inf
    assert not all_finite(huge)
