"""Benchmark of the GL renderer (client_gl) on make_scene.py scenes from the standard benchmark view.

Per scene size and preset: per-frame GPU time split into cull+keys, sort and draw (GL_TIME_ELAPSED timer
queries), wall-clock frame time (glFinish per frame), visible splats, sort throughput (visible keys / sort time,
and a standalone sort of random keys), GPU bytes per splat; the CPU-sort path; optionally gsplat on the same scene
and camera (CUDA, forward only).

    python3 bench/bench_render.py --splats 1000000 6000000 --presets very-high medium --gsplat \
        --make-scene ../shared/tools/make_scene.py --workdir /tmp/bench --json bench.json

Scenes: `make_scene.py --splats N --seed 0` (SH degree 3, spread 1.0). View: camera.standard_benchmark_view
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


def log(*args) -> None:
    print(*args, file=sys.stderr, flush=True)


def median(xs):
    return float(statistics.median(xs)) if xs else None


def make_scene(script: str, n: int, path: str, seed: int) -> None:
    if os.path.exists(path):
        return
    t = time.perf_counter()
    subprocess.run([sys.executable, script, "--splats", str(n), "--seed", str(seed), "--out", path], check=True)
    log(f"made {path} in {time.perf_counter() - t:.1f}s")


# Measurement flags of a --draw value ("fetch+f2b", "compute+t8+u2", ...) -> RenderOptions fields.
DRAW_FLAGS = {"f2b": {"front_to_back": True}, "nodepth": {"depth_test": False}, "noblend": {"blend": False},
              "discard": {"discard_fragments": True}, "t8": {"tile_px": 8}, "u1": {"unroll": 1}, "u2": {"unroll": 2},
              "wc": {"warp_cull": True}}


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


def bench_gl(ctx, scene, cam: Camera, frames: int, sort: str, color_dtype: str, draw: str = "instanced") -> dict:
    from client_gl.headless import HeadlessRenderer

    r = HeadlessRenderer(render_options(sort, draw, color_dtype), ctx=ctx)
    t = time.perf_counter()
    r.load_tiles(scene)
    ctx.finish()
    out = {"sort": r.sort_mode, "draw": draw, "color": color_dtype, "upload_s": time.perf_counter() - t}
    rend = r.renderer
    for _ in range(3):
        r.render_frame(cam)
    ctx.finish()
    stats = [r.render_frame(cam, timing=True) for _ in range(frames)]
    t = time.perf_counter()
    for _ in range(frames):
        r.render_frame(cam)
        ctx.finish()
    wall = (time.perf_counter() - t) / frames * 1e3
    out["wall_ms"] = wall
    if r.sort_mode == "gpu":
        out["visible"] = rend.read_visible_count()
        out["draw"] = draw if draw == rend.draw_mode else f"{draw}->{rend.draw_mode}"
        out["oversized"] = rend.read_oversized_count()
        out["cull_ms"] = median([s.cull_ms for s in stats])
        out["sort_ms"] = median([s.sort_ms for s in stats])
        out["draw_ms"] = median([s.draw_ms for s in stats])
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
    return {"n": n, "ms": ms, "keys_per_s": n / (ms * 1e-3), "sorted": ok}


def bench_gsplat(g, cam: Camera, frames: int) -> dict:
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

    t = time.perf_counter()
    with torch.no_grad():
        img = run()[0]
        torch.cuda.synchronize()
        first = time.perf_counter() - t
        for _ in range(3):
            run()
        times = []
        for _ in range(frames):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            run()
            b.record()
            torch.cuda.synchronize()
            times.append(a.elapsed_time(b))
    return {"ms": median(times), "first_call_s": first, "version": __import__("gsplat").__version__,
            "image": img[0].clamp(0, 1).cpu().numpy()}


def psnr(a, b) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def check_correctness(ctx, real_dir: str) -> dict:
    """GPU path on this GL vs the numpy reference on a real scene (small image)."""
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.headless import HeadlessRenderer
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", type=int, nargs="+", default=[1_000_000, 6_000_000])
    ap.add_argument("--presets", nargs="+", default=["very-high", "medium"])
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--make-scene", default=os.path.join(ROOT, "..", "shared", "tools", "make_scene.py"))
    ap.add_argument("--workdir", default="/tmp/splatstream-bench")
    ap.add_argument("--color", nargs="+", default=["f2"], choices=["f1", "f2", "f4"],
                    help="colour buffer types to time (default RGBA16F; the first is the reported one)")
    ap.add_argument("--draw", nargs="+", default=["auto"],
                    help="GPU-path draw modes to time: auto, compute, instanced, triangles, fetch, points, optionally "
                         "with measurement flags +f2b, +nodepth, +noblend, +discard (raster draws), +t8, +u1, +u2, "
                         "+wc (compute) (e.g. fetch+discard); the first is reported")
    ap.add_argument("--no-cpu-sort", action="store_true", help="skip the CPU-sort path")
    ap.add_argument("--gsplat", action="store_true", help="also time gsplat (CUDA) on the same scene and camera")
    ap.add_argument("--check", action="store_true", help="PSNR of the GL paths against render_ref on a real scene")
    ap.add_argument("--images", help="folder for PNGs of the rendered views")
    ap.add_argument("--json", help="write all numbers here")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))

    from client_gl.headless import create_context

    ctx = create_context()
    info = {k: ctx.info.get(k) for k in ("GL_RENDERER", "GL_VERSION", "GL_VENDOR", "GL_POINT_SIZE_RANGE",
                                         "GL_MAX_VIEWPORT_DIMS")}
    log("GL:", info)
    results = {"gl": info, "host": platform.node(), "size": [width, height], "frames": args.frames,
               "seed": args.seed, "color_buffer": args.color, "scenes": []}
    if args.check:
        real_dir = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(args.make_scene))), "data", "real")
        results["check_psnr_db"] = check_correctness(ctx, real_dir)
        log("check:", results["check_psnr_db"])
    os.makedirs(args.workdir, exist_ok=True)
    from client_gl.scene import tiles_from_gaussians

    gl_images: dict[int, np.ndarray] = {}
    for n in args.splats:
        ply = os.path.join(args.workdir, f"scene_{n}_seed{args.seed}.ply")
        make_scene(args.make_scene, n, ply, args.seed)
        t = time.perf_counter()
        g = read_gaussians(ply)
        log(f"read {n} splats in {time.perf_counter() - t:.1f}s")
        cam = standard_benchmark_view(g.positions, width, height)
        entry = {"splats": n, "camera": cam.to_dict(), "presets": {}}
        results["scenes"].append(entry)
        entry["sort_random"] = bench_sort_random(ctx, n)
        log("sort random:", entry["sort_random"])
        for preset in args.presets:
            t = time.perf_counter()
            scene = tiles_from_gaussians(g, preset)
            enc = time.perf_counter() - t
            res = {"encode_s": enc, "variants": []}
            for draw in args.draw:
                for color in args.color:
                    gpu = bench_gl(ctx, scene, cam, args.frames, "gpu", color, draw)
                    rgpu = gpu.pop("_renderer")
                    if preset == args.presets[0] and draw == args.draw[0] and color == args.color[0]:
                        gl_images[n] = rgpu.render(cam)
                        if args.images:
                            save_png(os.path.join(args.images, f"gl_{n}_{preset}.png"), gl_images[n])
                    rgpu.unload()
                    res["variants"].append(gpu)
                    log(n, preset, "gpu:", {k: v for k, v in gpu.items()})
            res["gpu_sort"] = res["variants"][0]
            if not args.no_cpu_sort:
                cpu = bench_gl(ctx, scene, cam, max(3, args.frames // 4), "cpu", args.color[0])
                cpu.pop("_renderer").unload()
                res["cpu_sort"] = cpu
                log(n, preset, "cpu:", cpu)
            entry["presets"][preset] = res
            del scene
        if args.gsplat:
            try:
                gs = bench_gsplat(g, cam, args.frames)
                img = gs.pop("image")
                if n in gl_images:
                    gs["psnr_gl_vs_gsplat_db"] = psnr(gl_images[n], img)
                if args.images:
                    save_png(os.path.join(args.images, f"gsplat_{n}.png"), img)
                entry["gsplat"] = gs
                log("gsplat:", gs)
            except Exception as exc:  # report and go on: the GL numbers stand on their own
                entry["gsplat"] = {"error": f"{type(exc).__name__}: {exc}"}
                log("gsplat failed:", exc)
        del g
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    # Summary table (last in the output).
    print(f"\nGL: {info['GL_RENDERER']} | {info['GL_VERSION']} | {width}x{height}, median of {args.frames} frames")
    print("splats   preset     draw/colour   visible  cull+keys  sort    draw    GPU total  wall    sort keys/s"
          "  B/splat(pool+work)  cpu-sort path (cull+sort / upload+draw / GPU draw)")
    for e in results["scenes"]:
        for preset, res in e["presets"].items():
            c_ = res.get("cpu_sort", {})
            cpu_txt = (f"{c_['cpu_cull_sort_ms']:.1f} / {c_['cpu_upload_draw_ms']:.1f} / {c_['draw_ms'] or 0:.2f} ms"
                       if c_ else "-")
            for g_ in res["variants"]:
                print(f"{e['splats']:>8} {preset:<10} {g_['draw'][:14]:<14}/{g_['color']} {g_['visible']:>8} "
                      f"{g_['cull_ms']:>8.2f} {g_['sort_ms']:>7.2f} {g_['draw_ms']:>7.2f} {g_['gpu_ms']:>8.2f} "
                      f"{g_['wall_ms']:>7.2f} {g_['sort_keys_per_s'] / 1e9:>8.2f} G"
                      f"   {g_['pool_bytes_per_splat']:.1f}+{g_['work_bytes_per_splat']:.1f} "
                      f"(clamped {g_.get('oversized', 0)})   {cpu_txt}")
                cpu_txt = ""
        s = e["sort_random"]
        print(f"{e['splats']:>8} random-key radix sort: {s['ms']:.2f} ms, {s['keys_per_s'] / 1e9:.2f} G keys/s, "
              f"sorted={s['sorted']}")
        if "gsplat" in e:
            gs = e["gsplat"]
            print(f"{e['splats']:>8} gsplat {gs.get('version', '')}: " +
                  (f"{gs['ms']:.2f} ms, PSNR GL vs gsplat {gs.get('psnr_gl_vs_gsplat_db', float('nan')):.1f} dB"
                   if "ms" in gs else gs.get("error", "")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
