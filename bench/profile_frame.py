"""Where a steady frame of SplatRenderer.render spends its CPU time, and how many GL calls it makes.

Renders a static camera on a small scene (a subset of a real scene, a small image, so that the GPU work is tiny and
the CPU side dominates) many times and reports:
  * submit_ms: render() without glFinish (median, p10, p90 over --frames frames): what the CPU spends to issue a
    frame (on a software GL such as llvmpipe this includes the compute work, which it runs at dispatch time);
  * wall_ms: render() followed by glFinish;
  * calls: moderngl / raw-GL calls per frame, counted in Python (--count): every moderngl method or property that
    reaches the driver, and the ctypes calls of client_gl/gpu/gl.py (texture binds of the pool);
  * with --profile, the cProfile functions of the frame loop by own time.

    .venv/bin/python bench/profile_frame.py --splats 2000 --size 64x48 --frames 400 --count --profile
    apitrace trace --api egl -o /tmp/f.trace .venv/bin/python bench/profile_frame.py --frames 50   # exact GL calls

Measured locally on llvmpipe these are CPU-side numbers only (BENCHMARKS.md, GPU renderer).
"""
from __future__ import annotations

import argparse
import collections
import cProfile
import functools
import io
import json
import os
import pstats
import statistics
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "bench"))

DEFAULT_PLY = os.path.join(ROOT, "..", "shared", "data", "real", "fruit_drops_sh3.ply")

# moderngl methods and property setters that reach the driver (each one GL call or a few).
_METHODS = {
    "Buffer": ("write", "read", "read_into", "clear", "bind_to_uniform_block", "bind_to_storage_buffer", "orphan"),
    "ComputeShader": ("run", "run_indirect"),
    "Query": ("__enter__", "__exit__"),
    "Framebuffer": ("use", "clear", "read"),
    "VertexArray": ("render", "render_indirect"),
    "Texture": ("bind_to_image", "use", "write", "read"),
    "Context": ("memory_barrier", "enable", "disable", "enable_only", "copy_buffer", "finish", "clear_samplers"),
}
_PROPERTIES = {
    "Framebuffer": ("depth_mask", "color_mask", "viewport", "scissor"),
    "Context": ("blend_func", "blend_equation", "depth_func", "viewport", "scissor", "point_size", "wireframe",
                "front_face", "cull_face", "polygon_offset"),
}


class _CountingMember:
    """A uniform of a program seen through __getitem__: counts value sets and writes."""

    def __init__(self, member, counts: collections.Counter, name: str):
        object.__setattr__(self, "_m", member)
        object.__setattr__(self, "_counts", counts)
        object.__setattr__(self, "_name", name)

    def __getattr__(self, attr):
        value = getattr(self._m, attr)
        if attr == "write":
            def write(*a, **k):
                self._counts["uniform.write"] += 1
                return value(*a, **k)
            return write
        return value

    def __setattr__(self, attr, value):
        if attr == "value":
            self._counts["uniform.value"] += 1
        setattr(self._m, attr, value)


def install_counters() -> collections.Counter:
    """Wrap moderngl's driver-reaching methods and client_gl.gpu.gl's raw calls; returns the live counter."""
    import moderngl

    import client_gl.gpu.gl as rawgl

    counts: collections.Counter = collections.Counter()

    def wrap(cls_name: str, name: str, fn):
        key = f"{cls_name}.{name}"

        @functools.wraps(fn)
        def counted(*a, **k):
            counts[key] += 1
            return fn(*a, **k)
        return counted

    for cls_name, names in _METHODS.items():
        cls = getattr(moderngl, cls_name)
        for name in names:
            if name in cls.__dict__:
                setattr(cls, name, wrap(cls_name, name, cls.__dict__[name]))
    for cls_name, names in _PROPERTIES.items():
        cls = getattr(moderngl, cls_name)
        for name in names:
            prop = cls.__dict__.get(name)
            if isinstance(prop, property) and prop.fset is not None:
                setattr(cls, name, property(prop.fget, wrap(cls_name, name + "=", prop.fset), prop.fdel))
    for cls_name in ("ComputeShader", "Program"):
        cls = getattr(moderngl, cls_name)
        orig_get = cls.__getitem__
        orig_set = cls.__setitem__

        def getitem(self, key, orig_get=orig_get):
            return _CountingMember(orig_get(self, key), counts, key)

        def setitem(self, key, value, orig_set=orig_set):
            counts["uniform.value"] += 1
            orig_set(self, key, value)
        cls.__getitem__ = getitem
        cls.__setitem__ = setitem

    class CountingGL:
        def __getattr__(self, name):
            fn = getattr(real_gl, name)

            def counted(*a):
                counts[f"gl.{name}"] += 1
                return fn(*a)
            return counted

    real_gl = rawgl.gl
    rawgl.gl = CountingGL()
    return counts


