"""Bytes per splat per attribute under today's coding and the transport candidates, and decode speed (one core).

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python bench/transport/measure.py SEC_DIR [--scenes ...]
        [--presets ...] [--webp] [--json OUT.json] [--markdown OUT.md]

Reads the sections dumped by collect.py. Columns (bytes per splat; ranges are counted with their plane):
  gpu           texel + range bytes as the GPU holds them
  today         byte shuffle + zstd 3, one frame per section (today's payload is one frame per group; the
                payload file sizes are within 0.5 % of the sum of its sections coded this way)
  zstd19        the same at zstd level 19
  fields        fields-zstd forced (split fields, per-block prediction, byte planes, zstd 3)
  transport     what transport.encode_section keeps (the smaller of fields-zstd and shuffle-zstd, decided on a
                band of the section), zstd 3: the proposed coding
  transport19   the same at zstd level 19 (slower to encode, decodes as fast)
  webp          lossless WebP (Pillow, method 4) of 8-bit four-channel planes (norm8x4), else the transport figure
Decode: M splats/s of the base payload's sections back to GPU bytes, one thread, median of 5 runs; today's decode
is zstd + unshuffle of the whole base payload file (container.unpack_group without the float conversion).
"""
from __future__ import annotations

import argparse
import io
import json
import os
import time
from collections import defaultdict

import numpy as np
import zstandard

from splatstream.texformats import FORMATS
from splatstream.transport import decode_section, encode_range_section, encode_section, encode_shuffle_zstd

ATTRS = ("position", "rotation", "scale", "color", "sh", "sh_codebook")
COLUMNS = ("gpu", "today", "zstd19", "fields", "transport", "transport19", "webp")


def attribute(s: dict) -> str:
    if s["payload"].startswith("codebook"):
        return "sh_codebook"
    name = s["name"].split(".")[0]
    return "sh" if name.startswith("sh") else name


def webp_size(buf: np.ndarray, width: int, height: int, layers: int) -> int:
    from PIL import Image

    unit = buf.size // layers
    total = 0
    for layer in range(layers):
        img = Image.frombytes("RGBA", (width, height), buf[layer * unit:(layer + 1) * unit].tobytes())
        out = io.BytesIO()
        img.save(out, "WEBP", lossless=True, quality=100, method=4, exact=True)
        total += len(out.getvalue())
    return total


def median_time(fn, runs: int = 5) -> float:
    times = []
    for _ in range(runs):  # CPU time of this thread: the machine is shared and wall time moves by 2-3x
        t = time.thread_time()
        fn()
        times.append(time.thread_time() - t)
    return float(np.median(times))


