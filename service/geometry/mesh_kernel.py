"""Compiled mesh kernels (numba): the runs of a plain OBJ file's ``v`` and ``f`` lines parsed in
one pass, and triangle areas.

Triangle areas (``triangle_areas``, called by ``service.geometry.mesh.triangle_areas``): the same
sums in the same order as np.cross and np.linalg.norm (bit-identical), in one loop: 0.4 against
7.7 ms with numpy's gathers for the bench's 100k triangles, which every mesh upload (GLB or OBJ)
pays before sampling.

OBJ: ``service.geometry.obj.read_obj_blocks`` reads a file laid out as one run of vertex lines and one
run of face lines; Arrow's CSV reader took about 6 of its 16 ms for the bench's 100k-triangle file
(the rest is finding the runs and making the surface). This reader takes only the most common
spelling of those runs and says so by returning False for anything else, so the Arrow reader
(and behind it the numpy one, then trimesh) still decides every other file:

* a vertex line is ``v``, then three numbers, one blank before each, then ``\\n`` or ``\\r\\n``
  (the run's last line may end without one); a number is an optional sign, digits, and an optional
  ``.`` with digits, at most 15 significant digits and no exponent. Such a number is an integer
  below 2^53 over a power of ten, both exact in float64, so one division gives the correctly
  rounded value: the one ``float()`` (and Arrow) reads;
* a face line is ``f``, then ``corners`` words, one blank before each, each a vertex reference
  (optional ``-``, digits) followed by exactly ``slashes`` slashes, each followed by optional
  digits (``i``, ``i/t``, ``i//n``, ``i/t/n``); only the vertex reference is kept.

Shapes: vertices (V, 3) float64; references (F, corners) int64, as written (1-based or negative).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Significant digits read exactly (an integer below 10^15 < 2^53), and powers of ten exact in float64.
_MAX_MANTISSA = 10 ** 15
_MAX_REFERENCE = 10 ** 18   # an index reference's digits: at most 18 (int64)
_POW10 = np.array([10.0 ** k for k in range(23)])
_NL, _CR, _BLANK, _SLASH, _DOT, _MINUS, _PLUS = 10, 13, 32, 47, 46, 45, 43


# Why the loops below are written out byte by byte, the digit loop and the line end repeated in
# both readers: the same reader built from small helpers (a word's blank and sign, a run of
# digits, a line end) took 5.5 and 6.3 ms for the bench file's vertex and face runs against 1.6
# and 1.9 ms written out; numba did not inline them (inline="always" did not help), and even the
# line end alone as a helper cost a quarter more (2.1 and 2.5 ms).


@njit(cache=True, nogil=True)
def read_vertices(a: np.ndarray, start: int, end: int, out: np.ndarray) -> bool:
    """Parse ``len(out)`` vertex lines from ``a[start:end]`` into ``out``; False if the run is not
    exactly that (see the module docstring).

    Shapes:
        a (n,) uint8; out (V, 3) float64.
    """
    i = start
    for r in range(out.shape[0]):
        if i + 1 >= end or a[i] != 118:   # 'v', then the first word's blank
            return False
        i += 1
        for c in range(3):
            if i >= end or a[i] != _BLANK:
                return False
            i += 1
            neg = False
            if i < end and (a[i] == _MINUS or a[i] == _PLUS):
                neg = a[i] == _MINUS
                i += 1
            mant = 0
            digits = 0
            while i < end:
                d = int(a[i]) - 48
                if d < 0 or d > 9:
                    break
                mant = mant * 10 + d
                digits += 1
                i += 1
                if mant >= _MAX_MANTISSA:
                    return False
            if digits == 0:
                return False
            frac = 0
            if i < end and a[i] == _DOT:
                i += 1
                while i < end:
                    d = int(a[i]) - 48
                    if d < 0 or d > 9:
                        break
                    mant = mant * 10 + d
                    frac += 1
                    i += 1
                    if mant >= _MAX_MANTISSA:
                        return False
                if frac == 0 or frac >= len(_POW10):
                    return False
            value = mant / _POW10[frac]
            out[r, c] = -value if neg else value
        if i < end:   # the line end: \n or \r\n (the run's last line may have none)
            if a[i] == _NL:
                i += 1
            elif a[i] == _CR and i + 1 < end and a[i + 1] == _NL:
                i += 2
            else:
                return False
    return i == end


@njit(cache=True, nogil=True)
def read_faces(a: np.ndarray, start: int, end: int, slashes: int, out: np.ndarray) -> bool:
    """Parse ``len(out)`` face lines of ``out.shape[1]`` corners from ``a[start:end]`` into ``out``
    (each corner's vertex reference); False if the run is not exactly that.

    Shapes:
        a (n,) uint8; out (F, corners) int64.
    """
    i = start
    for r in range(out.shape[0]):
        if i + 1 >= end or a[i] != 102:   # 'f', then the first word's blank
            return False
        i += 1
        for c in range(out.shape[1]):
            if i >= end or a[i] != _BLANK:
                return False
            i += 1
            neg = False
            if i < end and a[i] == _MINUS:
                neg = True
                i += 1
            ref = 0
            digits = 0
            while i < end:
                d = int(a[i]) - 48
                if d < 0 or d > 9:
                    break
                ref = ref * 10 + d
                digits += 1
                i += 1
                if ref >= _MAX_REFERENCE:
                    return False
            if digits == 0:
                return False
            for _ in range(slashes):   # texture and normal references: skipped
                if i >= end or a[i] != _SLASH:
                    return False
                i += 1
                skipped = 0
                while i < end:
                    d = int(a[i]) - 48
                    if d < 0 or d > 9:
                        break
                    skipped = skipped * 10 + d
                    i += 1
                    if skipped >= _MAX_REFERENCE:
                        break   # the digits left make the word's end fail below
            out[r, c] = -ref if neg else ref
        if i < end:
            if a[i] == _NL:
                i += 1
            elif a[i] == _CR and i + 1 < end and a[i + 1] == _NL:
                i += 2
            else:
                return False
    return i == end


@njit(cache=True, nogil=True)
def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each triangle; every index must be within ``vertices`` (nothing is checked here).

    Shapes:
        vertices (V, 3) float64, faces (F, 3) int64 -> (F,) float64.
    """
    out = np.empty(len(faces))
    for t in range(len(faces)):
        i, j, k = faces[t, 0], faces[t, 1], faces[t, 2]
        ax, ay, az = vertices[i, 0], vertices[i, 1], vertices[i, 2]
        bx, by, bz = vertices[j, 0] - ax, vertices[j, 1] - ay, vertices[j, 2] - az
        cx, cy, cz = vertices[k, 0] - ax, vertices[k, 1] - ay, vertices[k, 2] - az
        x = by * cz - bz * cy
        y = bz * cx - bx * cz
        z = bx * cy - by * cx
        out[t] = 0.5 * np.sqrt(x * x + y * y + z * z)
    return out


def warm() -> None:
    """Compile (or load from numba's cache) every kernel here with the argument types
    ``service.geometry`` passes: a few seconds the first time, milliseconds from the cache. The
    server's warm-up and the Docker build (``python -m service.geometry.mesh_kernel``) run it."""
    a = np.frombuffer(b"v 0 0 0\nf 1 1 1\n", dtype=np.uint8)
    read_vertices(a, 0, 8, np.empty((1, 3)))
    read_faces(a, 8, 16, 0, np.empty((1, 3), dtype=np.int64))
    triangle_areas(np.zeros((3, 3)), np.zeros((1, 3), dtype=np.int64))


if __name__ == "__main__":
    warm()
