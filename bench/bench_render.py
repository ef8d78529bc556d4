"""Benchmark of the GL renderer (client_gl) on make_scene.py scenes from the standard benchmark view.

Per scene (size, spread) and preset: per-frame GPU time split into stages (GL_TIME_ELAPSED timer queries), the wall
clock per frame (render + glFinish, median), the CPU submit time (render() returning, no glFinish, median), visible
splats, sort throughput (visible keys / sort time, and a standalone sort of random keys), GPU bytes per splat; the
CPU-sort path; optionally gsplat on the same scene and camera (CUDA, forward only: GPU time from CUDA events and wall
clock with a synchronize per frame), with the PSNR of our image against gsplat's at --psnr-preset (very-high).

Every measured variant (and gsplat) first warms up until its per-frame wall times settle: the median of the last
--settle-window frames within --settle-tol of the median of the window before, after at least --warmup-min frames
(at most --warmup-max frames or --warmup-s seconds). The first size of a run otherwise meets cold GPU clocks.

    python3 bench/bench_render.py --splats 1000000 6000000 --spread 1.0 0.25 --presets medium --gsplat \
        --make-scene ../shared/tools/make_scene.py --workdir /tmp/bench --json bench.json

Scenes: `make_scene.py --splats N --seed 0 [--spread S]` (SH degree 3; spread 1.0 is make_scene's default, sparse;
0.25 packs the copies densely and covers the screen like a real capture). View: camera.standard_benchmark_view
(target = median, eye = c + (-side, -side, 0.6 side), fov_y 50, 1920x1080).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import struct
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from splatstream.camera import Camera, standard_benchmark_view  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402

DEFAULT_SPREAD = 1.0


def log(*args) -> None:
    print(*args, file=sys.stderr, flush=True)


def median(xs):
    return float(statistics.median(xs)) if xs else None


def scene_path(workdir: str, n: int, seed: int, spread: float) -> str:
    """Cached scene file of (n, seed, spread); spread 1.0 keeps the name earlier runs used."""
    suffix = "" if spread == DEFAULT_SPREAD else f"_spread{spread:g}"
    return os.path.join(workdir, f"scene_{n}_seed{seed}{suffix}.ply")


def make_scene(script: str, n: int, path: str, seed: int, spread: float = DEFAULT_SPREAD) -> None:
    if os.path.exists(path):
        return
    t = time.perf_counter()
    cmd = [sys.executable, script, "--splats", str(n), "--seed", str(seed), "--out", path + ".part"]
    if spread != DEFAULT_SPREAD:
        cmd += ["--spread", repr(float(spread))]
    subprocess.run(cmd, check=True)
    os.replace(path + ".part", path)
    log(f"made {path} in {time.perf_counter() - t:.1f}s")


class Settle:
    """Warm-up rule: run until per-frame wall times settle (see the module doc)."""

    def __init__(self, min_frames: int = 30, max_frames: int = 400, window: int = 10, tol: float = 0.03,
                 max_s: float = 20.0):
        self.min_frames, self.max_frames, self.window, self.tol, self.max_s = (
            max(min_frames, 2 * window), max_frames, window, tol, max_s)

    def run(self, step) -> dict:
        """Call step() (one frame, synchronised) until settled; returns the frames run and the last window's median."""
        times: list[float] = []
        t_end = time.perf_counter() + self.max_s
        w = self.window
        settled = False
        while True:
            t = time.perf_counter()
            step()
            times.append(time.perf_counter() - t)
            if len(times) >= self.min_frames:
                last, prev = statistics.median(times[-w:]), statistics.median(times[-2 * w:-w])
                if abs(last - prev) <= self.tol * prev:
                    settled = True
                    break
            if len(times) >= self.max_frames or time.perf_counter() > t_end:
                break
        return {"frames": len(times), "ms": statistics.median(times[-w:]) * 1e3, "settled": settled}


