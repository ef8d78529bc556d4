"""A tile tree of ours (format_spec/lod.md) as Spark 2's RAD file (format_spec/foreign_formats.md, "Our RAD
export"), following Spark's own writer (rust/spark-lib/src/rad.rs) and its paged loader (src/SplatPager.ts).

RAD's LoD tree is a tree of **splats**, not of tiles: splat 0 is the root, every splat names a contiguous run of
children (`child_start`, `child_count`), and Spark's traversal replaces a splat by its children while their
projected size is above its pixel limit and its splat budget allows. Splats are stored in chunks of 65536 (the
paging unit: Spark fetches a chunk once a traversal needs a child in it, by an HTTP range request).

The mapping (pure; `splatstream/rad_export.py` wires it to a scene):

* Splats are written breadth-first by depth: the root splat, then the splats of our root tile, then those of our
  tiles at depth 1, and so on, so the coarse levels sit in the first chunks and a parent's children are one run.
* Splat 0 is a single splat standing for our root tile (its moment-matched merge: opacity-weighted mean and
  covariance, colour and SH the weighted mean, opacity the largest); unless the root tile holds one splat, which
  is then the root itself.
* The splats of our tile T at depth d + 1 become children of the splats of its parent tile: each goes to the
  parent tile's splat nearest to its centre. A parent splat that none chose takes, among its nearest child
  splats, the first whose parent keeps another child, so that no coarse splat survives into full detail (a
  parent with no children is a leaf to Spark and would be drawn at every distance), looking further (16, 64, 256,
  then 1,024 nearest) while any is left childless.
* Leaves of our tree shallower than the deepest are leaves of the splat tree at their depth: our REPLACE cut at
  depth d is exactly the splats at splat depth d + 1 plus the leaves above them.

Encodings (per chunk, every property deflate-compressed as Spark's "gz"), chosen by `encoding`:

* "exact" (the default): center f32, alpha f16 (linear opacity), rgb f16 (0.5 + SH_C0 * dc), scales f32
  (linear), orientation f32 (x, y, z with w >= 0), SH bands f16: our decoded values come back from a round trip.
* "spark": Spark's own defaults (RadEncoder's Auto choices, ported): center f32_lebytes, alpha r8 over [0, 2],
  rgb r8_delta and scales ln_0r8 over scene-wide ranges from percentiles, orientation oct88r8, SH s8.

Both: child_count u16, child_start u32, and `lodOpacity` set as Spark's writer sets it for every LoD tree (alpha
read in [0, 2]; ours stay in [0, 1]).
"""
from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..format.layout import morton_codes
from ..gaussians import SH_C0, Gaussians, covariances
from ..progress import Tally
from .sog_lod import TreeTile

RAD_MAGIC = 0x30444152  # "RAD0"
RAD_CHUNK_MAGIC = 0x43444152  # "RADC"
CHUNK_SPLATS = 65536  # Spark's traversal addresses a child as (chunk << 16) | index: the size is fixed
MAX_CHILDREN = 0xFFFF  # child_count is u16
GZ_LEVEL = 6
# A childless parent looks among this many nearest child splats for one to take, then 4x as many for those still
# childless, up to the last: on playbot's kept tree (PlayCanvas's own levels, issue 31) 16 left 61 coarse splats
# childless, each drawn by Spark at full detail and read back by `convert` as part of the finest level.
STEAL_CANDIDATES = (16, 64, 256, 1024)
NEAREST_BLOCK_BYTES = 32 << 20
NEAREST_BRUTE_PAIRS = 1 << 22  # below this many pairs, every pair
NEAREST_QUERY_BLOCK = 256
NEAREST_WINDOW = 128  # centres near a block in Morton order that bound its k-th distance
GENERATOR = "splatstream"
ENCODINGS = ("exact", "spark")
LOD_ALPHA_MAX = 2.0  # alpha's r8 range in a LoD tree (lodOpacity), as Spark's writer sets it
LN_SCALE_ZERO = -30.0  # ln scales at or below this are "flat" (code 0) in ln_0r8, as Spark's writer passes


@dataclass(frozen=True)
class RadTree:
    """A RAD splat tree: splats in file order, each with its run of children; `depth` per splat (0 = root)."""

    splats: Gaussians
    child_count: np.ndarray  # (N,) uint16
    child_start: np.ndarray  # (N,) uint32
    depth: np.ndarray  # (N,) int

    def levels(self) -> int:
        return int(self.depth.max()) + 1 if len(self.depth) else 0

    def cut(self, depth: int) -> np.ndarray:
        """Rows of the splats drawn when every splat above `depth` is refined: those at that depth and the leaves
        above it (REPLACE)."""
        return np.flatnonzero((self.depth == depth) | ((self.depth < depth) & (self.child_count == 0)))


