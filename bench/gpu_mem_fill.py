"""How much of `--gpu-mem-mb` a converged view fills (issue 31: "--gpu-mem-mb likewise").

For each scene and budget M (a share of the scene's full-detail GPU bytes, `splatstream info`'s gpu_bytes, or MiB),
what `splatstream view SCENE --headless --gpu-mem-mb M --size WxH` does at the scene's suggested camera, run to
convergence in this process, and where the gap between M and the bytes drawn goes:

  pool       the pool allocated for M (a grid of 256-splat slots, each with room for every SH band)
  byte_cap   the cut's byte budget (the pool's slots x target_fraction)
  cut        the cut's cost (its tiles' slots), drawn: the draw set's slots and splats
  resident   the slots resident (the draw set, ancestors kept for coarse to fine, prefetched tiles)
  splat_eq   drawn splats x the pool's bytes per slot / 256 (the drawn splats' bytes without slot rounding)

    PYTHONPATH=. python bench/gpu_mem_fill.py SCENE_DIR [SCENE_DIR ...] --shares 0.05,0.25,0.6 [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np


def measure(scene: str, mib: float, size: tuple[int, int], timeout_s: float = 120.0,
            target_fraction: float | None = None) -> dict:
    from dataclasses import replace

    from lod_vs_peers import stream_until_converged

    from client_gl.offscreen import create_context
    from client_gl.streaming import StreamingSession, ViewOptions
    from client_gl.view_headless import scene_camera

    ctx = create_context()
    session = StreamingSession.open(scene, ctx, ViewOptions(gpu_mem_mb=mib, cache=False))
    try:
        if target_fraction is not None:  # the engine's share of the pool the cut may fill (StreamOptions)
            session.engine.options = replace(session.engine.options, target_fraction=target_fraction)
        cam = scene_camera(session, size)
        stream_until_converged(session, cam, timeout_s, f"{scene} at {mib} MiB")
        eng, pool = session.engine, session.pool
        _, sel, *_ = eng.wanted(cam)
        ids = eng.ids
        pos = {int(t): i for i, t in enumerate(ids.tolist())}
        drawn = np.asarray([pos[int(t)] for t in session.last.draw], np.intp)
        slot_bytes = eng.slot_bytes
        cut = sel.cut_at
        budget = pool.capacity_slots * slot_bytes * eng.options.target_fraction
        out = {
            "scene": os.path.basename(scene.rstrip("/")), "mib": mib, "budget_bytes": session.budget,
            "pool_bytes": pool.gpu_bytes, "capacity_slots": pool.capacity_slots, "slot_bytes": slot_bytes,
            "byte_cap": budget, "cut_tiles": len(cut), "cut_bytes": int(eng.slots_needed[cut].sum()) * slot_bytes,
            "budget_limited": bool(sel.budget_limited),
            "drawn_tiles": len(drawn), "drawn_splats": int(eng.arrays.splats[drawn].sum()),
            "drawn_slot_bytes": int(eng.slots_needed[drawn].sum()) * slot_bytes,
            "resident_tiles": int(eng.resident.sum()), "resident_slots": pool.used_slots,
            "resident_bytes": pool.resident_bytes, "evictions": session.metrics.evictions
            if hasattr(session.metrics, "evictions") else None,
        }
        out["splat_eq_bytes"] = out["drawn_splats"] * slot_bytes / 256
        out["frac_drawn_slots"] = out["drawn_slot_bytes"] / session.budget
        out["frac_splat_eq"] = out["splat_eq_bytes"] / session.budget
        out["frac_resident"] = out["resident_bytes"] / session.budget
        out["frac_pool"] = out["pool_bytes"] / session.budget
        return out
    finally:
        session.close()
        ctx.release()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", nargs="+")
    p.add_argument("--shares", default="0.05,0.25,0.6", help="budgets as shares of full-detail GPU bytes")
    p.add_argument("--mib", default="", help="budgets in MiB instead")
    p.add_argument("--size", default="1280x720")
    p.add_argument("--target-fraction", type=float, help="the cut's share of the pool (default: the engine's)")
    p.add_argument("--json")
    args = p.parse_args(argv)
    from cli.commands.info import scene_info
    from splatstream.format.manifest import parse_manifest
    from splatstream.format.names import MANIFEST_NAME

    w, h = (int(x) for x in args.size.split("x"))
    rows = []
    for scene in args.scenes:
        with open(os.path.join(scene, MANIFEST_NAME), "rb") as f:
            full = scene_info(parse_manifest(f.read()))["gpu_bytes"]
        budgets = ([float(x) for x in args.mib.split(",")] if args.mib else
                   [float(s) * full / (1 << 20) for s in args.shares.split(",")])
        for mib in budgets:
            r = measure(scene, mib, (w, h), target_fraction=args.target_fraction)
            r["full_gpu_bytes"] = full
            rows.append(r)
            print(f"{r['scene']:>22} M={mib:7.3f} MiB ({r['budget_bytes'] / full:5.1%} of full) "
                  f"pool {r['frac_pool']:.1%} cut {r['cut_bytes'] / r['budget_bytes']:.1%} "
                  f"drawn(slots) {r['frac_drawn_slots']:.1%} drawn(splats) {r['frac_splat_eq']:.1%} "
                  f"resident {r['frac_resident']:.1%} limited={r['budget_limited']} "
                  f"drawn {r['drawn_splats']:,} in {r['drawn_tiles']} tiles", flush=True)
    if args.json:
        json.dump(rows, open(args.json, "w"), indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