def load(args):
    from client_gl.offscreen import HeadlessRenderer, create_context
    from splatstream.camera import suggested_camera
    from splatstream.io import read_gaussians

    ctx = create_context()
    g = read_gaussians(args.ply)
    if args.splats and args.splats < len(g):
        g = g.subset(np.arange(args.splats))
    width, height = (int(v) for v in args.size.lower().split("x"))
    cam = suggested_camera(g.positions, width=width, height=height)
    from bench_render import render_options  # the same --draw spelling as bench_render.py

    r = HeadlessRenderer(render_options(args.sort, args.draw, args.color), ctx=ctx)
    r.load_gaussians(g, args.preset)
    img = r.render(cam)
    return ctx, r, cam, img


def stub_gpu_work() -> None:
    """Replace the calls that make a software GL execute work (dispatches, draws, clears) with no-ops: what is left
    of render() is the CPU cost of issuing the frame (Python, moderngl, the driver's state calls)."""
    import moderngl

    def nothing(*a, **k):
        return None
    for cls, names in ((moderngl.ComputeShader, ("run", "run_indirect")),
                       (moderngl.VertexArray, ("render", "render_indirect")), (moderngl.Framebuffer, ("clear",))):
        for name in names:
            setattr(cls, name, nothing)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ply", default=DEFAULT_PLY)
    ap.add_argument("--splats", type=int, default=2000, help="first N splats of the PLY (0: all)")
    ap.add_argument("--size", default="64x48")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--sort", default="gpu")
    ap.add_argument("--draw", default="compute", help="as bench_render.py --draw (e.g. compute, compute+r8)")
    ap.add_argument("--color", default="f2")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--stub", action="store_true",
                    help="after loading, make dispatches, draws and clears no-ops (CPU cost of issuing a frame)")
    ap.add_argument("--count", action="store_true", help="count moderngl / raw GL calls per frame")
    ap.add_argument("--profile", action="store_true", help="cProfile of the frame loop (top functions by own time)")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--json", help="write the numbers here")
    args = ap.parse_args()

    ctx, r, cam, _ = load(args)
    if args.stub:
        stub_gpu_work()
    render = r.render_frame
    for _ in range(args.warmup):
        render(cam)
    ctx.finish()
    submit = []
    wall = []
    for _ in range(args.frames):
        t = time.perf_counter()
        render(cam)
        t1 = time.perf_counter()
        ctx.finish()
        t2 = time.perf_counter()
        submit.append((t1 - t) * 1e3)
        wall.append((t2 - t) * 1e3)
    q = statistics.quantiles(submit, n=10)
    out = {"gl": ctx.info.get("GL_RENDERER"), "draw": r.renderer.draw_mode, "stub": args.stub, "splats": args.splats,
           "size": args.size, "frames": args.frames,
           "submit_ms": {"median": statistics.median(submit), "p10": q[0], "p90": q[-1]},
           "wall_ms": statistics.median(wall)}
    if args.count:
        counts = install_counters()
        frames = 20
        for _ in range(frames):
            render(cam)
        ctx.finish()
        counts["Context.finish"] -= 1
        per_frame = {k: v / frames for k, v in sorted(counts.items()) if v}
        out["calls_per_frame"] = per_frame
        out["calls_total"] = sum(per_frame.values())
    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        for _ in range(args.frames):
            render(cam)
        prof.disable()
        ctx.finish()
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(args.top)
        print(s.getvalue())
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
