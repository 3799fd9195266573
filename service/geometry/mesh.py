"""Safe mesh loading, surface sampling and frame normalisation (torch-free, pure functions).

Shared by the HTTP service (mesh uploads) and by the trainer's ingest, so that both read a file
the same way and refuse the same things. Untrusted bytes must never make the loader touch other
files or the network: glTF/GLB buffers and images must be embedded ``data:`` URIs, OBJ material
libraries are refused (or dropped on request), PLY texture files are refused, and trimesh gets a
resolver that refuses every lookup. Declared element counts in PLY/OFF/STL/glTF headers are
checked against the limits before trimesh allocates anything.

Every failure is a ``MeshError`` whose ``code`` is one of ``MESH_ERROR_CODES`` and whose message
names the file (or ``"upload"``).
"""

from __future__ import annotations

import io
import json
import logging
import re
import struct
from functools import lru_cache
from typing import Any, NamedTuple

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as _cc
from trimesh.resolvers import Resolver

from service.geometry import mesh_kernel
from service.geometry.obj import ObjBlocks, ObjLayout, obj_blocks, obj_layout, read_obj_blocks, read_plain_obj

log = logging.getLogger(__name__)

MESH_FORMATS = ("obj", "ply", "stl", "off", "glb", "gltf")
MESH_ERROR_CODES = (
    "unsupported_format",  # not one of MESH_FORMATS
    "corrupt_mesh",        # the bytes do not parse as the declared format
    "empty_mesh",          # no triangles (or no points)
    "non_finite",          # NaN or infinite coordinates
    "zero_area",           # triangles present but all degenerate
    "degenerate",          # all points coincide: no frame can be normalised
    "external_reference",  # the file refers to another file or a URL
    "too_large",           # more vertices or faces than the configured limits
)


# Defaults of the structure limits (settings max_mesh_nodes, max_mesh_nesting): a scene's nodes and
# drawn instances, and the nesting of a glTF's JSON and of its node tree. Both are checked on the
# raw file, before trimesh builds a scene: a 4 KB glTF nested 2,000 deep crashed the JSON reader
# (RecursionError, a 500), and GLBs of 2 MB (100k instancing nodes) or 0.9 MB (a 40k-deep node
# chain) took trimesh 28 s and 34 s of CPU to build before their counts were checked.
MAX_NODES = 10_000
MAX_NESTING = 64


class MeshError(ValueError):
    """A mesh or point set that cannot be used; ``code`` says why (see ``MESH_ERROR_CODES``)."""

    def __init__(self, code: str, message: str):
        assert code in MESH_ERROR_CODES, f"unknown mesh error code {code!r}"
        super().__init__(message)
        self.code = code
        self.message = message


class SceneLeaf(NamedTuple):
    """One scene-graph leaf (or connected component) in the file's world frame.

    Shapes:
        vertices: (V, 3) float64; faces: (F, 3) int64.
    """

    name: str
    # Name of the geometry the leaf instances (leaves sharing it are copies of one mesh).
    geometry: str
    vertices: np.ndarray
    faces: np.ndarray


class _RefusingResolver(Resolver):
    """A trimesh resolver that refuses every lookup and remembers what was asked for.

    trimesh swallows some resolver errors (e.g. for textures), so the caller checks ``asked``
    after loading as well.
    """

    def __init__(self, name: str):
        self.name = name
        self.asked: list[str] = []

    def get(self, key: str) -> bytes:
        self.asked.append(str(key))
        raise MeshError("external_reference", f"{self.name}: refers to an external file {key!r}; "
                        "only self-contained files are accepted")

    def write(self, name: str, data: Any) -> None:
        raise MeshError("external_reference", f"{self.name}: loader tried to write {name!r}")

    def namespaced(self, namespace: str) -> _RefusingResolver:
        return self

    def keys(self) -> list[str]:
        return []


# --------------------------------------------------------------------------------------------
# Header checks, done on the raw bytes before trimesh sees them.


def _check_count(name: str, what: str, count: int, limit: int) -> None:
    if count < 0:
        raise MeshError("corrupt_mesh", f"{name}: negative {what} count {count} in header")
    if count > limit:
        raise MeshError("too_large", f"{name}: declares {count} {what}, more than the limit of {limit}")


_PLY_TYPE_BYTES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2,
                   "uint16": 2, "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4,
                   "double": 8, "float64": 8}


def _check_ply_header(data: bytes, name: str, max_vertices: int, max_faces: int) -> None:
    """Refuse external textures, counts over the limits, and counts the file's bytes cannot hold.

    Every element (not only vertices and faces: an ``element edge 1000000000000`` counts too)
    must fit in the bytes after the header: at least its smallest row size (binary) or two
    bytes per row (ASCII) times its count.
    """
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshError("corrupt_mesh", f"{name}: not a PLY file (no 'ply' magic or 'end_header')")
    newline = data.find(b"\n", end)
    body = len(data) - (newline + 1 if newline >= 0 else len(data))
    binary = True
    elements: list[list[Any]] = []  # [name, count, smallest row size in bytes]
    for raw in data[:end].decode("ascii", errors="replace").splitlines():
        tokens = raw.split()
        if len(tokens) >= 2 and tokens[0] == "comment" and tokens[1].lower() == "texturefile":
            ref = " ".join(tokens[2:])
            raise MeshError("external_reference", f"{name}: refers to an external texture file {ref!r}; "
                            "only self-contained files are accepted")
        if len(tokens) >= 2 and tokens[0] == "format":
            binary = tokens[1] != "ascii"
        elif len(tokens) == 3 and tokens[0] == "element":
            try:
                count = int(tokens[2])
            except ValueError as err:
                raise MeshError("corrupt_mesh", f"{name}: bad PLY element line {raw!r}") from err
            if tokens[1] == "vertex":
                _check_count(name, "vertices", count, max_vertices)
            elif tokens[1] == "face":
                _check_count(name, "faces", count, max_faces)
            elif count < 0:
                raise MeshError("corrupt_mesh", f"{name}: negative {tokens[1]} count {count} in header")
            elements.append([tokens[1], count, 0])
        elif tokens and tokens[0] == "property" and elements:
            # "property float x", or "property list uchar int vertex_indices": a list row holds at
            # least its length.
            is_list = len(tokens) >= 3 and tokens[1] == "list"
            size = _PLY_TYPE_BYTES.get(tokens[2] if is_list else (tokens[1] if len(tokens) >= 2 else ""))
            if size is None:
                raise MeshError("corrupt_mesh", f"{name}: unknown PLY property type in {raw!r}")
            elements[-1][2] += size
    for element, count, row in elements:
        least = count * (max(row, 1) if binary else 2)
        if least > body:
            raise MeshError("corrupt_mesh", f"{name}: declares {count} {element} element(s), which need at "
                            f"least {least} bytes; only {body} follow the header")


