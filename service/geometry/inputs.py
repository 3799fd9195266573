"""Turn what a caller sends (a list of points, base64 float32, a mesh file) into an (N, 3) array.

Each decoder only decodes and checks the shape; ``check_points`` applies the count and value
limits. Every failure is an ``InputError`` (or ``UnsupportedMediaError``, ``PayloadTooLargeError``)
with a code a client can branch on.
"""

from __future__ import annotations

import array
import base64
import binascii
import gc
import threading
import time
from collections.abc import Sequence
from itertools import chain
from pathlib import PurePath
from typing import Any

import numpy as np

from service.errors import (
    DeadlineError,
    InputError,
    PayloadTooLargeError,
    ServiceError,
    UnsupportedMediaError,
)
from service.geometry.mesh import MESH_FORMATS, MeshError, load_mesh_surface, sample_surface
from service.settings import Settings, check_point_count

# Mesh error codes that are the caller's format or size choice rather than a broken file.
_MESH_CODE_ERRORS: dict[str, type[ServiceError]] = {
    "unsupported_format": UnsupportedMediaError,
    "too_large": PayloadTooLargeError,
}


def upload_error(exc: MeshError) -> ServiceError:
    """The error a caller gets for a mesh it sent that cannot be used (``/suggest/mesh``,
    ``/assemble/mesh``, ``POST /parts``): 415 for its format, 413 over a size limit, else 422;
    the mesh error's code and message are kept."""
    return _MESH_CODE_ERRORS.get(exc.code, InputError)(exc.code, exc.message)


def points_from_json(value: Any) -> np.ndarray | list[Any]:
    """A parsed JSON ``points`` value as ``(N, 3) float64`` when it is N triples of numbers.

    Strict like a schema (a boolean, a string or null is not a coordinate: ``ValueError`` naming
    the first one), but checked in C rather than one Python call per number: 1000 points took
    0.32 ms against 0.52 ms for pydantic's per-element validation and the conversion after it.
    A list of numbers that is not N triples comes back as it is: ``points_from_list`` then says
    what is wrong with its shape (``bad_shape``, ``empty_points``).
    """
    if not isinstance(value, list):
        raise ValueError("points must be a list of [x, y, z] triples")
    try:
        triples = bool(value) and set(map(len, value)) == {3}
        numbers = array.array("d", chain.from_iterable(value))  # refuses str, None, lists, dicts
    except (TypeError, OverflowError):
        return _diagnose(value)
    arr = np.frombuffer(numbers, dtype=np.float64)
    # array("d") takes booleans as 1 and 0: look for them only when such values occur.
    if np.any((arr == 0.0) | (arr == 1.0)) and any(x.__class__ is bool for x in chain.from_iterable(value)):
        return _diagnose(value)
    if not triples:
        return value
    return arr.reshape(-1, 3)


def _diagnose(value: list[Any]) -> list[Any]:
    """Raise ``ValueError`` naming the first element that is not a number (and how many others
    are not); else return ``value``."""
    bad: list[str] = []
    for i, row in enumerate(value):
        if not isinstance(row, list):
            continue  # a shape problem, for points_from_list to name
        for j, x in enumerate(row):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                bad.append(f"points[{i}][{j}] is {_json_kind(x)}, not a number")
            elif isinstance(x, int) and abs(x) > 1e308:
                bad.append(f"points[{i}][{j}] is too large for a coordinate")
    if not bad:
        return value
    more = f" (and {len(bad) - 1} more values that are not numbers)" if len(bad) > 1 else ""
    raise ValueError(bad[0] + more)


def _json_kind(x: Any) -> str:
    if x is None:
        return "null"
    if isinstance(x, bool):
        return f"the boolean {str(x).lower()}"
    if isinstance(x, str):
        return f"the string {x[:20]!r}"
    return "a list" if isinstance(x, list) else "an object" if isinstance(x, dict) else type(x).__name__


def points_from_list(values: Sequence[Sequence[float]]) -> np.ndarray:
    """A JSON list of [x, y, z] triples as ``(N, 3) float64``; ``bad_shape`` if not triples."""
    if len(values) == 0:
        raise InputError("empty_points", "points is empty; send at least one [x, y, z] triple")
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (ValueError, TypeError, OverflowError):
        raise InputError("bad_shape", "points must be a list of [x, y, z] triples of equal length") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError("bad_shape", f"points must have shape (N, 3), found {arr.shape}")
    # Kept in float64 until the frame is applied: callers' frames may be far from the origin.
    return arr


