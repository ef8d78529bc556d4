"""The model of each bench/refiner_memory.py line recomputed with the code as committed (its estimate of the scene's
pairs a pixel, PAIRS_MARGIN), against the peak that line measured (branch memmodel31):

    PYTHONPATH=. python bench/results/memmodel31/remodel.py LINES.jsonl > OUT.jsonl

`need_m`: the margin at which the model would equal the peak (negative: the model without pairs is above it already);
`level_over_estimate`: the largest level's training pairs a training pixel over the estimate (before the margin).
"""
import json
import sys
import time

import numpy as np

sys.path.insert(0, ".")
import refine_cpu.levels as L  # noqa: E402
from splatstream.encode.partitioned import routed_row_bytes  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402

cache = {}
for line in open(sys.argv[1]):
    r = json.loads(line)
    if r["input"] not in cache:
        cache[r["input"]] = read_gaussians(r["input"])
    g = cache[r["input"]]
    g = g.subset(np.sort(np.argsort(g.positions[:, 0], kind="stable")[:r["splats"]]))
    ref = L.CpuLevelRefiner(L.CpuRefineSettings(size=r["size"], iterations=r["iterations"]))
    t = time.process_time()
    est = ref.scene_pairs(g, len(g), g.positions, (0.0, 0.0, 1.0), (0,))[0] / L.PAIRS_MARGIN
    cpu = time.process_time() - t
    rb = routed_row_bytes(g.sh_degree)
    lower = ref.with_pairs_per_pixel(0.0).peak_bytes(len(g), rb) / 2**20
    per_pair = ref.with_pairs_per_pixel(1.0).peak_bytes(len(g), rb) / 2**20 - lower
    const = ref.peak_bytes(len(g), rb) / 2**20
    peak = r["peak_above_mib"]
    model = lower + L.PAIRS_MARGIN * est * per_pair
    print(json.dumps({
        "input": r["input"].split("/")[-1], "splats": r["splats"], "sh": r["sh"], "peak": peak,
        "const": round(const), "const_ratio": round(const / peak, 2), "est": round(est, 2),
        "measured_train_ppp": r.get("max_training_pairs_per_pixel"), "est_cpu": round(cpu, 2), "fit_cpu": r["cpu_s"],
        **{f"m{m}": round((lower + m * est * per_pair) / peak, 2) for m in (0.6, 0.7, 0.8, 1.0, 1.2)},
        "need_m": round((peak - lower) / (est * per_pair), 2), "model_mib": round(model, 1),
        "model_ratio": round(model / peak, 2), "margin": L.PAIRS_MARGIN,
        "level_over_estimate": round(r["max_training_pairs_per_pixel"] / est, 2)}))
