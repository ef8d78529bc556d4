"""glTF 2.0 (.glb, or .gltf JSON with its buffers) holding KHR_gaussian_splatting point primitives, plain or
compressed with KHR_gaussian_splatting_compression_spz_2.

Every primitive of the default scene whose extensions hold KHR_gaussian_splatting is read, its node's world
transform applied (translation, rotation and uniform positive scale: the decomposable transforms the extension
allows, SH rotated with the node), converted from glTF's LUF axes to our RDF (see splatstream/axes.py), and
all primitives concatenated. Attribute component types: those the extension allows (float, normalized
integers, unnormalized unsigned integers for scale); byteStride, accessor offsets, and buffers that are the
GLB's binary chunk, a data: URI or a file beside the .gltf. Sparse accessors, external URIs outside the
directory and other kernels are refused. Every size is checked before anything is read.
"""
from __future__ import annotations

import base64
import json
import math
import os
import struct
import warnings
from urllib.parse import unquote

import numpy as np

from ..axes import RDF_TO_RUB, turn
from ..errors import InputError
from ..gaussians import SH_BAND_COEFFS, Gaussians, normalize_quaternions
from ..gltf_splats import EXTENSION, PREFIX, SPZ_EXTENSION, sh_attribute_names
from ..progress import some_of
from ..reader_support import DROP_INVALID_HINT, memory_budget, opacity_logits_from_unit, read_regular_file
from ..sh import sh_basis
from .splat import MIN_LOG_SCALE
from .spz import decode_spz

GLB_HEADER = struct.Struct("<4sII")
CHUNK_HEADER = struct.Struct("<II")
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
MAX_JSON_BYTES = 64 << 20
MAX_NODES = 1 << 16
COMPONENTS = {5120: ("i1", 127.0), 5121: ("u1", 255.0), 5122: ("<i2", 32767.0), 5123: ("<u2", 65535.0),
              5125: ("<u4", None), 5126: ("<f4", None)}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
# Component types the extension allows per attribute: (componentType, normalized).
ALLOWED = {
    "POSITION": {(5126, False)},
    "ROTATION": {(5126, False), (5120, True), (5122, True)},
    "SCALE": {(5126, False), (5121, False), (5121, True), (5123, False), (5123, True)},
    "OPACITY": {(5126, False), (5121, True), (5123, True)},
    "SH": {(5126, False)},
}
LUF_TO_RDF = (-1.0, -1.0, 1.0)


def _is_int(value: object) -> bool:
    """A JSON integer (true and false are not numbers here)."""
    return isinstance(value, int) and not isinstance(value, bool)


