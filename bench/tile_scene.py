"""A large scene from copies of one splat file on a ground grid (z up), for benchmarks that must not carry data:
    python bench/tile_scene.py samples/donut.ply --splats 6000000 --out big.ply [--seed 0]
Each copy is scaled to a radius of 0.5-2.5, turned about z and placed on a square whose side grows with the count
(as shared/tools/make_scene.py does with several real scenes)."""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from splatstream.gaussians import Gaussians  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.ply import write_gaussians_ply  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("source")
    ap.add_argument("--splats", type=int, required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    src = read_gaussians(args.source)
    rng = np.random.default_rng(args.seed)
    centre = src.positions.mean(0)
    size = float(np.percentile(np.linalg.norm(src.positions - centre, axis=1), 95)) + 1e-9
    side = max(1.0, np.sqrt(args.splats / 30000.0)) * 4.0
    parts, total = [], 0
    while total < args.splats:
        k = rng.uniform(0.5, 2.5) / size
        ang = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(ang), np.sin(ang)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
        off = np.array([rng.uniform(-side, side), rng.uniform(-side, side), k * size], np.float32)
        q = np.array([np.cos(ang / 2), 0, 0, np.sin(ang / 2)], np.float32)
        w1, z1 = q[0], q[3]
        w2, x2, y2, z2 = src.rotations.T
        quat = np.stack([w1 * w2 - z1 * z2, w1 * x2 - z1 * y2, w1 * y2 + z1 * x2, w1 * z2 + z1 * w2], 1)
        parts.append(Gaussians((src.positions - centre) * k @ rot.T + off, quat.astype(np.float32),
                               src.log_scales + np.float32(np.log(k)), src.opacity_logits, src.sh_dc, src.sh_rest))
        total += len(src)
    g = Gaussians.concatenate(parts).subset(np.arange(args.splats))
    write_gaussians_ply(g, args.out)
    print(f"wrote {args.out}: {len(g)} splats")


if __name__ == "__main__":
    main()
