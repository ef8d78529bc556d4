"""Where the SH codebook loses (BENCHMARKS.md, "SOG's point on playbot"): the fit (rows bit-exact, weighted RMS error)
and the entries' texel format (the codebook planes' round trip), for one scene and codebook size.

    PYTHONPATH=. python bench/codebook_entry_probe.py SCENE.ply large norm565,norm8x4,norm11,norm16x4
"""
from __future__ import annotations

import sys
import time

import numpy as np

from splatstream.encode.codebook import codebook_planes, codebook_rows, codebook_weights, fit_sh_codebook
from splatstream.format.codec import decode_plane
from splatstream.io import read_gaussians
from splatstream.vq import _unique_rows, parse_entries


def main(path: str, choice: str, fmts: list[str]) -> None:
    g = read_gaussians(path)
    rows, w = codebook_rows(g), codebook_weights(g)
    first, _ = _unique_rows(rows)
    print(f"{path}: {len(g)} splats, {len(first)} distinct rows, entries {parse_entries(choice, len(g))}", flush=True)
    t = time.process_time()
    cb = fit_sh_codebook(g, "probe", choice, g.sh_degree)
    print(f"fit {time.process_time() - t:.1f} CPU s", flush=True)
    labels = cb.assign(rows)

    def weighted_rms(err: np.ndarray) -> float:  # per value, weighted as the codebook's fit
        return float(np.sqrt((w * (err ** 2).sum(1)).sum() / w.sum() / rows.shape[1]))

    err = rows - cb.entries[labels]
    print(f"fit only: exact rows {(err == 0).all(axis=1).mean():.4f}, weighted RMS {weighted_rms(err):.6f}")
    k = len(cb.entries)
    for fmt in fmts:
        planes = codebook_planes(cb, g.sh_degree, fmt)
        deq = np.concatenate([decode_plane(planes[f"sh{b}"], k).reshape(k, -1) for b in range(1, g.sh_degree + 1)],
                             axis=1)
        raw = sum(len(layer) for p in planes.values() for layer in p.layers)
        print(f"{fmt}: entries RMS {np.sqrt(((deq - cb.entries) ** 2).mean()):.6f}; rows weighted RMS "
              f"{weighted_rms(rows - deq[labels]):.6f}; raw plane bytes {raw}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3].split(",") if len(sys.argv) > 3 else ["norm565"])
