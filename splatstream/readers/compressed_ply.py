"""PlayCanvas compressed PLY (`.compressed.ply`, written by SuperSplat and splat-transform).

Layout, as decoded by splat-transform's decompressPly: an element `chunk` (one row per 256 splats) with the
float bounds min/max_x,y,z, min/max_scale_x,y,z (log scales) and optionally min/max_r,g,b; an element
`vertex` with uint32 packed_position (11-10-11 unorm), packed_rotation (2-bit index of the largest
component + 3 x 10-bit smallest three, scaled by 1/sqrt(2)), packed_scale (11-10-11 unorm) and
packed_color (RGBA 8-8-8-8 unorm, alpha = sigmoid(opacity)); and optionally an element `sh` of uchar
f_rest_0..N in the channel-major order of the 3DGS PLY.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import InputError
from ..gaussians import SH_C0, Gaussians, normalize_quaternions
from ..ply import PlyHeader, check_element_sizes, read_elements, read_header
from ..reader_support import check_memory, model_bytes_per_splat, opacity_logits_from_unit

CHUNK_SIZE = 256
CHUNK_BOUNDS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
CHUNK_COLOR_BOUNDS = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
SH_DEGREE_OF = {3: 1, 8: 2, 15: 3}  # SH rest coefficients per channel -> degree


def is_compressed_ply(header: PlyHeader) -> bool:
    vertex = header.element("vertex")
    return header.element("chunk") is not None and vertex is not None and \
        "packed_position" in [p[0] for p in vertex.properties]


def _check_schema(path: str, header: PlyHeader) -> tuple[int, bool, int]:
    """Validate the element/property layout. Returns (splat count, has chunk colours, SH rest coeffs)."""
    names = [e.name for e in header.elements] + header.unread  # an element with a list property is refused here
    extra = [n for n in names if n not in ("chunk", "vertex", "sh")]
    if extra or header.unread or names[:2] != ["chunk", "vertex"] or len(names) != len(set(names)):
        lists = f" ({', '.join(header.unread)} from the first with a list property)" if header.unread else ""
        raise InputError(path, "header", f"elements {names}{lists}: a compressed PLY has the elements chunk, vertex "
                         "and optionally sh, in that order, of numbers")
    chunk, vertex = header.element("chunk"), header.element("vertex")
    chunk_props = dict(chunk.properties)
    missing = [p for p in CHUNK_BOUNDS if p not in chunk_props]
    if missing:
        raise InputError(path, "element chunk", f"missing properties {', '.join(missing)}")
    has_color = any(p in chunk_props for p in CHUNK_COLOR_BOUNDS)
    expected = CHUNK_BOUNDS + (CHUNK_COLOR_BOUNDS if has_color else [])
    if sorted(chunk_props) != sorted(expected):
        raise InputError(path, "element chunk", f"properties {list(chunk_props)}: expected exactly the 12 bounds "
                         "min/max_x,y,z and min/max_scale_x,y,z, optionally with the 6 colour bounds min/max_r,g,b")
    wrong = [p for p, t in chunk.properties if t != "f4"]
    if wrong:
        raise InputError(path, "element chunk", f"properties {', '.join(wrong)} must be float")
    vertex_props = dict(vertex.properties)
    if sorted(vertex_props) != sorted(PACKED) or any(t != "u4" for t in vertex_props.values()):
        raise InputError(path, "element vertex", f"properties {vertex.properties}: expected exactly the uint "
                         "properties packed_position, packed_rotation, packed_scale, packed_color")
    n = vertex.count
    if chunk.count != -(-n // CHUNK_SIZE):
        raise InputError(path, "element chunk", f"{chunk.count} chunks for {n} splats: expected "
                         f"ceil({n} / {CHUNK_SIZE}) = {-(-n // CHUNK_SIZE)}")
    k = 0
    sh = header.element("sh")
    if sh is not None:
        sh_names = [p[0] for p in sh.properties]
        if len(sh_names) not in (9, 24, 45) or sh_names != [f"f_rest_{i}" for i in range(len(sh_names))]:
            raise InputError(path, "element sh", f"{len(sh_names)} properties: expected f_rest_0.. f_rest_N with "
                             "N + 1 = 9, 24 or 45 (SH degree 1, 2 or 3)")
        if any(t != "u1" for _, t in sh.properties):
            raise InputError(path, "element sh", "f_rest_* properties must be uchar")
        if sh.count != n:
            raise InputError(path, "element sh", f"{sh.count} rows for {n} splats: expected one row per splat")
        k = len(sh_names) // 3
    return n, has_color, k


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    mask = (1 << bits) - 1
    return ((packed >> np.uint32(shift)) & np.uint32(mask)).astype(np.float64) / mask


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    # Same expression as the reference decoder (not lo + (hi - lo) * t) so results match to the last bit.
    return lo * (1.0 - t) + hi * t


def _unpack_11_10_11(packed: np.ndarray) -> np.ndarray:
    return np.stack([_unorm(packed, 21, 11), _unorm(packed, 11, 10), _unorm(packed, 0, 11)], axis=1)


def unpack_rotations(packed: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (rot_0..rot_3 = w, x, y, z) from 2-10-10-10 smallest-three words."""
    norm = np.sqrt(2.0)  # the three small components lie in [-1/sqrt(2), 1/sqrt(2)]
    small = np.stack([(_unorm(packed, s, 10) - 0.5) * norm for s in (20, 10, 0)], axis=1)
    largest = np.sqrt(np.maximum(0.0, 1.0 - (small * small).sum(axis=1)))
    which = (packed >> np.uint32(30)).astype(np.intp)
    out = np.empty((len(packed), 4), np.float64)
    for index in range(4):
        rows = which == index
        others = [c for c in range(4) if c != index]
        out[np.ix_(rows, others)] = small[rows]
        out[rows, index] = largest[rows]
    return out


