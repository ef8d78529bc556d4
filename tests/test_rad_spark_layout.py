"""Our RAD reader (splatstream/readers/rad.py) on files laid out byte for byte as Spark's own writer lays them out.

No .rad written by Spark could be had for these tests: Spark's writer is its Rust `build-lod` tool
(rust/spark-lib/src/rad.rs, `RadEncoder`), which is published neither on npm (@sparkjsdev/spark ships the
browser build: its WebAssembly decodes a RAD header but holds no encoder) nor in any package registry reachable
here, and cannot be built here (its crates, glam, hnsw and space among them, are on no reachable registry); the
.rad scenes Spark's examples load are on a storage host outside this machine's reach, and its repository holds
none. So `spark_rad` below is `RadEncoder` ported line by line from rad.rs and splat_encode.rs (Spark 2.2 /
commit 78bc65e of its repository): the same header (pretty JSON and a newline, padded to 8), the same chunks of
65,536 splats (compact JSON, u64 payload size, each property's raw-DEFLATE data padded to 8) and properties in
its order, each encoding its Rust function's arithmetic in f32 (rounding half away from zero, as Rust's `round`),
its `resolve_*` defaults when no encoding is set. What differs from a file Spark writes: the DEFLATE streams
(zlib's against miniz_oxide's at the same level 6: the same inflated bytes) and the digits of non-round numbers in
the JSON (serde prints an f32 in its shortest form, Python's json the same value as an f64). The encodings our
own writer never emits (f32, f16, f16_lebytes, ln_f16, s8_delta, r8 colour, u16 SH labels) are read here, and the
options of Spark's writer our reader takes (chunks in separate .radc files: `--rad-chunked`; SH by cluster codes:
`--cluster-sh`).
"""
from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
from test_sog_lod import _splats

from splatstream.errors import InputError
from splatstream.gaussians import SH_C0, Gaussians
from splatstream.readers.rad import read_rad, read_rad_tree

RAD_MAGIC, RAD_CHUNK_MAGIC = 0x30444152, 0x43444152
CHUNK_SIZE = 65536
F32 = np.float32


def _round(x: np.ndarray) -> np.ndarray:
    """Rust's f32::round: half away from zero."""
    return np.sign(x) * np.floor(np.abs(x) + F32(0.5))


def _planar(v: np.ndarray) -> np.ndarray:
    """rad.rs's loops `for d in 0..dims { for i in 0..count }`: the values of each dimension in turn."""
    return np.ascontiguousarray(v.reshape(len(v), -1).T).ravel()


def encode_f32(v):
    return _planar(v).astype("<f4").tobytes()


def encode_f16(v):
    return _planar(v).astype("<f2").tobytes()


def encode_lebytes(v, dtype):
    """encode_f32_lebytes / encode_f16_lebytes: `for b in bytes { for d in 0..dims { for i in 0..count } }`."""
    raw = _planar(v).astype(dtype).view(np.uint8).reshape(-1, np.dtype(dtype).itemsize)
    return np.ascontiguousarray(raw.T).tobytes()


def _r8(v, lo, hi):
    return _round(np.clip((_planar(v).astype(F32) - F32(lo)) / (F32(hi) - F32(lo)) * F32(255), 0, 255)).astype(np.uint8)


def _s8(v, mx):
    return _round(np.clip(_planar(v).astype(F32) / F32(mx) * F32(127), -127, 127)).astype(np.int8).view(np.uint8)


def _delta(q: np.ndarray, count: int) -> bytes:
    """`value.wrapping_sub(last)` along each dimension's run, `last` starting at 0."""
    q = q.reshape(-1, count)
    prev = np.concatenate([np.zeros((len(q), 1), np.uint8), q[:, :-1]], axis=1)
    return (q - prev).astype(np.uint8).tobytes()


def encode_r8(v, lo, hi):
    return _r8(v, lo, hi).tobytes()


def encode_r8_delta(v, lo, hi):
    return _delta(_r8(v, lo, hi), len(v))


def encode_s8(v, mx):
    return _s8(v, mx).tobytes()


def encode_s8_delta(v, mx):
    return _delta(_s8(v, mx), len(v))


