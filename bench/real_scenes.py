"""The real scenes of ../shared/data/real/ as a new user first sees them: `splatstream render FILE` with no camera
option (the scene's detected up and suggested camera), side by side with their names, for README/BENCHMARKS.

    python bench/real_scenes.py --out docs/images/real_scenes.png

biker is left out: its licence (CC BY-NC-ND 4.0) does not allow publishing derived images.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

from PIL import Image, ImageDraw

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REAL = os.path.join(os.environ.get("SPLATSTREAM_SHARED", os.path.join(ROOT, "..", "shared")), "data", "real")
SCENES = ["fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply", "donut_sh0_no_normals.ply", "guitar.compressed.ply",
          "winter_fountain.splat"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", default="640x360", help="each picture's size")
    ap.add_argument("--columns", type=int, default=3)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    tiles = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in SCENES:
            png = os.path.join(tmp, name + ".png")
            r = subprocess.run([sys.executable, "-m", "cli", "render", os.path.join(REAL, name), "--out",
                                png, "--size", args.size, "-q"], capture_output=True, text=True)
            if r.returncode != 0:
                print(f"{name}: {r.stderr.strip()}", file=sys.stderr)
                return 1
            img = Image.open(png).convert("RGB")
            ImageDraw.Draw(img).text((8, 6), name, fill=(255, 255, 255))
            tiles.append(img)
            print(f"rendered {name}")
    rows = -(-len(tiles) // args.columns)
    sheet = Image.new("RGB", (args.columns * w, rows * h), (40, 40, 40))
    for k, img in enumerate(tiles):
        sheet.paste(img, ((k % args.columns) * w, (k // args.columns) * h))
    tmp_out = args.out + ".part.png"
    sheet.save(tmp_out)
    os.replace(tmp_out, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
