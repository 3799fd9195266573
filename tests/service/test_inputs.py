"""Decoding and checking points: every refusal has its own code."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from service.errors import InputError, UnsupportedMediaError
from service.geometry.inputs import (
    check_points,
    mesh_format,
    points_from_base64,
    points_from_json,
    points_from_list,
    points_to_base64,
)


def _code(fn, *args) -> str:
    with pytest.raises(InputError) as info:
        fn(*args)
    return info.value.code


def test_base64_round_trip_is_exact() -> None:
    pts = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    np.testing.assert_array_equal(points_from_base64(points_to_base64(pts), 1000), pts)


def test_base64_is_little_endian_float32() -> None:
    text = base64.b64encode(np.array([[1.0, 2.0, 3.0]], dtype="<f4").tobytes()).decode()
    np.testing.assert_array_equal(points_from_base64(text, 10), [[1.0, 2.0, 3.0]])


def test_bad_base64() -> None:
    assert _code(points_from_base64, "not base64!", 10) == "invalid_base64"
    assert _code(points_from_base64, base64.b64encode(b"12345").decode(), 10) == "bad_shape"
    assert _code(points_from_base64, "", 10) == "empty_points"
    assert _code(points_from_base64, points_to_base64(np.zeros((11, 3))), 10) == "too_many_points"


def test_lists() -> None:
    assert points_from_list([[1, 2, 3]]).dtype == np.float64  # float32 only after the frame
    assert _code(points_from_list, []) == "empty_points"
    assert _code(points_from_list, [[1, 2]]) == "bad_shape"
    assert _code(points_from_list, [[1, 2, 3], [1, 2]]) == "bad_shape"


def test_check_points_limits_and_values() -> None:
    pts = np.zeros((20, 3), np.float32)
    assert check_points(pts, 16, 100).shape == (20, 3)
    assert _code(check_points, pts, 21, 100) == "too_few_points"
    assert _code(check_points, pts, 1, 19) == "too_many_points"
    bad = pts.copy()
    bad[3, 1] = np.inf
    with pytest.raises(InputError, match="point 3"):
        check_points(bad, 1, 100)
    bad[3, 1] = np.nan
    assert _code(check_points, bad, 1, 100) == "non_finite_points"


def test_mesh_format() -> None:
    assert mesh_format("chair.OBJ", None) == "obj"
    assert mesh_format("blob", "glb") == "glb"
    with pytest.raises(UnsupportedMediaError):
        mesh_format("chair.fbx", None)
    with pytest.raises(UnsupportedMediaError):
        mesh_format(None, None)


def test_base64_may_be_wrapped() -> None:
    pts = np.arange(60, dtype=np.float32).reshape(20, 3)
    text = points_to_base64(pts)
    wrapped = "\n".join(text[i:i + 76] for i in range(0, len(text), 76))
    np.testing.assert_array_equal(points_from_base64(wrapped, 100), pts)


def test_json_points_become_float64_triples() -> None:
    values = np.random.default_rng(0).normal(size=(50, 3)).tolist()
    values[3] = [0, 1, 2]  # integers are numbers, and exact 0 and 1 are coordinates
    got = points_from_json(values)
    assert isinstance(got, np.ndarray) and got.dtype == np.float64
    np.testing.assert_array_equal(got, np.asarray(values, dtype=np.float64))


@pytest.mark.parametrize(("bad", "named"), [
    (True, "the boolean true"), (False, "the boolean false"), ("1.5", "the string '1.5'"),
    (None, "null"), ([1.0], "a list"), ({"x": 1}, "an object"), (10**400, "too large"),
])
def test_json_points_that_are_not_numbers_are_named(bad: object, named: str) -> None:
    values: list = [[0.5, 0.5, 0.5] for _ in range(20)]
    values[7] = [0.0, bad, 1.0]
    with pytest.raises(ValueError, match=r"points\[7\]\[1\]") as info:
        points_from_json(values)
    assert named in str(info.value)


def test_json_points_of_the_wrong_shape_are_left_to_points_from_list() -> None:
    for values, code in (([], "empty_points"), ([[1, 2]], "bad_shape"), ([[1, 2, 3], [4, 5]], "bad_shape"),
                         ([[1, 2, 3, 4]], "bad_shape"), ([[1, 2, 3], 4], "bad_shape")):
        passed = points_from_json(values)
        assert passed is values
        assert _code(points_from_list, passed) == code
    with pytest.raises(ValueError, match="list of"):
        points_from_json("1 2 3")