def encode_ln_0r8(v, zero, lo, hi):
    """splat_encode::encode_scale8_zero for every value."""
    s = _planar(v).astype(F32)
    with np.errstate(divide="ignore", invalid="ignore"):
        ln = np.log(np.maximum(s, F32(1e-45))).astype(F32)
    code = _round(np.clip((ln - F32(lo)) / (F32(hi) - F32(lo)) * F32(254), 0, 254)) + 1
    return np.where((s <= 0) | (ln <= F32(zero)), 0, code).astype(np.uint8).tobytes()


def encode_ln_f16(v):
    return np.log(_planar(v).astype(F32)).astype("<f2").tobytes()


def encode_quat_oct88r8(q_xyzw: np.ndarray) -> bytes:
    """splat_encode::encode_quat_oct888 per splat (x, y, z, w)."""
    q = q_xyzw.astype(F32)
    q = np.where(q[:, 3:4] < 0, -q, q)
    theta = F32(2) * np.arccos(np.clip(q[:, 3], 0, 1)).astype(F32)
    s = np.sin(theta * F32(0.5)).astype(F32)
    small = np.abs(s) < 1e-6
    axis = np.where(small[:, None], np.array([1, 0, 0], F32), q[:, :3] / np.where(small, 1, s)[:, None])
    p = axis[:, :2] / np.abs(axis).sum(axis=1, keepdims=True)
    sign = np.where(p >= 0, F32(1), F32(-1))
    folded = np.column_stack([(1 - np.abs(p[:, 1])) * sign[:, 0], (1 - np.abs(p[:, 0])) * sign[:, 1]])
    p = np.where((axis[:, 2] < 0)[:, None], folded, p)

    def to_u8(x, lo, hi):
        return _round(np.clip((x - F32(lo)) / F32(hi - lo) * F32(255), 0, 255)).astype(np.uint8)

    return np.column_stack([to_u8(p[:, 0], -1, 1), to_u8(p[:, 1], -1, 1), to_u8(theta, 0, np.pi)]).tobytes()


def _quantile(values: np.ndarray, q: float) -> float:
    """rad.rs's `select_nth_unstable` at round(len * q), clamped to the last."""
    flat = np.sort(values.astype(F32).ravel())
    return float(flat[min(int(_round(np.array([len(flat) * q], F32))[0]), len(flat) - 1)])


def resolve(g: Gaussians, lod_tree: bool, max_sh: int, chosen: dict) -> tuple[dict, dict]:
    """RadEncoder::resolve_encoding: each property's encoding (`chosen` overrides Auto) and the SplatEncoding."""
    max_sh = min(max_sh, g.sh_degree)
    enc = {"rgbMin": 0.0, "rgbMax": 1.0, "lnScaleMin": -12.0, "lnScaleMax": 9.0, "sh1Max": 1.0, "sh2Max": 1.0,
           "sh3Max": 1.0}
    out = {"center": "f32_lebytes", "orientation": "oct88r8", **chosen}
    alpha = g.opacities.astype(F32)
    out.setdefault("alpha", "f16" if alpha.max() > 1.0 else "r8")
    rgb = (F32(0.5) + g.sh_dc.astype(F32) * F32(SH_C0)).ravel()
    rgb_min, rgb_max = min(_quantile(rgb, 0.01), 0.0), max(_quantile(rgb, 0.99), 1.0)
    if "rgb" not in out:
        out["rgb"] = "f16" if rgb_min < -1 or rgb_max > 2 else "r8_delta"
    if out["rgb"] in ("r8", "r8_delta"):
        enc["rgbMin"], enc["rgbMax"] = rgb_min, rgb_max
    scales = np.sort(np.exp(g.log_scales.astype(F32)), axis=1)[:, 1:]
    ln_min = min(float(np.log(max(_quantile(scales, 0.01), 1e-30))), -12.0)
    ln_max = max(float(np.log(max(_quantile(scales, 0.99), 1e-30))), 9.0)
    if "scales" not in out:
        out["scales"] = "ln_f16" if ln_max - ln_min > 25 else "ln_0r8"
    if out["scales"] == "ln_0r8":
        enc["lnScaleMin"], enc["lnScaleMax"] = ln_min, ln_max
    for band, (lo, hi) in zip((1, 2, 3), ((0, 3), (3, 8), (8, 15)), strict=True):
        if band <= max_sh:
            v = g.sh_rest[:, lo:hi, :]
            enc[f"sh{band}Max"] = max(abs(_quantile(v, 0.05)), abs(_quantile(v, 0.95)), 1.0)
    out.setdefault("sh", "s8")
    enc["lodOpacity"] = lod_tree
    return out, enc