class _Document:
    def __init__(self, path: str, gltf: dict, binary: bytes | None):
        self.path = path
        self.gltf = gltf
        self.binary = binary
        self.buffers: dict[int, bytes] = {}

    def list(self, key: str) -> list:
        value = self.gltf.get(key, [])
        if not isinstance(value, list):
            raise InputError(self.path, key, "expected a JSON array")
        return value

    def item(self, key: str, index: object) -> dict:
        items = self.list(key)
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(items) or \
                not isinstance(items[index], dict):
            raise InputError(self.path, key, f"index {index!r} does not name one of the {len(items)} {key}")
        return items[index]

    def buffer(self, index: object) -> bytes:
        buffer = self.item("buffers", index)  # checks the index (a JSON value of any type) first
        if index in self.buffers:
            return self.buffers[index]
        length = buffer.get("byteLength")
        if not _is_int(length) or length < 0:
            raise InputError(self.path, f"buffers[{index}].byteLength", f"{length!r} (expected a byte count)")
        uri = buffer.get("uri")
        if uri is None:
            if index != 0 or self.binary is None:
                raise InputError(self.path, f"buffers[{index}]", "no uri, and only buffer 0 of a .glb may use the "
                                 "binary chunk")
            data = self.binary
        elif not isinstance(uri, str):
            raise InputError(self.path, f"buffers[{index}].uri", "expected a string")
        elif uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64") or len(payload) > 4 * (length // 3 + 2):
                raise InputError(self.path, f"buffers[{index}].uri", "a data: URI must be base64 and no longer than "
                                 "byteLength implies")
            try:
                data = base64.b64decode(payload, validate=True)
            except ValueError as exc:
                raise InputError(self.path, f"buffers[{index}].uri", f"bad base64 ({exc})") from None
        else:
            data = self._external(index, uri)
        if len(data) < length:
            raise InputError(self.path, f"buffers[{index}]", f"holds {len(data)} bytes, byteLength says {length}")
        self.buffers[index] = data[:length]
        return self.buffers[index]

    def _external(self, index: int, uri: str) -> bytes:
        if "://" in uri or uri.startswith("/"):
            raise InputError(self.path, f"buffers[{index}].uri", f"{uri!r}: only files beside the glTF are read")
        root = os.path.realpath(os.path.dirname(self.path) or ".")
        full = os.path.realpath(os.path.join(root, unquote(uri)))
        if os.path.commonpath([root, full]) != root or not os.path.isfile(full):
            raise InputError(self.path, f"buffers[{index}].uri", f"{uri!r} is not a file inside {root}")
        return read_regular_file(full, memory_budget(), self.path, f"buffers[{index}].uri")

    def buffer_view(self, index: object) -> tuple[bytes, int, int, int | None]:
        """(buffer, byteOffset, byteLength, byteStride) of a buffer view, checked against its buffer."""
        view = self.item("bufferViews", index)
        buffer = self.buffer(view.get("buffer"))
        offset, length, stride = view.get("byteOffset", 0), view.get("byteLength"), view.get("byteStride")
        if not _is_int(offset) or not _is_int(length) or offset < 0 or length < 0 or \
                offset + length > len(buffer) or (stride is not None and (not _is_int(stride) or
                                                                          not 4 <= stride <= 252)):
            raise InputError(self.path, f"bufferViews[{index}]", f"byteOffset {offset!r}, byteLength {length!r}, "
                             f"byteStride {stride!r} do not fit its {len(buffer)}-byte buffer")
        return buffer, offset, length, stride


def _load(path: str) -> _Document:
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        head = f.read(12)
        if head[:4] == b"glTF":
            if len(head) < GLB_HEADER.size:  # said 'version None (expected 2)' (newuser64)
                raise InputError(path, "GLB header", f"the file is {size} bytes, a GLB header alone is "
                                 f"{GLB_HEADER.size}: truncated?")
            magic, version, length = GLB_HEADER.unpack(head)
            if version != 2:
                raise InputError(path, "GLB header", f"version {version!r} (expected 2)")
            if length != size:
                raise InputError(path, "GLB header", f"length {length} but the file has {size} bytes (truncated?)")
            if size > memory_budget():
                raise InputError(path, None, "larger than the memory budget")
            data = head + f.read()
        else:
            if size > MAX_JSON_BYTES:
                raise InputError(path, None, f"{size} bytes: a .gltf JSON document is at most {MAX_JSON_BYTES}")
            return _Document(path, _parse_json(path, head + f.read()), None)
    chunks: list[tuple[int, bytes]] = []
    offset = 12
    while offset < size:
        if size - offset < 8:
            raise InputError(path, f"GLB chunk at byte {offset}", "truncated chunk header")
        length, kind = CHUNK_HEADER.unpack_from(data, offset)
        if length > size - offset - 8:
            raise InputError(path, f"GLB chunk at byte {offset}", f"declares {length} bytes, {size - offset - 8} "
                             "remain")
        chunks.append((kind, data[offset + 8:offset + 8 + length]))
        offset += 8 + length + (-length % 4)
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise InputError(path, "GLB chunks", "the first chunk must be JSON")
    if len(chunks[0][1]) > MAX_JSON_BYTES:
        raise InputError(path, "GLB JSON chunk", f"more than {MAX_JSON_BYTES} bytes")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN else None
    return _Document(path, _parse_json(path, chunks[0][1]), binary)


