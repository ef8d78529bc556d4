"""Measure transport-coding candidates on dumped payload sections (bench/transport/collect.py).

    python bench/transport/candidates.py SEC_DIR [--scenes a,b] [--presets ...] [--json OUT]

For every texels section the packed texels are split into their fields (norm11 -> 11/10/11-bit integers, ...),
predicted (none, left, up, gradient L+U-UL in texture order; previous splat in splat order, across chunks or reset
per chunk), and the residuals (mod 2^bits, zigzag) measured by their order-0 entropy plus a table estimate. The
best predictor per field then goes through real coders: zstd (3 and 19) over byte planes, rANS (constriction,
static categorical), lossless WebP (8-bit planes). Today's coding (byte shuffle + zstd 3, per section) is the
baseline. Single thread.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import zstandard

from splatstream.layout import CHUNK_SIZE, chunk_texel_index
from splatstream.texformats import get_format, shuffle_bytes

FIELDS = {  # format -> (dtype of a texel word, [(shift, bits)])
    "norm11": ("<u4", [(0, 11), (11, 10), (21, 11)]),
    "norm10_2": ("<u4", [(0, 10), (10, 10), (20, 10), (30, 2)]),
    "norm8x4": ("<u4", [(0, 8), (8, 8), (16, 8), (24, 8)]),
    "norm565": ("<u2", [(0, 5), (5, 6), (11, 5)]),
    "index16": ("<u2", [(0, 16)]),
    "f16x4": ("<u8", [(0, 16), (16, 16), (32, 16), (48, 16)]),
}


def split_fields(buf: np.ndarray, fmt: str, width: int, height: int) -> list[tuple[int, np.ndarray]]:
    """One layer's texel bytes -> [(bits, (H, W) uint32 field)]."""
    dtype, fields = FIELDS[fmt]
    word = buf.view(dtype).reshape(height, width)
    return [(bits, ((word >> np.array(shift, word.dtype)) & np.array((1 << bits) - 1, word.dtype)).astype(np.uint32))
            for shift, bits in fields]


