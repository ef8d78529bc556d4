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
  parent with no children is a leaf to Spark and would be drawn at every distance).
* Leaves of our tree shallower than the deepest are leaves of the splat tree at their depth: our REPLACE cut at
  depth d is exactly the splats at splat depth d + 1 plus the leaves above them.

Encodings (per chunk, every property deflate-compressed as Spark's "gz"): center f32, alpha f16 (linear
opacity; `lodOpacity` is set as Spark's writer sets it for LoD trees, which only widens the range to [0, 2]),
rgb f16 (0.5 + SH_C0 * dc), scales f32 (linear), orientation f32 (x, y, z with w >= 0), SH bands f16,
child_count u16, child_start u32. Spark's own defaults quantise to 8 bits; these keep our decoded values so a
round trip returns them (sizes against that in BENCHMARKS.md).
"""
from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from ..gaussians import SH_C0, Gaussians

RAD_MAGIC = 0x30444152  # "RAD0"
RAD_CHUNK_MAGIC = 0x43444152  # "RADC"
CHUNK_SPLATS = 65536  # Spark's traversal addresses a child as (chunk << 16) | index: the size is fixed
MAX_CHILDREN = 0xFFFF  # child_count is u16
GZ_LEVEL = 6
STEAL_CANDIDATES = 16
NEAREST_BLOCK_BYTES = 32 << 20
GENERATOR = "splatstream"


@dataclass(frozen=True)
class TreeTile:
    """One tile of our tree as the export needs it: its depth, children and decoded splats."""

    id: int
    level: int
    children: tuple[int, ...]
    splats: Gaussians


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
    q = g.rotations.astype(np.float64)
    qw, qx, qy, qz = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rot = np.stack([
        np.stack([1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)], -1),
        np.stack([2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)], -1),
        np.stack([2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)], -1)], 1)
    s2 = np.exp(2 * g.log_scales.astype(np.float64))
    cov = np.einsum("nij,nj,nkj->nik", rot, s2, rot)
    d = p - mean
    total = np.einsum("n,nij->ij", w, cov + d[:, :, None] * d[:, None, :])
    values, vectors = np.linalg.eigh(total)
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] = -vectors[:, 0]
    m = vectors
    # Rotation matrix to a (w, x, y, z) quaternion (Shepperd's method, the w-largest branch is enough for the
    # sign-fixed matrix, with a fallback on the largest diagonal).
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
    first), in blocks of bounded memory."""
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
    orphans = np.flatnonzero(counts == 0)
    if len(orphans) and len(children) > 1:
        near = nearest(parents[orphans], children, STEAL_CANDIDATES).reshape(len(orphans), -1)
        for parent, candidates in zip(orphans, near, strict=True):
            for child in candidates:
                if counts[to[child]] > 1:
                    counts[to[child]] -= 1
                    to[child] = parent
                    counts[parent] = 1
                    break
    return to


def rad_tree(tiles: dict[int, TreeTile], root: int) -> RadTree:
    """The RAD splat tree of a tree of ours (see the module's docstring)."""
    root_tile = tiles[root]
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


def _properties(tree: RadTree, base: int, count: int, sh_degree: int) -> list[tuple[dict, bytes]]:
    g = tree.splats.subset(np.arange(base, base + count))
    q = g.rotations.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, :1] < 0, -q, q)  # Spark stores x, y, z and rebuilds w >= 0
    props = [
        ("center", "f32", _planar(g.positions, "<f4")),
        ("alpha", "f16", _planar(g.opacities, "<f2")),
        ("rgb", "f16", _planar(0.5 + SH_C0 * g.sh_dc.astype(np.float64), "<f2")),
        ("scales", "f32", _planar(np.exp(g.log_scales.astype(np.float64)), "<f4")),
        ("orientation", "f32", _planar(q[:, 1:], "<f4")),
    ]
    for band, (lo, hi) in zip((1, 2, 3), ((0, 3), (3, 8), (8, 15)), strict=True):
        if band <= sh_degree:
            props.append((f"sh{band}", "f16", _planar(g.sh_rest[:, lo:hi, :].reshape(count, -1), "<f2")))
    props.append(("child_count", "u16", _planar(tree.child_count[base:base + count], "<u2")))
    props.append(("child_start", "u32", _planar(tree.child_start[base:base + count], "<u4")))
    return [({"property": name, "encoding": enc, "compression": "gz"}, _deflate(data)) for name, enc, data in props]


def _encoding() -> dict:
    # Spark's writer sets lodOpacity on every LoD tree (alpha read in [0, 2]); our alphas stay in [0, 1].
    return {"lodOpacity": True}


def rad_chunk(tree: RadTree, base: int, count: int, sh_degree: int) -> bytes:
    """One RADC chunk: magic, JSON length, JSON (padded to 8), payload length u64, properties each padded to 8."""
    props = _properties(tree, base, count, sh_degree)
    offset = 0
    metas = []
    for meta, data in props:
        metas.append({"offset": offset, "bytes": len(data), **meta})
        offset += len(_pad8(data))
    meta = {"version": 1, "base": base, "count": count, "payloadBytes": offset, "maxSh": sh_degree,
            "lodTree": True, "splatEncoding": _encoding(), "properties": metas}
    text = json.dumps(meta, separators=(",", ":")).encode("utf-8")
    return b"".join([struct.pack("<II", RAD_CHUNK_MAGIC, len(text)), _pad8(text), struct.pack("<Q", offset),
                     *(_pad8(data) for _, data in props)])


def rad_bytes(tree: RadTree, sh_degree: int) -> bytes:
    """The whole .rad file: magic, JSON length, JSON (padded to 8), then the chunks at their offsets (which the
    header gives relative to the end of the padded JSON)."""
    n = len(tree.splats)
    chunks = [rad_chunk(tree, base, min(CHUNK_SPLATS, n - base), sh_degree) for base in range(0, n, CHUNK_SPLATS)]
    ranges, offset = [], 0
    for c in chunks:
        ranges.append({"offset": offset, "bytes": len(c)})
        offset += len(c)
    meta = {"version": 1, "type": "gsplat", "count": n, "maxSh": sh_degree, "lodTree": True,
            "chunkSize": CHUNK_SPLATS, "allChunkBytes": offset, "chunks": ranges, "splatEncoding": _encoding(),
            "comment": GENERATOR}
    text = json.dumps(meta, indent=2).encode("utf-8") + b"\n"
    return b"".join([struct.pack("<II", RAD_MAGIC, len(text)), _pad8(text), *chunks])
