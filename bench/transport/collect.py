"""Encode scenes with the presets (no LOD) and dump every payload section's GPU bytes for transport measurements.

    python bench/transport/collect.py OUT_DIR SCENE.ply[:NAME] ... [--presets medium,low,very-low,high]

Writes OUT_DIR/<scene>/<preset>/ (the encoded scene directory, kept for re-coding whole scenes) and
OUT_DIR/<scene>/<preset>.sections.npz + .json: per section of every payload its unfiltered bytes (what the GPU
receives) and descriptor (group, name, kind, format, width, height, layers / dtype, shape), plus today's payload
file sizes.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import zstandard

from splatstream.container import _element_of
from splatstream.encoder import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians
from splatstream.manifest import load_manifest
from splatstream.texformats import unshuffle_bytes


def payload_entries(m: dict):
    """(group label, entry) of every full-detail payload: leaf tile groups, then codebook groups."""
    for t in m["tiles"]:
        if not t.get("children"):
            for g, e in t["groups"].items():
                yield f"tile{t['id']}.{g}", e
    cb = m.get("sh_codebook")
    if cb:
        for g, e in cb["groups"].items():
            yield f"codebook.{g}", e


def dump_sections(scene_dir: str) -> tuple[dict[str, np.ndarray], list[dict]]:
    m = load_manifest(scene_dir)
    arrays, meta = {}, []
    for label, e in payload_entries(m):
        data = open(os.path.join(scene_dir, e["file"]), "rb").read()
        raw = np.frombuffer(zstandard.ZstdDecompressor().decompress(data), np.uint8)
        for s in e["sections"]:
            buf = raw[s["offset"]:s["offset"] + s["size"]]
            element = _element_of(s["filter"])
            if s["kind"] == "texels":
                unit = s["size"] // s["layers"]
                buf = np.concatenate([unshuffle_bytes(buf[i * unit:(i + 1) * unit], element)
                                      for i in range(s["layers"])])
            else:
                buf = unshuffle_bytes(buf, element)
            key = f"{label}.{s['name']}"
            arrays[key] = buf
            meta.append({"key": key, "payload": label, "payload_bytes": e["bytes"], "payload_raw": e["raw_bytes"],
                         "entries": (m.get("sh_codebook") or {}).get("entries") if label.startswith("codebook")
                         else None, "splats": m["splats"],
                         **{k: v for k, v in s.items() if k not in ("offset",)}})
    return arrays, meta


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--presets", default="medium,low,very-low,high")
    args = ap.parse_args()
    for spec in args.scenes:
        path, _, name = spec.partition(":")
        name = name or os.path.splitext(os.path.basename(path))[0]
        g = read_gaussians(path)
        for preset in args.presets.split(","):
            scene_dir = os.path.join(args.out, name, preset)
            if not os.path.exists(os.path.join(scene_dir, "manifest.msgpack")):
                t0 = time.perf_counter()
                encode_gaussians(g, scene_dir, EncodeOptions(preset=preset, lod=False), source_name=path)
                print(f"{name} {preset}: encoded in {time.perf_counter() - t0:.1f} s", flush=True)
            arrays, meta = dump_sections(scene_dir)
            np.savez(os.path.join(args.out, name, f"{preset}.sections.npz"), **arrays)
            with open(os.path.join(args.out, name, f"{preset}.sections.json"), "w") as f:
                json.dump({"scene": name, "preset": preset, "splats": len(g), "sections": meta}, f, indent=1)


if __name__ == "__main__":
    main()
