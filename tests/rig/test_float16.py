"""The compiled float32 -> float16 cast (``_kernel.f32_to_f16``, ``kernel.to_float16``).

It must give numpy's bits for every float32 (rounding ties, subnormals, overflow, Inf, NaN
payloads) on both its F16C and plain-C paths, reject bad buffers, and fall back to numpy.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.rig import kernel as rig_kernel

needs_kernel = pytest.mark.skipif(
    not rig_kernel.compiled(), reason="facecast.rig._kernel is not built (no C compiler?)"
)
PATHS = [pytest.param(False, id="dispatched"), pytest.param(True, id="generic")]


def numpy_bits(values: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return values.astype(np.float16).view(np.uint16)


def kernel_bits(values: np.ndarray, generic: bool) -> np.ndarray:
    out = np.empty(values.shape, np.float16)
    rig_kernel._kernel.f32_to_f16(values, out, generic)
    return out.view(np.uint16)


def float_patterns(bits: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(bits, dtype=np.uint32).view(np.float32)


@needs_kernel
@pytest.mark.parametrize("generic", PATHS)
def test_every_upper_half_pattern_with_edge_low_bits_matches_numpy(generic):
    # Every sign/exponent/top-7-mantissa combination with the low 16 bits that decide
    # rounding (zero, just under, at and just over a tie of each half step, all ones):
    # covers the whole exponent range including subnormal and overflow boundaries.
    high = np.arange(1 << 16, dtype=np.uint32) << 16
    low = np.array(
        [0, 1, 0x0FFF, 0x1000, 0x1001, 0x1FFF, 0x2000, 0x3000, 0x7FFF, 0x8000, 0xFFFF],
        dtype=np.uint32,
    )
    values = float_patterns((high[:, None] | low[None, :]).ravel())

    np.testing.assert_array_equal(kernel_bits(values, generic), numpy_bits(values))


@needs_kernel
@pytest.mark.parametrize("generic", PATHS)
def test_every_float32_near_the_float16_range_edges_matches_numpy(generic):
    # Exhaustive over the two binades where rounding is subtle: around the smallest
    # subnormal (2^-25 .. 2^-24) and around the largest finite half (2^15 .. 2^16).
    starts = [0x33000000 - 1024, 0x477F0000]
    bits = np.concatenate([np.arange(s, s + (1 << 20), dtype=np.uint32) for s in starts])
    values = float_patterns(np.concatenate([bits, bits | 0x80000000]))

    np.testing.assert_array_equal(kernel_bits(values, generic), numpy_bits(values))


@needs_kernel
@pytest.mark.parametrize("generic", PATHS)
def test_nan_payloads_inf_and_signed_zero_match_numpy(generic):
    specials = np.array(
        [0x7F800000, 0xFF800000, 0x7F800001, 0xFF800001, 0x7FC00000, 0x7F801FFF, 0x7F802000,
         0x7FBFFFFF, 0xFFFFFFFF, 0x7FFFE000, 0x00000000, 0x80000000, 0x00000001, 0x807FFFFF],
        dtype=np.uint32,
    )  # fmt: skip
    # Each special alone among finite neighbours, at every lane of an 8-value block.
    rows = np.full((specials.size * 8, 19), 0x3F800000, np.uint32)
    for i, special in enumerate(np.repeat(specials, 8)):
        rows[i, i % 8] = special
    values = float_patterns(rows)

    np.testing.assert_array_equal(kernel_bits(values, generic), numpy_bits(values))


@needs_kernel
@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=40),
    st.booleans(),
)
def test_any_bit_patterns_of_any_length_match_numpy(patterns, generic):
    values = float_patterns(np.array(patterns, dtype=np.uint64))

    np.testing.assert_array_equal(kernel_bits(values, generic), numpy_bits(values))


@needs_kernel
@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(width=32, allow_nan=True), min_size=1, max_size=40))
def test_any_float32_values_match_numpy(floats):
    values = np.array(floats, dtype=np.float32)

    np.testing.assert_array_equal(kernel_bits(values, False), numpy_bits(values))


@needs_kernel
@pytest.mark.parametrize(
    ("src", "dst", "message"),
    [
        (np.zeros(8, np.float64), np.zeros(8, np.float16), "src must be"),
        (np.zeros(8, np.float32), np.zeros(8, np.float32), "dst must be"),
        (np.zeros(8, np.float32), np.zeros(7, np.float16), "same number"),
        (np.zeros(16, np.float32)[::2], np.zeros(8, np.float16), "contiguous"),
    ],
)
def test_bad_buffers_are_refused_with_value_or_buffer_errors(src, dst, message):
    with pytest.raises((ValueError, BufferError), match=message):
        rig_kernel._kernel.f32_to_f16(src, dst)


@needs_kernel
def test_read_only_destination_and_overlap_are_refused():
    read_only = np.zeros(8, np.float16)
    read_only.flags.writeable = False
    shared = np.zeros(16, np.float32)

    with pytest.raises((ValueError, BufferError)):
        rig_kernel._kernel.f32_to_f16(np.zeros(8, np.float32), read_only)
    with pytest.raises(ValueError, match="overlap"):
        rig_kernel._kernel.f32_to_f16(shared[:8], shared[4:8].view(np.float16))


@pytest.mark.parametrize(
    "src",
    [
        pytest.param(np.linspace(-7e4, 7e4, 3 * 1001, dtype=np.float32).reshape(-1, 3), id="f32"),
        pytest.param(np.linspace(-7e4, 7e4, 3 * 1001).reshape(-1, 3), id="f64"),
        pytest.param(np.linspace(-7e4, 7e4, 6 * 1001, dtype=np.float32)[::2].reshape(-1, 3),
                     id="strided"),
    ],
)  # fmt: skip
def test_to_float16_equals_numpy_cast_for_any_input(src):
    out = np.empty(src.shape, np.float16)

    with np.errstate(over="ignore"):
        result = rig_kernel.to_float16(src, out)

    assert result is out
    np.testing.assert_array_equal(out.view(np.uint16), numpy_bits(src))


def test_to_float16_uses_numpy_when_the_kernel_is_disabled(monkeypatch):
    monkeypatch.setenv(rig_kernel.DISABLE_ENV, "1")
    src = np.array([[1.0, np.nan, 65520.0]], np.float32)
    out = np.empty(src.shape, np.float16)

    with np.errstate(over="ignore", invalid="ignore"):
        rig_kernel.to_float16(src, out)

    np.testing.assert_array_equal(out.view(np.uint16), numpy_bits(src))