def measure(sec: str, scene: str, preset: str, webp: bool) -> dict:
    meta = json.load(open(os.path.join(sec, scene, f"{preset}.sections.json")))
    arrays = np.load(os.path.join(sec, scene, f"{preset}.sections.npz"))
    n = meta["splats"]
    sizes: dict[str, dict[str, float]] = defaultdict(lambda: dict.fromkeys(COLUMNS, 0.0))
    codings: dict[str, list[str]] = defaultdict(list)
    base_coded, encode_s = [], 0.0
    for s in meta["sections"]:
        buf = arrays[s["key"]]
        a = attribute(s)
        row = sizes[a]
        row["gpu"] += buf.size
        if s["kind"] == "range":
            element = 4 if s["dtype"] == "f32" else 2
            coded, d = encode_range_section(buf, element)
            for c in COLUMNS[1:]:
                row[c] += len(coded)
            row["zstd19"] += len(encode_shuffle_zstd(buf, element, 1, 19)) - len(coded)
            row["transport19"] += len(encode_shuffle_zstd(buf, element, 1, 19)) - len(coded)
            if s["payload"].endswith(".base"):
                base_coded.append((coded, d, None, 0, 0, 1, buf.size, buf))
            continue
        fmt, w, h, layers = s["format"], s["width"], s["height"], s["layers"]
        element = max(1, FORMATS[fmt].shuffle)
        row["today"] += len(encode_shuffle_zstd(buf, element, layers, 3))
        row["zstd19"] += len(encode_shuffle_zstd(buf, element, layers, 19))
        t = time.perf_counter()
        coded, d = encode_section(buf, fmt, w, h, layers)
        encode_s += time.perf_counter() - t
        row["transport"] += len(coded)
        codings[a].append(d["coding"])
        forced, _ = encode_section(buf, fmt, w, h, layers, codings=("fields-zstd",))
        row["fields"] += len(forced)
        row["transport19"] += len(encode_section(buf, fmt, w, h, layers, level=19)[0])
        row["webp"] += webp_size(buf, w, h, layers) if webp and fmt == "norm8x4" else len(coded)
        if s["payload"].endswith(".base"):
            base_coded.append((coded, d, fmt, w, h, layers, buf.size, buf))
    for coded, d, fmt, w, h, layers, size, buf in base_coded:  # bit-exact, or the numbers mean nothing
        assert np.array_equal(decode_section(coded, d, fmt, w, h, layers, size=size), buf)

    def decode_base():
        for coded, d, fmt, w, h, layers, size, _ in base_coded:
            decode_section(coded, d, fmt, w, h, layers, size=size)

    base_entry = next(s for s in meta["sections"] if s["payload"].endswith(".base"))
    payload_file = os.path.join(sec, scene, preset, _payload_path(os.path.join(sec, scene, preset), base_entry))
    data = open(payload_file, "rb").read()

    def decode_today():
        raw = np.frombuffer(zstandard.ZstdDecompressor().decompress(data), np.uint8)
        for s in meta["sections"]:
            if s["payload"].endswith(".base"):
                from splatstream.texformats import unshuffle_bytes

                unshuffle_bytes(raw[:s["size"]], int(s["filter"][7:]) if s["filter"] != "none" else 1)

    decode_base()
    t_new = median_time(decode_base)
    t_today = median_time(decode_today)
    return {"scene": scene, "preset": preset, "splats": n,
            "bytes_per_splat": {a: {c: v / n for c, v in row.items()} for a, row in sizes.items()},
            "codings": {a: sorted(set(v)) for a, v in codings.items()},
            "base_decode_msplats_s": n / t_new / 1e6, "base_decode_today_msplats_s": n / t_today / 1e6,
            "transport_encode_s": encode_s}


def _payload_path(scene_dir: str, section: dict) -> str:
    from splatstream.manifest import load_manifest

    m = load_manifest(scene_dir)
    tile, group = section["payload"].split(".")
    return next(t for t in m["tiles"] if f"tile{t['id']}" == tile)["groups"][group]["file"]


def markdown(results: list[dict]) -> str:
    lines = ["| scene | preset | attribute | " + " | ".join(COLUMNS) + " | transport vs today |",
             "|---" * (4 + len(COLUMNS)) + "|"]
    for r in results:
        total = dict.fromkeys(COLUMNS, 0.0)
        for a in ATTRS:
            v = r["bytes_per_splat"].get(a)
            if v is None:
                continue
            for c in COLUMNS:
                total[c] += v[c]
            lines.append(f"| {r['scene']} | {r['preset']} | {a} | " + " | ".join(f"{v[c]:.2f}" for c in COLUMNS)
                         + f" | {(v['transport'] / v['today'] - 1) * 100:+.1f} % |")
        lines.append(f"| {r['scene']} | {r['preset']} | **total** | " + " | ".join(f"**{total[c]:.2f}**"
                                                                                for c in COLUMNS)
                     + f" | **{(total['transport'] / total['today'] - 1) * 100:+.1f} %** |")
    lines += ["", "| scene | preset | base decode, transport (M splats/s) | base decode, today | transport "
              "encode s (one thread, all sections) |", "|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['scene']} | {r['preset']} | {r['base_decode_msplats_s']:.1f} | "
                     f"{r['base_decode_today_msplats_s']:.1f} | {r['transport_encode_s']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("sec")
    ap.add_argument("--scenes", default="fruit,lodtile,donut,biker,fountain,s1m,s1mj")
    ap.add_argument("--presets", default="high,medium,low,very-low")
    ap.add_argument("--webp", action="store_true")
    ap.add_argument("--json")
    ap.add_argument("--markdown")
    args = ap.parse_args()
    results = []
    for scene in args.scenes.split(","):
        for preset in args.presets.split(","):
            if os.path.exists(os.path.join(args.sec, scene, f"{preset}.sections.json")):
                results.append(measure(args.sec, scene, preset, args.webp))
                print(f"{scene} {preset} done", flush=True)
    text = markdown(results)
    print(text)
    if args.json:
        json.dump(results, open(args.json, "w"), indent=1)
    if args.markdown:
        open(args.markdown, "w").write(text)


if __name__ == "__main__":
    main()
