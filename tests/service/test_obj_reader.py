"""The fast OBJ reader (``service.geometry.obj``): the surface trimesh reads, for the files it takes.

trimesh is the reference: every plain file below must give the same triangles (as coordinates)
through the fast readers as through trimesh's own OBJ loader, and every file the readers do not
take must go back to trimesh's path, so that its refusals and errors stay what they were. The
block reader (``obj_blocks``) takes a subset of what the numpy reader (``obj_layout``) takes, and
where it takes a file it reads the surface the numpy reader reads.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geometry.mesh import MeshError, load_mesh_surface, sample_surface
from service.geometry.obj import (
    _arrow_runs,
    _compiled_runs,
    _numbers,
    obj_blocks,
    obj_layout,
    read_obj_blocks,
    read_plain_obj,
)

MAX = 1_000_000


def fast(text: bytes, drop_materials: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    layout = obj_layout(text, drop_materials)
    return None if layout is None else read_plain_obj(layout)


def blocks(text: bytes, drop_materials: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    found = obj_blocks(text, drop_materials)
    return None if found is None else read_obj_blocks(found)


def same_or_left(text: bytes, drop_materials: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """The block reader's surface, checked to be the numpy reader's wherever it takes the file."""
    read = blocks(text, drop_materials)
    if read is not None:
        numpy_read = fast(text, drop_materials)
        assert numpy_read is not None, "the block reader took a file the numpy reader leaves to trimesh"
        assert np.array_equal(read[1], numpy_read[1])
        # Correctly rounded (Arrow) against within a few ulps (numpy, exponents, 16+ digits).
        assert np.allclose(read[0], numpy_read[0], rtol=1e-14, atol=0)
    return read


def trimesh_mesh(text: bytes) -> trimesh.Trimesh:
    mesh = trimesh.load(io.BytesIO(text), file_type="obj", process=False, force="mesh", skip_materials=True)
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


def trimesh_triangles(text: bytes) -> np.ndarray:
    """trimesh's reading, as each triangle's corners sorted: (F, 9), rows sorted."""
    mesh = trimesh_mesh(text)
    return _canonical(np.asarray(mesh.vertices)[np.asarray(mesh.faces)])


def _canonical(tris: np.ndarray) -> np.ndarray:
    """Triangles (F, 3, 3) as rows of their corners in sorted order, the rows sorted: an order-free form."""
    point = [("x", tris.dtype), ("y", tris.dtype), ("z", tris.dtype)]
    corners = np.sort(np.ascontiguousarray(tris).view(point).reshape(len(tris), 3), axis=1)
    rows = corners.view(tris.dtype).reshape(len(tris), 9)
    return rows[np.lexsort(rows.T[::-1])]


QUAD_FAN = b"""# a cube of quads, a pentagon, groups, smoothing, texture and normal data
o box
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
vt 0 0
vt 1 0
vt 1 1
vn 0 0 1
g bottom
s off
f 1 4 3 2
g top
f 5/1 6/2 7/3 8/1
g sides
f 1//1 2//1 6//1 5//1
f 2/1/1 3/2/1 7/3/1 6/1/1
v 2 0 0
v 3 0 0.5
v 3 1 1
v 2.5 1.5 1.25
v 2 1 1
f -5 -4 -3 -2 -1
"""

PLAIN = {
    "triangles": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\n",
    "quads, polygons, references": QUAD_FAN,
    "crlf and tabs": b"v 0\t0 0\r\nv 1\t0 0\r\nv 0 1 0\r\n\r\nf 1 2\t3\r\n",
    "signs and dots": b"v -.5 +1.25 3.\nv 1e2 -2.5E-1 0\nv 0.125 1 -0\nf 1 2 3\n",
    "materials dropped": b"mtllib parts.mtl\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemap x\nf 1 2 3\n",
    "unused vertices": b"v 9 9 9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 7 7 7\nf 2 3 4\n",
    "no final newline": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3",
}
# The files of PLAIN the block reader takes (the others go on to the numpy reader).
IN_BLOCKS = {"triangles", "signs and dots", "materials dropped", "unused vertices", "no final newline",
             "corner forms", "corner forms, crlf, quads"}
PLAIN.update({
    "corner forms": (b"o thing\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvt 1 0\nvn 0 0 1\n"
                     b"s off\nf 1/1/1 2/2/1 3/1/1\nf -4/1/1 -2/2/1 -1/1/1\n"),
    "corner forms, crlf, quads": (b"v 0 0 0\r\nv 1 0 0\r\nv 1 1 0\r\nv 0 1 0\r\nv 0 0 1\r\nvn 0 0 1\r\n"
                                  b"f 1//1 2//1 3//1 4//1\r\nf 1//1 2//1 5//1 4//1"),
})


@pytest.mark.parametrize("name", list(PLAIN))
def test_plain_files_read_as_trimesh_reads_them(name: str) -> None:
    text = PLAIN[name]
    read = fast(text)
    assert read is not None, "the fast reader should take this file"
    vertices, faces = read
    assert faces.dtype == np.int64 and faces.min() >= 0 and faces.max() < len(vertices)
    assert np.unique(faces).size == len(vertices)            # only the vertices a face uses
    assert np.array_equal(_canonical(vertices[faces]), trimesh_triangles(text))
    assert (same_or_left(text) is not None) == (name in IN_BLOCKS)


LEFT_TO_NUMPY = {
    "corner forms mixed": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nf 1/1 2/1 3/1\nf 1 3 4\n",
    "as wide, other words": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 1 1 1\nv 2 2 2\nv 3 3 3\nvt 0 0\n"
                             b"vt 1 1\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1\nf 4/1/1/1 5 6/1/1\n"),
    "triangles and quads": b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 2 3 4\n",
    "a group between faces": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\ng a\nf 1 2 3\ng b\nf 1 3 4\n",
    "vertices between faces": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nv 0 0 1\nf 1 3 4\n",
    "a blank line among vertices": b"v 0 0 0\n\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "two blanks": b"v 0  0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "a tab": b"v 0 0\t0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "a blank at a line's end": b"v 0 0 0 \nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
}


@pytest.mark.parametrize("name", list(LEFT_TO_NUMPY))
def test_files_the_block_reader_leaves_are_read_by_the_next_reader(name: str) -> None:
    text = LEFT_TO_NUMPY[name]
    assert blocks(text) is None
    assert fast(text) is not None
    surface = load_mesh_surface(text, "obj", max_vertices=MAX, max_faces=MAX)
    assert np.array_equal(_canonical(surface.vertices[surface.faces]), trimesh_triangles(text))


def test_corners_of_two_slashes_are_read_alike_whatever_lies_between() -> None:
    """``i//n`` and ``i/t/n`` both put the vertex reference first: a line mixing them reads as the
    numpy reader reads it."""
    text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf 1/1/1 2//1 3/1/1\n"
    read = same_or_left(text)
    assert read is not None and read[0][read[1]].tolist() == [[[0, 0, 0], [1, 0, 0], [0, 1, 0]]]


def test_a_large_exported_mesh_reads_exactly_as_trimesh_reads_it() -> None:
    """A trimesh-written OBJ (one group, triangles): the same vertices and faces in the same order,
    so an upload samples the same points whichever reader took it."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    sphere.vertices *= np.array([310.25, 120.5, 77.125])     # caller units, not a unit sphere
    text = trimesh.exchange.obj.export_obj(sphere).encode()
    mesh = trimesh_mesh(text)
    for read in (fast(text), same_or_left(text)):
        assert read is not None
        assert np.array_equal(read[0][read[1]], np.asarray(mesh.vertices)[np.asarray(mesh.faces)])
    surface = load_mesh_surface(text, "obj", max_vertices=MAX, max_faces=MAX)
    ours = sample_surface(surface.vertices, surface.faces, 512, seed=3, areas=surface.areas)
    theirs = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), 512, seed=3)
    assert np.array_equal(ours, theirs)


