"""Plot bench_scale.py results: peak memory of the process tree and wall time per splat against scene size (and,
for several worker counts, the speed-up). Pillow only.

    python bench/plot_scale.py bench/results/bench_scale_2core.json bench/results/bench_scale_2core.png
    python bench/plot_scale.py bench/results/bench_scale_16core_16m.json bench/results/bench_scale_16core_60m.json \
        bench/results/bench_scale_16core_60m.png
"""
from __future__ import annotations

import json
import math
import sys

from PIL import Image, ImageDraw

W, H, PAD = 520, 360, 60
COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14)]


def panel(draw: ImageDraw.ImageDraw, ox: int, title: str, xlabel: str, ylabel: str,
          series: dict[str, list[tuple[float, float]]], log_x: bool, legend_left: bool = False) -> None:
    xs = [x for pts in series.values() for x, _ in pts]
    ys = [y for pts in series.values() for _, y in pts]
    fx = (lambda v: math.log10(v)) if log_x else (lambda v: v)
    x0, x1 = fx(min(xs)), fx(max(xs))
    x0, x1 = (x0 - 0.1, x1 + 0.1) if x1 > x0 else (x0 - 1, x1 + 1)
    y1 = max(ys) * 1.15
    left, top, right, bottom = ox + PAD, PAD // 2 + 10, ox + W - 20, H - PAD

    def px(x: float, y: float) -> tuple[float, float]:
        return (left + (fx(x) - x0) / (x1 - x0) * (right - left), bottom - y / y1 * (bottom - top))

    draw.rectangle([left, top, right, bottom], outline=(0, 0, 0))
    draw.text((left, 8), title, fill=(0, 0, 0))
    draw.text(((left + right) // 2 - 40, bottom + 28), xlabel, fill=(0, 0, 0))
    draw.text((ox + 4, top - 14), ylabel, fill=(0, 0, 0))
    for k in range(6):
        y = y1 * k / 5
        _, yy = px(min(xs), y)
        draw.line([left - 4, yy, left, yy], fill=(0, 0, 0))
        draw.text((ox + 8, yy - 6), f"{y:.3g}", fill=(0, 0, 0))
    for x in sorted(set(xs)):
        xx, _ = px(x, 0)
        draw.line([xx, bottom, xx, bottom + 4], fill=(0, 0, 0))
        draw.text((xx - 12, bottom + 8), f"{x / 1e6:g}M" if log_x else f"{x:g}", fill=(0, 0, 0))
    legend_x = left + 10 if legend_left else right - 10 - max(draw.textlength(n) for n in series)
    for i, (name, pts) in enumerate(series.items()):
        c = (128, 128, 128) if name == "ideal" else COLOURS[i % len(COLOURS)]
        pts = sorted(pts)
        coords = [px(x, y) for x, y in pts]
        if len(coords) > 1:
            draw.line(coords, fill=c, width=2)
        for xx, yy in coords:
            draw.ellipse([xx - 3, yy - 3, xx + 3, yy + 3], fill=c)
        draw.text((legend_x, top + 8 + 14 * i), name, fill=c)


def speedup_series(runs: list[dict]) -> tuple[dict, dict]:
    """Speed-up against one worker and peak memory per worker, one curve per scene size. A size without a
    1-worker run is compared with the 1-worker time per splat of the nearest size that has one (named in the
    legend): the partitioned encoder's time per splat is about flat in scene size."""
    dask = [r for r in runs if r["engine"].startswith("dask-")]
    one = {r["splats"]: r["us_per_splat"] for r in dask if r["engine"] == "dask-1"}
    speed, mem = {}, {}
    for n in sorted({r["splats"] for r in dask}):
        # "dask-W" or, with bench_scale --lod-merge, "dask-W-MERGE" (several runs of one worker count)
        here = sorted(((int(r["engine"].split("-")[1]), r) for r in dask if r["splats"] == n), key=lambda t: t[0])
        base_n = n if n in one else min(one, key=lambda m: abs(m - n), default=None)
        if base_n is None:  # no 1-worker run at all: relative to the fewest workers, as if they scaled perfectly
            base_s = here[0][1]["wall_s"] * here[0][0]
            label = f"{n / 1e6:g}M (base: {here[0][0]} workers x {here[0][0]})"
        else:
            base_s = one[base_n] * n / 1e6
            label = f"{n / 1e6:g}M" + ("" if base_n == n else f" (1-worker us/splat of {base_n / 1e6:g}M)")
        speed[label] = [(w, base_s / r["wall_s"]) for w, r in here]
        mem[f"{n / 1e6:g}M largest process"] = [(w, r["peak_process_mb"] / 1024) for w, r in here]
        mem[f"{n / 1e6:g}M tree / workers"] = [(w, r["peak_tree_mb"] / 1024 / w) for w, r in here]
    workers = sorted({w for pts in speed.values() for w, _ in pts} | {1})
    speed["ideal"] = [(w, float(w)) for w in workers]
    return speed, mem


def main() -> None:
    """plot_scale.py RESULTS.json [MORE.json ...] OUT.png"""
    if len(sys.argv) < 3:
        raise SystemExit(main.__doc__)
    files = [json.load(open(f)) for f in sys.argv[1:-1]]
    data = files[0]
    runs = [r for f in files for r in f["runs"]]
    engines = sorted({r["engine"] for r in runs})
    sizes = sorted({r["splats"] for r in runs})
    workers = {r["engine"] for r in runs if r["engine"].startswith("dask-")}
    img = Image.new("RGB", (2 * W, H), (255, 255, 255))
    d = ImageDraw.Draw(img)
    if len(workers) <= 1:
        mem = {e: [(r["splats"], r["peak_tree_mb"] / 1024) for r in runs if r["engine"] == e] for e in engines}
        per = {e: [(r["splats"], r["us_per_splat"]) for r in runs if r["engine"] == e] for e in engines}
        panel(d, 0, f"peak memory, whole process tree ({data['machine']['cpus']} cores)", "splats", "GiB", mem, True)
        panel(d, W, "wall time per splat", "splats", "us / splat", per, True)
    else:
        speed, mem = speedup_series(runs)
        title = ", ".join(f"{n / 1e6:g}M" for n in sizes)
        panel(d, 0, f"speed-up against 1 worker ({data['machine']['cpus']} cores; {title} splats)", "workers", "x",
              speed, False, legend_left=True)
        panel(d, W, "peak memory per worker (PSS)", "workers", "GiB", mem, False)
    img.save(sys.argv[-1])


if __name__ == "__main__":
    main()
