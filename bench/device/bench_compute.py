"""bench/bench_render.py with the compute rasterizer's extra stages (binning, tile sort) and entry counts.

Run like bench_render.py (same arguments; bench/device/run_bench.sh with BENCH=bench/device/bench_compute.py).
Adds to every GPU-path variant: bin_ms, tile_sort_ms (medians, GL_TIME_ELAPSED), entries / entries_needed /
entry_capacity (compute draw), and psnr_vs_first_draw_db: the frame against the first draw mode's frame of the same
scene and preset (e.g. compute vs fetch).
"""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import bench_render  # noqa: E402

_first_images: dict[tuple, object] = {}
_orig_bench_gl = bench_render.bench_gl


def bench_gl(ctx, scene, cam, frames, sort, color_dtype, draw="instanced", settle=None):
    from client_gl.offscreen import HeadlessRenderer

    collected: list = []
    orig = HeadlessRenderer.render_frame

    def render_frame(self, *args, **kwargs):
        s = orig(self, *args, **kwargs)
        collected.append(s)
        return s

    HeadlessRenderer.render_frame = render_frame
    try:
        out = _orig_bench_gl(ctx, scene, cam, frames, sort, color_dtype, draw, settle)
    finally:
        HeadlessRenderer.render_frame = orig
    timed = [s for s in collected if s.cull_ms is not None]
    for key in ("bin_ms", "tile_sort_ms"):
        vals = [getattr(s, key) for s in timed if getattr(s, key) is not None]
        out[key] = bench_render.median(vals) if vals else None
    r = out["_renderer"]
    rend = r.renderer
    if sort == "gpu" and rend.draw_mode == "compute":
        entries, needed = rend.read_bin_counts()
        out.update(entries=entries, entries_needed=needed, entry_capacity=rend.craster.entry_capacity)
    if sort == "gpu":
        img = r.render(cam)
        key = (scene.splats, str(sorted(scene.formats.items())), tuple(cam.eye))  # one scene, one preset
        first = _first_images.setdefault(key, img)
        if first is not img:
            out["psnr_vs_first_draw_db"] = bench_render.psnr(img, first)
    return out


bench_render.bench_gl = bench_gl

if __name__ == "__main__":
    sys.exit(bench_render.main())