def points_from_base64(text: str, max_points: int) -> np.ndarray:
    """Base64 of little-endian float32 x, y, z triples (12 bytes per point) as ``(N, 3) float32``.

    ``max_points``: the limit (``Limits.max_points``), applied to the text's length before
    decoding; the decoded points are counted by ``check_points``.
    """
    if not text:
        raise InputError("empty_points", "points_base64 is empty")
    # Refuse oversized payloads before decoding them (4 base64 characters carry 3 bytes).
    if len(text) > 4 * ((12 * max_points + 2) // 3):
        raise InputError("too_many_points", f"points_base64 holds more than the limit of {max_points} points")
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        try:
            # Line breaks and spaces (MIME-style wrapping) are allowed; any other stray character is not.
            raw = base64.b64decode("".join(text.split()), validate=True)
        except (binascii.Error, ValueError) as exc:
            raise InputError("invalid_base64", f"points_base64 is not valid base64 ({exc})") from None
    if len(raw) % 12:
        raise InputError("bad_shape", f"points_base64 decodes to {len(raw)} bytes, not a multiple of 12 "
                         "(3 little-endian float32 per point)")
    if not raw:
        raise InputError("empty_points", "points_base64 decodes to no points")
    # A read-only view of the decoded bytes (no copy on little-endian machines): nothing writes
    # into request points, and a copy here released the GIL mid-request (numpy casts large
    # arrays without it) only to wait for the batch worker to hand it back.
    return np.frombuffer(raw, dtype="<f4").reshape(-1, 3).astype(np.float32, copy=False)


def points_to_base64(points: np.ndarray) -> str:
    """The inverse of ``points_from_base64``: (N, 3) -> base64 of little-endian float32."""
    return base64.b64encode(np.ascontiguousarray(points, dtype="<f4").tobytes()).decode("ascii")


def check_points(points: np.ndarray, min_points: int, max_points: int) -> np.ndarray:
    """Enforce the point-count limits (``Limits``) and finite values; returns the points unchanged."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError("bad_shape", f"points must have shape (N, 3), found {points.shape}")
    if len(points) == 0:
        raise InputError("empty_points", "no points given")
    check_point_count(len(points), min_points, max_points)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise InputError("non_finite_points", f"point {bad} has a NaN or infinite coordinate "
                         f"({int((~finite).sum())} such points)")
    return points


def mesh_format(filename: str | None, declared: str | None) -> str:
    """The mesh format from an explicit ``format`` field, else from the file name's extension."""
    fmt = (declared or PurePath(filename or "").suffix).lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        shown = fmt or "(none: give a file name with an extension or a format field)"
        raise UnsupportedMediaError("unsupported_format", f"mesh format {shown!r} is not supported; "
                                    f"expected one of {', '.join(MESH_FORMATS)}")
    return fmt


def points_from_mesh(data: bytes, file_type: str, *, n: int, seed: int, name: str,
                     max_vertices: int, max_faces: int, **limits: int) -> np.ndarray:
    """Load an uploaded mesh and sample ``n`` points on its surface, area-weighted and seeded.

    ``limits``: ``max_nodes`` and ``max_nesting`` of ``service.geometry.mesh.load_mesh_surface``.

    Shapes:
        returns (n, 3) float32, in the mesh's own frame.
    """
    return _sample_mesh(data, file_type, n=n, seed=seed, name=name, max_vertices=max_vertices,
                        max_faces=max_faces, **limits)[0]


def _sample_mesh(data: bytes, file_type: str, *, n: int, seed: int, name: str, max_vertices: int,
                 max_faces: int, **limits: int) -> tuple[np.ndarray, float]:
    """``n`` surface samples (as ``points_from_mesh``) and the mesh's total area."""
    try:
        mesh = load_mesh_surface(data, file_type, name=name, max_vertices=max_vertices, max_faces=max_faces,
                                 ignore_obj_materials=True, **limits)
        return sample_surface(mesh.vertices, mesh.faces, n, seed, areas=mesh.areas), float(mesh.areas.sum())
    except MeshError as exc:
        raise upload_error(exc) from None


class MeshUploads:
    """Sample uploaded meshes with the settings' limits, a few at a time, leaving nothing behind.

    At most ``max_concurrent_uploads`` are parsed at once (a thread waits for its turn until the
    request's deadline): parsing an 18 MB OBJ peaks at about 0.4 GB, and six at once took one
    worker to 2.77 GB. trimesh's scenes hold reference cycles that the raised collector threshold
    (``gc_threshold``) rarely reaches: every 18 MB OBJ left about 60 MB behind, 16 of them 1.1 GB.
    A full collection after each upload over ``COLLECT_BYTES`` returns it (measured: RSS flat
    over 12 such uploads; the collection took 5-50 ms against 3-5 s for the parse itself). Not
    only trimesh's: an upload the plain OBJ readers take (no scene) still left about 21 MB behind
    per 18 MB file without it (2026-12-04, ``test_large_uploads_leave_memory_behind_no_more_than_150_mb``):
    the request's own objects hold its body in cycles too, so every large upload is collected.
    """

    COLLECT_BYTES = 1 << 20

    def __init__(self, settings: Settings):
        self.settings = settings
        self._turns = threading.BoundedSemaphore(settings.max_concurrent_uploads)

    def sample(self, data: bytes, file_type: str, *, n: int, name: str,
               deadline: float | None = None) -> tuple[np.ndarray, float]:
        """``n`` seeded surface samples of the upload and its total area (blocking; threadpool).

        Shapes:
            returns (n, 3) float32 in the mesh's own frame, and a float.

        Raises:
            InputError, PayloadTooLargeError, UnsupportedMediaError: the upload's problem.
            DeadlineError: no turn came before ``deadline`` (``time.monotonic()``).
        """
        s = self.settings
        wait = None if deadline is None else max(0.0, deadline - time.monotonic())
        if not self._turns.acquire(timeout=wait):
            raise DeadlineError("deadline_exceeded", f"no turn to parse the upload came before the request's "
                                f"deadline ({s.max_concurrent_uploads} uploads are parsed at once)")
        try:
            return _sample_mesh(data, file_type, n=n, seed=s.seed, name=name,
                                max_vertices=s.max_mesh_vertices, max_faces=s.max_mesh_faces,
                                max_nodes=s.max_mesh_nodes, max_nesting=s.max_mesh_nesting)
        finally:
            self._turns.release()
            if len(data) > self.COLLECT_BYTES:
                gc.collect()
