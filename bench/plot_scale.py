"""Plot bench_scale.py results: peak memory of the process tree and wall time per splat against scene size (and,
for several worker counts, the speed-up). Pillow only.

    python bench/plot_scale.py bench/results/bench_scale_2core.json bench/results/bench_scale_2core.png
"""
from __future__ import annotations

import json
import math
import sys

from PIL import Image, ImageDraw

W, H, PAD = 520, 360, 60
COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14)]


def panel(draw: ImageDraw.ImageDraw, ox: int, title: str, xlabel: str, ylabel: str,
          series: dict[str, list[tuple[float, float]]], log_x: bool) -> None:
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
    for i, (name, pts) in enumerate(series.items()):
        c = COLOURS[i % len(COLOURS)]
        pts = sorted(pts)
        coords = [px(x, y) for x, y in pts]
        if len(coords) > 1:
            draw.line(coords, fill=c, width=2)
        for xx, yy in coords:
            draw.ellipse([xx - 3, yy - 3, xx + 3, yy + 3], fill=c)
        draw.text((right - 110, top + 8 + 14 * i), name, fill=c)


def main() -> None:
    data = json.load(open(sys.argv[1]))
    runs = data["runs"]
    engines = sorted({r["engine"] for r in runs})
    sizes = sorted({r["splats"] for r in runs})
    img = Image.new("RGB", (2 * W, H), (255, 255, 255))
    d = ImageDraw.Draw(img)
    if len(sizes) > 1:
        mem = {e: [(r["splats"], r["peak_tree_mb"] / 1024) for r in runs if r["engine"] == e] for e in engines}
        per = {e: [(r["splats"], r["us_per_splat"]) for r in runs if r["engine"] == e] for e in engines}
        panel(d, 0, f"peak memory, whole process tree ({data['machine']['cpus']} cores)", "splats", "GiB", mem, True)
        panel(d, W, "wall time per splat", "splats", "us / splat", per, True)
    else:
        dask = sorted((int(r["engine"].split("-")[1]), r) for r in runs if r["engine"].startswith("dask-"))
        base = dask[0][1]["wall_s"] * dask[0][0]
        panel(d, 0, f"speed-up, {sizes[0] / 1e6:g}M splats", "workers", "x",
              {"measured": [(w, base / r["wall_s"]) for w, r in dask], "ideal": [(w, float(w)) for w, _ in dask]},
              False)
        panel(d, W, "peak memory per worker process", "workers", "GiB",
              {"largest process": [(w, r["peak_process_mb"] / 1024) for w, r in dask],
               "tree / workers": [(w, r["peak_tree_mb"] / 1024 / w) for w, r in dask]}, False)
    img.save(sys.argv[2])


if __name__ == "__main__":
    main()
