"""Probe of the CPU refinement of the merged LOD levels (refine_cpu/, issue 31): the default encode and the encode with
refine_cpu.levels.CpuLevelRefiner of one canonical PLY (bench/lod_vs_peers.py's CACHE/SCENE/full.ply), each timed in
CPU seconds (user + sys of this process) with its peak resident memory, and the refiner's per-level report; then
bench/lod_vs_peers.py streams the refined scene with the real client (--our-scene-dir OUT/refined; OUT/plain:
the default).

    PYTHONPATH=. nice -n 19 python bench/probe_cpurefine.py /tmp/cache/statue-st-peter/full.ply OUT [--plain]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from refine_cpu.levels import CpuLevelRefiner, CpuRefineSettings  # noqa: E402
from splatstream.encode import encode_file  # noqa: E402


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed_encode(src: str, out: str, **kw) -> dict:
    if os.path.exists(out):
        shutil.rmtree(out)
    c0, w0 = cpu_seconds(), time.perf_counter()
    m = encode_file(src, out, **kw)
    return {"cpu_s": round(cpu_seconds() - c0, 1), "wall_s": round(time.perf_counter() - w0, 1),
            "bytes_on_disk": m.bytes_on_disk,
            "peak_rss_mb_so_far": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("full_ply")
    ap.add_argument("out")
    ap.add_argument("--plain", action="store_true", help="also the default encode (OUT/plain), timed")
    ap.add_argument("--iterations", type=int, default=CpuRefineSettings.iterations)
    ap.add_argument("--size", type=int, default=CpuRefineSettings.size)
    ap.add_argument("--training-cameras", type=int, default=CpuRefineSettings.training_cameras)
    ap.add_argument("--validation-cameras", type=int, default=CpuRefineSettings.validation_cameras)
    ap.add_argument("--far-training-cameras", type=int, default=CpuRefineSettings.far_training_cameras,
                    help="each level's far training cameras (0: none, the refinement before far31)")
    ap.add_argument("--far-validation-cameras", type=int, default=CpuRefineSettings.far_validation_cameras)
    ap.add_argument("--lr-opacity", type=float, default=CpuRefineSettings.lr_opacity_logit)
    ap.add_argument("--lr-dc", type=float, default=CpuRefineSettings.lr_sh_dc)
    ap.add_argument("--lr-final", type=float, default=CpuRefineSettings.lr_final)
    ap.add_argument("--batches", type=int, default=CpuRefineSettings.batches)
    ap.add_argument("--far-weight", type=float, default=CpuRefineSettings.far_weight)
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    scene = os.path.basename(os.path.dirname(os.path.abspath(args.full_ply)))  # CACHE/SCENE/full.ply
    res: dict = {"input": args.full_ply, "scene": scene}
    if args.plain:
        res["plain"] = timed_encode(args.full_ply, os.path.join(args.out, "plain", scene))
        print("plain", res["plain"], flush=True)
    refiner = CpuLevelRefiner(CpuRefineSettings(iterations=args.iterations, size=args.size,
                                           training_cameras=args.training_cameras,
                                           validation_cameras=args.validation_cameras,
                                           far_training_cameras=args.far_training_cameras,
                                           far_validation_cameras=args.far_validation_cameras,
                                           far_weight=args.far_weight, lr_opacity_logit=args.lr_opacity,
                                           lr_sh_dc=args.lr_dc, lr_final=args.lr_final,
                                           batches=args.batches,
                                           log=lambda m: print("lod-refine:", m, flush=True)))
    res["refined"] = timed_encode(args.full_ply, os.path.join(args.out, "refined", scene), lod_refiner=refiner)
    res["refined"]["levels"] = refiner.report
    res["settings"] = {"iterations": args.iterations, "size": args.size, "training_cameras": args.training_cameras,
                       "validation_cameras": args.validation_cameras,
                       "far_training_cameras": args.far_training_cameras,
                       "far_validation_cameras": args.far_validation_cameras, "far_weight": args.far_weight,
                       "lr_opacity": args.lr_opacity, "lr_dc": args.lr_dc, "lr_final": args.lr_final,
                       "batches": args.batches}
    print("refined", json.dumps(res["refined"]), flush=True)
    json.dump(res, open(os.path.join(args.out, f"probe_{scene}.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
