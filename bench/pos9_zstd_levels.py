"""Disk bytes per splat and encode time of preset variants at several zstd levels (issue 15, norm9x3 positions).

    .venv/bin/python bench/pos9_zstd_levels.py SCENE.ply --variants NAME:PRESET[,ATTR=FORMAT...] ... \
        [--levels 1,9,16,19] [--json OUT.json]

Encodes SCENE without LOD (as `splatstream eval` does) with each variant at each level and reports the bytes on disk
(every file, the manifest included: eval's `disk`) per splat and the encode wall time. The texels, and so the PSNR,
do not depend on the level: take PSNR from the variant's eval row.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.evaluate import parse_variant
from splatstream.io import read_gaussians


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--variants", nargs="+", required=True)
    ap.add_argument("--levels", default="1,9,16,19")
    ap.add_argument("--json")
    a = ap.parse_args()
    g = read_gaussians(a.scene)
    n = len(g)
    rows = []
    print(f"{os.path.basename(a.scene)}: {n:,} splats; disk B/splat (encode s) per zstd level")
    levels = [int(x) for x in a.levels.split(",")]
    print("| variant | " + " | ".join(f"level {lv}" for lv in levels) + " |")
    print("|---|" + "---|" * len(levels))
    for text in a.variants:
        name, preset, overrides, _, _ = parse_variant(text)  # eval's --variants syntax
        cells = []
        for level in levels:
            with tempfile.TemporaryDirectory(prefix="pos9-") as tmp:
                t0 = time.perf_counter()
                m = encode_gaussians(g, os.path.join(tmp, "s"), EncodeOptions(
                    preset=preset, overrides=overrides, lod=False, zstd_level=level), source_name=a.scene)
                seconds = time.perf_counter() - t0
            rows.append({"variant": name, "preset": preset, "overrides": overrides, "level": level,
                         "disk_bytes": m.bytes_on_disk, "disk_bytes_per_splat": m.bytes_on_disk / n,
                         "encode_seconds": seconds})
            cells.append(f"{m.bytes_on_disk / n:.3f} ({seconds:.2f} s)")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"scene": a.scene, "splats": n, "rows": rows}, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    sys.exit(main())