def _parse_json(path: str, data: bytes) -> dict:
    try:
        value = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(path, "glTF JSON", f"not valid JSON ({exc})") from None
    if not isinstance(value, dict) or not isinstance(value.get("asset"), dict):
        raise InputError(path, "glTF JSON", "not a glTF document (expected an object with 'asset')")
    version = str(value["asset"].get("version", ""))
    if not version.startswith("2."):
        raise InputError(path, "asset.version", f"{version!r} (expected 2.x)")
    return value


def _accessor(doc: _Document, index: object, semantic: str, kind: str, gl_type: str, count: int | None) -> np.ndarray:
    """Accessor `index` as float32 (count, width), dequantised as its componentType and `normalized` say."""
    accessor = doc.item("accessors", index)
    field = f"accessor {index} ({semantic})"
    component, normalized = accessor.get("componentType"), accessor.get("normalized", False)
    if not _is_int(component):
        raise InputError(doc.path, f"{field} componentType", f"{component!r} (expected an integer GL component type)")
    if not isinstance(normalized, bool):
        raise InputError(doc.path, f"{field} normalized", f"{normalized!r} (expected true or false)")
    if accessor.get("type") != gl_type:
        raise InputError(doc.path, field, f"type {accessor.get('type')!r} (expected {gl_type})")
    if (component, normalized) not in ALLOWED[kind]:
        raise InputError(doc.path, field, f"componentType {component!r}{' normalized' if normalized else ''} is not "
                         f"one the extension allows for {semantic}")
    n = accessor.get("count")
    if not _is_int(n) or n < 1 or (count is not None and n != count):
        raise InputError(doc.path, field, f"count {n!r} (expected {count if count is not None else 'at least 1'}, "
                         "the POSITION count)")
    if "sparse" in accessor:
        raise InputError(doc.path, field, "sparse accessors are not supported")
    if "bufferView" not in accessor:
        raise InputError(doc.path, field, "has no bufferView (no data)")
    code, scale = COMPONENTS[component]
    itemsize = np.dtype(code).itemsize
    width = WIDTH[gl_type]
    buffer, view_offset, view_length, stride = doc.buffer_view(accessor["bufferView"])
    offset = accessor.get("byteOffset", 0)
    element = itemsize * width
    stride = stride or element
    if not _is_int(offset) or offset < 0 or offset % itemsize or stride < element or \
            offset + stride * (n - 1) + element > view_length:
        raise InputError(doc.path, field, f"{n} elements of {element} bytes at byteOffset {offset} with stride "
                         f"{stride} do not fit the {view_length}-byte buffer view")
    start = view_offset + offset
    raw = np.ndarray((n, width), np.dtype(code), buffer=buffer, offset=start, strides=(stride, itemsize))
    values = raw.astype(np.float32)
    if normalized:
        values = np.maximum(values / np.float32(scale), np.float32(-1.0))
    return values


