"""Where `encode --lod-refine cpu`'s CPU goes, phase by phase (issue 31, branch refinefast31): the encode of one PLY
through the encoder API with refine_cpu.levels.CpuLevelRefiner, as bench/probe_cpurefine.py runs it, with the
process's user + sys CPU seconds added up inside the full-detail renders (`raster.render`), the pair lists
(`raster.pair_lists`: the training and the validation cameras'), the fit's forward and backward passes
(`raster.loss_and_grad` with gradients) and the validation's forward passes (without); the rest is the encode and the
refiner's numpy (Adam steps, concatenations). One JSON line: the phases, the whole encode's CPU and wall seconds, the
peak RSS, and the refined directory's digest (to compare two versions' bytes).

    PYTHONPATH=. nice -n 19 python bench/probe_refine_phases.py CACHE/SCENE/full.ply OUT [--label main]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from refine_cpu import raster  # noqa: E402
from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings  # noqa: E402
from splatstream.encode import encode_file  # noqa: E402


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def directory_digest(root: str) -> str:
    h = hashlib.sha256()
    for dirpath, dirnames, files in sorted(os.walk(root)):
        dirnames.sort()
        for name in sorted(files):
            path = os.path.join(dirpath, name)
            h.update(os.path.relpath(path, root).encode())
            with open(path, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("full_ply")
    ap.add_argument("out")
    ap.add_argument("--label", default="")
    ap.add_argument("--json", help="append the line to this file")
    ap.add_argument("--before-refinecheap31", action="store_true",
                    help="the settings before branch refinecheap31: 60 full-batch steps at learning rates 0.1 / 0.02, "
                         "16 validation cameras, 16 + 8 far cameras a level")
    args = ap.parse_args()
    phases = {"renders": 0.0, "pair_lists": 0.0, "fit_steps": 0.0, "validation": 0.0}
    calls = {k: 0 for k in phases}

    def timed(name, fn, pick=None):
        def wrapper(*a, **kw):
            key = pick(a, kw) if pick else name
            c0 = cpu_seconds()
            try:
                return fn(*a, **kw)
            finally:
                phases[key] += cpu_seconds() - c0
                calls[key] += 1
        return wrapper

    raster.render = timed("renders", raster.render)
    raster.pair_lists = timed("pair_lists", raster.pair_lists)
    raster.loss_and_grad = timed("", raster.loss_and_grad,
                                 lambda a, kw: "fit_steps" if kw.get("grad", a[4] if len(a) > 4 else True)
                                 else "validation")
    out = os.path.join(args.out, "refined")
    if os.path.exists(out):
        shutil.rmtree(out)
    settings = CpuRefineSettings()
    if args.before_refinecheap31:
        settings = CpuRefineSettings(iterations=60, batches=1, lr_opacity_logit=0.1, lr_sh_dc=0.02, lr_final=1.0,
                                     validation_cameras=16, far_training_cameras=16, far_validation_cameras=8)
    refiner = CpuLevelRefiner(settings)
    c0, w0 = cpu_seconds(), time.perf_counter()
    encode_file(args.full_ply, out, lod_refiner=refiner)
    cpu, wall = cpu_seconds() - c0, time.perf_counter() - w0
    row = {"label": args.label, "before_refinecheap31": args.before_refinecheap31,
           "input": args.full_ply, "cpu_s": round(cpu, 1), "wall_s": round(wall, 1),
           "phases_cpu_s": {k: round(v, 1) for k, v in phases.items()},
           "rest_cpu_s": round(cpu - sum(phases.values()), 1), "calls": calls,
           "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
           "load_average": os.getloadavg()[0], "numba_threads": raster.numba.get_num_threads(),
           "digest": directory_digest(out)}
    print(json.dumps(row), flush=True)
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
