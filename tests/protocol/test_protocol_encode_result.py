"""``encode_result`` lays out a result as msgpack does, at every int and bin size boundary."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from facecast.protocol import Result, encode, encode_result

# msgpack's int formats change after these (fixint, uint8, uint16, uint32; uint64 ends).
_INT_EDGES = [0, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**64 - 1]
# Array byte sizes around the bin8 / bin16 / bin32 boundaries (float16 vertices, 6 B a row).
_ROWS = [1, 42, 43, 10922, 10923, 26719]


@pytest.mark.parametrize("size", [6, 6000])  # msgpack's Packer, and the joined layout
@pytest.mark.parametrize("value", _INT_EDGES)
def test_encode_result_ints_match_msgpack_at_each_format_edge(value: int, size: int) -> None:
    values = np.arange(size, dtype=np.float32)
    result = Result(seq=value, ts=-0.0, weights=values, proc_us=value, dropped=value)
    assert encode_result(value, -0.0, "weights", values, value, value) == encode(result)


@pytest.mark.parametrize("rows", _ROWS)
def test_encode_result_array_bytes_match_msgpack_at_each_bin_edge(rows: int) -> None:
    values = np.linspace(-1, 1, rows * 3, dtype=np.float16).reshape(rows, 3)
    result = Result(seq=7, ts=1e300, vertices=values, proc_us=12, dropped=0)
    assert encode_result(7, 1e300, "vertices", values, 12, 0) == encode(result)


def test_encode_result_of_a_non_contiguous_float64_array_is_its_little_endian_copy() -> None:
    values = np.arange(2048, dtype=">f8")[::-2]
    data = encode_result(1, 0.5, "weights", values, 3, 4)
    decoded = msgpack.unpackb(data)
    assert decoded["weights"]["dtype"] == "f64"
    assert np.frombuffer(decoded["weights"]["data"], "<f8").tolist() == values.tolist()
    assert data == encode(Result(seq=1, ts=0.5, weights=values, proc_us=3, dropped=4))


def test_encode_result_points_output_has_the_points_key() -> None:
    values = np.ones((400, 3), np.float32)
    decoded = msgpack.unpackb(encode_result(2, 0.0, "points", values, 0, 0))
    assert list(decoded) == ["v", "type", "seq", "ts", "points", "proc_us", "dropped"]
    assert decoded["points"]["shape"] == [400, 3]
    array = {"dtype": "f32", "shape": [400, 3], "data": values.tobytes()}
    expected = {"v": 1, "type": "result", "seq": 2, "ts": 0.0, "points": array}
    expected |= {"proc_us": 0, "dropped": 0}
    assert encode_result(2, 0.0, "points", values, 0, 0) == msgpack.packb(expected)