def _node_matrices(doc: _Document) -> list[tuple[int, np.ndarray]]:
    """(mesh index, world matrix) of every node with a mesh in the default scene (or all root nodes)."""
    nodes = doc.list("nodes")
    scenes = doc.list("scenes")
    if scenes:
        scene = doc.item("scenes", doc.gltf.get("scene", 0))
        roots = scene.get("nodes", [])
    else:
        children = {c for node in nodes if isinstance(node, dict) for c in node.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    if not isinstance(roots, list):
        raise InputError(doc.path, "scene.nodes", "expected a list")
    out: list[tuple[int, np.ndarray]] = []
    stack = [(r, np.eye(4)) for r in reversed(roots)]
    visited: set[int] = set()
    while stack:
        index, parent = stack.pop()
        # glTF nodes form disjoint strict trees: a node reached twice is a cycle or a shared child (refused at
        # once: a cycle used to be walked 65,536 times; BENCHMARKS.md, "Fuzz and fault campaign").
        if isinstance(index, int) and index in visited:
            raise InputError(doc.path, f"nodes[{index}]", "reached twice: the node hierarchy is not a set of trees "
                             "(a cycle, or a node with two parents)")
        if isinstance(index, int):
            visited.add(index)
        if len(visited) > MAX_NODES:
            raise InputError(doc.path, "nodes", f"more than {MAX_NODES} nodes")
        node = doc.item("nodes", index)
        world = parent @ _local_matrix(doc.path, index, node)
        if "mesh" in node:
            out.append((node["mesh"], world))
        children = node.get("children", [])
        if not isinstance(children, list):
            raise InputError(doc.path, f"nodes[{index}].children", "expected a list")
        stack.extend((c, world) for c in reversed(children))
    return out


def _local_matrix(path: str, index: int, node: dict) -> np.ndarray:
    try:
        if "matrix" in node:
            m = np.asarray(node["matrix"], np.float64)
            if m.shape != (16,) or not np.isfinite(m).all():
                raise ValueError
            return m.reshape(4, 4).T  # column-major
        t = np.asarray(node.get("translation", [0, 0, 0]), np.float64)
        x, y, z, w = np.asarray(node.get("rotation", [0, 0, 0, 1]), np.float64)
        s = np.asarray(node.get("scale", [1, 1, 1]), np.float64)
        if t.shape != (3,) or s.shape != (3,) or not (np.isfinite(t).all() and np.isfinite(s).all() and
                                                       np.isfinite([x, y, z, w]).all()):
            raise ValueError
    except (ValueError, TypeError):
        raise InputError(path, f"nodes[{index}]", "matrix / translation / rotation / scale of the wrong shape "
                         "or type, or not finite") from None
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = t
    return m


def sh_rotation(rotation: np.ndarray, degree: int) -> np.ndarray:
    """(K, K) matrix taking rest coefficients (bands 1..degree) of f to those of f(R^T d), band by band, fitted
    exactly on sample directions (each band is closed under rotation, so the least-squares fit is exact)."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    basis = sh_basis(d, degree)[:, 1:]
    rotated = sh_basis(d @ rotation, degree)[:, 1:]  # rows are (R^T d)^T = d^T R
    k = basis.shape[1]
    out = np.zeros((k, k))
    start = 0
    for band in range(1, degree + 1):
        size = SH_BAND_COEFFS[band]
        block = slice(start, start + size)
        out[block, block] = np.linalg.lstsq(basis[:, block], rotated[:, block], rcond=None)[0]
        start += size
    return out


def _apply_matrix(path: str, g: Gaussians, m: np.ndarray) -> Gaussians:
    if np.allclose(m, np.eye(4), atol=0, rtol=0):
        return g
    a = m[:3, :3]
    if not np.isfinite(m).all() or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise InputError(path, "node transform", "not a finite affine matrix")
    norms = np.linalg.norm(a, axis=0)
    if not norms.min() > 0 or norms.max() / norms.min() > 1 + 1e-5 or \
            np.abs((a / norms).T @ (a / norms) - np.eye(3)).max() > 1e-5 or np.linalg.det(a / norms) < 0:
        raise InputError(path, "node transform", f"column lengths {norms.round(6).tolist()}: only rotations with a "
                         "uniform positive scale are supported (the extension leaves other transforms undefined)")
    rotation = a / norms[None, :]
    scale = float(norms.mean())
    # A huge scale or translation overflows float32 here; the value screen of io.read_gaussians reports those.
    with np.errstate(over="ignore", invalid="ignore"):
        positions = (g.positions.astype(np.float64) @ a.T + m[:3, 3]).astype(np.float32)
    # Node rotation as a quaternion (w, x, y, z), composed in front of every splat's rotation.
    qn = _matrix_to_quaternion(rotation)
    q = g.rotations.astype(np.float64)
    w0, x0, y0, z0 = qn
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    composed = np.stack([w0 * w - x0 * x - y0 * y - z0 * z, w0 * x + x0 * w + y0 * z - z0 * y,
                         w0 * y - x0 * z + y0 * w + z0 * x, w0 * z + x0 * y - y0 * x + z0 * w], axis=1)
    rest = g.sh_rest
    if rest.shape[1]:
        rest = np.einsum("jk,nkc->njc", sh_rotation(rotation, g.sh_degree), rest.astype(np.float64))
    return Gaussians(positions, normalize_quaternions(composed), g.log_scales + np.float32(math.log(scale)),
                     g.opacity_logits, g.sh_dc, rest)


def _matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return np.array([w, x, y, z])


def _sh_degree(path: str, field: str, attributes: dict) -> int:
    degree = 0
    for band in (1, 2, 3):
        present = [f"{PREFIX}SH_DEGREE_{band}_COEF_{n}" in attributes for n in range(SH_BAND_COEFFS[band])]
        if all(present) and degree == band - 1:
            degree = band
        elif any(present):
            raise InputError(path, field, f"SH degree {band} is partially defined or follows a missing degree "
                             "(every coefficient of every degree up to the highest must be present)")
    return degree


def _primitive(doc: _Document, mesh: int, number: int, primitive: dict, drop_invalid: bool,
               spz_axes: str) -> Gaussians:
    field = f"meshes[{mesh}].primitives[{number}]"
    splat = primitive["extensions"][EXTENSION]
    if not isinstance(splat, dict):
        raise InputError(doc.path, field, f"{EXTENSION} must be an object")
    kernel = splat.get("kernel", "ellipse")
    if kernel != "ellipse":
        raise InputError(doc.path, f"{field} kernel", f"{kernel!r} (only 'ellipse' is supported)")
    if splat.get("colorSpace", "srgb_rec709_display") != "srgb_rec709_display":
        warnings.warn(f"{doc.path}: {field}: colorSpace {splat.get('colorSpace')!r}: colours are kept as stored "
                      "(our renderer blends display sRGB values)", stacklevel=4)
    if primitive.get("mode", 4) != 0:
        raise InputError(doc.path, f"{field} mode",
                         f"{primitive.get('mode', 4)!r} (a splat primitive must be POINTS, 0)")
    attributes = primitive.get("attributes")
    if not isinstance(attributes, dict) or "POSITION" not in attributes:
        raise InputError(doc.path, f"{field} attributes", "missing, or without POSITION")
    nested = splat.get("extensions", {}) if isinstance(splat.get("extensions", {}), dict) else {}
    position_count = doc.item("accessors", attributes["POSITION"]).get("count")
    if SPZ_EXTENSION in nested:
        spz = nested[SPZ_EXTENSION]
        if not isinstance(spz, dict) or "bufferView" not in spz:
            raise InputError(doc.path, f"{field} {SPZ_EXTENSION}", "needs a bufferView")
        buffer, offset, length, _ = doc.buffer_view(spz["bufferView"])
        g = decode_spz(f"{doc.path} (bufferView {spz['bufferView']}, SPZ)", bytes(buffer[offset:offset + length]))
        if position_count != len(g):
            raise InputError(doc.path, f"{field} POSITION accessor", f"count {position_count!r}, but the SPZ data "
                             f"holds {len(g)} splats")
        # SPZ content is packed from glTF's LUF into SPZ's RUB; our SPZ decoder returns RDF: turn to LUF so node
        # transforms apply in glTF space like for plain accessors. With spz_axes "luf" the SPZ holds the glTF values
        # unconverted (as CesiumJS reads it): undo the decoder's RUB -> RDF turn instead.
        return turn(g, LUF_TO_RDF if spz_axes == "rub" else RDF_TO_RUB)
    for name in ("ROTATION", "SCALE", "OPACITY", "SH_DEGREE_0_COEF_0"):
        if PREFIX + name not in attributes:
            raise InputError(doc.path, f"{field} attributes", f"missing {PREFIX}{name} (required by {EXTENSION})")
    positions = _accessor(doc, attributes["POSITION"], "POSITION", "POSITION", "VEC3", None)
    n = len(positions)
    xyzw = _accessor(doc, attributes[PREFIX + "ROTATION"], "ROTATION", "ROTATION", "VEC4", n)
    scales = _accessor(doc, attributes[PREFIX + "SCALE"], "SCALE", "SCALE", "VEC3", n)
    opacity = _accessor(doc, attributes[PREFIX + "OPACITY"], "OPACITY", "OPACITY", "SCALAR", n)[:, 0]
    sh_dc = _accessor(doc, attributes[PREFIX + "SH_DEGREE_0_COEF_0"], "SH_DEGREE_0_COEF_0", "SH", "VEC3", n)
    degree = _sh_degree(doc.path, f"{field} attributes", attributes)
    rest = [_accessor(doc, attributes[name], name[len(PREFIX):], "SH", "VEC3", n) for name in
            sh_attribute_names(degree)]
    sh_rest = np.stack(rest, axis=1) if rest else np.zeros((n, 0, 3), np.float32)
    with np.errstate(invalid="ignore"):
        checks = {
            "non-finite POSITION": ~np.isfinite(positions).all(axis=1),
            "non-finite or zero-length ROTATION": ~np.isfinite(xyzw).all(axis=1) | ~(np.abs(xyzw) > 0).any(axis=1),
            "negative or non-finite SCALE": ~((scales >= 0) & np.isfinite(scales)).all(axis=1),
            "OPACITY outside [0, 1]": ~((opacity >= 0) & (opacity <= 1)),
            "non-finite SH": ~np.isfinite(sh_dc).all(axis=1) | ~np.isfinite(sh_rest).all(axis=(1, 2)),
        }
    bad = np.zeros(n, bool)
    for mask in checks.values():
        bad |= mask
    if bad.any():
        detail = ", ".join(f"{int(mask.sum())} {what}" for what, mask in checks.items() if mask.any())
        msg = f"{some_of(int(bad.sum()), n, 'splats', ('is', 'are'))} invalid ({detail})"
        if not drop_invalid:
            raise InputError(doc.path, field, f"{msg}; {DROP_INVALID_HINT}")
        warnings.warn(f"{doc.path}: {field}: {msg}; dropped", stacklevel=4)
        keep = ~bad
        positions, xyzw, scales, opacity, sh_dc, sh_rest = (a[keep] for a in (positions, xyzw, scales, opacity,
                                                                              sh_dc, sh_rest))
    with np.errstate(divide="ignore"):
        log_scales = np.maximum(np.log(scales), MIN_LOG_SCALE)
    return Gaussians(positions=positions, rotations=normalize_quaternions(xyzw[:, [3, 0, 1, 2]]),
                     log_scales=log_scales, opacity_logits=opacity_logits_from_unit(opacity), sh_dc=sh_dc,
                     sh_rest=sh_rest)


def read_gltf(path: str | os.PathLike, drop_invalid: bool = False, spz_axes: str = "rub") -> Gaussians:
    """Every KHR_gaussian_splatting primitive of a .glb / .gltf, in world space, in our RDF axes.

    spz_axes: how SPZ content stores glTF's axes: "rub" (the extension's text) or "luf" (unconverted, as CesiumJS
    reads it; see splatstream/writers/glb.py)."""
    path = os.fspath(path)
    doc = _load(path)
    used = doc.gltf.get("extensionsUsed", [])
    required = doc.gltf.get("extensionsRequired", [])
    supported = {EXTENSION, SPZ_EXTENSION}
    if not isinstance(required, list) or not all(isinstance(e, str) for e in required):
        raise InputError(path, "extensionsRequired", f"{required!r} (expected a list of extension names)")
    unknown = [e for e in required if e not in supported]
    if unknown:
        raise InputError(path, "extensionsRequired", f"{unknown} are not supported (we read {sorted(supported)})")
    parts: list[Gaussians] = []
    for mesh, world in _node_matrices(doc):
        primitives = doc.item("meshes", mesh).get("primitives", [])
        if not isinstance(primitives, list):
            raise InputError(path, f"meshes[{mesh}].primitives", "expected a list")
        for number, primitive in enumerate(primitives):
            extensions = primitive.get("extensions") if isinstance(primitive, dict) else None
            if not isinstance(extensions, dict) or EXTENSION not in extensions:
                continue
            g = _primitive(doc, mesh, number, primitive, drop_invalid, spz_axes)
            parts.append(_apply_matrix(path, g, world))
    if not parts:
        hint = "" if isinstance(used, list) and EXTENSION in used else f" (extensionsUsed does not list {EXTENSION})"
        raise InputError(path, "meshes", f"no primitive with {EXTENSION} in the scene{hint}")
    return turn(Gaussians.concatenate(parts), LUF_TO_RDF)
