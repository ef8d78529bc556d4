"""Plot of issue 38's series: first frame and per-frame selection against scene size (GPU machine runs).

    python bench/plot_city_sizes.py [--sizes bench/results/city_sizes_h200x2] [--city bench/results/city250m_r3]

Reads what `bash bench/device/run_city.sh sizes ...` and `... stream` wrote (a size whose files did not come back
from the device has a summary.json of its printed numbers) and writes plot.png and table.md beside the sizes.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _load(d: Path, fly_name: str = "flythrough.json") -> dict:
    if (d / "summary.json").exists():
        s = json.loads((d / "summary.json").read_text())
        return {"warm": s["first_frame_warm"]["first_frame_s"], "cold": s["first_frame_cold"]["first_frame_s"],
                **s["streaming"]}
    warm = json.loads((d / "first_frame_warm.json").read_text())
    cold = json.loads((d / "first_frame_cold.json").read_text())
    fly = json.loads((d / fly_name).read_text())["streaming"]
    return {"warm": warm["first_frame_s"], "cold": cold["first_frame_s"], **fly}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=Path, default=Path("bench/results/city_sizes_h200x2"))
    ap.add_argument("--city", type=Path, default=Path("bench/results/city250m_r3"), help="the 250M stream run")
    ap.add_argument("--city-splats", type=int, default=250_000_000)
    ap.add_argument("--city-fly", default="flythrough.json",
                    help="the 250M run's fly-through JSON (a second, warm pass: fly_2.json)")
    ap.add_argument("--sizes-fly", default="flythrough.json",
                    help="each size's fly-through JSON (fly_2.json: the second pass, SIZE_PASSES=2)")
    ap.add_argument("--cold", action="store_true", help="plot the cold first frame too (driver caches empty)")
    ap.add_argument("--caption", default="one H200 of nvidia-h200-x2 (32 cores), 2026-11-28: "
                                          "bench/device/run_city.sh sizes + stream")
    args = ap.parse_args()
    rows = {int(d.name.split("_")[1]): _load(d, args.sizes_fly) for d in sorted(args.sizes.glob("size_*"))}
    rows[args.city_splats] = _load(args.city, args.city_fly)
    sizes = sorted(rows)
    keys = ("warm", "cold", "median_ms", "p99_ms", "update_ms_median", "update_ms_p99", "select_ms_median",
            "select_ms_p99")
    lines = ["| splats | first frame s (warm / cold) | frame ms median / p99 | update ms median / p99 | "
             "selection ms median / p99 |", "|---|---|---|---|---|"]
    for n in sizes:
        r = {k: rows[n].get(k) for k in keys}
        lines.append(f"| {n / 1e6:g}M | {r['warm']:.3f} / {r['cold']:.3f} | {r['median_ms']:.1f} / {r['p99_ms']:.1f} | "
                     f"{r['update_ms_median']:.1f} / {r['update_ms_p99']:.1f} | "
                     f"{r['select_ms_median']:.2f} / {r['select_ms_p99']:.2f} |")
    (args.sizes / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    sys.path.insert(0, str(Path(__file__).parent))
    from PIL import Image, ImageDraw
    from plot_scale import PAD, H, W, panel

    img = Image.new("RGB", (2 * W, H + PAD // 2), "white")
    draw = ImageDraw.Draw(img)
    first = {"first frame": [(n, rows[n]["warm"]) for n in sizes]}
    if args.cold:
        first["first frame, cold driver"] = [(n, rows[n]["cold"]) for n in sizes]
    first["goal 0.3 s"] = [(n, 0.3) for n in sizes]
    title = "First frame on loopback (s)" + (", warm and cold" if args.cold else ", warm shader cache") + "; goal 0.3"
    panel(draw, 0, title, "splats", "s", first, True)
    panel(draw, W, "Fly-through, 3M budget (ms a frame); goals 1 / 16.7", "splats", "ms",
          {"frame p99": [(n, rows[n]["p99_ms"]) for n in sizes],
           "engine update p99": [(n, rows[n]["update_ms_p99"]) for n in sizes],
           "selection p99": [(n, rows[n]["select_ms_p99"]) for n in sizes],
           "selection median": [(n, rows[n]["select_ms_median"]) for n in sizes],
           "16.7 ms": [(n, 16.7) for n in sizes]}, True, legend_left=True)
    draw.text((10, H + 2), args.caption, fill=(0, 0, 0))
    img.save(args.sizes / "plot.png")

if __name__ == "__main__":
    main()