def _check_off_header(data: bytes, name: str, max_vertices: int, max_faces: int) -> None:
    tokens: list[str] = []
    for raw in data[:4096].decode("ascii", errors="replace").splitlines():
        tokens.extend(raw.split("#", 1)[0].split())
        if len(tokens) >= 4:
            break
    # ModelNet's files glue the counts to the keyword ("OFF490 972 0"), so split them off.
    head = re.match(r"^([A-Z0-9]*OFF)(\d*)$", tokens[0]) if tokens else None
    if head is None:
        raise MeshError("corrupt_mesh", f"{name}: not an OFF file (no 'OFF' header)")
    counts = ([head.group(2)] if head.group(2) else []) + tokens[1:]
    try:
        nv, nf = int(counts[0]), int(counts[1])
    except (ValueError, IndexError) as err:
        raise MeshError("corrupt_mesh", f"{name}: bad OFF header, expected vertex and face counts") from err
    _check_count(name, "vertices", nv, max_vertices)
    _check_count(name, "faces", nf, max_faces)


def _check_stl_header(data: bytes, name: str, max_vertices: int, max_faces: int) -> None:
    binary_count = struct.unpack("<I", data[80:84])[0] if len(data) >= 84 else None
    if binary_count is not None and 84 + 50 * binary_count == len(data):
        _check_count(name, "faces", binary_count, max_faces)  # binary STL: the count is exact
    elif data.lstrip()[:5].lower() == b"solid":  # ASCII STL (binary headers may also say "solid")
        _check_count(name, "faces", data.count(b"facet normal"), max_faces)
    elif binary_count is None:
        raise MeshError("corrupt_mesh", f"{name}: not an STL file (neither binary nor ASCII 'solid')")
    else:
        _check_count(name, "faces", binary_count, max_faces)
        if 84 + 50 * binary_count > len(data):
            raise MeshError("corrupt_mesh", f"{name}: truncated binary STL ({binary_count} triangles "
                            f"declared, {len(data)} bytes)")


_OBJ_REFUSED = ("mtllib", "maplib", "call", "csh")
_OBJ_MATERIAL = ("mtllib", "usemtl", "maplib", "usemap")


# ASCII whitespace, as bytes.split() and bytes.lstrip() see it.
_WHITESPACE = np.zeros(256, dtype=bool)
_WHITESPACE[list(b" \t\n\r\x0b\x0c")] = True


def _prepare_obj(data: bytes, name: str, max_vertices: int, max_faces: int,
                 ignore_materials: bool, max_nodes: int = MAX_NODES) -> bytes:
    """Refuse OBJ directives that pull in other files; count vertices, faces, groups and objects.

    Each line's first word is its keyword. The words are found by numpy over the bytes, not by a
    Python loop over the lines (a 100k-triangle OBJ has 150k lines): only lines whose keyword
    could be a material or external-file directive are looked at one by one.
    """
    text = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")  # the line ends bytes.splitlines() knows
    arr = np.frombuffer(text + b"\n", dtype=np.uint8)  # a final newline: every line ends in one
    ws = _WHITESPACE[arr]
    newline = np.flatnonzero(arr == 10)
    word = np.flatnonzero(~ws & np.concatenate([[True], ws[:-1]]))      # where each word starts
    line_of = np.searchsorted(newline, word)                            # its line (newlines before it)
    first = np.concatenate([[True], line_of[1:] != line_of[:-1]]) if len(word) else np.zeros(0, bool)
    start = word[first]                                                 # each non-blank line's keyword
    words = np.bincount(line_of, minlength=len(newline) + 1)[line_of[first]]
    spaces = np.flatnonzero(ws)
    after = np.searchsorted(spaces, start)
    end = np.where(after < len(spaces), spaces[np.minimum(after, len(spaces) - 1)], len(arr))
    one = (end - start) == 1
    letter = arr[start]
    n_vertices = int(np.count_nonzero(one & (letter == ord("v"))))
    faces = one & (letter == ord("f"))
    n_faces = int(np.maximum(1, words[faces] - 3).sum())  # a polygon of k corners is k - 2 triangles
    n_groups = int(np.count_nonzero(one & ((letter == ord("g")) | (letter == ord("o")))))  # scene nodes
    dropped: list[int] = []  # lines of material directives (dropped when ignore_materials)
    for k in np.flatnonzero(np.isin(end - start, [len(w) for w in (*_OBJ_REFUSED, *_OBJ_MATERIAL)])).tolist():
        keyword = text[start[k]:end[k]].decode("ascii", errors="replace")
        if ignore_materials and keyword in _OBJ_MATERIAL:
            dropped.append(int(line_of[first][k]))  # never handed to the loader, so nothing is looked up
        elif keyword in _OBJ_REFUSED:
            line_end = newline[line_of[first][k]] if line_of[first][k] < len(newline) else len(text)
            ref = text[end[k]:line_end].strip().decode("utf-8", errors="replace")
            raise MeshError("external_reference", f"{name}: '{keyword} {ref}' refers to an external file; "
                            "only self-contained files are accepted")
    _check_count(name, "vertices", n_vertices, max_vertices)
    _check_count(name, "faces", n_faces, max_faces)
    _check_count(name, "groups and objects", n_groups, max_nodes)
    if not dropped:
        return data
    bounds = np.concatenate([[0], newline + 1, [len(text) + 1]])
    pieces, at = [], 0
    for line in dropped:
        pieces.append(text[at:bounds[line]])
        at = int(bounds[line + 1])
    pieces.append(text[at:])
    return b"".join(pieces)


