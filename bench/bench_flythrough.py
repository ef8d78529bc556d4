"""Frame times while streaming: a large scene served on loopback, a scripted fly-through, a splat budget.

Runs the viewer's StreamingSession (the same code as `view`) headless at 1920x1080 along a camera path that starts
at the standard overview of a make_scene scene and flies in over it, with `--max-splats` (default 2M); every frame
ends with glFinish, so its wall time includes the GPU's work. Then, at the converged end of the path, the same tiles
and bands are loaded whole into the plain renderer (`splatstream render`'s HeadlessRenderer) and both draw the same
view N times, in turn and with the session still open: the streaming session's converged frame time against the
renderer's.

    python bench/bench_flythrough.py --scene SCENE_DIR_OR_URL --ply SCENE.ply --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from dataclasses import replace

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from bench_stream import serve_scene  # noqa: E402 (bench/ is on the path: scripts run from it)

from splatstream.camera import standard_benchmark_view  # noqa: E402
from splatstream.camera_path import parse_camera_path  # noqa: E402


def fly_path(ply: str, seconds: float) -> dict:
    """Overview -> in over the scene -> a turn -> back up: keyframes every `seconds` / 4."""
    from splatstream.io import read_gaussians

    g = read_gaussians(ply)
    over = standard_benchmark_view(g.positions)
    c, eye = np.array(over.target), np.array(over.eye)
    d = eye - c
    side = np.array([-d[1], d[0], 0.0])
    keys = [eye, c + d * 0.35, c + d * 0.15 + side * 0.2, c + d * 0.1 - side * 0.2, c + d * 0.5]
    targets = [c, c, c + side * 0.1, c - side * 0.1, c]
    step = seconds / (len(keys) - 1)
    return {"fov_y": over.fov_y_deg, "up": [0, 0, 1], "keyframes": [
        {"time": k * step, "eye": e.tolist(), "target": t.tolist()} for k, (e, t) in enumerate(zip(keys, targets,
                                                                                                   strict=True))]}


class StepTimer:
    """Milliseconds spent in named methods during the current frame (wraps them on their classes; bench only)."""

    def __init__(self) -> None:
        self.now: dict[str, float] = {}

    def wrap(self, cls, names) -> None:
        for name in names:
            setattr(cls, name, self._timed(getattr(cls, name), f"{cls.__name__}.{name}"))

    def wrap_compiled_selection(self, cls) -> None:
        """The compiled selection (engine.CompiledSelection.get hands it out once its kernels are ready) timed as
        client_gl.stream.engine.select_near_compiled, its draw set (CompiledSelection.draw) as the numpy draw set,
        client_gl.stream.engine.draw_set."""
        get = cls.get

        def timed_get(selection, *args, **kwargs):
            fn = get(selection, *args, **kwargs)
            return None if fn is None else self._timed(fn, "client_gl.stream.engine.select_near_compiled")
        cls.get = timed_get
        draw = cls.draw

        def timed_draw(selection):  # the compiled draw set, timed as the numpy one (draw_set)
            fn = draw(selection)
            return None if fn is None else self._timed(fn, "client_gl.stream.engine.draw_set")
        cls.draw = timed_draw

    def _timed(self, fn, label):
        def timed(*args, **kwargs):
            t, c = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.now[label] = self.now.get(label, 0.0) + (time.perf_counter() - t) * 1e3
                self.now[label + " cpu"] = self.now.get(label + " cpu", 0.0) + (time.thread_time() - c) * 1e3
        return timed

    def take(self) -> dict[str, float]:
        out, self.now = {k: round(v, 2) for k, v in self.now.items() if v >= 0.05}, {}
        return out


class GcPauses:
    """The garbage collector's pauses while it runs (gc.callbacks): count, longest and total ms per generation."""

    def __init__(self) -> None:
        import gc

        self.gc, self.t = gc, 0.0
        self.by_gen: dict[int, list[float]] = {0: [], 1: [], 2: []}
        gc.callbacks.append(self._cb)

    def _cb(self, phase: str, info: dict) -> None:
        if phase == "start":
            self.t = time.perf_counter()
        else:
            self.by_gen[info["generation"]].append((time.perf_counter() - self.t) * 1e3)

    def stop(self) -> dict:
        self.gc.callbacks.remove(self._cb)
        return {f"gen{g}": {"count": len(v), "max_ms": round(max(v, default=0.0), 2), "total_ms": round(sum(v), 1)}
                for g, v in self.by_gen.items()}


