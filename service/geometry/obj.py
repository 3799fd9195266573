"""A fast reader of the plain OBJ files most tools write: numpy over the bytes, no loop over lines.

trimesh reads an OBJ with Python list work per line: 225 ms of a 240 ms ``/suggest/mesh`` for a
100k-triangle file (docs/performance.md, issue 20), against 21 ms for the same mesh as GLB. Most
OBJ files are plain: ``v x y z`` lines, ``f`` lines of vertex references (``i``, ``i/t``,
``i//n``, ``i/t/n``, negative = relative), and lines the surface does not need (``vt``, ``vn``,
``vp``, ``g``, ``o``, ``s``, comments, blank lines; material lines when the caller drops them),
each keyword at the start of its line and ``v`` and ``f`` followed by a space, as trimesh wants.
``read_plain_obj`` reads those; any other file (another keyword, a line starting with blanks, a
line continuation, a vertex with other than three coordinates, a number it cannot read, an index
out of range) gets ``None`` and is left to trimesh, so every refusal and error message stays the
one ``service.geometry.mesh`` gives.

The surface is the one trimesh reads: the same vertices (those some face uses) and the same
triangles, a polygon split into a fan from its first corner (a quad's second triangle
``(0, 2, 3)`` is trimesh's ``(2, 3, 0)``). One exception: a relative reference (``-1``) counts
back from its face line, as the OBJ format says; trimesh counts from the file's last vertex, which
differs only where vertex lines follow face lines. Coordinates with at most 15 significant digits and no
exponent are read exactly as ``float()`` reads them (an integer over a power of ten, both exact in
float64, is one correctly rounded division); longer ones (up to 18 significant digits) and
exponents to within a few ulps.

Two readers, tried in this order (``service.geometry.mesh`` asks for both):

* ``obj_blocks`` / ``read_obj_blocks``: the file as most exporters write one object (trimesh,
  Blender), all ``v`` lines in one run, then all ``f`` lines in one run, every face of the same
  corner count and corner form (``i``, ``i/t``, ``i//n`` or ``i/t/n``). Each run is read by
  ``service.geometry.mesh_kernel`` (compiled, one pass) when it is in that reader's spelling
  (single blanks, plain decimals of at most 15 significant digits), else by Arrow's CSV reader
  (``pyarrow.csv``: C++, one pass, numbers parsed correctly rounded); both read the numbers
  ``float()`` reads. Any byte Arrow cannot take (a tab, two blanks, a corner of another form, a
  number it cannot read, a row of another length) makes it give None and the next reader runs.
* ``obj_layout`` / ``read_plain_obj``: any plain file, in numpy.

Shapes: vertices (V, 3) float64, faces (F, 3) int64.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv

from service.geometry import mesh_kernel
from service.geometry.arrays import concat_ranges

# Keywords whose lines the surface does not need; the material ones only when the caller drops them.
_SKIPPED = (b"vt", b"vn", b"vp", b"g", b"o", b"s")
_MATERIAL = (b"mtllib", b"usemtl", b"maplib", b"usemap")
# Longest number token read (longer ones go to trimesh), and the most digits an int64 holds exactly.
_MAX_TOKEN = 32
_MAX_DIGITS = 18
_NEWLINE, _HASH, _SLASH, _DOT, _MINUS, _PLUS = 10, 35, 47, 46, 45, 43


@dataclass(frozen=True)
class ObjLayout:
    """Where a plain OBJ's vertex and face data lie (``obj_layout``), counted before anything is parsed.

    Shapes:
        tok_start, tok_end: (T,) byte offsets of every word; v_first: (V,) the first coordinate
        word of each ``v`` line; f_first, f_corners: (P,) the first corner word and the corner
        count of each ``f`` line; f_vertices: (P,) how many ``v`` lines precede it (for negative
        references).
    """

    data: np.ndarray
    tok_start: np.ndarray
    tok_end: np.ndarray
    v_first: np.ndarray
    f_first: np.ndarray
    f_corners: np.ndarray
    f_vertices: np.ndarray
    groups: int

    @cached_property
    def padded(self) -> np.ndarray:
        """The bytes followed by ``_MAX_TOKEN`` zeros, so a word's column j can be read past the
        end of the file: made once, for both readers (coordinates and corners)."""
        return np.concatenate((self.data, np.zeros(_MAX_TOKEN, dtype=np.uint8)))

    @property
    def vertices(self) -> int:
        return len(self.v_first)

    @property
    def triangles(self) -> int:
        """Triangles after splitting polygons (a polygon of k corners is k - 2)."""
        return int(np.maximum(self.f_corners - 2, 1).sum())


def obj_layout(data: bytes, drop_materials: bool) -> ObjLayout | None:
    """The layout of a plain OBJ (see the module doc), or None when the file is not one."""
    if not data or b"\\" in data:            # a backslash continues a line: trimesh's reading
        return None
    a = np.frombuffer(data, dtype=np.uint8)
    low = a[a < 32]                          # control bytes: tabs and line ends only
    if np.any((low != 9) & (low != _NEWLINE) & (low != 13)):
        return None
    cr = np.count_nonzero(low == 13)
    if cr and cr != data.count(b"\r\n"):
        return None                          # a lone CR ends a line for trimesh, not here
    word = a > 32
    # Word edges alternate (start, end, start, ...) once the bytes are framed by blanks.
    edges = np.flatnonzero(word[1:] != word[:-1]) + 1
    if word[0]:
        edges = np.concatenate(([0], edges))
    if word[-1]:
        edges = np.concatenate((edges, [len(a)]))
    starts, ends = edges[0::2], edges[1::2]
    newline = np.flatnonzero(a == _NEWLINE)
    line_start = np.concatenate(([0], newline + 1))
    first = np.searchsorted(starts, line_start)          # each line's first word (words never span lines)
    n_words = np.diff(np.concatenate((first, [len(starts)])))
    lines = np.flatnonzero(n_words > 0)
    kw = first[lines]
    if np.any(starts[kw] != line_start[lines]):
        return None                          # a line that starts with blanks: trimesh skips it
    kw_len = ends[kw] - starts[kw]
    c0 = a[starts[kw]]
    c1 = a[np.minimum(starts[kw] + 1, len(a) - 1)]
    is_v = (kw_len == 1) & (c0 == ord("v"))
    is_f = (kw_len == 1) & (c0 == ord("f"))
    known = is_v | is_f | (c0 == _HASH)
    for keyword in _SKIPPED + (_MATERIAL if drop_materials else ()):
        known |= (kw_len == len(keyword)) & (c0 == keyword[0]) & (
            c1 == keyword[1] if len(keyword) > 1 else True)
    long = starts[kw[known & (kw_len > 2) & (c0 != _HASH)]]   # material keywords: checked in full
    if len(long):
        spelled = a[np.minimum(long[:, None] + np.arange(6), len(a) - 1)]
        names = np.frombuffer(b"".join(_MATERIAL), dtype=np.uint8).reshape(-1, 6)
        if not (spelled[:, None, :] == names[None]).all(axis=2).any(axis=1).all():
            return None
    if not known.all():
        return None
    after = a[np.minimum(ends[kw[is_v | is_f]], len(a) - 1)]
    if np.any(after != 32):
        return None                          # 'v' then a tab: trimesh does not take it for a vertex
    words = n_words[lines]
    if np.any(words[is_v] != 4) or np.any(words[is_f] < 4):
        return None                          # colours or w after a vertex, or a face of < 3 corners
    groups = int(np.count_nonzero((kw_len == 1) & ((c0 == ord("g")) | (c0 == ord("o")))))
    return ObjLayout(data=a, tok_start=starts, tok_end=ends, v_first=kw[is_v] + 1, f_first=kw[is_f] + 1,
                     f_corners=words[is_f] - 1, f_vertices=np.cumsum(is_v)[is_f], groups=groups)


def read_plain_obj(layout: ObjLayout) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertices some face uses and the triangles of a plain OBJ, or None (see the module doc).

    Shapes:
        returns vertices (V, 3) float64, faces (F, 3) int64 indexing them.
    """
    if not layout.vertices or not len(layout.f_first):
        return None                          # nothing to read: trimesh's path says what is missing
    coords = _numbers(layout, (layout.v_first[:, None] + np.arange(3)).ravel())
    if coords is None:
        return None
    vertices = coords.reshape(-1, 3)
    corner_words = concat_ranges(layout.f_first, layout.f_corners)
    refs = _references(layout, corner_words)
    if refs is None:
        return None
    corners = _vertex_indices(refs, np.repeat(layout.f_vertices, layout.f_corners), len(vertices))
    if corners is None:
        return None
    return _used_surface(vertices, _fans(corners, layout.f_corners))


