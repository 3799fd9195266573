"""Caller frame <-> canonical frame: round trips, the z-up turn, boxes."""

from __future__ import annotations

import numpy as np

from service.geometry.frames import Frame


def test_round_trip() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    frames = (Frame(), Frame(np.array([1.0, -2.0, 0.5]), 3.7, "z"),
              Frame(np.array([0.0, 5.0, 0.0]), 0.2, "y"))
    for frame in frames:
        np.testing.assert_allclose(frame.from_canonical(frame.to_canonical(pts)), pts, atol=1e-5)


def test_z_up_turns_z_into_y() -> None:
    frame = Frame(up_axis="z")
    np.testing.assert_allclose(frame.to_canonical(np.array([[0.0, 0.0, 1.0]])), [[0.0, 1.0, 0.0]])
    # A proper rotation: x stays, handedness is kept.
    assert np.isclose(np.linalg.det(frame.rotation), 1.0)
    np.testing.assert_allclose(frame.to_canonical(np.array([[1.0, 0.0, 0.0]])), [[1.0, 0.0, 0.0]])


def test_centre_and_radius() -> None:
    frame = Frame(np.array([10.0, 0.0, 0.0]), 2.0, "y")
    np.testing.assert_allclose(frame.to_canonical(np.array([[12.0, 0.0, 0.0]])), [[1.0, 0.0, 0.0]])


def test_placing_a_part_with_scale_and_rotation() -> None:
    # A part vertex v at canonical translation t lands at scale * R^T v + T in the caller's frame.
    rng = np.random.default_rng(1)
    frame = Frame(np.array([1.0, 2.0, 3.0]), 2.5, "z")
    v, t = rng.normal(size=(4, 3)), rng.normal(size=3)
    placed = frame.radius * v @ frame.part_rotation.T + frame.from_canonical(t[None])[0]
    np.testing.assert_allclose(placed, frame.from_canonical(v + t), atol=1e-9)


def test_boxes_stay_ordered() -> None:
    frame = Frame(np.zeros(3), 2.0, "z")
    lo, hi = frame.box_from_canonical(np.array([[-1.0, -2.0, -3.0]]), np.array([[1.0, 2.0, 3.0]]))
    assert np.all(lo <= hi)
    np.testing.assert_allclose(lo, [[-2.0, -6.0, -4.0]])
    np.testing.assert_allclose(hi, [[2.0, 6.0, 4.0]])
