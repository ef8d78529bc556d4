"""Write a copy of a scene whose SH rest rows are all distinct (for codebook and transport measurements).

make_scene.py copies the SH rows of a few real scenes, so a 1M scene holds only 4,517 distinct rows and every
codebook is exact on it. This adds Gaussian noise of 5 % of each SH coefficient's standard deviation (over the
scene) to every coefficient, seed 1, and checks that every row is then distinct. (BENCHMARKS.md mentions a jittered
scene for codebook timing without giving the noise; this is the one the transport measurements use.)

    python bench/transport/make_jitter.py /tmp/s1m.ply /tmp/s1m_jitter.ply
"""
from __future__ import annotations

import sys

import numpy as np

from splatstream.io import read_gaussians
from splatstream.ply import write_gaussians_ply

JITTER_OF_STD = 0.05
SEED = 1


def main() -> None:
    src, dst = sys.argv[1], sys.argv[2]
    g = read_gaussians(src)
    rng = np.random.default_rng(SEED)
    std = g.sh_rest.reshape(len(g), -1).std(axis=0).reshape(1, *g.sh_rest.shape[1:])
    g.sh_rest += (rng.standard_normal(g.sh_rest.shape, dtype=np.float32) * (JITTER_OF_STD * std)).astype(np.float32)
    rows = np.ascontiguousarray(g.sh_rest.reshape(len(g), -1))
    distinct = len(np.unique(rows.view(np.dtype((np.void, rows.itemsize * rows.shape[1])))))
    print(f"{len(g)} splats, {distinct} distinct SH rows")
    write_gaussians_ply(g, dst)


if __name__ == "__main__":
    main()