def _vertex_indices(refs: np.ndarray, before: np.ndarray | int, vertices: int) -> np.ndarray | None:
    """0-based vertex indices of OBJ corner references (1-based, or relative to the ``before``
    vertex lines read before the face when negative), or None when one is 0 or out of range.

    Shapes:
        refs (...,) int64, before broadcast to it -> same as refs.
    """
    if refs.size and refs.min() >= 1 and refs.max() <= vertices:
        return refs - 1                      # all absolute and in range, as most files are: one pass
    corners = np.where(refs > 0, refs - 1, before + refs)
    if np.any((refs == 0) | (corners < 0) | (corners >= vertices)):
        return None
    return corners


def _used_surface(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices some face uses, in file order, and the faces indexing them (trimesh's surface).

    Shapes:
        vertices (V, 3), faces (F, 3) -> (V', 3), (F, 3).
    """
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    if used.all():
        return vertices, faces               # every vertex used, as exporters write: nothing to renumber
    index = np.cumsum(used) - 1
    return vertices[used], index[faces]


def _fans(corners: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each polygon's corners split into a fan of triangles from its first corner.

    Shapes:
        corners (sum(counts),), counts (P,) >= 3 -> (sum(counts - 2), 3).
    """
    if np.all(counts == 3):
        return corners.reshape(-1, 3)
    first = np.cumsum(counts) - counts
    tris = counts - 2
    at = np.repeat(first, tris)                                  # each triangle's polygon start
    i = concat_ranges(np.zeros(len(tris), dtype=np.int64), tris) + 1   # its second corner, 1..k-2
    return np.stack([corners[at], corners[at + i], corners[at + i + 1]], axis=1)


def _columns(layout: ObjLayout, words: np.ndarray) -> Iterator[np.ndarray] | None:
    """The words' bytes column by column: column j holds byte j of every word (0 past its end).

    Column-major because every step of the readers below is a vector operation across all words,
    repeated for the few columns a number has (about 10), not a reduction along each short row;
    made one at a time, so a reader that is done early reads no more of them.

    Shapes:
        words (N,) -> W arrays (N,) uint8, W the longest word's length (None past ``_MAX_TOKEN``).
    """
    s, e = layout.tok_start[words], layout.tok_end[words]
    width = int((e - s).max()) if len(s) else 0
    if width > _MAX_TOKEN:
        return None
    data, length = layout.padded, e - s
    return (np.where(length > j, data[s + j], np.uint8(0)) for j in range(width))


def _numbers(layout: ObjLayout, words: np.ndarray) -> np.ndarray | None:
    """Decimal numbers (``[+-]digits[.digits][(e|E)[+-]digits]``) of the given words, or None.

    Read left to right like ``strtod``: the mantissa's digits accumulate in an int64 (at most
    ``_MAX_DIGITS`` of them), the digits after the dot are counted, the exponent's accumulate
    apart; any other byte, or a byte out of place, makes the whole file trimesh's.
    """
    found = _columns(layout, words)
    if found is None:
        return None
    cols = list(found)
    if any(np.any((c | 32) == ord("e")) for c in cols):     # 'e' or 'E' somewhere: exponents
        return _scientific(cols)
    n = len(words)
    mantissa = np.zeros(n, dtype=np.int64)
    digits = np.zeros(n, dtype=np.int64)                      # significant: from the first non-zero
    fraction = np.zeros(n, dtype=np.int64)
    dot = np.zeros(n, dtype=bool)
    seen = np.zeros(n, dtype=bool)                            # a digit, zero or not
    bad = np.zeros(n, dtype=bool)
    negative = cols[0] == _MINUS
    for j, c in enumerate(cols):
        d = c - np.uint8(48)                                  # wraps above 9 for every non-digit
        is_digit = d < 10
        is_dot = c == _DOT
        other = ~is_digit & (c != 0)
        if j == 0:
            other &= (c != _MINUS) & (c != _PLUS)
        bad |= other & ~(is_dot & ~dot)
        mantissa = np.where(is_digit, mantissa * 10 + d, mantissa)
        digits += is_digit & ((mantissa > 0) | (digits > 0))
        seen |= is_digit
        fraction += is_digit & dot
        dot |= is_dot
    if bad.any() or not seen.all() or np.any(digits > _MAX_DIGITS):
        return None
    # Exact (at most 22 digits after the dot): an integer over a power of ten, one division.
    out = mantissa / 10.0 ** fraction
    return np.where(negative, -out, out)


def _scientific(cols: list[np.ndarray]) -> np.ndarray | None:
    """``_numbers`` for words some of which carry an exponent (``e`` or ``E``, signed)."""
    n = len(cols[0])
    mantissa = np.zeros(n, dtype=np.int64)
    exponent = np.zeros(n, dtype=np.int64)
    digits = np.zeros(n, dtype=np.int64)
    fraction = np.zeros(n, dtype=np.int64)
    exp_digits = np.zeros(n, dtype=np.int64)
    dot = np.zeros(n, dtype=bool)
    in_exp = np.zeros(n, dtype=bool)
    exp_negative = np.zeros(n, dtype=bool)
    seen = np.zeros(n, dtype=bool)
    negative = cols[0] == _MINUS
    for j, c in enumerate(cols):
        d = c - np.uint8(48)                                  # wraps above 9 for every non-digit
        is_digit = d < 10
        ok = is_digit | (c == 0)
        if j == 0:
            ok |= (c == _MINUS) | (c == _PLUS)
        else:
            after_e = in_exp & (exp_digits == 0) & (cols[j - 1] > 57)   # the byte right after e/E
            ok |= ((c == _MINUS) | (c == _PLUS)) & after_e
            exp_negative |= (c == _MINUS) & after_e
        is_e = ((c | 32) == ord("e")) & ~in_exp & seen
        is_dot = (c == _DOT) & ~dot & ~in_exp
        if not np.all(ok | is_e | is_dot):
            return None
        in_mantissa = is_digit & ~in_exp
        mantissa = np.where(in_mantissa, mantissa * 10 + d, mantissa)
        digits += in_mantissa & ((mantissa > 0) | (digits > 0))
        seen |= in_mantissa
        fraction += in_mantissa & dot
        in_exponent = is_digit & in_exp
        exponent = np.where(in_exponent, exponent * 10 + d, exponent)
        exp_digits += in_exponent
        dot |= is_dot
        in_exp |= is_e
    if not seen.all() or np.any(digits > _MAX_DIGITS) or np.any(in_exp & (exp_digits == 0)) \
            or np.any(exp_digits > 4):
        return None
    power = np.where(exp_negative, -exponent, exponent) - fraction
    with np.errstate(over="ignore", under="ignore", divide="ignore"):
        # Exact where the power is down to -22 (one division); within a few ulps elsewhere.
        out = np.where(power <= 0, mantissa / 10.0 ** np.minimum(-power, 308),
                       mantissa * 10.0 ** np.minimum(power, 400).astype(np.float64))
    return np.where(negative, -out, out)


def _references(layout: ObjLayout, words: np.ndarray) -> np.ndarray | None:
    """The vertex reference of each corner word (the integer before its first '/'), or None."""
    cols = _columns(layout, words)
    if cols is None:
        return None
    n = len(words)
    value = np.zeros(n, dtype=np.int32)          # int32 is twice as fast, and 9 digits is plenty
    digits = np.zeros(n, dtype=np.int32)
    head = np.ones(n, dtype=bool)                            # before the first '/' (and the end)
    negative = np.zeros(n, dtype=bool)
    for j, c in enumerate(cols):
        if j == 0:
            negative = c == _MINUS
        d = c - np.uint8(48)
        is_digit = (d < 10) & head
        head &= (c != _SLASH) & (c != 0)
        if not np.all(is_digit | ~head | (negative & (j == 0))):
            return None
        value = np.where(is_digit, value * 10 + d.astype(np.int32), value)
        digits += is_digit
        if not head.any():
            break                                             # texture and normal indices: unread
    if np.any(digits == 0) or np.any(digits > 9):
        return None
    return np.where(negative, -value, value).astype(np.int64)


@dataclass(frozen=True)
class ObjBlocks:
    """Where an OBJ's one run of ``v`` lines and one run of ``f`` lines lie (``obj_blocks``).

    Counted before anything is parsed, so limits are checked first, as for ``ObjLayout``.
    """

    data: bytes
    v_start: int
    v_end: int
    f_start: int
    f_end: int
    vertices: int
    faces: int          # ``f`` lines
    corners: int        # corners of every face
    slashes: int        # '/' in each corner word: 0 (``i``), 1 (``i/t``) or 2 (``i//n``, ``i/t/n``)
    groups: int

    @property
    def triangles(self) -> int:
        return self.faces * (self.corners - 2)


def _runs(data: bytes, keywords: tuple[bytes, ...]) -> list[tuple[int, int, int] | None]:
    """For each one-letter keyword: the bytes from the first line starting with it and a blank to
    the end of the last one (its line end included), and the number of those lines; None when
    there is no such line or a line of another kind (or a blank one) lies between them.

    Only the first two bytes of each line are gathered (not a lines x 2 index array): 2.7 against
    4.9 ms on the bench's 3.8 MB file.
    """
    a = np.frombuffer(data, dtype=np.uint8)
    n = len(a)
    starts = np.flatnonzero(a[:-1] == _NEWLINE) + 1          # every line's start but the first (0)
    first_byte = np.concatenate((a[:1], a[starts]))
    second_byte = np.zeros(len(first_byte), dtype=np.uint8)   # 0 where a line is its last byte
    if n > 1:
        second_byte[0] = a[1]
    after = starts + 1
    inside = after < n
    second_byte[1:][inside] = a[after[inside]]
    found: list[tuple[int, int, int] | None] = []
    for keyword in keywords:
        lines = np.flatnonzero((first_byte == keyword[0]) & (second_byte == 32))
        if not len(lines) or lines[-1] - lines[0] + 1 != len(lines):
            found.append(None)
            continue
        first = int(starts[lines[0] - 1]) if lines[0] else 0
        end = int(starts[lines[-1]]) if lines[-1] < len(starts) else n
        found.append((first, end, len(lines)))
    return found


def obj_blocks(data: bytes, drop_materials: bool) -> ObjBlocks | None:
    """The runs of a file laid out as one ``v`` run then one ``f`` run, or None (see the module doc).

    Every other line must be one ``obj_layout`` takes and reads as neither vertex nor face (a
    comment, ``vt``, ``vn``, ``g``, ...): checked by ``obj_layout`` on those lines alone. Corner
    words are counted, and their ``/`` too, on the first face line: every other line must match it
    (``read_obj_blocks`` checks).
    """
    if not data:
        return None
    v, f = _runs(data, (b"v", b"f"))
    if v is None or f is None or v[1] > f[0]:
        return None                          # vertices after faces: relative references differ
    rest = data[:v[0]] + data[v[1]:f[0]] + data[f[1]:]
    groups = 0
    if rest:
        layout = obj_layout(rest, drop_materials)
        if layout is None or layout.vertices or len(layout.f_first):
            return None
        groups = layout.groups
    line_end = data.find(b"\n", f[0], f[1])
    words = data[f[0]:f[1] if line_end < 0 else line_end].rstrip(b"\r").split(b" ")[1:]
    slashes = words[0].count(b"/") if words else 0
    if len(words) < 3 or slashes > 2:
        return None
    return ObjBlocks(data, v[0], v[1], f[0], f[1], vertices=v[2], faces=f[2], corners=len(words),
                     slashes=slashes, groups=groups)


def _uniform_corners(run: np.ndarray, faces: int, corners: int, slashes: int) -> bool:
    """Whether every line of a face run is ``f``, a blank, then ``corners`` words of ``slashes``
    slashes each, one blank between them: its blanks, slashes and line ends, in byte order, repeat
    one line's pattern exactly (a line's last word ends at its line end or the run's end).

    What makes a corner's vertex reference a fixed column once each '/' is a blank: the words'
    first fields. (A line of the same width but other words, ``1/2/3/4 5 6/7`` against
    ``1/2 3/4 5/6``, would put other numbers in those columns.)

    Shapes:
        run (n,) uint8, the run's bytes.
    """
    tokens = run[np.flatnonzero((run == 32) | (run == _NEWLINE) | (run == _SLASH))]
    pattern = np.concatenate((np.full(1, 32, np.uint8),
                              np.tile(np.concatenate((np.full(slashes, _SLASH, np.uint8), [32])), corners)))
    pattern[-1] = _NEWLINE
    if len(tokens) == faces * len(pattern) - 1 and run[-1] != _NEWLINE:
        tokens = np.concatenate((tokens, [_NEWLINE]))
    return len(tokens) == faces * len(pattern) and bool(np.all(tokens.reshape(faces, -1) == pattern))


# Blocks a run is cut into for Arrow's reader (its threads parse blocks in parallel), and the
# smallest block worth its own task.
_BLOCKS_PER_RUN = 4
_MIN_BLOCK = 1 << 16


def _read_run(run: bytes | memoryview, rows: int, fields: int, used: list[int],
              kind: pa.DataType) -> np.ndarray | None:
    """The ``used`` fields (1 is the first after the keyword) of one run of lines, each a keyword
    then ``fields`` fields one blank apart, as numbers; or None.

    Shapes:
        -> (rows, len(used)).
    """
    names = [f"c{j}" for j in range(fields + 1)]
    try:
        table = pa_csv.read_csv(
            pa.py_buffer(run),
            # Arrow's threads on a few blocks per run: 2.5 and 3.4 ms for the bench file's two runs,
            # against 6.7 and 8.8 in one block on one thread and 3.9 and 5.3 in one block on
            # threads (whose columns convert in parallel), measured in the same hour. The work is
            # the same; under load the server's other worker has the other core anyway.
            read_options=pa_csv.ReadOptions(column_names=names, use_threads=True,
                                            block_size=max(len(run) // _BLOCKS_PER_RUN + 1, _MIN_BLOCK)),
            # No quoting, no escapes: a '"' is a byte like any other (and no number).
            parse_options=pa_csv.ParseOptions(delimiter=" ", quote_char=False, escape_char=False,
                                              ignore_empty_lines=False),
            # No null spellings: an empty field or "NA" is not a number, so the file goes on.
            convert_options=pa_csv.ConvertOptions(
                column_types={names[j]: kind for j in used}, include_columns=[names[j] for j in used],
                null_values=[], strings_can_be_null=False))
    except pa.ArrowException:
        return None
    if table.num_rows != rows or any(col.null_count for col in table.columns):
        return None                          # a lone CR splits a line for the reader, not for the count
    return np.stack([col.to_numpy() for col in table.columns], axis=1)


def read_obj_blocks(blocks: ObjBlocks) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertices some face uses and the triangles of a file ``obj_blocks`` laid out, or None
    (the numpy reader then runs). The same surface as ``read_plain_obj`` reads.

    The runs are parsed by ``service.geometry.mesh_kernel`` when they are in its spelling (most
    files), else by Arrow's reader: there corners with texture or normal references (``i/t``,
    ``i//n``, ``i/t/n``) are read with every '/' made a blank (``i//n`` then has an empty middle
    field): each corner is ``slashes + 1`` fields, the first its vertex reference, the others not
    read (as the numpy reader does not). Both read the same numbers.

    Shapes:
        returns vertices (V, 3) float64, faces (F, 3) int64 indexing them.
    """
    parsed = _compiled_runs(blocks) or _arrow_runs(blocks)
    if parsed is None:
        return None
    vertices, refs = parsed
    # Every vertex line precedes every face: a relative reference counts back from the last.
    corners = _vertex_indices(refs, len(vertices), len(vertices))
    if corners is None:
        return None
    counts = np.full(len(corners), blocks.corners, dtype=np.int64)
    return _used_surface(np.ascontiguousarray(vertices, dtype=np.float64), _fans(corners.ravel(), counts))


def _compiled_runs(blocks: ObjBlocks) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertex and face runs read by ``service.geometry.mesh_kernel`` (the most common spelling,
    4x faster than Arrow's reader), or None for anything it does not take.

    Shapes:
        -> vertices (V, 3) float64, references (F, corners) int64.
    """
    a = np.frombuffer(blocks.data, dtype=np.uint8)
    vertices = np.empty((blocks.vertices, 3))
    refs = np.empty((blocks.faces, blocks.corners), dtype=np.int64)
    if not mesh_kernel.read_vertices(a, blocks.v_start, blocks.v_end, vertices):
        return None
    if not mesh_kernel.read_faces(a, blocks.f_start, blocks.f_end, blocks.slashes, refs):
        return None
    return vertices, refs


def _arrow_runs(blocks: ObjBlocks) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertex and face runs read by Arrow's CSV reader, or None.

    Shapes:
        -> vertices (V, 3) float64, references (F, corners) int64.
    """
    data = blocks.data
    vertices = _read_run(memoryview(data)[blocks.v_start:blocks.v_end], blocks.vertices, 3, [1, 2, 3],
                         pa.float64())
    if vertices is None or not np.isfinite(vertices).all():
        return None                          # 'nan', 'inf': words the numpy reader does not take
    k, per = blocks.corners, blocks.slashes + 1
    run: bytes | memoryview = memoryview(data)[blocks.f_start:blocks.f_end]
    if blocks.slashes:
        if not _uniform_corners(np.frombuffer(run, dtype=np.uint8), blocks.faces, k, blocks.slashes):
            return None
        run = data[blocks.f_start:blocks.f_end].replace(b"/", b" ")
    elif data.find(b"/", blocks.f_start, blocks.f_end) >= 0:
        return None                          # the first line plain, another not
    refs = _read_run(run, blocks.faces, k * per, [1 + j * per for j in range(k)], pa.int64())
    if refs is None:
        return None
    return vertices, refs