# Measurement flags of a --draw value ("fetch+f2b", "compute+nowc+tr8", ...) -> RenderOptions fields.
DRAW_FLAGS = {"f2b": {"front_to_back": True}, "nodepth": {"depth_test": False}, "noblend": {"blend": False},
              "wc": {"warp_cull": True}, "nowc": {"warp_cull": False}, "r8": {"radix_bits": 8},
              "classic": {"fused_sort": False}, "fb": {"full_barriers": True},
              # dense-scene variants of the compute draw (RenderOptions; issue 20). Former defaults: d32 (32-bit depth
              # keys), tr4 (4-bit tile sort digits). The binning and flush variants of that round (fl, fls, nofl, tb,
              # er, tpe, box), discard, and 8-pixel tiles and shorter unrolls (t8, u1, u2) are measured
              # (BENCHMARKS.md) and gone from the renderer.
              "tr4": {"tile_radix_bits": 4}, "tr5": {"tile_radix_bits": 5}, "tr8": {"tile_radix_bits": 8},
              "dr4": {"radix_bits": 4}, "dr5": {"radix_bits": 5}, "dr6": {"radix_bits": 6}, "dr8": {"radix_bits": 8},
              "d16": {"depth_bits": 16}, "d20": {"depth_bits": 20}, "d32": {"depth_bits": 32}}


def render_options(sort: str, draw: str, color_dtype: str):
    """RenderOptions of a --draw value: a draw mode with optional +flags (DRAW_FLAGS)."""
    from client_gl.gpu.renderer import RenderOptions

    mode, *flags = draw.split("+")
    fields = {}
    for flag in flags:
        if flag not in DRAW_FLAGS:
            raise SystemExit(f"--draw {draw}: unknown flag +{flag} (known: {', '.join(DRAW_FLAGS)})")
        fields.update(DRAW_FLAGS[flag])
    return RenderOptions(sort=sort, draw=mode, color_dtype=color_dtype, **fields)


def timed_frames(ctx, render, frames: int) -> tuple[list[float], list[float]]:
    """(submit ms, wall ms) per frame: render() returning, and render() + glFinish."""
    submit, wall = [], []
    for _ in range(frames):
        t0 = time.perf_counter()
        render()
        t1 = time.perf_counter()
        ctx.finish()
        t2 = time.perf_counter()
        submit.append((t1 - t0) * 1e3)
        wall.append((t2 - t0) * 1e3)
    return submit, wall


def bench_gl(ctx, scene, cam: Camera, frames: int, sort: str, color_dtype: str, draw: str = "instanced",
             settle: Settle | None = None) -> dict:
    from client_gl.offscreen import HeadlessRenderer

    r = HeadlessRenderer(render_options(sort, draw, color_dtype), ctx=ctx)
    t = time.perf_counter()
    r.load_tiles(scene)
    ctx.finish()
    out = {"sort": r.sort_mode, "draw": draw, "color": color_dtype, "upload_s": time.perf_counter() - t}
    rend = r.renderer
    r.render(cam)  # first frame: shaders, buffers, the entry buffer's check
    settle = settle or Settle()
    if r.sort_mode != "gpu":
        settle = Settle(min_frames=2, window=1, max_frames=3)

    def frame():
        r.render_frame(cam)
        ctx.finish()

    out["warmup"] = settle.run(frame)
    submit, wall = timed_frames(ctx, lambda: r.render_frame(cam), frames)
    out["wall_ms"] = median(wall)
    out["wall_mean_ms"] = float(np.mean(wall))
    out["submit_ms"] = median(submit)
    stats = [r.render_frame(cam, timing=True) for _ in range(frames)]
    if r.sort_mode == "gpu":
        out["visible"] = rend.read_visible_count()
        out["draw"] = draw if draw.split("+")[0] == rend.draw_mode else f"{draw}->{rend.draw_mode}"
        out["oversized"] = rend.read_oversized_count()
        out["cull_ms"] = median([s.cull_ms for s in stats])
        out["sort_ms"] = median([s.sort_ms for s in stats])
        out["draw_ms"] = median([s.draw_ms for s in stats])
        if stats[0].bin_ms is not None:  # compute draw: binning and tile sort
            out["bin_ms"] = median([s.bin_ms for s in stats])
            out["tile_sort_ms"] = median([s.tile_sort_ms for s in stats])
        out["gpu_ms"] = median([s.total_ms for s in stats])
        out["sort_keys_per_s"] = out["visible"] / (out["sort_ms"] * 1e-3) if out["sort_ms"] else None
    else:
        out["visible"] = stats[-1].visible
        out["cpu_cull_sort_ms"] = median([s.cpu_ms["cull_sort"] for s in stats])
        out["cpu_upload_draw_ms"] = median([s.cpu_ms["upload_draw"] for s in stats])
        out["draw_ms"] = median([s.draw_ms for s in stats])
    pool = r.pool
    n = scene.splats
    out["pool_bytes_per_splat"] = pool.gpu_bytes / n
    out["pool_bytes_per_slot"] = pool.bytes_per_splat
    out["texel_bytes_per_splat"] = pool.texel_bytes / n
    out["range_bytes_per_splat"] = pool.range_bytes / n
    out["work_bytes_per_splat"] = rend.work_bytes / n
    r.last_image = None
    out["_renderer"] = r
    return out