NOT_PLAIN = {
    "a tab after the keyword": b"v\t0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "leading blanks": b"  v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "line continuation": b"v 0 0 \\\n0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "vertex colours": b"v 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 0 1 0 1 0 0\nf 1 2 3\n",
    "polyline": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\nf 1 2 3\n",
    "unknown keyword": b"v 0 0 0\nv 1 0 0\nv 0 1 0\ncurv 0 1 1 2\nf 1 2 3\n",
    "not a number": b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "hex": b"v 0x1 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "two dots": b"v 1.2.3 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "reference out of range": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
    "reference zero": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
    "relative before the first vertex": b"v 0 0 0\nv 1 0 0\nf -1 -2 -3\nv 0 1 0\n",
    "a face of two corners": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n",
    "lone carriage returns": b"v 0 0 0\rv 1 0 0\rv 0 1 0\rf 1 2 3\r",
    "control byte": b"v 0 0 0\x00\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "shell call": b"v 0 0 0\nv 1 0 0\nv 0 1 0\ncsh rm -rf x\nf 1 2 3\n",
    "no faces": b"v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "empty": b"",
    "a quoted number": b'v "0" 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n',
    "infinity": b"v inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
}


@pytest.mark.parametrize("name", list(NOT_PLAIN))
def test_other_files_are_left_to_trimesh(name: str) -> None:
    assert fast(NOT_PLAIN[name]) is None
    assert blocks(NOT_PLAIN[name]) is None


