"""Decoding and checking points: every refusal has its own code."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from service.errors import InputError, UnsupportedMediaError
from service.inputs import check_points, mesh_format, points_from_base64, points_from_list, points_to_base64


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
