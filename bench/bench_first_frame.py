"""Where the time to the first frame goes: `view --headless`'s session, with its steps timed (wall clock).

Streams a scene from a URL (or a scene directory, served here on loopback) with a fixed camera until the first
frame with splats drawn, timing the manifest, the pool, the renderer, program compiles (`compute_shader`), buffer
allocations and each frame's engine update and draw. Run it twice on a fresh machine: the first run shows the GL
driver's cold shader compiles, the second its disk cache.

    python bench/bench_first_frame.py --scene bench/out/stream-work/root/s1000000 --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from bench_stream import serve_scene  # noqa: E402 (bench/ is on the path: scripts run from it)


class Timeline:
    """Wall-clock milliseconds spent in wrapped callables, in order, with their start time since t0 (nesting
    counted per thread: the decode threads' steps are timed beside the frame loop's)."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.events: list[tuple[float, str, float]] = []
        self._local = threading.local()

    def wrap(self, owner, name: str, label: str, finish=None) -> None:
        """Time owner.name under `label`; finish: called (the GPU waited for) before the step's time is taken."""
        fn = getattr(owner, name)

        def timed(*args, **kwargs):
            t = time.perf_counter()
            local = self._local
            local.depth = getattr(local, "depth", 0) + 1
            try:
                out = fn(*args, **kwargs)
                if finish is not None:
                    finish()
                return out
            finally:
                local.depth -= 1
                if local.depth == 0 or label.startswith(("compile", "alloc", "step", "gl ")):
                    self.events.append((round((t - self.t0) * 1e3, 2), label,
                                        round((time.perf_counter() - t) * 1e3, 2)))
        setattr(owner, name, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True, help="scene directory (served on loopback here) or URL")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--sync", action="store_true",
                    help="wait for the GPU (glFinish) after each renderer and pool step, so that each step's time "
                         "includes its GPU work: which step the first frame with splats waits for")
    ap.add_argument("--sort-pass-programs", action="store_true",
                    help="each sort pass its own programs (RenderOptions.sort_pass_programs: the A/B of their count)")
    ap.add_argument("--sort", default="auto", help="RenderOptions.sort (gpu: the GPU path on software GL too)")
    ap.add_argument("--frames-after", type=int, default=0,
                    help="frames drawn after the first one with splats (the deferred compiles, the draw's switch)")
    ap.add_argument("--draw", default="auto", help="RenderOptions.draw")
    ap.add_argument("--no-defer", action="store_true",
                    help="RenderOptions.defer_compute=False: every compute draw program before the first compute frame")
    ap.add_argument("--no-cpu-first", action="store_true",
                    help="RenderOptions.cpu_first=False: the GPU path's programs before the first frame (the A/B of "
                         "the CPU-sorted first frames)")
    ap.add_argument("--no-warm-compile", action="store_true",
                    help="RenderOptions.warm_compile=False: the programs deferred from the first frame compiled cold "
                         "by the frame loop (the A/B of the warmer thread; see the compiles after the first frame with "
                         "--frames-after 30)")
    ap.add_argument("--atlas-prime", default="clear", choices=("compute", "clear", "none"),
                    help="RenderOptions.atlas_prime: how the pool's atlases are made GPU-written before their first "
                         "upload (compute: prime_texels.comp; clear: glClearTexSubImage, no compile; none)")
    ap.add_argument("--no-early-target", action="store_true",
                    help="RenderOptions.early_target=False: the first frame's framebuffer made and first cleared by "
                         "the first frame, not while the manifest is fetched (view --headless's order before)")
    ap.add_argument("--as-hardware", action="store_true",
                    help="treat a software GL (llvmpipe) as hardware in the renderer's auto choices (GPU sort, "
                         "compute draw): the GPU machine's programs, their count and order, here")
    ap.add_argument("--probe-first-clear", action="store_true",
                    help="before the timed window: one clear of a framebuffer of --size, finished, its wall and CPU "
                         "ms reported (is a fresh machine's 57-58 ms first clear per process, and GPU or CPU time?)")
    ap.add_argument("--gpu-mem-mb", type=float, help="ViewOptions.gpu_mem_mb (default: the viewer's)")
    args = ap.parse_args()
    import moderngl

    from client_gl import streaming
    from client_gl.gpu import compute_raster, pool, renderer, sort
    from client_gl.gpu.renderer import RenderOptions
    from client_gl.offscreen import create_context
    from client_gl.stream import engine
    from client_gl.streaming import PreparedSource, StreamingSession, ViewOptions, early_target
    from splatstream.camera import Camera

    w, h = (int(v) for v in args.size.split("x"))
    server, url = (None, args.scene) if "://" in args.scene else serve_scene(args.scene)
    t = time.perf_counter()
    ctx = create_context()
    context_ms = (time.perf_counter() - t) * 1e3
    probe_clear = None
    if args.probe_first_clear:
        w0, h0 = (int(v) for v in args.size.split("x"))
        t, c = time.perf_counter(), time.process_time()
        fbo = ctx.framebuffer(color_attachments=[ctx.texture((w0, h0), 4)],
                              depth_attachment=ctx.depth_renderbuffer((w0, h0)))
        made_ms = (time.perf_counter() - t) * 1e3
        fbo.clear(0.0, 0.0, 0.0, 1.0)
        issued_ms = (time.perf_counter() - t) * 1e3
        ctx.finish()
        probe_clear = {"made_ms": round(made_ms, 2), "clear_issued_ms": round(issued_ms, 2),
                       "finished_ms": round((time.perf_counter() - t) * 1e3, 2),
                       "cpu_ms": round((time.process_time() - c) * 1e3, 2)}
        print("probe first clear", probe_clear, flush=True)
    tl = Timeline()
    tl.wrap(moderngl.Context, "compute_shader", "compile compute")
    tl.wrap(moderngl.Context, "program", "compile program")
    tl.wrap(moderngl.Context, "buffer", "alloc buffer")
    # the pool's atlases and the renderer's framebuffer (made by the first render: what a frame that draws nothing
    # costs) and its clears
    tl.wrap(moderngl.Context, "texture", "gl texture")
    tl.wrap(moderngl.Context, "depth_renderbuffer", "gl depth renderbuffer")
    tl.wrap(moderngl.Context, "framebuffer", "gl framebuffer")
    tl.wrap(moderngl.Framebuffer, "clear", "gl clear", finish=ctx.finish if args.sync else None)
    tl.wrap(PreparedSource, "open", "manifest (PreparedSource.open)")
    # the first frame's framebuffer made and cleared while the manifest is fetched (RenderOptions.early_target), and
    # the pool's prime (RenderOptions.atlas_prime)
    tl.wrap(streaming, "prepare_target", "gl early target")
    tl.wrap(pool.ChunkPool, "_prime_atlases", "gl prime atlases")
    tl.wrap(pool.ChunkPool, "__init__", "pool")
    tl.wrap(renderer.SplatRenderer, "__init__", "renderer")
    tl.wrap(compute_raster.ComputeRaster, "__init__", "compute raster")
    tl.wrap(sort.GpuRadixSort, "__init__", "radix sort")
    tl.wrap(engine.StreamEngine, "update", "engine.update")
    if hasattr(engine.StreamEngine, "take_arrived"):  # the root's decode started while the renderer is built
        tl.wrap(engine.StreamEngine, "take_arrived", "engine.take_arrived")
    tl.wrap(engine, "decode_job", "decode (thread)")  # a payload decoded on a decode thread (the root's first)
    tl.wrap(engine, "decode_batch_job", "decode batch (thread)")
    tl.wrap(renderer.SplatRenderer, "render", "render")
    tl.wrap(pool.ChunkPool, "join", "gl pool.join")  # recorded inside engine.update too (a first upload's cost)
    if args.sync:
        steps = [(renderer.SplatRenderer, ("_ensure_work", "_start_cull", "_cull", "check_bins")),
                 (sort.GpuRadixSort, ("sort",)),
                 (compute_raster.ComputeRaster, ("bin", "sort", "raster", "grow_if_needed", "grow_ahead")),
                 (pool.ChunkPool, ("join", "add_band", "set_draw_set", "bind"))]
        for owner, names in steps:
            for name in names:
                tl.wrap(owner, name, f"step {owner.__name__}.{name} (+GPU)", finish=ctx.finish)
    out: dict = {"url": url, "size": [w, h], "gl_renderer": ctx.info.get("GL_RENDERER"), "context_ms": context_ms,
                 "sync_steps": bool(args.sync), "probe_first_clear": probe_clear}
    try:
        if args.as_hardware:
            renderer.SOFTWARE_RENDERERS = ()
        render = RenderOptions(sort=args.sort, draw=args.draw, sort_pass_programs=args.sort_pass_programs,
                               defer_compute=not args.no_defer, cpu_first=not args.no_cpu_first,
                               warm_compile=not args.no_warm_compile, atlas_prime=args.atlas_prime,
                               early_target=not args.no_early_target)
        view = ViewOptions(cache=False, render=render, **({"gpu_mem_mb": args.gpu_mem_mb} if args.gpu_mem_mb else {}))
        # as `view --headless` opens its session (StreamingSession.open with its output size)
        prepared = PreparedSource.open(url, view, while_fetching=early_target(ctx, view, (w, h)))
        session = StreamingSession(prepared, ctx, view)
        cam_info = session.manifest.camera
        cam = Camera(cam_info.eye, cam_info.target, cam_info.up, cam_info.fov_y, w, h)
        frames = 0
        while frames < 400:
            rec = session.frame(cam)
            ctx.finish()
            frames += 1
            tl.events.append((round((time.perf_counter() - tl.t0) * 1e3, 2), f"frame {frames} done "
                              f"({rec.drawn_splats} drawn)", 0.0))
            if rec.drawn_splats:
                break
            session.wait(0.002)
        m = session.metrics
        first_sort = session.renderer.sort_mode  # the path that drew the first frame with splats
        compiles = [ms for _, label, ms in tl.events if label.startswith("compile")]
        # The frames after the first one with splats: when the deferred programs compile (and the draw switches).
        first_events = len(tl.events)
        frames_after = []  # (wall ms, compile calls ms, sort, draw) of each
        for _ in range(args.frames_after):
            t = time.perf_counter()
            n = len(tl.events)
            session.frame(cam)
            ctx.finish()
            frame_compiles = sum(ms for _, label, ms in tl.events[n:] if label.startswith("compile"))
            frames_after.append((round((time.perf_counter() - t) * 1e3, 2), round(frame_compiles, 2),
                                 session.renderer.sort_mode, session.renderer.draw_mode))
            tl.events.append((round((time.perf_counter() - tl.t0) * 1e3, 2),
                              f"frame after: {session.renderer.sort_mode} {session.renderer.draw_mode}", 0.0))
        after = [ms for _, label, ms in tl.events[first_events:] if label.startswith("compile")]
        compiles_after = len(after)
        to_compute = next((i + 1 for i, f in enumerate(frames_after) if f[3] == "compute"), None)
        out.update(compile_after_ms=round(sum(after), 1), compile_after_max_ms=max(after, default=0.0),
                   compile_after_each_ms=after, frames_after=frames_after, frames_to_compute=to_compute,
                   warm_compile=not args.no_warm_compile,
                   warmer_ms={k: round(v * 1e3, 1) for k, v in session.renderer.warm_compile_seconds.items()},
                   loop_compile_ms={k: round(v * 1e3, 2) for k, v in session.renderer.compile_seconds.items()},
                   warm_compile_missed=session.renderer.warm_compile_missed)
        def first_ms(label: str) -> float | None:
            return next((ms for _, name, ms in tl.events if name == label), None)

        out.update(atlas_prime=args.atlas_prime, early_target=not args.no_early_target,
                   early_target_ms=first_ms("gl early target"), prime_ms=first_ms("gl prime atlases"),
                   first_clear_ms=first_ms("gl clear"), first_join_ms=first_ms("gl pool.join"))
        out.update(first_frame_s=m.first_frame_s, manifest_s=m.manifest_s, pool_s=m.pool_s, built_s=m.built_s,
                   frames=frames, sort_pass_programs=args.sort_pass_programs, programs_compiled=len(compiles),
                   programs_compiled_after=compiles_after, draw=args.draw, defer_compute=not args.no_defer,
                   cpu_first=not args.no_cpu_first, first_sort=first_sort,
                   compile_ms=round(sum(compiles), 1), timeline=tl.events)
        session.close()
    finally:
        if server is not None:
            server.send_signal(signal.SIGTERM)
            server.wait(10)
    for t_ms, label, ms in tl.events:
        print(f"{t_ms:9.1f} ms  {label:34s} {ms:8.1f} ms")
    print({k: out[k] for k in ("first_frame_s", "manifest_s", "pool_s", "built_s", "context_ms", "programs_compiled",
                               "compile_ms", "programs_compiled_after", "first_sort", "early_target_ms", "prime_ms",
                               "first_clear_ms", "first_join_ms")})
    if args.frames_after:
        print({k: out[k] for k in ("compile_after_ms", "compile_after_max_ms", "frames_to_compute", "warmer_ms",
                                   "loop_compile_ms", "warm_compile_missed")})
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