def read_compressed_ply(path: str | os.PathLike, drop_invalid: bool = False, header: PlyHeader | None = None
                        ) -> Gaussians:
    """Decode a compressed PLY. Once the chunk bounds are checked finite every packed word decodes to finite
    values, so there are no invalid splats to drop (`drop_invalid` is accepted for a uniform signature).
    `header`: the file's, when the caller parsed it already (io.open_input)."""
    path = os.fspath(path)
    header = header or read_header(path)
    if header.format != "binary_little_endian":
        raise InputError(path, "header", f"format {header.format}: a compressed PLY is binary_little_endian")
    n, has_color, k = _check_schema(path, header)
    check_element_sizes(path, header)
    # Packed words, SH bytes, and the float64 temporaries of decoding (about 6x the float32 model).
    check_memory(path, "element vertex", n, 16 + 3 * k + 6 * model_bytes_per_splat(k and SH_DEGREE_OF[k]))
    _, elements = read_elements(path, header)  # checks every element's size against the file length
    chunk, vertex = elements["chunk"], elements["vertex"]
    bound_names = CHUNK_BOUNDS + (CHUNK_COLOR_BOUNDS if has_color else [])
    for name in bound_names:
        finite = np.isfinite(chunk[name])
        if not finite.all():
            raise InputError(path, f"element chunk, property {name}",
                             f"chunk {int(np.argmin(finite))} has a non-finite bound (expected finite floats)")
    chunk_of = np.arange(n) // CHUNK_SIZE

    def bounds(axis_names: list[str]) -> tuple[np.ndarray, np.ndarray]:
        lo = np.stack([chunk["min_" + a].astype(np.float64)[chunk_of] for a in axis_names], axis=1)
        hi = np.stack([chunk["max_" + a].astype(np.float64)[chunk_of] for a in axis_names], axis=1)
        return lo, hi

    positions = _lerp(*bounds(["x", "y", "z"]), _unpack_11_10_11(vertex["packed_position"]))
    log_scales = _lerp(*bounds(["scale_x", "scale_y", "scale_z"]), _unpack_11_10_11(vertex["packed_scale"]))
    color_word = vertex["packed_color"]
    rgba = np.stack([_unorm(color_word, s, 8) for s in (24, 16, 8, 0)], axis=1)
    rgb = _lerp(*bounds(["r", "g", "b"]), rgba[:, :3]) if has_color else rgba[:, :3]
    rotations = unpack_rotations(vertex["packed_rotation"])
    if k:
        sh_bytes = elements["sh"].view("u1").reshape(n, 3 * k)
        unit = (sh_bytes.astype(np.float64) + 0.5) / 256.0
        unit[sh_bytes == 0] = 0.0
        unit[sh_bytes == 255] = 1.0
        # f_rest is channel-major (all R coefficients, then G, then B): (N, 3, K) -> (N, K, 3).
        sh_rest = ((unit - 0.5) * 8.0).reshape(n, 3, k).transpose(0, 2, 1)
    else:
        sh_rest = np.zeros((n, 0, 3))
    return Gaussians(
        positions=positions,
        rotations=normalize_quaternions(rotations.astype(np.float32)),
        log_scales=log_scales,
        opacity_logits=opacity_logits_from_unit(rgba[:, 3]),
        sh_dc=(rgb - 0.5) / SH_C0,
        sh_rest=sh_rest,
    )