def _find_uris(node: Any, path: str = "") -> list[tuple[str, str]]:
    """Every ``uri`` string anywhere in a glTF JSON tree (buffers, images, extensions)."""
    found: list[tuple[str, str]] = []
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "uri":
                found.append((f"{path}.uri", value if isinstance(value, str) else repr(value)))
            else:
                found.extend(_find_uris(value, f"{path}.{key}"))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            found.extend(_find_uris(value, f"{path}[{i}]"))
    return found


_DATA_URI = re.compile(r"^data:[\w.+/-]*(;[\w=.+-]+)*;base64,", re.ASCII)


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


def _json_nesting(raw: bytes) -> int:
    """Deepest bracket nesting of JSON text (brackets inside strings not counted), without parsing it.

    Vectorised: a 1 MB glTF header takes about a millisecond.
    """
    codes = np.frombuffer(_JSON_STRING.sub(b'""', raw), dtype=np.uint8)
    step = np.isin(codes, (0x5B, 0x7B)).astype(np.int32) - np.isin(codes, (0x5D, 0x7D))
    return int(np.cumsum(step).max()) if len(step) else 0


def _gltf_json(data: bytes, file_type: str, name: str, max_nesting: int = MAX_NESTING) -> dict[str, Any]:
    if file_type == "glb":
        if len(data) < 20 or data[:4] != b"glTF":
            raise MeshError("corrupt_mesh", f"{name}: not a GLB file (no 'glTF' magic)")
        version, length = struct.unpack("<II", data[4:12])
        chunk_len, chunk_type = struct.unpack("<II", data[12:20])
        if version != 2:
            raise MeshError("corrupt_mesh", f"{name}: GLB version {version} is not supported (expected 2)")
        if length > len(data) or chunk_type != 0x4E4F534A or 20 + chunk_len > len(data):
            raise MeshError("corrupt_mesh", f"{name}: truncated or malformed GLB header")
        raw = data[20:20 + chunk_len]
    else:
        raw = data
    depth = _json_nesting(raw)
    if depth > max_nesting:
        raise MeshError("too_large", f"{name}: glTF JSON nests {depth} deep, more than the limit of "
                        f"{max_nesting}")
    try:
        tree = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MeshError("corrupt_mesh", f"{name}: glTF JSON does not parse ({err})") from err
    if not isinstance(tree, dict):
        raise MeshError("corrupt_mesh", f"{name}: glTF JSON is not an object")
    return tree


# Compressed geometry expands far beyond the file (and needs decoders we do not ship).
_COMPRESSED_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression")
_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
# Everything beyond geometry is dropped before trimesh reads the file: decoding textures could
# allocate far more than the file holds (a small PNG may declare 20000 x 20000 pixels).
_GLTF_DROPPED = ("images", "textures", "samplers", "materials")
_GLB_JSON, _GLB_BIN = 0x4E4F534A, 0x004E4942


def _glb_bin_length(data: bytes) -> int:
    """Length of a GLB's binary chunk (0 when there is none)."""
    json_len = struct.unpack("<I", data[12:16])[0]
    at = 20 + json_len
    if len(data) >= at + 8:
        length, kind = struct.unpack("<II", data[at:at + 8])
        if kind == _GLB_BIN:
            return min(length, len(data) - at - 8)
    return 0