def _property(name: str, encoding: str, values: np.ndarray, splat_enc: dict, lod_tree: bool,
              sh_max: float = 1.0) -> tuple[dict, bytes]:
    prop: dict = {"property": name, "encoding": encoding, "compression": "gz"}
    lo = hi = None
    if encoding == "f32":
        raw = encode_f32(values)
    elif encoding == "f16":
        raw = encode_f16(values)
    elif encoding == "f32_lebytes":
        raw = encode_lebytes(values, "<f4")
    elif encoding == "f16_lebytes":
        raw = encode_lebytes(values, "<f2")
    elif encoding in ("r8", "r8_delta"):
        lo, hi = (0.0, 2.0 if lod_tree else 1.0) if name == "alpha" else (splat_enc["rgbMin"], splat_enc["rgbMax"])
        raw = (encode_r8 if encoding == "r8" else encode_r8_delta)(values, lo, hi)
    elif encoding in ("s8", "s8_delta"):
        lo, hi = -sh_max, sh_max
        raw = (encode_s8 if encoding == "s8" else encode_s8_delta)(values, sh_max)
    elif encoding == "ln_0r8":
        lo, hi = splat_enc["lnScaleMin"], splat_enc["lnScaleMax"]
        raw = encode_ln_0r8(values, -30.0, lo, hi)
    elif encoding == "ln_f16":
        raw = encode_ln_f16(values)
    elif encoding == "oct88r8":
        raw = encode_quat_oct88r8(values)
    elif encoding in ("u16", "u32"):
        raw = _planar(values).astype("<u2" if encoding == "u16" else "<u4").tobytes()
    else:
        raise AssertionError(encoding)
    if lo is not None:
        prop["min"], prop["max"] = float(F32(lo)), float(F32(hi))
    deflate = zlib.compressobj(6, zlib.DEFLATED, -15)  # miniz_oxide's compress_to_vec: raw DEFLATE
    return prop, deflate.compress(raw) + deflate.flush()


def _pad8(data: bytes) -> bytes:
    return data + bytes(-len(data) % 8)


