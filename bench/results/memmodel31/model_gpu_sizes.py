"""The estimate and the model at 2^20 / 2^21 splats of donut copies against the peaks the GPU machine measured
(bench/results/refinefast31/refiner_memory_gpu.jsonl; branch memmodel31):

    python bench/tile_scene.py samples/donut.ply --splats 2100000 --out /tmp/big.ply
    PYTHONPATH=. python bench/results/memmodel31/model_gpu_sizes.py /tmp/big.ply > OUT.jsonl
"""
import json
import sys
import time

import numpy as np

sys.path.insert(0, ".")
import refine_cpu.levels as L  # noqa: E402
from splatstream.encode.partitioned import routed_row_bytes  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402

g0 = read_gaussians(sys.argv[1])
for n, peak in ((1048576, 990.5), (2097152, 1741.3)):
    g = g0.subset(np.sort(np.argsort(g0.positions[:, 0], kind="stable")[:n]))
    ref = L.CpuLevelRefiner(L.CpuRefineSettings())
    t = time.process_time()
    est = ref.scene_pairs(g, len(g), g.positions, (0.0, 0.0, 1.0), (0,))[0] / L.PAIRS_MARGIN
    cpu = time.process_time() - t
    rb = routed_row_bytes(0)
    lower = ref.with_pairs_per_pixel(0.0).peak_bytes(n, rb) / 2**20
    per_pair = ref.with_pairs_per_pixel(1.0).peak_bytes(n, rb) / 2**20 - lower
    model = lower + L.PAIRS_MARGIN * est * per_pair
    print(json.dumps({"splats": n, "gpu_peak": peak, "est": round(est, 2), "model_mib": round(model, 1),
                      "ratio": round(model / peak, 2), "const": round(ref.peak_bytes(n, rb) / 2**20, 1),
                      "lower": round(lower, 1), "est_cpu": round(cpu, 2)}))