def _nonneg_int(value: Any, what: str, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise MeshError("corrupt_mesh", f"{name}: {what} must be a non-negative integer, found {value!r}")
    return value


def _check_gltf_sizes(tree: dict[str, Any], bin_length: int, file_size: int, name: str,
                      max_vertices: int, max_faces: int) -> None:
    """Every declared size must fit in the file and the limits, before anything is allocated.

    Buffers may not declare more bytes than the file holds for them; views must lie inside their
    buffer, accessors inside their view; no accessor may hold more elements than the mesh limits
    allow, and all accessors together may not decode to more than twice the file's size (plus
    1 MiB), which also catches accessors without a view (zero-filled, no bytes in the file).
    """
    buffers = []
    for i, buf in enumerate(tree.get("buffers", [])):
        declared = _nonneg_int(buf.get("byteLength"), f"buffers[{i}].byteLength", name)
        uri = buf.get("uri")
        # The GLB's binary chunk backs buffer 0 when it has no uri; a data: URI holds 3/4 of its text.
        held = (bin_length if i == 0 else 0) if uri is None else (len(uri) - uri.find(",") - 1) * 3 // 4
        if declared > held:
            raise MeshError("corrupt_mesh", f"{name}: buffers[{i}] declares {declared} bytes, but the file "
                            f"holds {held} for it")
        buffers.append(declared)
    views = []
    for j, view in enumerate(tree.get("bufferViews", [])):
        b = _nonneg_int(view.get("buffer"), f"bufferViews[{j}].buffer", name)
        start = _nonneg_int(view.get("byteOffset", 0), f"bufferViews[{j}].byteOffset", name)
        length = _nonneg_int(view.get("byteLength"), f"bufferViews[{j}].byteLength", name)
        if b >= len(buffers) or start + length > buffers[b]:
            raise MeshError("corrupt_mesh", f"{name}: bufferViews[{j}] lies outside its buffer")
        views.append((length, view.get("byteStride")))
    most = max(max_vertices, 3 * max_faces)
    total = 0
    for k, acc in enumerate(tree.get("accessors", [])):
        count = _nonneg_int(acc.get("count"), f"accessors[{k}].count", name)
        if acc.get("componentType") not in _COMPONENT_BYTES or acc.get("type") not in _TYPE_SIZES:
            raise MeshError("corrupt_mesh", f"{name}: accessors[{k}] has an unknown componentType or type")
        elem = _COMPONENT_BYTES[acc["componentType"]] * _TYPE_SIZES[acc["type"]]
        if count > most:
            raise MeshError("too_large", f"{name}: accessors[{k}] declares {count} elements, more than the "
                            f"limit of {most}")
        total += count * elem
        if "bufferView" in acc:
            v = _nonneg_int(acc["bufferView"], f"accessors[{k}].bufferView", name)
            if v >= len(views):
                raise MeshError("corrupt_mesh", f"{name}: accessors[{k}] names a missing bufferView {v}")
            length, stride = views[v]
            stride = stride if isinstance(stride, int) and stride > 0 else elem
            start = _nonneg_int(acc.get("byteOffset", 0), f"accessors[{k}].byteOffset", name)
            if count and start + stride * (count - 1) + elem > length:
                raise MeshError("corrupt_mesh", f"{name}: accessors[{k}] declares {count} elements, more "
                                f"than its bufferView's {length} bytes hold")
        sparse = acc.get("sparse")
        if isinstance(sparse, dict):
            n = _nonneg_int(sparse.get("count"), f"accessors[{k}].sparse.count", name)
            if n > count:
                raise MeshError("corrupt_mesh", f"{name}: accessors[{k}] has more sparse values than "
                                "elements")
            total += n * (elem + 4)
    budget = 2 * file_size + (1 << 20)
    if total > budget:
        raise MeshError("too_large", f"{name}: accessors decode to {total} bytes, more than twice the file's "
                        f"size (a file whose data expands like this is refused)")


def _check_gltf_nodes(tree: dict[str, Any], name: str, max_nodes: int, max_nesting: int) -> None:
    """Refuse node trees that are too large, too deep, cyclic, or draw too many instances.

    Counted iteratively from the scenes' roots (every node when there is no scene): the depth of
    the deepest chain, and the node instances, i.e. the nodes reached along every path (a node
    reached twice is transformed and drawn twice, as trimesh does).
    """
    nodes = tree.get("nodes", [])
    if not isinstance(nodes, list) or not all(isinstance(n, dict) for n in nodes):
        raise MeshError("corrupt_mesh", f"{name}: glTF nodes must be a list of objects")
    _check_count(name, "nodes", len(nodes), max_nodes)
    children: list[list[int]] = []
    for i, node in enumerate(nodes):
        kids = node.get("children", [])
        if not isinstance(kids, list) or not all(
                isinstance(k, int) and not isinstance(k, bool) and 0 <= k < len(nodes) for k in kids):
            raise MeshError("corrupt_mesh", f"{name}: nodes[{i}].children must list node indices")
        children.append(kids)
    child_set = {k for kids in children for k in kids}
    scenes = tree.get("scenes") or [{"nodes": [i for i in range(len(nodes)) if i not in child_set]}]
    try:
        roots = [r for scene in scenes for r in scene.get("nodes", [])]
    except AttributeError as err:
        raise MeshError("corrupt_mesh", f"{name}: glTF scenes must be objects") from err
    instances = 0
    stack: list[tuple[int, int, tuple[int, ...]]] = [
        (r, 1, (r,)) for r in roots if isinstance(r, int) and 0 <= r < len(nodes)]
    while stack:
        i, depth, path = stack.pop()
        if depth > max_nesting:
            raise MeshError("too_large", f"{name}: glTF node tree nests more than {max_nesting} deep")
        instances += 1
        if instances > max_nodes:
            raise MeshError("too_large", f"{name}: its scenes reach more than {max_nodes} node instances")
        for k in children[i]:
            if k in path:
                raise MeshError("corrupt_mesh", f"{name}: glTF node {k} is its own ancestor (a cycle)")
            stack.append((k, depth + 1, (*path, k)))


def _check_gltf(data: bytes, file_type: str, name: str, max_vertices: int, max_faces: int,
                max_nodes: int = MAX_NODES, max_nesting: int = MAX_NESTING) -> bytes:
    """Check a glTF/GLB before trimesh reads it; return it with everything but geometry removed."""
    tree = _gltf_json(data, file_type, name, max_nesting)
    _check_gltf_nodes(tree, name, max_nodes, max_nesting)
    for where, uri in _find_uris(tree):
        if not _DATA_URI.match(uri):
            shown = uri if len(uri) < 200 else uri[:200] + "..."
            raise MeshError("external_reference", f"{name}: {where[1:]} refers to {shown!r}; only "
                            "embedded data: URIs are accepted")
    accessors = tree.get("accessors", [])
    n_vertices = n_faces = 0
    try:
        used = [*(tree.get("extensionsUsed") or []), *(tree.get("extensionsRequired") or []),
                *(e for mesh in tree.get("meshes", []) for prim in mesh.get("primitives", [])
                  for e in (prim.get("extensions") or {})),
                *(e for view in tree.get("bufferViews", []) for e in (view.get("extensions") or {}))]
        compressed = sorted({e for e in used if e in _COMPRESSED_EXTENSIONS})
        if compressed:
            raise MeshError("unsupported_format", f"{name}: compressed geometry ({', '.join(compressed)}) is "
                            "not accepted; export the mesh without compression")
        _check_gltf_sizes(tree, _glb_bin_length(data) if file_type == "glb" else 0, len(data), name,
                          max_vertices, max_faces)
        for mesh in tree.get("meshes", []):
            for prim in mesh.get("primitives", []):
                n_vertices += int(accessors[prim["attributes"]["POSITION"]]["count"])
                if "indices" in prim:
                    n_faces += int(accessors[prim["indices"]]["count"]) // 3
                prim.pop("material", None)
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as err:
        if isinstance(err, MeshError):
            raise
        raise MeshError("corrupt_mesh", f"{name}: malformed glTF meshes or accessors ({err!r})") from err
    _check_count(name, "vertices", n_vertices, max_vertices)
    _check_count(name, "faces", n_faces, max_faces)
    for key in _GLTF_DROPPED:
        tree.pop(key, None)
    text = json.dumps(tree).encode("utf-8")
    if file_type != "glb":
        return text
    text += b" " * (-len(text) % 4)
    json_len = struct.unpack("<I", data[12:16])[0]
    rest = data[20 + json_len:]  # the binary chunk (header included), unchanged
    chunks = struct.pack("<II", len(text), _GLB_JSON) + text + rest
    return b"glTF" + struct.pack("<II", 2, 12 + len(chunks)) + chunks


# --------------------------------------------------------------------------------------------
# Loading.


def _load_scene(data: bytes, file_type: str, name: str, max_vertices: int, max_faces: int,
                ignore_obj_materials: bool, max_nodes: int = MAX_NODES,
                max_nesting: int = MAX_NESTING) -> trimesh.Scene:
    file_type = file_type.lower().lstrip(".")
    if file_type not in MESH_FORMATS:
        raise MeshError("unsupported_format", f"{name}: format {file_type!r} is not supported; expected one "
                        f"of {', '.join(MESH_FORMATS)}")
    if not data:
        raise MeshError("empty_mesh", f"{name}: the file is empty")
    kwargs: dict[str, Any] = {}
    if file_type == "ply":
        _check_ply_header(data, name, max_vertices, max_faces)
    elif file_type == "off":
        _check_off_header(data, name, max_vertices, max_faces)
    elif file_type == "stl":
        _check_stl_header(data, name, max_vertices, max_faces)
    elif file_type == "obj":
        data = _prepare_obj(data, name, max_vertices, max_faces, ignore_obj_materials, max_nodes)
        # One piece per group / object, not per material.
        kwargs = {"split_groups": True, "split_objects": True, "group_material": False}
    else:
        data = _check_gltf(data, file_type, name, max_vertices, max_faces, max_nodes, max_nesting)
    resolver = _RefusingResolver(name)
    try:
        scene = trimesh.load_scene(io.BytesIO(data), file_type=file_type, resolver=resolver,
                                   process=False, **kwargs)
    except MeshError:
        raise
    except Exception as err:  # trimesh raises many types on malformed input
        raise MeshError("corrupt_mesh", f"{name}: could not be read as {file_type.upper()} "
                        f"({type(err).__name__}: {err})") from err
    if resolver.asked:
        raise MeshError("external_reference", f"{name}: refers to external file(s) {resolver.asked}; "
                        "only self-contained files are accepted")
    return scene


def _scene_leaves(scene: trimesh.Scene, name: str, max_vertices: int, max_faces: int) -> list[SceneLeaf]:
    """Scene-graph leaves with triangles, transformed to the world frame."""
    nodes = [n for n in scene.graph.nodes_geometry
             if isinstance(scene.geometry.get(scene.graph[n][1]), trimesh.Trimesh)]
    # Instancing can multiply a small file into a huge mesh: count before transforming anything.
    total_v = sum(len(scene.geometry[scene.graph[n][1]].vertices) for n in nodes)
    total_f = sum(len(scene.geometry[scene.graph[n][1]].faces) for n in nodes)
    _check_count(name, "vertices (after instancing)", total_v, max_vertices)
    _check_count(name, "faces (after instancing)", total_f, max_faces)
    leaves = []
    for node in nodes:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        vertices = np.asarray(geom.vertices, dtype=np.float64)
        faces = np.asarray(geom.faces, dtype=np.int64)
        # A damaged file can leave trimesh with vertices of other than 3 coordinates (an OBJ
        # vertex line with two numbers) or a ragged face array; refuse it here, not in numpy.
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.size % 3:
            raise MeshError("corrupt_mesh", f"{name}: node {node!r} has vertices of shape {vertices.shape} "
                            f"and faces of shape {faces.shape}; expected (V, 3) and (F, 3)")
        faces = faces.reshape(-1, 3)
        if len(faces) == 0:
            continue
        if not np.isfinite(vertices).all():
            raise MeshError("non_finite", f"{name}: node {node!r} has NaN or infinite vertex coordinates")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise MeshError("corrupt_mesh", f"{name}: node {node!r} has face indices outside its "
                            f"{len(vertices)} vertices")
        transform = np.asarray(transform, dtype=np.float64)
        if not np.isfinite(transform).all():
            raise MeshError("non_finite", f"{name}: node {node!r} has a non-finite transform")
        world = vertices @ transform[:3, :3].T + transform[:3, 3]
        leaves.append(SceneLeaf(str(node), str(geom_name), world, faces))
    if not leaves:
        raise MeshError("empty_mesh", f"{name}: contains no triangles (empty, or points/lines only)")
    return leaves


def _drop_zero_area(leaves: list[SceneLeaf], name: str) -> tuple[list[SceneLeaf], list[np.ndarray]]:
    """The leaves of positive area, and their triangles' areas (computed once: on a 100k-triangle
    upload they are a large share of the parse, and the sampler needs them again)."""
    areas = [triangle_areas(leaf.vertices, leaf.faces) for leaf in leaves]
    kept = [(leaf, a) for leaf, a in zip(leaves, areas, strict=True) if a.sum() > 0]
    if not kept:
        raise MeshError("zero_area", f"{name}: every triangle is degenerate (total surface area is zero)")
    return [leaf for leaf, _ in kept], [a for _, a in kept]


class MeshSurface(NamedTuple):
    """A loaded mesh and its triangles' areas.

    Shapes:
        vertices: (V, 3) float64; faces: (F, 3) int64; areas: (F,) float64.
    """

    vertices: np.ndarray
    faces: np.ndarray
    areas: np.ndarray


def load_mesh_bytes(data: bytes, file_type: str, *, name: str = "upload", max_vertices: int,
                    max_faces: int, ignore_obj_materials: bool = False, max_nodes: int = MAX_NODES,
                    max_nesting: int = MAX_NESTING) -> trimesh.Trimesh:
    """Load one mesh from untrusted bytes; a scene is concatenated in its world frame.

    Args:
        data: the file's bytes.
        file_type: one of ``MESH_FORMATS`` (case-insensitive, leading dot allowed).
        name: how errors name the file.
        max_vertices, max_faces: refuse larger meshes (checked on headers, then after loading).
        ignore_obj_materials: drop OBJ ``mtllib``/``usemtl`` lines instead of refusing the file.
        max_nodes, max_nesting: refuse larger or deeper scenes (checked before one is built).

    Raises:
        MeshError: with a ``code`` from ``MESH_ERROR_CODES``.
    """
    surface = load_mesh_surface(data, file_type, name=name, max_vertices=max_vertices, max_faces=max_faces,
                                ignore_obj_materials=ignore_obj_materials, max_nodes=max_nodes,
                                max_nesting=max_nesting)
    return trimesh.Trimesh(vertices=surface.vertices, faces=surface.faces, process=False)


def load_mesh_surface(data: bytes, file_type: str, *, name: str = "upload", max_vertices: int,
                      max_faces: int, ignore_obj_materials: bool = False, max_nodes: int = MAX_NODES,
                      max_nesting: int = MAX_NESTING) -> MeshSurface:
    """``load_mesh_bytes`` as arrays, with the triangles' areas it computed on the way.

    Raises:
        MeshError: with a ``code`` from ``MESH_ERROR_CODES``.
    """
    if file_type.lower().lstrip(".") == "obj":
        plain = _plain_obj_surface(data, name, max_vertices, max_faces, ignore_obj_materials, max_nodes)
        if plain is not None:
            return plain
    scene = _load_scene(data, file_type, name, max_vertices, max_faces, ignore_obj_materials, max_nodes,
                        max_nesting)
    leaves, areas = _drop_zero_area(_scene_leaves(scene, name, max_vertices, max_faces), name)
    offsets = np.cumsum([0] + [len(leaf.vertices) for leaf in leaves[:-1]])
    vertices = np.concatenate([leaf.vertices for leaf in leaves])
    faces = np.concatenate([leaf.faces + off for leaf, off in zip(leaves, offsets, strict=True)])
    return MeshSurface(vertices, faces, np.concatenate(areas))


def _plain_obj_surface(data: bytes, name: str, max_vertices: int, max_faces: int, ignore_materials: bool,
                       max_nodes: int) -> MeshSurface | None:
    """A plain OBJ's surface by ``service.geometry.obj`` (its block reader, else its numpy reader:
    3x and 5x faster than trimesh on a 100k-triangle file); None for any other file, and for one
    whose surface is not plainly usable (no triangles, a non-finite coordinate, no area), so that
    trimesh's path reads it and says what is wrong.

    The limits are checked on the counted lines before any number is read, as ``_prepare_obj``
    checks them before trimesh reads anything.
    """
    read = None
    blocks = obj_blocks(data, drop_materials=ignore_materials)
    if blocks is not None:
        _check_obj_counts(name, blocks, max_vertices, max_faces, max_nodes)
        read = read_obj_blocks(blocks)
    if read is None:
        layout = obj_layout(data, drop_materials=ignore_materials)
        if layout is None:
            return None
        _check_obj_counts(name, layout, max_vertices, max_faces, max_nodes)
        read = read_plain_obj(layout)
    if read is None or not len(read[1]) or not np.isfinite(read[0]).all():
        return None
    vertices, faces = read
    areas = triangle_areas(vertices, faces)
    if not areas.sum() > 0:
        return None
    return MeshSurface(vertices, faces, areas)


def _check_obj_counts(name: str, counted: ObjBlocks | ObjLayout, max_vertices: int, max_faces: int,
                      max_nodes: int) -> None:
    _check_count(name, "vertices", counted.vertices, max_vertices)
    _check_count(name, "faces", counted.triangles, max_faces)
    _check_count(name, "groups and objects", counted.groups, max_nodes)


def load_scene_leaves(data: bytes, file_type: str, *, name: str = "upload", max_vertices: int,
                      max_faces: int, ignore_obj_materials: bool = False,
                      split_components: bool = True, max_nodes: int = MAX_NODES,
                      max_nesting: int = MAX_NESTING) -> list[SceneLeaf]:
    """Scene-graph leaves of untrusted bytes, in the world frame, zero-area leaves dropped.

    A file with a single leaf (an STL, PLY or OFF mesh, an OBJ without groups, a glTF with one
    node) is split into its connected components when ``split_components`` is true, since those
    mostly follow part boundaries (paper, Section 4); components are named ``<leaf>/<i>``.

    Raises:
        MeshError: with a ``code`` from ``MESH_ERROR_CODES``.
    """
    scene = _load_scene(data, file_type, name, max_vertices, max_faces, ignore_obj_materials, max_nodes,
                        max_nesting)
    leaves, _ = _drop_zero_area(_scene_leaves(scene, name, max_vertices, max_faces), name)
    if split_components and len(leaves) == 1:
        leaf = leaves[0]
        parts = connected_components(leaf.vertices, leaf.faces)
        leaves = [SceneLeaf(f"{leaf.name}/{i}", f"{leaf.geometry}/{i}", v, f)
                  for i, (v, f) in enumerate(parts)]
        leaves, _ = _drop_zero_area(leaves, name)
    return leaves


def load_scene_pieces(data: bytes, file_type: str, *, name: str = "upload", max_vertices: int,
                      max_faces: int, ignore_obj_materials: bool = False
                      ) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Pieces of a shape file: scene-graph leaves, or connected components of a single mesh.

    Returns:
        list of (node name, vertices (V, 3) float64 in the world frame, faces (F, 3) int64).
    """
    leaves = load_scene_leaves(data, file_type, name=name, max_vertices=max_vertices,
                               max_faces=max_faces, ignore_obj_materials=ignore_obj_materials)
    return [(leaf.name, leaf.vertices, leaf.faces) for leaf in leaves]


# --------------------------------------------------------------------------------------------
# Pure geometry.


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each triangle.

    Shapes:
        vertices (V, 3), faces (F, 3) int -> (F,) float64.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
    if len(f):
        lo, hi = int(f.min()), int(f.max())
        if lo < -len(v) or hi >= len(v):   # as numpy's indexing refuses them
            bad = lo if lo < -len(v) else hi
            raise IndexError(f"face index {bad} is out of bounds for {len(v)} vertices")
        if lo < 0:                          # counted from the end, as numpy's indexing reads them
            f = np.where(f < 0, f + len(v), f)
    # Compiled (numba): the same sums in the same order as np.cross and np.linalg.norm
    # (bit-identical), 0.4 against 7.7 ms for 100k triangles with numpy's gathers.
    return mesh_kernel.triangle_areas(v, f)


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total surface area of a triangle mesh (0 for no faces)."""
    if len(faces) == 0:
        return 0.0
    return float(triangle_areas(vertices, faces).sum())


def connected_components(vertices: np.ndarray, faces: np.ndarray,
                         merge_tolerance: float = 1e-8) -> list[tuple[np.ndarray, np.ndarray]]:
    """Split a mesh into vertex-connected components (coincident vertices are welded first).

    Formats such as STL store every triangle with its own corners, so corners closer than
    ``merge_tolerance`` count as one vertex. Components are ordered by their first face.

    Shapes:
        vertices (V, 3), faces (F, 3) -> list of ((Vi, 3) float64, (Fi, 3) int64).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return []
    keys = np.round(vertices / merge_tolerance).astype(np.int64) if merge_tolerance > 0 else vertices
    _, weld = np.unique(keys, axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    n = int(weld.max()) + 1
    welded = weld[faces]
    rows = np.concatenate([welded[:, 0], welded[:, 1]])
    cols = np.concatenate([welded[:, 1], welded[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, labels = _cc(graph, directed=False)
    face_label = labels[welded[:, 0]]
    # Order components by their first face so the result does not depend on scipy's labelling.
    _, first = np.unique(face_label, return_index=True)
    order = np.unique(face_label)[np.argsort(first)]
    out = []
    for lab in order:
        f = faces[face_label == lab]
        used, local = np.unique(f, return_inverse=True)
        out.append((vertices[used], local.reshape(-1, 3).astype(np.int64)))
    return out


def valid_point_set(points: np.ndarray, name: str = "points") -> np.ndarray:
    """A point set read from a file, checked: ``(N, 3)``, N >= 1, all finite; as float64.

    A caller's query points go through ``service.geometry.inputs.check_points`` instead, which
    also applies the request limits and answers with the API's error codes.

    Raises:
        MeshError: ``empty_mesh`` or ``non_finite``; ``corrupt_mesh`` for a wrong shape.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MeshError("corrupt_mesh", f"{name}: expected points of shape (N, 3), found {pts.shape}")
    if len(pts) == 0:
        raise MeshError("empty_mesh", f"{name}: no points")
    if not np.isfinite(pts).all():
        raise MeshError("non_finite", f"{name}: NaN or infinite coordinates")
    return pts


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int,
                   areas: np.ndarray | None = None) -> np.ndarray:
    """Sample ``n`` points uniformly on a triangle mesh's surface (area-weighted, seeded).

    The points of ``sample_surface_faces``, as float32.

    Shapes:
        vertices (V, 3), faces (F, 3), areas (F,) -> (n, 3) float32.

    Raises:
        MeshError: ``empty_mesh`` (no faces), ``non_finite``, ``zero_area``.
    """
    return sample_surface_faces(vertices, faces, n, seed, areas)[0].astype(np.float32)


