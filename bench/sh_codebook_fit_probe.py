"""CPU time and error of the `large` SH codebook's fit on one scene, for fit settings (issue 32, cb8's encode time).

    python bench/sh_codebook_fit_probe.py SCENE ITERATIONS,PRODUCT_SEEDING ...   (e.g. 8,0 8,1 5,1 4,1)

For each setting (vq.LARGE_ITERATIONS Lloyd rounds in the cells; PRODUCT_SEEDING 1: the cells seeded from dot
products, 0: from differences, as the other codebooks) it fits the encoder's codebook to the scene's SH rows with
the encoder's weights (fit and renumbering by use, CPU seconds of this process) and prints the weighted RMS error
of every row against its entry, the figure BENCHMARKS.md quotes ("The large codebook's encode time"). Run it with
OPENBLAS_NUM_THREADS=1, as the CLI encodes.
"""
from __future__ import annotations

import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import numpy as np  # noqa: E402

from splatstream import vq  # noqa: E402
from splatstream.encode.codebook import codebook_rows, codebook_weights, order_by_use  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        raise SystemExit(__doc__)
    g = read_gaussians(argv[0])
    rows, w = codebook_rows(g), codebook_weights(g)
    k = vq.large_entries(len(rows))
    wn = w / w.sum()
    real_kmeans = vq.kmeans
    for spec in argv[1:]:
        iterations, product = spec.split(",")
        vq.LARGE_ITERATIONS = int(iterations)
        vq.kmeans = (lambda *a, product_seeding=False, **kw: real_kmeans(*a, **kw)) if product == "0" else real_kmeans
        t = time.process_time()
        cb = order_by_use(vq.build_codebook(rows, k, weights=w, probes=vq.probes_for(k)), rows)
        fit = time.process_time() - t
        err = rows - cb.entries[cb.assign(rows)]
        rms = np.sqrt((wn[:, None] * err ** 2).sum() / rows.shape[1])
        print(f"{k} entries, {iterations} Lloyd rounds, product seeding {product}: fit + renumbering {fit:.2f} CPU s, "
              f"weighted RMS {rms:.6f}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