def splat_order_index(width: int, height: int) -> np.ndarray:
    chunks = (width // 16) * (height // 16)
    return chunk_texel_index(chunks, width)


def predict(field: np.ndarray, bits: int, mode: str) -> np.ndarray:
    """Residuals (mod 2^bits) of a (H, W) field under a predictor, in the order the mode codes them (flat)."""
    f = field.astype(np.int64)
    h, w = f.shape
    if mode == "none":
        r = f.reshape(-1)
    elif mode == "left":
        p = np.zeros_like(f)
        p[:, 1:] = f[:, :-1]
        r = (f - p).reshape(-1)
    elif mode == "up":
        p = np.zeros_like(f)
        p[1:] = f[:-1]
        r = (f - p).reshape(-1)
    elif mode == "grad":
        left = np.zeros_like(f)
        left[:, 1:] = f[:, :-1]
        up = np.zeros_like(f)
        up[1:] = f[:-1]
        ul = np.zeros_like(f)
        ul[1:, 1:] = f[:-1, :-1]
        r = (f - (left + up - ul)).reshape(-1)
    elif mode in ("seq", "chunk"):
        s = f.reshape(-1)[splat_order_index(w, h)]
        p = np.zeros_like(s)
        p[1:] = s[:-1]
        if mode == "chunk":
            p[::CHUNK_SIZE] = 0
        r = s - p
    else:
        raise ValueError(mode)
    m = (1 << bits) - 1
    r &= m
    # zigzag of the centred residual
    half = 1 << (bits - 1)
    signed = np.where(r >= half, r - (1 << bits), r)
    return np.where(signed >= 0, 2 * signed, -2 * signed - 1).astype(np.uint32)


def entropy_bytes(sym: np.ndarray, bits: int) -> float:
    """Order-0 entropy of the symbols in bytes, plus a table cost of ~1.5 bytes per used symbol (capped)."""
    counts = np.bincount(sym, minlength=1)
    counts = counts[counts > 0]
    p = counts / counts.sum()
    h = float(-(counts * np.log2(p)).sum() / 8)
    return h + min(1.5 * len(counts), 2 + (1 << bits) * bits / 8 / 2)


def byte_planes(sym: np.ndarray, bits: int) -> bytes:
    if bits <= 8:
        return sym.astype(np.uint8).tobytes()
    if bits <= 16:
        v = sym.astype("<u2")
        return shuffle_bytes(v.view(np.uint8), 2).tobytes()
    return shuffle_bytes(sym.astype("<u4").view(np.uint8), 4).tobytes()


def zstd_size(data: bytes, level: int) -> int:
    return len(zstandard.ZstdCompressor(level=level).compress(data))


def today_size(buf: np.ndarray, fmt_or_dtype: str, layers: int, level: int = 3) -> int:
    """Byte shuffle by the format's element per layer + zstd (today's filter, one frame per section)."""
    if fmt_or_dtype in ("f32", "f16"):
        element = 4 if fmt_or_dtype == "f32" else 2
        return zstd_size(shuffle_bytes(buf, element).tobytes(), level)
    element = get_format(fmt_or_dtype).shuffle
    unit = buf.size // layers
    parts = [shuffle_bytes(buf[i * unit:(i + 1) * unit], element) if element > 1 else buf[i * unit:(i + 1) * unit]
             for i in range(layers)]
    return zstd_size(np.concatenate(parts).tobytes(), level)


PREDICTORS = ("none", "left", "up", "grad", "seq", "chunk")


def rans_size(sym: np.ndarray, bits: int) -> int:
    """Real rANS (constriction stack coder, static categorical from the histogram) + a table estimate."""
    import constriction

    counts = np.bincount(sym)
    used = np.flatnonzero(counts)
    remap = np.zeros(len(counts), np.int32)
    remap[used] = np.arange(len(used))
    probs = (counts[used] / counts.sum()).astype(np.float32)
    if len(used) == 1:
        return 4 + 2
    model = constriction.stream.model.Categorical(probs, perfect=False)
    enc = constriction.stream.stack.AnsCoder()
    enc.encode_reverse(remap[sym].astype(np.int32), model)
    return enc.get_compressed().nbytes + int(1.5 * len(used)) + 4


def measure_texels(buf: np.ndarray, fmt: str, width: int, height: int, layers: int) -> dict:
    out = {"gpu": int(buf.size), "today": today_size(buf, fmt, layers), "zstd19": today_size(buf, fmt, layers, 19)}
    if fmt not in FIELDS:
        # BC blocks: try a split of BC1 into endpoints / indices, BC7 as is
        out["best_entropy"] = None
        return out
    unit = buf.size // layers
    per_pred = dict.fromkeys(PREDICTORS, 0.0)
    best_fields = []
    for layer in range(layers):
        for bits, field in split_fields(buf[layer * unit:(layer + 1) * unit], fmt, width, height):
            best = None
            for mode in PREDICTORS:
                sym = predict(field, bits, mode)
                e = entropy_bytes(sym, bits)
                per_pred[mode] += e
                if best is None or e < best[0]:
                    best = (e, mode, sym)
            best_fields.append((bits, best[1], best[2], best[0]))
    out["entropy_by_predictor"] = {k: round(v) for k, v in per_pred.items()}
    out["best_entropy"] = round(sum(b[3] for b in best_fields))
    out["best_modes"] = [b[1] for b in best_fields]
    planes = b"".join(byte_planes(sym, bits) for bits, _, sym, _ in best_fields)
    out["pred_zstd3"] = zstd_size(planes, 3)
    out["pred_zstd19"] = zstd_size(planes, 19)
    # zstd per field (each field its own frame): shows whether mixing fields in one frame hurts zstd's tables
    out["pred_zstd3_perfield"] = sum(zstd_size(byte_planes(sym, bits), 3) + 0 for bits, _, sym, _ in best_fields)
    out["pred_rans"] = sum(rans_size(sym, bits) for bits, _, sym, _ in best_fields)
    # splitting without prediction (fields as their own byte planes), zstd 3
    raw_planes = b"".join(byte_planes(predict(field, bits, "none"), bits) if False else
                          byte_planes(field.reshape(-1), bits)
                          for layer in range(layers)
                          for bits, field in split_fields(buf[layer * unit:(layer + 1) * unit], fmt, width, height))
    out["split_zstd3"] = zstd_size(raw_planes, 3)
    return out


def measure_range(buf: np.ndarray, dtype: str, shape: list[int]) -> dict:
    out = {"gpu": int(buf.size), "today": today_size(buf, dtype, 1), "zstd19": today_size(buf, dtype, 1, 19)}
    # delta of the bit patterns along chunks (ranges of neighbouring chunks are close)
    item = 4 if dtype == "f32" else 2
    v = buf.view("<u4" if item == 4 else "<u2").reshape(shape[0], -1).astype(np.int64)
    d = v.copy()
    d[1:] -= v[:-1]
    d &= (1 << (8 * item)) - 1
    d = d.astype("<u4" if item == 4 else "<u2")
    out["delta_zstd3"] = zstd_size(shuffle_bytes(d.reshape(-1).view(np.uint8), item).tobytes(), 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("sec")
    ap.add_argument("--scenes", default="fruit,lodtile,donut,biker,fountain,s1m,s1mj")
    ap.add_argument("--presets", default="medium,low,very-low,high")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    results = []
    for scene in args.scenes.split(","):
        for preset in args.presets.split(","):
            jpath = os.path.join(args.sec, scene, f"{preset}.sections.json")
            if not os.path.exists(jpath):
                continue
            meta = json.load(open(jpath))
            arrays = np.load(os.path.join(args.sec, scene, f"{preset}.sections.npz"))
            t0 = time.perf_counter()
            for s in meta["sections"]:
                buf = arrays[s["key"]]
                if s["kind"] == "texels":
                    r = measure_texels(buf, s["format"], s["width"], s["height"], s["layers"])
                else:
                    r = measure_range(buf, s["dtype"], s["shape"])
                results.append({"scene": scene, "preset": preset, "splats": meta["splats"], "key": s["key"],
                                "name": s["name"], "kind": s["kind"], "format": s.get("format", s.get("dtype")),
                                **r})
            print(f"{scene} {preset}: {time.perf_counter() - t0:.1f} s", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