def bench_sort_random(ctx, n: int, reps: int = 10) -> dict:
    """Standalone GPU radix sort of n random uint32 keys with uint32 values (GPU time, timer queries)."""
    from client_gl.gpu.sort import GpuRadixSort

    s = GpuRadixSort(ctx, n)
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    kb = ctx.buffer(keys.tobytes())
    vb = ctx.buffer(np.arange(n, dtype=np.uint32).tobytes())
    params = ctx.buffer(struct.pack("4I", n, 0, 0, 0))
    s.setup(params)
    t_end = time.perf_counter() + 1.0  # warm-up: the clocks ramp up from idle
    while time.perf_counter() < t_end:
        s.sort(params, kb, vb)
        ctx.finish()
    times = []
    q = ctx.query(time=True)
    for _ in range(reps):
        kb.write(keys.tobytes())
        with q:
            s.sort(params, kb, vb)
        times.append(q.elapsed / 1e6)
    out_k = np.frombuffer(kb.read(), np.uint32)
    ok = bool(np.all(out_k[1:] >= out_k[:-1]))
    ms = median(times)
    for b in (kb, vb, params):
        b.release()
    s.release()
    return {"n": n, "ms": ms, "keys_per_s": n / (ms * 1e-3), "sorted": ok}


def bench_gsplat(g, cam: Camera, frames: int, settle: Settle | None = None) -> dict:
    import torch
    from gsplat import rasterization

    dev = "cuda"
    means = torch.from_numpy(g.positions).to(dev)
    quats = torch.from_numpy(g.rotations).to(dev)
    scales = torch.from_numpy(np.exp(g.log_scales)).to(dev)
    opac = torch.from_numpy(g.opacities).to(dev)
    colors = torch.from_numpy(np.concatenate([g.sh_dc[:, None, :], g.sh_rest], axis=1)).to(dev)
    view = torch.from_numpy(cam.world_to_camera_cv().astype(np.float32))[None].to(dev)
    k = torch.from_numpy(cam.intrinsics().astype(np.float32))[None].to(dev)
    degree = g.sh_degree

    def run():
        return rasterization(means, quats, scales, opac, colors, view, k, cam.width, cam.height, sh_degree=degree,
                             near_plane=cam.near, far_plane=cam.far)

    def frame():
        run()
        torch.cuda.synchronize()

    t = time.perf_counter()
    with torch.no_grad():
        img = run()[0]
        torch.cuda.synchronize()
        first = time.perf_counter() - t
        warm = (settle or Settle()).run(frame)
        times = []
        for _ in range(frames):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            run()
            b.record()
            torch.cuda.synchronize()
            times.append(a.elapsed_time(b))
        wall = []
        for _ in range(frames):
            t0 = time.perf_counter()
            frame()
            wall.append((time.perf_counter() - t0) * 1e3)
    return {"ms": median(times), "wall_ms": median(wall), "first_call_s": first, "warmup": warm,
            "version": __import__("gsplat").__version__, "image": img[0].clamp(0, 1).cpu().numpy()}


