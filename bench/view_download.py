#!/usr/bin/env python3
"""What a user's `splatstream view SCENE --headless --max-splats N` reads, prefetch on (the default) and off, against
the bytes of the tiles it draws (issue 31: "bytes downloaded at convergence at most 1.2x the bytes of the tiles
drawn"), and the GPU memory its summary reports.

The real CLI in a subprocess, one camera of a lod_vs_peers JSON (its `cameras`, --view), each budget of that JSON's
`budget_splats` (or --budgets), once with the default prefetch and once with --no-prefetch; from each run's --record:
the bytes read at exit (the run stops at convergence, before prefetch starts: it fetches only once nothing the view
needs is missing; a third run draws --settle-frames more frames after convergence, as an open window would, and
reports what prefetch read by then), the splats drawn in the last frame, the tiles drawn (the last
frame's draw set is not in the record: the drawn tiles' bytes are those of the same camera's cut in the lod_vs_peers
JSON, `drawn_tile_ids_per_view`, whose runs used --no-prefetch; a run whose drawn splat count differs from that JSON's
is flagged), and the summary line's GPU memory (the resident splats' memory against the --gpu-mem-mb budget).

    PYTHONPATH=. .venv/bin/python bench/view_download.py SCENE_DIR bench/results/lod_vs_peers_heldout/playbot.json \
        --view 0 --out bench/results/lod_vs_peers_heldout/view_download_default.json
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import lod_vs_peers as lvp  # noqa: E402  (bench/ is not a package)


def view_once(scene: str, cam: dict, n: int, size: int, prefetch: bool, workdir: str, settle: int = 0) -> dict:
    rec_path = os.path.join(workdir, f"rec_{n}_{int(prefetch)}_{settle}.json")
    argv = lvp.view_argv(scene, n, size, cam["eye"], cam["target"], cam["up"], cam["fov_y_deg"], timeout_s=300)
    argv += ["--record", rec_path]
    if not prefetch:
        argv.append("--no-prefetch")
    if settle:  # frames drawn after convergence, as an open window keeps drawing: what prefetch fetches meanwhile
        argv += ["--measure-frames", str(settle)]
    t0 = time.process_time()
    proc = subprocess.run([sys.executable, "-m", "cli", *argv], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"splatstream {' '.join(argv)}: rc {proc.returncode}\n{proc.stderr[-2000:]}")
    rec = json.load(open(rec_path))
    last = rec["frames"][-1]
    summary = [ln for ln in proc.stderr.splitlines() if ln.startswith("view: first frame")]
    return {"argv": ["splatstream", *argv[:4], *(["--no-prefetch"] if not prefetch else []),
                     *(["--measure-frames", str(settle)] if settle else [])],
            "prefetch": prefetch, "frames_after_convergence": settle, "bytes_downloaded": rec["bytes_downloaded"],
            "drawn_splats": last["drawn_splats"], "resident_tiles": last["resident_tiles"],
            "resident_splats": rec["resident_splats"], "resident_gpu_bytes": rec["resident_gpu_bytes"],
            "gpu_bytes_peak": rec["gpu_bytes_peak"], "gpu_budget_bytes": rec["gpu_budget_bytes"],
            "converged_s": rec["converged_s"], "summary": summary[-1] if summary else None,
            "children_cpu_s": round(time.process_time() - t0, 2)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="our encoded scene directory")
    ap.add_argument("bench_json", help="lod_vs_peers' SCENE.json of this scene directory (cameras, cuts)")
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--budgets", default=None, help="comma list of splat counts (default: the JSON's)")
    ap.add_argument("--settle-frames", type=int, default=60,
                    help="a third run: the default prefetch and this many frames after convergence (0: none)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from splatstream.format.manifest import parse_manifest
    from splatstream.format.names import MANIFEST_NAME

    res = json.load(open(args.bench_json))
    cam = res["cameras"][args.view]
    size = res["size"][0]
    manifest = parse_manifest(open(os.path.join(args.scene, MANIFEST_NAME), "rb").read())
    ours = {r["budget"]: r for r in res["ours"]}
    budgets = [int(b) for b in args.budgets.split(",")] if args.budgets else list(res["budget_splats"])
    rows = []
    with tempfile.TemporaryDirectory(prefix="vdl-") as work:
        for n in budgets:
            o = ours.get(n)
            row = {"budget": n}
            if o is not None:
                row["bench_drawn_splats"] = o["splats_drawn_per_view"][args.view]
                row["drawn_tile_bytes"] = lvp.drawn_tile_bytes(manifest, o["drawn_tile_ids_per_view"][args.view])[0]
                row["bench_bytes_downloaded"] = o["bytes_downloaded_per_view"][args.view]
            modes = [("prefetch", True, 0), ("no_prefetch", False, 0)]
            if args.settle_frames:
                modes.append(("prefetch_settled", True, args.settle_frames))
            for key, prefetch, settle in modes:
                r = view_once(args.scene, cam, n, size, prefetch, work, settle)
                row[key] = r
                if "drawn_tile_bytes" in row:
                    r["x_drawn_tile_bytes"] = round(r["bytes_downloaded"] / row["drawn_tile_bytes"], 3)
                    r["same_cut_as_bench"] = r["drawn_splats"] == row["bench_drawn_splats"]
                print(f"N {n:>8,} {key:>11}: {r['bytes_downloaded'] / 1e6:7.2f} MB"
                      + (f" ({r['x_drawn_tile_bytes']}x the drawn tiles' {row['drawn_tile_bytes'] / 1e6:.2f} MB)"
                         if "drawn_tile_bytes" in row else "")
                      + f", drawn {r['drawn_splats']:,}; {r['summary']}", file=sys.stderr, flush=True)
            rows.append(row)
    out = {"scene": args.scene, "bench_json": args.bench_json, "view": args.view, "camera": cam, "size": size,
           "rows": rows, "load_average": os.getloadavg()}
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