def merge_splats(g: Gaussians) -> Gaussians:
    """One splat moment-matched to `g`: opacity-weighted mean and covariance; colour and SH weighted means."""
    alpha = g.opacities.astype(np.float64)
    w = alpha / alpha.sum() if alpha.sum() > 0 else np.full(len(g), 1.0 / len(g))
    p = g.positions.astype(np.float64)
    mean = w @ p
    cov = covariances(g).astype(np.float64)
    d = p - mean
    total = np.einsum("n,nij->ij", w, cov + d[:, :, None] * d[:, None, :])
    values, vectors = np.linalg.eigh(total)
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] = -vectors[:, 0]
    m = vectors
    # The eigenvectors (a rotation once the determinant is +1) as a (w, x, y, z) quaternion: Shepperd's method,
    # from the trace when it is positive, else from the largest diagonal element (numerically stable both ways).
    tr = np.trace(m)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        quat = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diagonal(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        quat = [0.0] * 4
        quat[0] = (m[k, j] - m[j, k]) / s
        quat[1 + i] = 0.25 * s
        quat[1 + j] = (m[j, i] + m[i, j]) / s
        quat[1 + k] = (m[k, i] + m[i, k]) / s
    quat = np.array(quat) / np.linalg.norm(quat)
    top = float(min(max(alpha.max(), 1e-6), 1 - 1e-6))
    return Gaussians(
        positions=mean[None].astype(np.float32), rotations=quat[None].astype(np.float32),
        log_scales=(0.5 * np.log(np.maximum(values, 1e-30)))[None].astype(np.float32),
        opacity_logits=np.array([np.log(top / (1 - top))], np.float32),
        sh_dc=(w @ g.sh_dc.astype(np.float64))[None].astype(np.float32),
        sh_rest=np.einsum("n,nkc->kc", w, g.sh_rest.astype(np.float64))[None].astype(np.float32))


def nearest(points: np.ndarray, centres: np.ndarray, k: int = 1) -> np.ndarray:
    """Indices of the k nearest centres of every point (squared Euclidean; (N,) for k = 1, else (N, k) nearest
    first; equal distances in index order), the same as `nearest_brute`.

    Spatial blocks instead of every pair (a 16,384-splat leaf tile against its 8,192 parents was 134 M pairs, and
    export-rad of a 1M scene with such leaves took 320 s): the points in Morton order, in blocks of
    NEAREST_QUERY_BLOCK; for each block, the k-th nearest among the centres near it in Morton order bounds every
    point's k-th distance by r, so only the centres inside the block's box grown by r can be among the k nearest,
    and the exact search runs over those (in index order, so ties break as in `nearest_brute`)."""
    k = min(k, len(centres))
    if len(points) * len(centres) <= NEAREST_BRUTE_PAIRS or k == 0:
        return nearest_brute(points, centres, k)
    points = np.asarray(points, np.float64)
    centres = np.asarray(centres, np.float64)
    lo = np.minimum(points.min(axis=0), centres.min(axis=0))
    hi = np.maximum(points.max(axis=0), centres.max(axis=0))
    point_codes = morton_codes(points, lo, hi)
    centre_codes = morton_codes(centres, lo, hi)
    point_order = np.argsort(point_codes, kind="stable")
    centre_order = np.argsort(centre_codes, kind="stable")
    sorted_codes = centre_codes[centre_order]
    x_order = np.argsort(centres[:, 0], kind="stable")
    sorted_x = centres[x_order, 0]
    cc = (centres ** 2).sum(axis=1)
    out = np.empty((len(points), k), np.int64)
    half = max(NEAREST_WINDOW // 2, k)
    for start in range(0, len(points), NEAREST_QUERY_BLOCK):
        rows = point_order[start:start + NEAREST_QUERY_BLOCK]
        block = points[rows]
        a = int(np.searchsorted(sorted_codes, point_codes[rows[0]]))
        b = int(np.searchsorted(sorted_codes, point_codes[rows[-1]], side="right"))
        near = centre_order[max(0, a - half):min(len(centres), b + half)]
        d = (block ** 2).sum(axis=1)[:, None] - 2.0 * (block @ centres[near].T) + cc[near][None, :]
        kth = d.min(axis=1) if k == 1 else np.partition(d, k - 1, axis=1)[:, k - 1]
        radius = float(np.sqrt(max(0.0, kth.max())))
        radius = radius * (1 + 1e-9) + 1e-12 * (1 + float(np.abs(hi - lo).max()))
        box_lo, box_hi = block.min(axis=0) - radius, block.max(axis=0) + radius
        in_x = x_order[np.searchsorted(sorted_x, box_lo[0]):np.searchsorted(sorted_x, box_hi[0], side="right")]
        c = centres[in_x]
        candidates = np.sort(in_x[np.all((c[:, 1:] >= box_lo[1:]) & (c[:, 1:] <= box_hi[1:]), axis=1)])
        found = nearest_brute(block, centres[candidates], k)
        out[rows] = candidates[found.reshape(len(rows), k)]
    return out[:, 0] if k == 1 else out


def nearest_brute(points: np.ndarray, centres: np.ndarray, k: int = 1) -> np.ndarray:
    """`nearest` over every pair, in blocks of bounded memory (the reference, and the path for small inputs)."""
    cc = (centres ** 2).sum(axis=1)
    k = min(k, len(centres))
    out = np.empty((len(points), k), np.int64)
    step = max(1, NEAREST_BLOCK_BYTES // (8 * max(1, len(centres))))
    for i in range(0, len(points), step):
        d = points[i:i + step] @ centres.T
        d *= -2.0
        d += cc[None, :]
        if k == 1:
            out[i:i + step, 0] = np.argmin(d, axis=1)
        else:
            part = np.argpartition(d, k - 1, axis=1)[:, :k]
            order = np.argsort(np.take_along_axis(d, part, axis=1), axis=1, kind="stable")
            out[i:i + step] = np.take_along_axis(part, order, axis=1)
    return out[:, 0] if k == 1 else out


def _parents(children: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """For each child centre, the index of its parent: the nearest parent centre, then every parent given at
    least one child where a neighbouring parent can spare one (see the module's docstring)."""
    to = nearest(children, parents)
    counts = np.bincount(to, minlength=len(parents))
    for k in STEAL_CANDIDATES:
        orphans = np.flatnonzero(counts == 0)
        if not len(orphans) or len(children) <= 1:
            break
        near = nearest(parents[orphans], children, k).reshape(len(orphans), -1)
        for parent, candidates in zip(orphans, near, strict=True):
            for child in candidates:
                if counts[to[child]] > 1:
                    counts[to[child]] -= 1
                    to[child] = parent
                    counts[parent] = 1
                    break
        if k >= len(children):
            break
    return to


def rad_tree(tiles: dict[int, TreeTile], root: int,
             progress: Callable[[float], None] | None = None) -> RadTree:
    """The RAD splat tree of a tree of ours (see the module's docstring). `progress` hears the share of the splats
    below the root given their parents (the nearest-parent searches are most of an export's time: 31 of 34 s of
    CPU for playbot's 500,000 splats on a busy 2-core machine, rad_bytes the rest)."""
    root_tile = tiles[root]
    placed = Tally(progress, sum(len(t.splats) for t in tiles.values()) - len(root_tile.splats))
    # Each depth as (tile, row) per splat in file order; the splats of a depth are the children of the one above.
    tile_ids = np.full(len(root_tile.splats), root, np.int64)
    rows = np.arange(len(root_tile.splats))
    parts: list[Gaussians] = [root_tile.splats]
    child_count: list[np.ndarray] = []
    depths = [np.zeros(len(root_tile.splats), np.int64)]
    if len(root_tile.splats) > 1:
        if len(root_tile.splats) > MAX_CHILDREN:
            raise ValueError(f"root tile of {len(root_tile.splats)} splats: a RAD splat has at most "
                             f"{MAX_CHILDREN} children")
        parts.insert(0, merge_splats(root_tile.splats))
        child_count.append(np.array([len(root_tile.splats)], np.int64))
        depths = [np.zeros(1, np.int64), np.ones(len(root_tile.splats), np.int64)]
    depth = int(depths[-1][0])
    while len(tile_ids):
        kid_tiles, kid_rows, kid_parent = [], [], []
        for tid in np.unique(tile_ids):
            tile = tiles[int(tid)]
            if not tile.children:
                continue
            mine = np.flatnonzero(tile_ids == tid)
            kids = [tiles[c] for c in tile.children]
            pos = np.concatenate([k.splats.positions for k in kids]).astype(np.float64)
            to = _parents(pos, tile.splats.positions[rows[mine]].astype(np.float64))
            kid_tiles.append(np.concatenate([np.full(len(k.splats), k.id, np.int64) for k in kids]))
            kid_rows.append(np.concatenate([np.arange(len(k.splats)) for k in kids]))
            kid_parent.append(mine[to])
            placed.add(len(pos))
        if not kid_tiles:
            child_count.append(np.zeros(len(tile_ids), np.int64))
            break
        parent = np.concatenate(kid_parent)
        order = np.argsort(parent, kind="stable")
        counts = np.bincount(parent, minlength=len(tile_ids))
        if counts.max() > MAX_CHILDREN:
            raise ValueError(f"depth {depth}: a splat would get {counts.max()} children; a RAD splat has at most "
                             f"{MAX_CHILDREN}")
        child_count.append(counts)
        tile_ids = np.concatenate(kid_tiles)[order]
        rows = np.concatenate(kid_rows)[order]
        depth += 1
        depths.append(np.full(len(tile_ids), depth, np.int64))
        parts.extend(tiles[t].splats.subset(rows[a:b]) for t, a, b in _runs(tile_ids))
    count = np.concatenate(child_count)
    # Every splat but the root is the child of one earlier splat and the file is ordered by parent: the children
    # of splat i follow the root and the children of every splat before i.
    start = 1 + np.concatenate([[0], np.cumsum(count)[:-1]])
    start[count == 0] = 0
    placed.finish()
    return RadTree(Gaussians.concatenate(parts), count.astype(np.uint16), start.astype(np.uint32),
                   np.concatenate(depths))


def _runs(tile_ids: np.ndarray) -> list[tuple[int, int, int]]:
    """(tile, first row, end row) of each run of equal consecutive `tile_ids`."""
    edges = np.concatenate([[0], np.flatnonzero(np.diff(tile_ids)) + 1, [len(tile_ids)]])
    return [(int(tile_ids[a]), int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def _deflate(data: bytes) -> bytes:
    """Spark's "gz" compression: raw DEFLATE (miniz_oxide's compress_to_vec), no zlib or gzip header."""
    c = zlib.compressobj(GZ_LEVEL, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush()


def _pad8(b: bytes) -> bytes:
    return b + bytes(-len(b) % 8)


def _planar(values: np.ndarray, dtype: str) -> bytes:
    """Spark's f32/f16/u16/u32 layouts: one plane per component (all splats' x, then y, ...), little-endian."""
    v = values.reshape(len(values), -1)
    return np.ascontiguousarray(v.T).astype(dtype).tobytes()


def _lebytes(values: np.ndarray) -> bytes:
    """f32_lebytes: the f32 components planar, then split into byte planes (every value's byte 0, then 1, ...)."""
    raw = np.frombuffer(_planar(values, "<f4"), np.uint8).reshape(-1, 4)
    return np.ascontiguousarray(raw.T).tobytes()


def _r8(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Spark's r8 bytes, planar: (value - min) / (max - min) in 255 steps, rounded and clamped."""
    v = values.reshape(len(values), -1).T.astype(np.float64)
    return np.clip(np.round((v - lo) / (hi - lo) * 255.0), 0, 255).astype(np.uint8)


def _delta(planes: np.ndarray) -> bytes:
    """r8_delta / s8_delta: each plane's bytes as differences from the previous splat's, modulo 256."""
    out = planes.astype(np.int16)
    out[:, 1:] -= planes[:, :-1].astype(np.int16)
    return (out % 256).astype(np.uint8).tobytes()


def _s8(values: np.ndarray, top: float) -> bytes:
    v = values.reshape(len(values), -1).T.astype(np.float64)
    return np.clip(np.round(v / top * 127.0), -127, 127).astype(np.int8).tobytes()


def _ln_0r8(scales: np.ndarray, lo: float, hi: float) -> bytes:
    """Spark's 8-bit log scales: 0 for a flat axis (ln scale at most -30), else 1 + ln scale in 254 steps."""
    ln = np.log(np.maximum(scales.T.astype(np.float64), 1e-38))
    code = np.clip(np.round((ln - lo) / (hi - lo) * 254.0), 0, 254) + 1
    return np.where(ln <= LN_SCALE_ZERO, 0, code).astype(np.uint8).tobytes()


def _oct88r8(q_wxyz: np.ndarray) -> bytes:
    """Spark's 3-byte quaternion (splat_encode::encode_quat_oct888): the rotation axis octahedrally mapped to two
    bytes, the angle (0..pi) in the third; splats interleaved, not planar."""
    w = np.clip(q_wxyz[:, 0], 0.0, 1.0)  # w >= 0 already
    theta = 2.0 * np.arccos(w)
    s = np.sin(theta * 0.5)
    small = np.abs(s) < 1e-6
    axis = np.where(small[:, None], [1.0, 0.0, 0.0], q_wxyz[:, 1:] / np.where(small, 1.0, s)[:, None])
    p = axis[:, :2] / np.abs(axis).sum(axis=1, keepdims=True)
    fold = axis[:, 2] < 0
    sign = np.where(p >= 0, 1.0, -1.0)
    folded = np.stack([(1 - np.abs(p[:, 1])) * sign[:, 0], (1 - np.abs(p[:, 0])) * sign[:, 1]], axis=1)
    p = np.where(fold[:, None], folded, p)
    uv = np.clip(np.round((p + 1.0) / 2.0 * 255.0), 0, 255)
    r = np.clip(np.round(theta / np.pi * 255.0), 0, 255)
    return np.column_stack([uv, r]).astype(np.uint8).tobytes()


@dataclass(frozen=True)
class SparkRanges:
    """The scene-wide ranges of Spark's 8-bit encodings, resolved as its RadEncoder resolves them."""

    rgb_min: float
    rgb_max: float
    ln_scale_min: float
    ln_scale_max: float
    sh_max: tuple[float, float, float]

    def splat_encoding(self) -> dict:
        return {"rgbMin": self.rgb_min, "rgbMax": self.rgb_max, "lnScaleMin": self.ln_scale_min,
                "lnScaleMax": self.ln_scale_max, "sh1Max": self.sh_max[0], "sh2Max": self.sh_max[1],
                "sh3Max": self.sh_max[2], "lodOpacity": True}


def spark_ranges(g: Gaussians) -> SparkRanges:
    """RadEncoder's resolve_*_encoding: colour between its 1st and 99th percentiles widened to [0, 1]; log scales
    of the two larger axes between the 1st and 99th percentiles widened to [-12, 9]; each SH band to the larger
    of |5th| and |95th| percentile, at least 1."""
    rgb = (0.5 + SH_C0 * g.sh_dc.astype(np.float64)).ravel()
    scales = np.sort(np.exp(g.log_scales.astype(np.float64)), axis=1)[:, 1:].ravel()
    sh = []
    for lo, hi in ((0, 3), (3, 8), (8, 15)):
        band = g.sh_rest[:, lo:hi, :].astype(np.float64).ravel()
        sh.append(max(abs(float(np.percentile(band, 5))), abs(float(np.percentile(band, 95))), 1.0)
                  if band.size else 1.0)
    return SparkRanges(
        rgb_min=min(float(np.percentile(rgb, 1)), 0.0), rgb_max=max(float(np.percentile(rgb, 99)), 1.0),
        ln_scale_min=min(float(np.log(max(np.percentile(scales, 1), 1e-30))), -12.0),
        ln_scale_max=max(float(np.log(max(np.percentile(scales, 99), 1e-30))), 9.0), sh_max=tuple(sh))


def _properties(tree: RadTree, base: int, count: int, sh_degree: int,
                ranges: SparkRanges | None) -> list[tuple[dict, bytes]]:
    g = tree.splats.subset(np.arange(base, base + count))
    q = g.rotations.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, :1] < 0, -q, q)  # Spark stores x, y, z and rebuilds w >= 0
    rgb = 0.5 + SH_C0 * g.sh_dc.astype(np.float64)
    scales = np.exp(g.log_scales.astype(np.float64))
    bands = [(band, g.sh_rest[:, lo:hi, :].reshape(count, -1))
             for band, (lo, hi) in zip((1, 2, 3), ((0, 3), (3, 8), (8, 15)), strict=True) if band <= sh_degree]
    if ranges is None:
        props = [
            ({"property": "center", "encoding": "f32"}, _planar(g.positions, "<f4")),
            ({"property": "alpha", "encoding": "f16"}, _planar(g.opacities, "<f2")),
            ({"property": "rgb", "encoding": "f16"}, _planar(rgb, "<f2")),
            ({"property": "scales", "encoding": "f32"}, _planar(scales, "<f4")),
            ({"property": "orientation", "encoding": "f32"}, _planar(q[:, 1:], "<f4")),
            *(({"property": f"sh{band}", "encoding": "f16"}, _planar(v, "<f2")) for band, v in bands),
        ]
    else:
        r = ranges
        props = [
            ({"property": "center", "encoding": "f32_lebytes"}, _lebytes(g.positions)),
            ({"property": "alpha", "encoding": "r8", "min": 0.0, "max": LOD_ALPHA_MAX},
             _r8(g.opacities, 0.0, LOD_ALPHA_MAX).tobytes()),
            ({"property": "rgb", "encoding": "r8_delta", "min": r.rgb_min, "max": r.rgb_max},
             _delta(_r8(rgb, r.rgb_min, r.rgb_max))),
            ({"property": "scales", "encoding": "ln_0r8", "min": r.ln_scale_min, "max": r.ln_scale_max},
             _ln_0r8(scales, r.ln_scale_min, r.ln_scale_max)),
            ({"property": "orientation", "encoding": "oct88r8"}, _oct88r8(q)),
            *(({"property": f"sh{band}", "encoding": "s8", "min": -r.sh_max[band - 1], "max": r.sh_max[band - 1]},
               _s8(v, r.sh_max[band - 1])) for band, v in bands),
        ]
    props.append(({"property": "child_count", "encoding": "u16"},
                  _planar(tree.child_count[base:base + count], "<u2")))
    props.append(({"property": "child_start", "encoding": "u32"},
                  _planar(tree.child_start[base:base + count], "<u4")))
    return [({**meta, "compression": "gz"}, _deflate(data)) for meta, data in props]


def rad_chunk(tree: RadTree, base: int, count: int, sh_degree: int, ranges: SparkRanges | None = None) -> bytes:
    """One RADC chunk: magic, JSON length, JSON (padded to 8), payload length u64, properties each padded to 8."""
    props = _properties(tree, base, count, sh_degree, ranges)
    offset = 0
    metas = []
    for meta, data in props:
        metas.append({"offset": offset, "bytes": len(data), **meta})
        offset += len(_pad8(data))
    meta = {"version": 1, "base": base, "count": count, "payloadBytes": offset, "maxSh": sh_degree,
            "lodTree": True, "splatEncoding": _encoding(ranges), "properties": metas}
    text = json.dumps(meta, separators=(",", ":")).encode("utf-8")
    return b"".join([struct.pack("<II", RAD_CHUNK_MAGIC, len(text)), _pad8(text), struct.pack("<Q", offset),
                     *(_pad8(data) for _, data in props)])


def _encoding(ranges: SparkRanges | None) -> dict:
    # Spark's writer sets lodOpacity on every LoD tree (alpha read in [0, 2]); our alphas stay in [0, 1].
    return {"lodOpacity": True} if ranges is None else ranges.splat_encoding()


def rad_bytes(tree: RadTree, sh_degree: int, encoding: str = "exact",
              progress: Callable[[float], None] | None = None) -> bytes:
    """The whole .rad file: magic, JSON length, JSON (padded to 8), then the chunks at their offsets (which the
    header gives relative to the end of the padded JSON). `encoding`: "exact" (f32/f16: our decoded values) or
    "spark" (Spark's own 8-bit defaults, RadEncoder's, with its scene-wide ranges). `progress` hears the share
    of the chunks written."""
    if encoding not in ENCODINGS:
        raise ValueError(f"RAD encoding {encoding!r}: expected one of {', '.join(ENCODINGS)}")
    ranges = spark_ranges(tree.splats) if encoding == "spark" else None
    n = len(tree.splats)
    chunks = []
    written = Tally(progress, n)
    for base in range(0, n, CHUNK_SPLATS):
        chunks.append(rad_chunk(tree, base, min(CHUNK_SPLATS, n - base), sh_degree, ranges))
        written.add(min(CHUNK_SPLATS, n - base))
    table, offset = [], 0
    for c in chunks:
        table.append({"offset": offset, "bytes": len(c)})
        offset += len(c)
    meta = {"version": 1, "type": "gsplat", "count": n, "maxSh": sh_degree, "lodTree": True,
            "chunkSize": CHUNK_SPLATS, "allChunkBytes": offset, "chunks": table, "splatEncoding": _encoding(ranges),
            "comment": GENERATOR}
    text = json.dumps(meta, indent=2).encode("utf-8") + b"\n"
    return b"".join([struct.pack("<II", RAD_MAGIC, len(text)), _pad8(text), *chunks])