def psnr(a, b) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def check_correctness(ctx, real_dir: str) -> dict:
    """GPU path on this GL vs the numpy reference on a real scene (small image)."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import HeadlessRenderer
    from splatstream import render_ref
    from splatstream.camera import suggested_camera

    out = {}
    path = os.path.join(real_dir, "fruit_drops_sh3.ply")
    if not os.path.exists(path):
        return out
    g = read_gaussians(path)
    cam = suggested_camera(g.positions, width=256, height=192)
    ref = render_ref.render(g, cam)
    for sort in ("gpu", "cpu"):
        r = HeadlessRenderer(RenderOptions(sort=sort), ctx=ctx)
        for preset in ("very-high", "medium"):
            r.load_gaussians(g, preset)
            out[f"{sort}/{preset}"] = psnr(r.render(cam), ref)
        r.unload()
    return out


def save_png(path: str, img: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path)


def scene_jobs(args) -> list[dict]:
    """(label, path, splats, spread) of every scene to measure: make_scene sizes x spreads, then --ply files."""
    jobs = []
    for spread in args.spread:
        for n in args.splats:
            jobs.append({"label": f"{n}" + ("" if spread == DEFAULT_SPREAD else f"@{spread:g}"), "splats": n,
                         "spread": spread, "path": scene_path(args.workdir, n, args.seed, spread)})
    for path in args.ply or []:
        jobs.append({"label": os.path.basename(path), "splats": None, "spread": None, "path": path})
    return jobs


def summary(results: dict, args, info: dict, width: int, height: int) -> None:
    """The table printed last: one row per variant, gsplat beside the scene."""
    print(f"\nGL: {info['GL_RENDERER']} | {info['GL_VERSION']} | {width}x{height}, median of {args.frames} frames "
          "after a settled warm-up; times in ms; wall = render + glFinish, submit = render() returning")
    print(f"{'scene':<14} {'preset':<10} {'draw/colour':<22} {'visible':>9} {'cull':>6} {'sort':>6} {'bin':>6} "
          f"{'tsort':>6} {'draw':>6} {'GPU':>6} {'wall':>6} {'submit':>6}  {'vs gsplat':>9} {'entries':>10} "
          f"{'diff':>7}  B/splat")
    for e in results["scenes"]:
        gs = e.get("gsplat", {})
        gs_wall = gs.get("wall_ms")
        for preset, res in e["presets"].items():
            for g_ in res["variants"]:
                def f(key, g_=g_):
                    v = g_.get(key)
                    return f"{v:>6.2f}" if isinstance(v, (int, float)) else f"{'-':>6}"
                speed = f"{gs_wall / g_['wall_ms']:>8.2f}x" if gs_wall and g_.get("wall_ms") else f"{'-':>9}"
                diff = f"{g_['max_diff_vs_first']:.2g}" if "max_diff_vs_first" in g_ else "-"
                print(f"{e['label']:<14} {preset:<10} {(g_['draw'] + '/' + g_['color'])[:22]:<22} "
                      f"{g_.get('visible') or 0:>9} {f('cull_ms')} {f('sort_ms')} {f('bin_ms')} {f('tile_sort_ms')} "
                      f"{f('draw_ms')} {f('gpu_ms')} {f('wall_ms')} {f('submit_ms')}  {speed} "
                      f"{g_.get('entries', '-'):>10} {diff:>7}  "
                      f"{g_['pool_bytes_per_splat']:.1f}+{g_['work_bytes_per_splat']:.1f}")
            c_ = res.get("cpu_sort")
            if c_:
                print(f"{e['label']:<14} {preset:<10} cpu-sort path: cull+sort {c_['cpu_cull_sort_ms']:.1f}, "
                      f"upload+draw {c_['cpu_upload_draw_ms']:.1f}, GPU draw {c_['draw_ms'] or 0:.2f}")
        if "sort_random" in e:
            s = e["sort_random"]
            print(f"{e['label']:<14} random-key radix sort: {s['ms']:.2f} ms, {s['keys_per_s'] / 1e9:.2f} G keys/s, "
                  f"sorted={s['sorted']}")
        if gs:
            print(f"{e['label']:<14} gsplat {gs.get('version', '')}: " +
                  (f"GPU {gs['ms']:.2f} ms, wall {gs['wall_ms']:.2f} ms; PSNR GL ({gs.get('psnr_preset')}) vs gsplat "
                   f"{gs.get('psnr_gl_vs_gsplat_db', float('nan')):.1f} dB" if "ms" in gs else gs.get("error", "")))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", type=int, nargs="+", default=[1_000_000, 6_000_000])
    ap.add_argument("--spread", type=float, nargs="+", default=[DEFAULT_SPREAD],
                    help="make_scene.py --spread values (1.0: its default sparse grid; 0.25: dense, the screen "
                         "covered); every size is measured at every spread")
    ap.add_argument("--ply", nargs="+", help="also measure these splat files (real scenes)")
    ap.add_argument("--presets", nargs="+", default=["very-high", "medium"])
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--warmup-min", type=int, default=30, help="warm-up: at least this many frames")
    ap.add_argument("--warmup-max", type=int, default=400, help="warm-up: at most this many frames")
    ap.add_argument("--warmup-s", type=float, default=20.0, help="warm-up: at most this many seconds")
    ap.add_argument("--settle-window", type=int, default=10)
    ap.add_argument("--settle-tol", type=float, default=0.03)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--make-scene", default=os.path.join(ROOT, "..", "shared", "tools", "make_scene.py"))
    ap.add_argument("--workdir", default="/tmp/splatstream-bench")
    ap.add_argument("--color", nargs="+", default=["f2"], choices=["f1", "f2", "f4"],
                    help="colour buffer types to time (default RGBA16F; the first is the reported one)")
    ap.add_argument("--draw", nargs="+", default=["auto"],
                    help="GPU-path draw modes to time: auto, compute, instanced, triangles, fetch, points, optionally "
                         "with measurement flags " + ", ".join("+" + f for f in DRAW_FLAGS) +
                         " (e.g. fetch+f2b, compute+nowc); the first is reported")
    ap.add_argument("--variants", nargs="+", default=[],
                    help="flag sets measured after the first --draw, each as that mode with these flags: "
                         "'tr8 d16 tr8+d16' adds compute+tr8, compute+d16 and compute+tr8+d16 when --draw is compute")
    ap.add_argument("--no-cpu-sort", action="store_true", help="skip the CPU-sort path")
    ap.add_argument("--no-sort-random", action="store_true", help="skip the standalone sort of random keys")
    ap.add_argument("--gsplat", action="store_true", help="also time gsplat (CUDA) on the same scene and camera")
    ap.add_argument("--psnr-preset", default="very-high",
                    help="preset of the GL image compared with gsplat's (encoded for it when not among --presets)")
    ap.add_argument("--check", action="store_true", help="PSNR of the GL paths against render_ref on a real scene")
    ap.add_argument("--images", help="folder for PNGs of the rendered views")
    ap.add_argument("--json", help="write all numbers here")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    args.draw = list(args.draw) + [f"{args.draw[0]}+{v.lstrip('+')}" for v in args.variants]
    from splatstream.errors import SplatstreamError

    for draw in args.draw:  # a typo fails here, before any scene is made
        try:
            render_options("gpu", draw, args.color[0])
        except SplatstreamError as exc:
            raise SystemExit(f"--draw/--variants {draw}: {exc}") from None
    settle = Settle(args.warmup_min, args.warmup_max, args.settle_window, args.settle_tol, args.warmup_s)

    from client_gl.offscreen import create_context

    ctx = create_context()
    info = {k: ctx.info.get(k) for k in ("GL_RENDERER", "GL_VERSION", "GL_VENDOR", "GL_POINT_SIZE_RANGE",
                                         "GL_MAX_VIEWPORT_DIMS")}
    log("GL:", info)
    results = {"gl": info, "host": platform.node(), "size": [width, height], "frames": args.frames,
               "seed": args.seed, "color_buffer": args.color, "warmup": vars(settle), "scenes": []}
    if args.check:
        real_dir = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(args.make_scene))), "data", "real")
        results["check_psnr_db"] = check_correctness(ctx, real_dir)
        log("check:", results["check_psnr_db"])
    os.makedirs(args.workdir, exist_ok=True)
    from client_gl.scene import tiles_from_gaussians

    for job in scene_jobs(args):
        label = job["label"]
        if job["splats"] is not None:
            make_scene(args.make_scene, job["splats"], job["path"], args.seed, job["spread"])
        t = time.perf_counter()
        g = read_gaussians(job["path"])
        n = len(g)
        log(f"read {label} ({n} splats) in {time.perf_counter() - t:.1f}s")
        cam = standard_benchmark_view(g.positions, width, height)
        entry = {"label": label, "splats": n, "spread": job["spread"], "path": os.path.basename(job["path"]),
                 "camera": cam.to_dict(), "presets": {}}
        results["scenes"].append(entry)
        if not args.no_sort_random:
            entry["sort_random"] = bench_sort_random(ctx, n)
            log("sort random:", entry["sort_random"])
        gl_image = None  # at --psnr-preset, the first draw mode and colour type
        for preset in args.presets:
            t = time.perf_counter()
            scene = tiles_from_gaussians(g, preset)
            enc = time.perf_counter() - t
            res = {"encode_s": enc, "variants": []}
            first_image = None
            for draw in args.draw:
                for color in args.color:
                    gpu = bench_gl(ctx, scene, cam, args.frames, "gpu", color, draw, settle)
                    rgpu = gpu.pop("_renderer")
                    img = rgpu.render(cam)
                    if rgpu.renderer.draw_mode == "compute":
                        gpu["entries"] = rgpu.renderer.read_bin_counts()[1]  # (tile, splat) pairs binned
                    if first_image is None:
                        first_image = img
                    elif color == args.color[0]:  # the variants change no pixel: how far from the first one
                        gpu["max_diff_vs_first"] = float(np.abs(img - first_image).max())
                    if draw == args.draw[0] and color == args.color[0]:
                        if preset == args.psnr_preset:
                            gl_image = img
                        if args.images:
                            save_png(os.path.join(args.images, f"gl_{label}_{preset}.png"), img)
                    rgpu.unload()
                    res["variants"].append(gpu)
                    log(label, preset, "gpu:", gpu)
            res["gpu_sort"] = res["variants"][0]
            if not args.no_cpu_sort:
                cpu = bench_gl(ctx, scene, cam, max(3, args.frames // 4), "cpu", args.color[0])
                cpu.pop("_renderer").unload()
                res["cpu_sort"] = cpu
                log(label, preset, "cpu:", cpu)
            entry["presets"][preset] = res
            del scene
        if args.gsplat:
            if gl_image is None:  # the comparison's preset was not measured: render it once
                from client_gl.offscreen import HeadlessRenderer

                r = HeadlessRenderer(render_options("gpu", args.draw[0], args.color[0]), ctx=ctx)
                r.load_gaussians(g, args.psnr_preset)
                gl_image = r.render(cam)
                r.unload()
            try:
                gs = bench_gsplat(g, cam, args.frames, settle)
                img = gs.pop("image")
                gs["psnr_preset"] = args.psnr_preset
                gs["psnr_gl_vs_gsplat_db"] = psnr(gl_image, img)
                if args.images:
                    save_png(os.path.join(args.images, f"gsplat_{label}.png"), img)
                entry["gsplat"] = gs
                log("gsplat:", gs)
            except Exception as exc:  # report and go on: the GL numbers stand on their own
                entry["gsplat"] = {"error": f"{type(exc).__name__}: {exc}"}
                log("gsplat failed:", exc)
        del g
        if args.json:  # after every scene: a run cut short keeps what it measured
            with open(args.json, "w") as f:
                json.dump(results, f, indent=1)
    summary(results, args, info, width, height)
    return 0


if __name__ == "__main__":
    sys.exit(main())