def spark_rad(g: Gaussians, child_count=None, child_start=None, max_sh: int = 3, chosen: dict | None = None,
              chunk_prefix: str = "", clusters: tuple[np.ndarray, list[np.ndarray]] | None = None,
              comment: str | None = None) -> tuple[bytes, dict[str, bytes]]:
    """The bytes RadEncoder::encode_with_chunks writes for these splats (and .radc files by name where
    `chunk_prefix` is given, as `build-lod --rad-chunked` does). `clusters`: (per-splat label, per band the
    codebook of cluster values), as RadEncoder::with_sh_clusters."""
    lod_tree = child_count is not None
    max_sh = min(g.sh_degree, max_sh)
    encodings, splat_enc = resolve(g, lod_tree, max_sh, chosen or {})
    q_xyzw = np.column_stack([g.rotations[:, 1:], g.rotations[:, :1]]).astype(F32)
    q_xyzw /= np.linalg.norm(q_xyzw, axis=1, keepdims=True)
    columns = {"center": g.positions.astype(F32), "alpha": g.opacities.astype(F32)[:, None],
               "rgb": F32(0.5) + g.sh_dc.astype(F32) * F32(SH_C0), "scales": np.exp(g.log_scales.astype(F32)),
               "orientation": q_xyzw if encodings["orientation"] == "oct88r8" else q_xyzw[:, :3]}
    bands = [("sh1", 0, 3), ("sh2", 3, 8), ("sh3", 8, 15)][:max_sh]
    chunks, ranges, offset = [], [], 0
    for base in range(0, len(g), CHUNK_SIZE):
        count = min(CHUNK_SIZE, len(g) - base)
        rows = slice(base, base + count)
        props = [_property(name, encodings[name], columns[name][rows], splat_enc, lod_tree)
                 for name in ("center", "alpha", "rgb", "scales", "orientation")]
        if clusters is not None:
            labels, books = clusters
            if base == 0:
                props += [_property(f"{name}_code", encodings["sh"], book.reshape(len(book), -1), splat_enc,
                                    lod_tree, splat_enc[f"{name}Max"])
                          for (name, _, _), book in zip(bands, books[:len(bands)], strict=True)]
            if max_sh:
                label_enc = "u32" if len(books[0]) > 65536 else "u16"
                props.append(_property("sh_label", label_enc, labels[rows, None], splat_enc, lod_tree))
        else:
            props += [_property(name, encodings["sh"], g.sh_rest[rows, lo:hi, :].reshape(count, -1), splat_enc,
                                lod_tree, splat_enc[f"{name}Max"]) for name, lo, hi in bands]
        if lod_tree:
            props.append(_property("child_count", "u16", child_count[rows, None], splat_enc, lod_tree))
            props.append(_property("child_start", "u32", child_start[rows, None], splat_enc, lod_tree))
        at = 0
        for prop, data in props:
            prop["offset"], prop["bytes"] = at, len(data)
            at += len(_pad8(data))
        meta = {"version": 1, "base": base, "count": count, "payloadBytes": at, "maxSh": max_sh}
        if lod_tree:
            meta["lodTree"] = True
        meta["splatEncoding"] = splat_enc
        meta["properties"] = [{k: p[k] for k in ("offset", "bytes", "property", "encoding", "compression", "min",
                                                 "max") if k in p} for p, _ in props]
        text = json.dumps(meta, separators=(",", ":")).encode()
        chunk = struct.pack("<II", RAD_CHUNK_MAGIC, len(text)) + _pad8(text) + struct.pack("<Q", at) + \
            b"".join(_pad8(d) for _, d in props)
        rng = {"offset": 0 if chunk_prefix else offset, "bytes": len(chunk)}
        if chunk_prefix:
            rng["filename"] = f"{chunk_prefix}{len(chunks)}.radc"
        ranges.append(rng)
        offset += len(chunk)
        chunks.append(chunk)
    header = {"version": 1, "type": "gsplat", "count": len(g), "maxSh": max_sh}
    if lod_tree:
        header["lodTree"] = True
    header |= {"chunkSize": CHUNK_SIZE, "allChunkBytes": offset, "chunks": ranges, "splatEncoding": splat_enc}
    if clusters is not None:
        header["shCodeCount"] = len(clusters[1][0])
    if comment is not None:
        header["comment"] = comment
    text = json.dumps(header, indent=2).encode() + b"\n"  # serde_json's pretty printer, and a newline
    head = struct.pack("<II", RAD_MAGIC, len(text)) + _pad8(text)
    if chunk_prefix:
        return head, {r["filename"]: c for r, c in zip(ranges, chunks, strict=True)}
    return head + b"".join(chunks), {}