def test_material_library_goes_to_trimesh_unless_dropped() -> None:
    text = PLAIN["materials dropped"]
    assert fast(text, drop_materials=False) is None
    assert blocks(text, drop_materials=False) is None
    with pytest.raises(MeshError) as err:          # trimesh's path refuses the external file, as before
        load_mesh_surface(text, "obj", name="m.obj", max_vertices=MAX, max_faces=MAX)
    assert err.value.code == "external_reference"


@pytest.mark.parametrize("text, code", [
    (b"v 1e999 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "non_finite"),
    (b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "zero_area"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "corrupt_mesh"),
])
def test_unusable_plain_files_get_trimesh_paths_errors(text: bytes, code: str) -> None:
    with pytest.raises(MeshError) as err:
        load_mesh_surface(text, "obj", name="m.obj", max_vertices=MAX, max_faces=MAX)
    assert err.value.code == code and "m.obj" in str(err.value)


def test_limits_are_checked_on_the_counted_lines() -> None:
    text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3 4\n"           # a quad: two triangles
    assert fast(text) is not None and blocks(text) is not None
    with pytest.raises(MeshError) as err:
        load_mesh_surface(text, "obj", name="m.obj", max_vertices=3, max_faces=10)
    assert err.value.code == "too_large" and "vertices" in str(err.value)
    with pytest.raises(MeshError) as err:
        load_mesh_surface(text, "obj", name="m.obj", max_vertices=10, max_faces=1)
    assert err.value.code == "too_large" and "faces" in str(err.value)


def test_numbers_read_as_float_reads_them() -> None:
    """Decimals of up to 15 significant digits: exactly ``float()``; with exponents: within 2 ulps."""
    rng = np.random.default_rng(0)
    words = []
    for _ in range(3000):
        whole = str(int(rng.integers(0, 10 ** int(rng.integers(1, 8)))))
        frac = "".join(map(str, rng.integers(0, 10, size=int(rng.integers(0, 8)))))
        sign = str(rng.choice(["", "-", "+"]))
        words.append(f"{sign}{whole}.{frac}" if frac or rng.random() < 0.5 else f"{sign}{whole}")
    scientific = [f"{x:.{int(rng.integers(1, 12))}e}" for x in rng.normal(scale=1e3, size=1000)]
    for batch, exact in ((words, True), (scientific, False)):
        rows = [" ".join(batch[i:i + 3]) for i in range(0, len(batch) - 2, 3)]
        text = ("".join(f"v {r}\n" for r in rows) + "f 1 2 3\n").encode()
        layout = obj_layout(text, True)
        assert layout is not None
        got = _numbers(layout, (layout.v_first[:, None] + np.arange(3)).ravel())
        assert got is not None
        want = np.array([float(w) for r in rows for w in r.split()])
        if exact:
            assert np.array_equal(got, want)
        else:
            assert np.all(np.abs(got - want) <= 2 * np.spacing(np.abs(want)))


# -- generated files ------------------------------------------------------------------------------

_FUZZ = settings(max_examples=60, deadline=None)


@st.composite
def plain_objs(draw: st.DrawFn) -> bytes:
    """A random plain OBJ: random vertices written in a random number format, random polygons in
    a random corner form (absolute or relative references), comments, groups and blank lines."""
    n = draw(st.integers(3, 12))
    coords = draw(st.lists(st.floats(-1e3, 1e3, allow_nan=False, width=32), min_size=3 * n, max_size=3 * n))
    style = draw(st.sampled_from(["{:.6f}", "{:.3g}", "{:.4e}", "{}"]))
    lines = [f"v {' '.join(style.format(c) for c in coords[3 * i:3 * i + 3])}" for i in range(n)]
    # One corner form per file, as tools write them (trimesh misreads some mixes of forms).
    form = draw(st.sampled_from(["{}", "{}/1", "{}//1", "{}/1/1"]))
    for _ in range(draw(st.integers(1, 6))):
        k = draw(st.integers(3, min(6, n)))
        corners = draw(st.lists(st.integers(0, n - 1), min_size=k, max_size=k, unique=True))
        relative = draw(st.booleans())
        lines.append("f " + " ".join(form.format(c - n if relative else c + 1) for c in corners))
        if draw(st.booleans()):
            lines.append(draw(st.sampled_from(["# note", "g part", "o thing", "s 1", "", "vt 0.5 0.5",
                                               "vn 0 0 1"])))
    end = draw(st.sampled_from(["\n", "\r\n"]))
    return (end.join(lines) + end).encode()


@_FUZZ
@given(plain_objs())
def test_generated_plain_files_read_as_trimesh_reads_them(text: bytes) -> None:
    read = fast(text)
    assert read is not None
    vertices, faces = read
    # Exponents and 16-17 significant digits are read to within a few ulps of strtod.
    assert np.allclose(_canonical(vertices[faces]), trimesh_triangles(text), rtol=1e-14, atol=0)
    same_or_left(text)


@_FUZZ
@given(plain_objs(), st.data())
def test_damaged_files_get_a_surface_or_a_mesh_error(text: bytes, data: st.DataObject) -> None:
    """Bytes changed, cut or repeated anywhere: a surface or a ``MeshError``, never another error."""
    raw = bytearray(text)
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(raw) - 1))
        how = data.draw(st.sampled_from(["byte", "cut", "repeat"]))
        if how == "byte":
            raw[at] = data.draw(st.sampled_from(list(b"0123456789-+.eE/ \t\r\n#vfgx\\\x00\xff")))
        elif how == "cut":
            del raw[at:at + data.draw(st.integers(1, 8))]
        else:
            raw[at:at] = raw[max(0, at - 8):at]
        if not raw:
            return
    try:
        surface = load_mesh_surface(bytes(raw), "obj", name="m.obj", max_vertices=MAX, max_faces=MAX)
    except MeshError:
        return
    assert np.isfinite(surface.vertices).all() and surface.areas.sum() > 0
    assert surface.faces.min() >= 0 and surface.faces.max() < len(surface.vertices)


