"""Bytes of the position plane alone, per texel format, and where they go (issue 15, norm16x4).

    .venv/bin/python bench/pos16_position_bytes.py SCENE.ply [--formats norm11,norm16x4,f16x4] [--level 9]
        [--json OUT.json]

Encodes SCENE in memory without LOD at `medium-low` with each position format (one tile, as `encode --no-lod`
writes it), takes the position plane's GPU texels and codes them as the encoder does (fields1 against the byte
shuffle, zstd at `--level`, a zstd block per part), and reports B/splat of: the texels, the shuffle, fields1 and
the encoder's choice; then, for the fields1 coding with the modes the encoder chose, each field's byte planes on
their own: zstd bytes and order-0 entropy (bits a byte; 8 is incompressible noise). The per-attribute disk bytes in
the manifest share a payload's bytes out by raw section size, so they cannot say what the position plane costs.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import zstandard

from client_gl.scene import tiles_from_gaussians
from splatstream.format.transport import (
    _zstd_size,
    assemble,
    code_layer,
    field_bits,
    filter_texels,
    shuffle_element,
    shuffle_planes,
)
from splatstream.io import read_gaussians


def entropy_bits(plane: np.ndarray) -> float:
    counts = np.bincount(np.ravel(plane).view(np.uint8), minlength=256).astype(np.float64)
    p = counts[counts > 0] / counts.sum()
    return float(-(p * np.log2(p)).sum())


def measure(g, fmt: str, level: int) -> dict:
    scene = tiles_from_gaussians(g, "medium-low", overrides={"position": fmt}, with_mirror=False)
    if len(scene.tiles) != 1:
        raise SystemExit(f"expected one tile, got {len(scene.tiles)}")
    plane = scene.tiles[0].planes["position"]
    n = len(g)
    layer = np.frombuffer(plane.layers[0], np.uint8)
    w, h = plane.width, plane.height
    element = shuffle_element(fmt)
    shuffled = _zstd_size(shuffle_planes(layer, element), level)
    coded = code_layer(layer, fmt, w, h)
    fields = _zstd_size(assemble([coded]), level)
    chosen, parts = filter_texels([layer], fmt, w, h, 1, level)
    ranges = len(zstandard.ZstdCompressor(level=level).compress(np.asarray(plane.ranges).tobytes()))
    bits = field_bits(fmt)
    planes = []
    k = 0
    for f, b in enumerate(bits):
        for byte in range((b + 7) // 8):
            p = coded.planes[k]
            k += 1
            planes.append({"field": f, "byte": byte, "delta": bool(coded.modes[f][0]), "ref": coded.modes[f][1],
                           "zstd_B_per_splat": len(zstandard.ZstdCompressor(level=level).compress(p.tobytes())) / n,
                           "entropy_bits": round(entropy_bits(p), 3)})
    return {"format": fmt, "splats": n, "texels": f"{w}x{h}", "texel_B_per_splat": layer.size / n,
            "shuffle_B_per_splat": shuffled / n, "fields1_B_per_splat": fields / n, "encoder_choice": chosen,
            "chosen_B_per_splat": _zstd_size(parts, level) / n, "ranges_B_per_splat": ranges / n, "planes": planes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--formats", default="norm11,norm16x4,f16x4")
    ap.add_argument("--level", type=int, default=9, help="zstd level (medium-low's: 9)")
    ap.add_argument("--json")
    a = ap.parse_args()
    g = read_gaussians(a.scene)
    rows = [measure(g, fmt, a.level) for fmt in a.formats.split(",")]
    print(f"{a.scene}: {len(g):,} splats, zstd level {a.level}; B/splat of the position plane")
    print("| format | texels | shuffle | fields1 | encoder's choice | ranges | fields1 planes (field.byte: B/splat, "
          "entropy bits) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        ps = ", ".join(f"{p['field']}.{p['byte']}: {p['zstd_B_per_splat']:.2f} ({p['entropy_bits']:.2f})"
                       for p in r["planes"] if p["field"] < 3)
        print(f"| {r['format']} | {r['texel_B_per_splat']:.2f} | {r['shuffle_B_per_splat']:.2f} | "
              f"{r['fields1_B_per_splat']:.2f} | {r['encoder_choice']} {r['chosen_B_per_splat']:.2f} | "
              f"{r['ranges_B_per_splat']:.3f} | {ps} |")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"scene": a.scene, "splats": len(g), "level": a.level, "rows": rows}, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    sys.exit(main())