def converged_split(frame, ctx, repeat: int = 20) -> dict:
    """Where a converged frame's time goes: the CPU's part (the call returning, no wait) and the GPU's stage timers,
    medians over `repeat` frames. frame(timing) draws one frame and returns its FrameStats."""
    submit, stages = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        frame(False)
        submit.append((time.perf_counter() - t) * 1e3)
        ctx.finish()
    for _ in range(repeat):
        st = frame(True)
        stages.append({k: getattr(st, k) for k in ("cull_ms", "sort_ms", "bin_ms", "tile_sort_ms", "draw_ms")})
    out = {"submit_ms": round(float(np.median(submit)), 3)}
    for k in stages[0]:
        vals = [x[k] for x in stages if x[k] is not None]
        if vals:
            out[k] = round(float(np.median(vals)), 3)
    return out


def thread_usage() -> tuple[float, float, int, int, int]:
    """(user s, system s, minor page faults, voluntary, involuntary context switches) of the calling thread."""
    import resource

    r = resource.getrusage(resource.RUSAGE_THREAD)
    return r.ru_utime, r.ru_stime, r.ru_minflt, r.ru_nvcsw, r.ru_nivcsw


def machine_steal_s() -> float | None:
    """Seconds the hypervisor ran other guests on this machine's CPUs, all CPUs together (/proc/stat 'steal')."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def thread_cpu_seconds() -> dict[str, float]:
    """CPU seconds (user + system) of each thread of this process so far, by thread name (Linux /proc): which
    threads compete with the frame loop for the interpreter lock and the cores."""
    import threading

    names = {t.native_id: t.name for t in threading.enumerate()}
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        name = names.get(int(tid), f"native-{tid}")
        out[name] = out.get(name, 0.0) + round((int(fields[11]) + int(fields[12])) / tick, 2)
    return out


class OtherThreadsCpu:
    """CPU milliseconds each other thread of this process used during a call (its clock: pthread_getcpuclockid +
    clock_gettime), by thread name: who ran while the frame thread waited (the decode threads, the fetch loop, the
    executor's verify threads, a decode process pool's feeder). Threads started meanwhile count from zero."""

    def __init__(self) -> None:
        import threading

        self.threading = threading
        self.me = threading.get_ident()

    def _clocks(self) -> dict[int, tuple[str, float]]:
        out = {}
        for t in self.threading.enumerate():
            if t.ident is None or t.ident == self.me:
                continue
            try:
                out[t.ident] = (t.name, time.clock_gettime(time.pthread_getcpuclockid(t.ident)))
            except (OSError, ValueError):  # the thread ended between enumerate() and the clock's read
                continue
        return out

    def start(self) -> dict[int, tuple[str, float]]:
        return self._clocks()

    def since(self, before: dict[int, tuple[str, float]]) -> dict[str, float]:
        out: dict[str, float] = {}
        for ident, (name, now) in self._clocks().items():
            used = now - before.get(ident, (name, 0.0))[1]
            if used > 0:
                key = "asyncio (verify)" if name.startswith("asyncio_") else name
                out[key] = out.get(key, 0.0) + used * 1e3
        return {k: round(v, 2) for k, v in out.items() if v >= 0.01}


class GrowthLog:
    """GPU buffer allocations during the current frame (bench only): the renderer's work buffers (_ensure_work
    grows them to twice the drawn splats; a session with a splat budget reserves them before its first frame) and
    the compute draw's entry buffers (ComputeRaster.resize), each as 'what old->new'; a frame whose render step
    spends system time in the driver is then seen to have allocated."""

    def __init__(self) -> None:
        from client_gl.gpu.compute_raster import ComputeRaster
        from client_gl.gpu.renderer import SplatRenderer

        self.now: list[str] = []
        allocate, resize = SplatRenderer._allocate_work, ComputeRaster.resize
        log = self.now

        def allocate_work(renderer, splats):
            old = renderer._work_splats
            allocate(renderer, splats)
            if renderer._work_splats != old:
                log.append(f"work {old}->{renderer._work_splats}")

        def craster_resize(cr, visible_capacity, entry_capacity=None):
            old = cr.entry_capacity
            resize(cr, visible_capacity, entry_capacity)
            if cr.entry_capacity != old:
                log.append(f"entries {old}->{cr.entry_capacity}")
        SplatRenderer._allocate_work, ComputeRaster.resize = allocate_work, craster_resize

    def take(self) -> list[str]:
        out = list(self.now)
        self.now.clear()
        return out


SELECTION_STEPS = tuple(f"client_gl.stream.engine.{n}"
                        for n in ("select", "select_near", "view_numbers", "PartialView", "select_near_compiled"))


def _selection_ms(splits: list[dict]) -> dict:
    """Median and p99 of the selection's time a frame (the wrapped steps of --breakdown; nothing without it)."""
    if not any(splits):
        return {}
    sel = np.array([sum(s.get(k, 0.0) for k in SELECTION_STEPS) for s in splits])
    return {"select_ms_median": float(np.median(sel)), "select_ms_p99": float(np.percentile(sel, 99))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True, help="scene directory (served on loopback here) or URL")
    ap.add_argument("--ply", required=True, help="the scene's source PLY (for the standard view)")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--max-splats", type=int, default=2_000_000)
    ap.add_argument("--gpu-mem-mb", type=float, default=2048)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--repeat", type=int, default=60, help="converged frames timed at the end")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--switch-interval", type=float,
                    help="the interpreter's switch interval in seconds, set after the session opens (CPython's is "
                         "0.005; 0.0005 made upload frames slower on the GPU machine, BENCHMARKS.md)")
    ap.add_argument("--select-switch-interval", type=float, metavar="S",
                    help="the switch interval while the frame loop computes the view and the cut, the process's "
                         "restored after (StreamOptions.select_switch_interval, seconds; 0: untouched; default: "
                         "the option's default)")
    ap.add_argument("--gl-release-gil", action="store_true",
                    help="the A/B of client_gl.gpu.gl.FUNCTION_TYPE: our GL entry points as CFUNCTYPE (released "
                         "the GIL in every call) instead of PYFUNCTYPE")
    ap.add_argument("--breakdown", action="store_true",
                    help="time the engine's and the pool's steps in each frame; the slowest frames' split is reported")
    ap.add_argument("--decode-workers", type=int, default=2, help="decode threads (StreamOptions.decode_workers)")
    ap.add_argument("--decode-processes", type=int, default=0,
                    help="decode in this many processes instead of threads (StreamOptions.decode_processes)")
    ap.add_argument("--decode-workers-moving", type=int, default=1,
                    help="decode threads while the camera moves (StreamOptions.decode_workers_moving; 0: all)")
    ap.add_argument("--sort-pass-programs", action="store_true",
                    help="each GPU sort pass its own programs (RenderOptions.sort_pass_programs, the A/B)")
    ap.add_argument("--no-decode-batch", action="store_true",
                    help="one decode job a payload (the A/B of StreamOptions.decode_batch)")
    ap.add_argument("--finish-keeps-gil", action="store_true",
                    help="wait for the GPU after each frame with moderngl's finish() (keeps the GIL) instead of "
                         "client_gl.gpu.gl.wait_for_gpu (releases it, as a display's swap does)")
    ap.add_argument("--no-gc-freeze", action="store_true",
                    help="leave the collector walking the session's long-lived objects (the A/B of freeze_long_lived)")
    ap.add_argument("--profile", action="store_true", help="print where the streaming loop's time went (cProfile)")
    ap.add_argument("--no-wait-compiled-selection", action="store_true",
                    help="fly at once, as a viewer starts: the numpy selection until the compiled one is ready "
                         "(default: wait for it first, so that the path measures the steady state)")
    ap.add_argument("--compiled-selection-from", type=int, default=0, metavar="TILES",
                    help="the compiled selection only from this many tiles held (4096: as before it was used from the "
                         "first frames; the A/B of the selection's first seconds)")
    ap.add_argument("--no-warm-compile", action="store_true",
                    help="RenderOptions.warm_compile=False: the programs deferred from the first frame compiled cold "
                         "by the frame loop (the A/B of the warmer thread; a cold driver cache shows it)")
    args = ap.parse_args()
    if args.gl_release_gil:
        import ctypes

        from client_gl.gpu import gl as gl_entry_points

        gl_entry_points.FUNCTION_TYPE = ctypes.CFUNCTYPE
    from client_gl.gpu.gl import wait_for_gpu
    from client_gl.offscreen import HeadlessRenderer, RenderOptions, create_context
    from client_gl.scene import SceneTiles, load_tile
    from client_gl.streaming import StreamingSession, ViewOptions, freeze_long_lived
    from splatstream.scene_decode import read_codebook
    from splatstream.store import DirectoryStore, load_manifest

    w, h = (int(v) for v in args.size.split("x"))
    server, url = (None, args.scene) if "://" in args.scene else serve_scene(args.scene)
    path = parse_camera_path(fly_path(args.ply, args.seconds))
    ctx = create_context()
    finish = ctx.finish if args.finish_keeps_gil else wait_for_gpu
    out: dict = {"size": [w, h], "max_splats": args.max_splats, "gpu_mem_mb": args.gpu_mem_mb,
                 "gl_renderer": ctx.info.get("GL_RENDERER"), "path_seconds": args.seconds}
    try:
        session = StreamingSession.open(url, ctx, ViewOptions(gpu_mem_mb=args.gpu_mem_mb, max_splats=args.max_splats,
                                                              cache=False, decode_workers=args.decode_workers,
                                                              decode_processes=args.decode_processes,
                                                              decode_workers_moving=args.decode_workers_moving,
                                                              decode_batch=not args.no_decode_batch,
                                                              render=RenderOptions(
                                                                  sort_pass_programs=args.sort_pass_programs,
                                                                  warm_compile=not args.no_warm_compile)))
        if not args.no_gc_freeze:
            freeze_long_lived()
        out["gc_freeze"] = not args.no_gc_freeze
        if args.select_switch_interval is not None:  # the A/B of StreamOptions.select_switch_interval
            session.engine.options = replace(session.engine.options,
                                             select_switch_interval=args.select_switch_interval or None)
        out["select_switch_interval_s"] = session.engine.options.select_switch_interval
        out["decode_workers"], out["decode_processes"] = args.decode_workers, args.decode_processes
        out["decode_workers_moving"], out["decode_batch"] = args.decode_workers_moving, not args.no_decode_batch
        out["sort_pass_programs"] = bool(args.sort_pass_programs)
        out["finish_keeps_gil"] = bool(args.finish_keeps_gil)
        out["warm_compile"] = not args.no_warm_compile
        if not args.no_wait_compiled_selection:
            from client_gl.stream.engine import COMPILED_SELECTION

            t_wait = time.perf_counter()
            out["compiled_selection"] = COMPILED_SELECTION.wait(600) is not None
            out["compiled_selection_wait_s"] = round(time.perf_counter() - t_wait, 2)
            error = COMPILED_SELECTION.error
            out["compiled_selection_error"] = None if error is None else repr(error)
            print(f"compiled selection: {out['compiled_selection']} after {out['compiled_selection_wait_s']} s "
                  f"({out['compiled_selection_error'] or 'ready'})", flush=True)
        out["compiled_selection_from"] = args.compiled_selection_from
        if args.compiled_selection_from:
            # the A/B of the compiled selection from the first frames: as before it, the numpy path (view_numbers
            # and select over every tile held) while fewer tiles than this are held
            from client_gl.stream import engine as sel_engine

            wanted_of, shared = sel_engine.StreamEngine.wanted, sel_engine.COMPILED_SELECTION

            def wanted_held_back(engine, cam, _wanted=wanted_of, _from=args.compiled_selection_from):
                fn = shared._fn
                if fn is None or len(engine.resident) >= _from:
                    return _wanted(engine, cam)
                shared._fn = None  # get() answers None: the numpy path
                try:
                    return _wanted(engine, cam)
                finally:
                    shared._fn = fn
            sel_engine.StreamEngine.wanted = wanted_held_back
        if args.switch_interval:
            sys.setswitchinterval(args.switch_interval)
        out["switch_interval_s"] = sys.getswitchinterval()
        out["gl_calls_release_gil"] = bool(args.gl_release_gil)
        import cProfile
        import pstats

        profiler = cProfile.Profile() if args.profile else None
        if profiler:
            profiler.enable()
        gc_pauses = GcPauses()
        start = time.perf_counter()
        steps = StepTimer() if args.breakdown else None
        if steps:
            from client_gl.gpu.pool import ChunkPool
            from client_gl.gpu.renderer import SplatRenderer
            from client_gl.stream import engine as engine_module
            from client_gl.stream.engine import StreamEngine
            from client_gl.stream.fetch import Fetcher
            from client_gl.stream.pages import PagedTree

            steps.wrap(StreamEngine, ["wanted", "_collect", "_upload", "_make_room", "_trim_ready", "_coarse_to_fine",
                                      "_tend_pages", "_add_pages", "_evict_pages", "_tell_fetcher", "_draw_counts"])
            # the frame thread's calls into the fetcher take its lock, which the fetch loop holds in _pump/_complete
            steps.wrap(Fetcher, ["want", "done", "stats"])
            steps.wrap(PagedTree, ["insert"])
            steps.wrap(engine_module, ["view_numbers", "select", "PartialView", "select_near", "wanted_bands_at",
                                       "prefetch", "draw_set"])
            steps.wrap_compiled_selection(engine_module.CompiledSelection)
            steps.wrap(ChunkPool, ["join", "add_band", "leave", "set_codebook_band", "_upload_plane", "_write_records",
                                   "set_draw_set", "bind"])
            steps.wrap(SplatRenderer, ["render"])
        walls, drawn, updates, uploads, splits, usage = [], [], [], [], [], []
        others, frame_calls, grown = [], [], []
        other_cpu = OtherThreadsCpu()
        growth = GrowthLog()
        steal0 = machine_steal_s()
        last = time.perf_counter()
        while True:
            now = time.perf_counter() - start
            cam = path.camera(now, w, h)
            o0 = other_cpu.start()
            u0 = thread_usage()
            tc = time.perf_counter()
            rec = session.frame(cam)
            frame_calls.append((time.perf_counter() - tc) * 1e3)
            u1 = thread_usage()
            others.append(other_cpu.since(o0))
            grown.append(growth.take())
            finish()
            t = time.perf_counter()
            walls.append((t - last) * 1e3)
            drawn.append(rec.drawn_splats)
            updates.append(rec.update_ms)
            uploads.append(rec.uploaded_bytes)
            splits.append(steps.take() if steps else {})
            # the frame call's own thread: CPU split user/system, page faults, switches (why a frame's CPU spikes)
            usage.append({"user_ms": round((u1[0] - u0[0]) * 1e3, 2), "system_ms": round((u1[1] - u0[1]) * 1e3, 2),
                          "minor_faults": u1[2] - u0[2], "voluntary_switches": u1[3] - u0[3],
                          "involuntary_switches": u1[4] - u0[4]})
            last = t
            if now > path.end and session.converged:
                break
            if now > path.end + 60:
                break
        out["gc_pauses"] = gc_pauses.stop()
        steal1 = machine_steal_s()
        out["machine_steal_s"] = None if steal0 is None else round(steal1 - steal0, 2)
        out["thread_cpu_s"] = thread_cpu_seconds()
        out["streaming_wall_s"] = time.perf_counter() - start
        if profiler:
            profiler.disable()
            stats = pstats.Stats(profiler)
            stats.sort_stats("tottime").print_stats(25)
            stats.sort_stats("cumulative").print_callees("wanted")
        rend = session.renderer  # the deferred programs: the frame loop's compile of each and the warmer's (ms)
        out["loop_compile_ms"] = {k: round(v * 1e3, 2) for k, v in rend.compile_seconds.items()}
        out["warmer_ms"] = {k: round(v * 1e3, 1) for k, v in rend.warm_compile_seconds.items()}
        out["warm_compile_missed"] = rend.warm_compile_missed
        eng = session.engine
        out["decode_jobs"] = {"jobs": eng.decode_jobs, "payloads": eng.decode_job_payloads,
                              "moving_frames": eng.moving_frames}
        out["streaming"] = {"frames": len(walls), "median_ms": float(np.median(walls)),
                            "p99_ms": float(np.percentile(walls, 99)), "max_ms": float(np.max(walls)),
                            "max_drawn_splats": int(max(drawn)), "first_frame_s": session.metrics.first_frame_s,
                            "bytes": session.fetcher.stats().bytes_downloaded,
                            "converged_after_path_s": time.perf_counter() - start - path.end}
        walls_a, up_a, upd_a = np.array(walls), np.array(uploads), np.array(updates)
        # the frame call's wall less its own thread's CPU: what it waited (the interpreter lock, the fetcher's lock,
        # the driver), against the CPU the other threads used during the call
        waited = np.array([c - u["user_ms"] - u["system_ms"] for c, u in zip(frame_calls, usage, strict=True)])
        others_ms = np.array([sum(o.values()) for o in others])
        by_thread: dict[str, float] = {}
        for o in others:
            for k, v in o.items():
                by_thread[k] = by_thread.get(k, 0.0) + v
        slow = walls_a >= np.percentile(walls_a, 99)
        with_up = up_a > 0
        out["streaming"].update({
            "frames_with_uploads": int(with_up.sum()),
            "p99_ms_with_uploads": float(np.percentile(walls_a[with_up], 99)) if with_up.any() else None,
            "p99_ms_without_uploads": float(np.percentile(walls_a[~with_up], 99)) if (~with_up).any() else None,
            "median_upload_mb": float(np.median(up_a[with_up]) / 1e6) if with_up.any() else 0.0,
            "thread_user_ms_total": round(sum(u["user_ms"] for u in usage), 1),
            "thread_system_ms_total": round(sum(u["system_ms"] for u in usage), 1),
            "thread_minor_faults_total": sum(u["minor_faults"] for u in usage),
            "thread_involuntary_switches_total": sum(u["involuntary_switches"] for u in usage),
            "update_ms_median": float(np.median(upd_a)), "update_ms_p99": float(np.percentile(upd_a, 99)),
            **_selection_ms(splits),
            "frame_call_waited_ms_median": float(np.median(waited)),
            "frame_call_waited_ms_p99": float(np.percentile(waited, 99)),
            "others_cpu_in_frame_ms_median": float(np.median(others_ms)),
            "others_cpu_in_frame_ms_p99": float(np.percentile(others_ms, 99)),
            # CPU other threads used while a frame call ran, by thread, summed over the path (seconds), and over the
            # frames of the top 1 % (ms): the GIL's competitors where it matters
            "others_cpu_in_frames_s": {k: round(v / 1e3, 3) for k, v in sorted(by_thread.items())},
            "others_cpu_in_p99_frames_ms": {k: round(sum(o.get(k, 0.0) for o, s in zip(others, slow, strict=True)
                                                         if s), 1) for k in sorted(by_thread)},
            "p99_frames": int(slow.sum()),
            "p99_frames_waited_ms": round(float(waited[slow].sum()), 1),
            "growth_frames": [{"frame": i, "ms": round(float(walls_a[i]), 1), "grew": g}
                              for i, g in enumerate(grown) if g],
            "slowest": [{"ms": round(float(walls_a[i]), 1), "uploaded_bytes": int(up_a[i]),
                         "update_ms": round(float(upd_a[i]), 2), "steps_ms": splits[i],
                         "thread": usage[i], "call_ms": round(float(frame_calls[i]), 2),
                         "waited_ms": round(float(waited[i]), 2), "others_cpu_ms": others[i],
                         "grew": grown[i], "frame": int(i)}
                        for i in np.argsort(-walls_a, kind="stable")[:12]]})
        cam = path.camera(path.end, w, h)
        for _ in range(5):
            session.frame(cam)
            ctx.finish()
        tiles = list(session.last.draw)
        bands = {t: session.pool.tile_bands(t) for t in tiles}
        store = DirectoryStore(args.scene) if "://" not in args.scene else None
        # every tile, read from every page of a paged scene (the session's tree holds only the pages it reached)
        manifest = load_manifest(store) if store is not None else session.manifest
        # the same tiles and bands, loaded whole, drawn by the plain renderer; timed frame by frame in turn with the
        # streamed frame while the session (its fetch loop and decode threads) is still open, so that both see the
        # same process and the same GPU clocks
        r = None
        if store is not None:
            top = max(bands.values(), default=0)
            r = HeadlessRenderer(RenderOptions(), ctx=ctx)
            loaded = {t: load_tile(store, manifest, manifest.tile(t), bands[t], with_mirror=r.needs_host_mirror)
                      for t in tiles}
            cb = read_codebook(store, manifest, top) if top else None
            r.load_tiles(SceneTiles(dict(manifest.formats), top, loaded, manifest, cb))
            r.render_frame(cam)
            ctx.finish()
        stream_times, render_times, stream_update = [], [], []
        for _ in range(args.repeat):
            t = time.perf_counter()
            rec = session.frame(cam)
            ctx.finish()
            stream_times.append((time.perf_counter() - t) * 1e3)
            stream_update.append(rec.update_ms)
            if r is not None:
                t = time.perf_counter()
                r.render_frame(cam)
                ctx.finish()
                render_times.append((time.perf_counter() - t) * 1e3)
        out["converged_timing"] = "interleaved, session open"
        out["converged_stream_ms"] = float(np.median(stream_times[5:]))
        out["converged_stream_update_ms"] = float(np.median(stream_update[5:]))  # the engine's part, before the draw

        def stream_frame(timing: bool):
            session.frame(cam, timing=timing)
            return session.last_stats
        out["converged_stream_split"] = converged_split(stream_frame, ctx)
        out["converged_drawn_splats"] = int(session.last.drawn_splats)
        if r is not None:
            out["render_same_set_ms"] = float(np.median(render_times[5:]))
            out["render_same_set_split"] = converged_split(lambda timing: r.render_frame(cam, timing=timing), ctx)
            out["stream_vs_render"] = out["converged_stream_ms"] / out["render_same_set_ms"]
            r.unload()
        session.close()
    finally:
        if server is not None:
            server.send_signal(signal.SIGTERM)
            server.wait(10)
    print(json.dumps(out, indent=1))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