def test_relative_references_count_back_from_their_face() -> None:
    """As the OBJ format says (trimesh counts from the file's last vertex: both triangles would be
    the second one)."""
    text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf -3 -2 -1\n"
    read = fast(text)
    assert read is not None
    vertices, faces = read
    assert vertices[faces].tolist() == [[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[5, 5, 5], [6, 5, 5], [5, 6, 5]]]


# -- the compiled reader of the block layout -------------------------------------------------------


Runs = tuple[np.ndarray, np.ndarray] | None


def _both_runs(text: bytes) -> tuple[Runs, Runs]:
    found = obj_blocks(text, True)
    assert found is not None
    return _compiled_runs(found), _arrow_runs(found)


def test_the_compiled_reader_reads_what_arrow_reads() -> None:
    """Plain decimals (signs, leading zeros, up to 15 significant digits) and every corner form,
    LF and CRLF: the same numbers as Arrow's reader, and as ``float()``."""
    rng = np.random.default_rng(1)
    for form in ("{}", "{}/7", "{}//7", "{}/7/7", "{}/"):
        for end in ("\n", "\r\n"):
            words = []
            for _ in range(300):
                zeros = "0" * int(rng.integers(0, 3))
                whole = zeros + str(int(rng.integers(0, 10 ** int(rng.integers(1, 8)))))
                frac = "".join(map(str, rng.integers(0, 10, size=int(rng.integers(1, 8)))))
                sign = str(rng.choice(["", "-", "+"]))
                words.append(f"{sign}{whole}.{frac}" if rng.random() < 0.8 else f"{sign}{whole}")
            rows = [" ".join(words[i:i + 3]) for i in range(0, len(words), 3)]
            faces = [" ".join(form.format(int(c)) for c in rng.integers(1, len(rows) + 1, size=3))
                     for _ in range(50)]
            text = end.join([f"v {r}" for r in rows] + [f"f {f}" for f in faces]).encode() + end.encode()
            compiled, arrow = _both_runs(text)
            assert compiled is not None and arrow is not None, (form, end)
            assert np.array_equal(compiled[0], arrow[0]) and np.array_equal(compiled[1], arrow[1])
            assert np.array_equal(compiled[0].ravel(), [float(w) for r in rows for w in r.split()])


@pytest.mark.parametrize("vertex", [b"v 1e-3 0 0", b"v 0.1234567890123456 0 0", b"v 1. 0 0", b"v .5 0 0",
                                    b"v 0\t0 0", b"v 0  0 0", b"v 0 0 0 ", b"v 0 0", b"v 0 0 0 1",
                                    b"v nan 0 0"])
def test_the_compiled_reader_leaves_other_spellings_to_arrow(vertex: bytes) -> None:
    text = vertex + b"\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    found = obj_blocks(text, True)
    if found is not None:
        assert _compiled_runs(found) is None
    # Whatever reads it, the surface is the one the readers behind agree on.
    same_or_left(text)


@pytest.mark.parametrize("face", [b"f 1 2 3 ", b"f 1 2 3/1", b"f 1  2 3", b"f 1 2", b"f 1 2 x", b"f +1 2 3"])
def test_the_compiled_reader_leaves_other_faces_to_arrow(face: bytes) -> None:
    found = obj_blocks(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + face + b"\n", True)
    if found is not None:
        assert _compiled_runs(found) is None