def sample_surface_faces(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int,
                         areas: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` area-weighted surface samples of a triangle mesh (seeded) and the face of each.

    The one surface sampler: uploads, catalog parts, training data and contact refinement (which
    takes each sample's face normal) all sample through it, so the same mesh and seed give the
    same points everywhere. Triangles are drawn with probability proportional to their area,
    then a point uniformly inside each drawn triangle (square-root barycentric trick).
    ``areas``: the triangles' areas (``triangle_areas``) when the caller has them already (a
    100k-triangle upload spends about as long on them as on the sampling).

    Shapes:
        vertices (V, 3), faces (F, 3), areas (F,) -> points (n, 3) float64, face ids (n,) int64.

    Raises:
        MeshError: ``empty_mesh`` (no faces), ``non_finite``, ``zero_area``.
    """
    assert n >= 0, f"n must be >= 0, found {n}"
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise MeshError("empty_mesh", "cannot sample a surface without faces of positive area (no faces)")
    vertices = np.asarray(vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise MeshError("non_finite", "cannot sample a surface with NaN or infinite vertices")
    areas = triangle_areas(vertices, faces) if areas is None else areas
    assert areas.shape == (len(faces),), f"areas must have shape ({len(faces)},), found {areas.shape}"
    total = areas.sum()
    if not total > 0:
        raise MeshError("zero_area", "cannot sample a surface whose area is zero")
    rng = np.random.default_rng(seed)
    cdf = np.cumsum(areas)
    tri = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(faces) - 1)
    r1 = np.sqrt(rng.random(n))[:, None]
    r2 = rng.random(n)[:, None]
    corners = vertices[faces[tri]]  # (n, 3, 3)
    pts = (1 - r1) * corners[:, 0] + r1 * (1 - r2) * corners[:, 1] + r1 * r2 * corners[:, 2]
    return pts, tri.astype(np.int64)


def normalize_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre at the bounding-box centre and scale to unit radius (max distance to the centre).

    Works on points or mesh vertices alike; apply ``(x - center) / radius`` to map other data
    into the same frame and ``x * radius + center`` to map back.

    Shapes:
        points (N, 3) -> normalised (N, 3) float64, center (3,) float64, radius float.

    Raises:
        MeshError: ``empty_mesh``, ``non_finite``, or ``degenerate`` when all points coincide.
    """
    pts = valid_point_set(points)
    center = (pts.min(axis=0) + pts.max(axis=0)) / 2
    radius = float(np.linalg.norm(pts - center, axis=1).max())
    if not radius > 0:
        raise MeshError("degenerate", "all points coincide: the frame cannot be normalised")
    return (pts - center) / radius, center, radius


def resample_points(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Exactly ``n`` points: a subset without replacement, or all points plus random repeats.

    Shapes:
        points (N, 3) -> (n, 3), same dtype as the input.

    Raises:
        MeshError: ``empty_mesh`` when there are no points.
    """
    assert n >= 0, f"n must be >= 0, found {n}"
    points = np.asarray(points)
    if points.ndim != 2 or len(points) == 0:
        raise MeshError("empty_mesh", f"cannot resample an empty point set (shape {points.shape})")
    return points[_resample_rows(len(points), n, seed)]


@lru_cache(maxsize=1024)
def _resample_rows(m: int, n: int, seed: int) -> np.ndarray:
    """The rows ``resample_points`` takes from m points: they depend on (m, n, seed) alone, and
    clients send the same count again and again (cached: 0.1 ms of every request otherwise)."""
    rng = np.random.default_rng(seed)
    if m >= n:
        rows = np.sort(rng.choice(m, size=n, replace=False))
    else:
        rows = np.concatenate([np.arange(m), rng.integers(0, m, size=n - m)])
    rows.setflags(write=False)
    return rows


def points_to_mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                            chunk: int = 2_000_000) -> np.ndarray:
    """Exact distance from each point to the nearest triangle (brute force, for small meshes).

    Uses the closest-point-on-triangle regions of Ericson, "Real-Time Collision Detection",
    5.1.5, over every (point, triangle) pair, ``chunk`` pairs at a time.

    Shapes:
        points (N, 3), vertices (V, 3), faces (F, 3) -> (N,) float64.
    """
    p_all = np.asarray(points, dtype=np.float64)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    if len(tri) == 0:
        raise MeshError("empty_mesh", "cannot measure distances to a mesh without faces")
    a, b, c = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
    ab, ac = b - a, c - a
    out = np.empty(len(p_all))
    step = max(1, chunk // len(tri))
    for s in range(0, len(p_all), step):
        p = p_all[s:s + step, None, :]
        ap, bp, cp = p - a, p - b, p - c
        d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
        d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
        d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = va + vb + vc
            v_in, w_in = vb / denom, vc / denom
            closest = a + ab * v_in[..., None] + ac * w_in[..., None]  # inside the face
            # Edges (each replaces the face result where the point projects onto it).
            t = d1 / (d1 - d3)
            closest = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + t[..., None] * ab, closest)
            t = d2 / (d2 - d6)
            closest = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + t[..., None] * ac, closest)
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            closest = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None],
                               b + t[..., None] * (c - b), closest)
        # Vertices.
        closest = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, closest)
        closest = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, closest)
        closest = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, closest)
        dist = np.linalg.norm(p - closest, axis=-1)
        out[s:s + step] = np.nan_to_num(dist, nan=np.inf).min(axis=1)
    return out