def scene(n: int, sh_degree: int = 3, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[:, 0] = np.abs(q[:, 0])  # w >= 0: Spark's xyz-only encodings rebuild w as the positive root
    rest = {0: 0, 1: 3, 2: 8, 3: 15}[sh_degree]
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32) * 5, q.astype(np.float32),
                     rng.uniform(-6, -1, (n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                     rng.normal(scale=0.8, size=(n, 3)).astype(np.float32),
                     rng.normal(scale=0.3, size=(n, rest, 3)).astype(np.float32))


def binary_tree(n_leaves: int) -> tuple[np.ndarray, np.ndarray]:
    """child_count, child_start of a breadth-first tree whose interior splats have two children (one the last
    if the count is odd), `n_leaves` splats at the bottom: the shape of Spark's bhatt-lod output."""
    levels = [n_leaves]
    while levels[-1] > 1:
        levels.append((levels[-1] + 1) // 2)
    levels.reverse()  # root first
    count, start, first_child = [], [], 1
    for depth, width in enumerate(levels[:-1]):
        below = levels[depth + 1]
        for i in range(width):
            c = min(2, below - 2 * i)
            count.append(c)
            start.append(first_child)
            first_child += c
    count += [0] * levels[-1]
    start += [0] * levels[-1]
    return np.array(count, np.uint16), np.array(start, np.uint32)


def check_within_steps(g: Gaussians, back: Gaussians, encodings: dict, splat_enc: dict, lod_tree: bool) -> None:
    """Each attribute read back within its encoding's step (exact for f32, f32_lebytes)."""
    def tol(encoding: str, span: float, value_scale: np.ndarray | float = 1.0):
        return {"f32": 1e-6 * (1 + np.abs(value_scale)), "f32_lebytes": 1e-6 * (1 + np.abs(value_scale)),
                "f16": 1e-3 * (1 + np.abs(value_scale)), "f16_lebytes": 1e-3 * (1 + np.abs(value_scale)),
                "r8": span / 255 / 2 + 1e-5, "r8_delta": span / 255 / 2 + 1e-5, "s8": span / 254 / 2 + 1e-5,
                "s8_delta": span / 254 / 2 + 1e-5}[encoding]

    assert np.all(np.abs(back.positions - g.positions) <= tol(encodings["center"], 0, g.positions))
    alpha_span = 2.0 if lod_tree else 1.0
    assert np.all(np.abs(back.opacities - g.opacities) <= tol(encodings["alpha"], alpha_span, g.opacities) + 1e-4)
    rgb, rgb_back = 0.5 + g.sh_dc * SH_C0, 0.5 + back.sh_dc * SH_C0
    inside = (rgb >= splat_enc["rgbMin"]) & (rgb <= splat_enc["rgbMax"])
    span = splat_enc["rgbMax"] - splat_enc["rgbMin"]
    assert np.all(np.abs(rgb - rgb_back)[inside] <= tol(encodings["rgb"], span, rgb[inside]) + 1e-5)
    if encodings["scales"] == "ln_0r8":
        step = (splat_enc["lnScaleMax"] - splat_enc["lnScaleMin"]) / 254
        assert np.abs(back.log_scales - g.log_scales).max() <= step / 2 + 1e-4
    else:  # ln_f16: the log in f16
        assert np.abs(back.log_scales - g.log_scales).max() <= 4e-3
    dot = np.abs((g.rotations.astype(np.float64) * back.rotations).sum(axis=1))
    # oct88r8: 8-bit axis and angle; f16: xyz in f16, w rebuilt as the root of 1 - |xyz|^2 (coarse near w = 0)
    limit = {"oct88r8": 3.0, "f16": 3.0, "f32": 0.05}[encodings["orientation"]]
    assert np.degrees(2 * np.arccos(np.minimum(dot, 1))).max() < limit
    for band, (lo, hi) in zip((1, 2, 3), ((0, 3), (3, 8), (8, 15)), strict=True):
        if band > back.sh_degree:
            continue
        mx = splat_enc[f"sh{band}Max"]
        a, b = g.sh_rest[:, lo:hi], back.sh_rest[:, lo:hi]
        inside = np.abs(a) <= mx
        assert np.all(np.abs(a - b)[inside] <= tol(encodings["sh"], 2 * mx, a[inside]) + 1e-5), band


# Spark's defaults (Auto everywhere), then each encoding its writer offers that the defaults do not pick.
CASES = {
    "defaults": {},
    "exact": {"center": "f32", "alpha": "f32", "rgb": "f32", "scales": "f32", "orientation": "f32", "sh": "f32"},
    "half": {"center": "f16_lebytes", "alpha": "f16", "rgb": "f16", "scales": "ln_f16", "orientation": "f16",
             "sh": "s8_delta"},
    "plain_bytes": {"center": "f16", "rgb": "r8", "sh": "f16"},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_spark_layout_reads_back_within_each_encoding(tmp_path, case):
    g = scene(3000)
    count, start = binary_tree(len(g))
    n = len(count)
    # The tree's splats: the leaves are the scene; interior splats are copies of the leaves (values only).
    tree_splats = g.subset(np.arange(n) % len(g))
    data, _ = spark_rad(tree_splats, count, start, chosen=CASES[case], comment="spark layout test")
    (tmp_path / "s.rad").write_bytes(data)
    back = read_rad_tree(tmp_path / "s.rad")
    assert len(back.splats) == n and (back.child_count == count).all() and (back.child_start == start).all()
    assert back.levels() == int(np.ceil(np.log2(len(g)))) + 1
    encodings, splat_enc = resolve(tree_splats, True, 3, CASES[case])
    check_within_steps(tree_splats, back.splats, encodings, splat_enc, True)
    leaves = read_rad(tmp_path / "s.rad")
    assert len(leaves) == len(g)


def test_spark_flat_file_of_several_chunks(tmp_path):
    """No LoD tree (Spark's writer given plain splats): every splat a leaf; 70,000 splats fill two chunks."""
    g = scene(70_000, sh_degree=1, seed=2)
    data, _ = spark_rad(g)
    (tmp_path / "flat.rad").write_bytes(data)
    header = json.loads(data[8:8 + struct.unpack_from("<I", data, 4)[0]])
    assert len(header["chunks"]) == 2 and "lodTree" not in header
    back = read_rad_tree(tmp_path / "flat.rad")
    assert len(back.splats) == len(g) and (back.child_count == 0).all() and back.levels() == 1
    encodings, splat_enc = resolve(g, False, 3, {})
    assert encodings["rgb"] == "r8_delta" and encodings["alpha"] == "r8" and encodings["scales"] == "ln_0r8"
    check_within_steps(g, back.splats, encodings, splat_enc, False)


def test_spark_rad_chunked_reads_its_radc_files(tmp_path):
    """`build-lod --rad-chunked`: the header file names a .radc file per chunk, beside it."""
    g = scene(70_000, sh_degree=0, seed=3)
    head, files = spark_rad(g, chunk_prefix="scene-lod-")
    (tmp_path / "scene-lod.rad").write_bytes(head)
    for name, chunk in files.items():
        (tmp_path / name).write_bytes(chunk)
    assert sorted(files) == ["scene-lod-0.radc", "scene-lod-1.radc"]
    back = read_rad_tree(tmp_path / "scene-lod.rad")
    assert len(back.splats) == len(g) and np.array_equal(back.splats.positions, g.positions)
    (tmp_path / "scene-lod-1.radc").unlink()
    with pytest.raises(InputError, match="scene-lod-1.radc"):
        read_rad_tree(tmp_path / "scene-lod.rad")
    head, files = spark_rad(g, chunk_prefix="../x-")  # a name leaving the header's folder is refused
    (tmp_path / "escape.rad").write_bytes(head)
    with pytest.raises(InputError, match="filename"):
        read_rad_tree(tmp_path / "escape.rad")


def test_spark_clustered_sh_reads_its_codebook(tmp_path):
    """`build-lod --cluster-sh`: SH as per-band codebooks (sh1_code.., in chunk 0, one row per cluster) and a
    per-splat label (u16 up to 65,536 clusters): each splat's SH is its cluster's row."""
    rng = np.random.default_rng(4)
    n, k = 70_000, 300
    books = [rng.normal(scale=0.3, size=(k, m, 3)).astype(np.float32) for m in (3, 5, 7)]
    labels = rng.integers(0, k, n)
    g = scene(n, sh_degree=3, seed=4)
    g = Gaussians(g.positions, g.rotations, g.log_scales, g.opacity_logits, g.sh_dc,
                  np.concatenate([b[labels] for b in books], axis=1))
    data, _ = spark_rad(g, clusters=(labels, books))
    (tmp_path / "c.rad").write_bytes(data)
    back = read_rad_tree(tmp_path / "c.rad")
    encodings, splat_enc = resolve(g, False, 3, {})
    check_within_steps(g, back.splats, encodings, splat_enc, False)


def test_spark_layout_matches_our_writer_framing():
    """The port's framing agrees with our reader's expectations on a one-splat file (a smoke check of the port
    itself: magic, 8-byte alignment of the header and of every property)."""
    data, _ = spark_rad(_splats([[1.0, 2.0, 3.0]]))
    assert struct.unpack_from("<I", data)[0] == RAD_MAGIC and len(data) % 8 == 0
    length = struct.unpack_from("<I", data, 4)[0]
    assert data[8:8 + length].endswith(b"}\n")
