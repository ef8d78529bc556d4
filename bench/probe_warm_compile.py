"""Does a program compiled and linked on another thread's EGL context make the frame loop's moderngl compile of the
same source a driver-cache hit? (issue 38; client_gl/gpu/warm_compile.py; BENCHMARKS.md "Deferred compiles warmed
off the frame loop".)

The renderer's deferred programs that need no decode header (the compute draw's 5, the depth/tile sort's 4) and the
fetch draw's pair, each compiled through moderngl on the main thread, timed (wall and thread CPU):
  --mode cold    nothing before (the driver's cache as the environment leaves it)
  --mode warmed  ShaderWarmer compiled them all first on its thread (waited for), then the main thread's compiles
  --mode twice   the main thread compiled each once before (the in-process cache of the same context)
  --mode beside  the warmer runs while the main thread counts Python steps (does the thread hold the GIL?), then
                 the main thread's compiles
Run each in a fresh process with a fresh cache directory for a cold driver, e.g. on Mesa:
  MESA_SHADER_CACHE_DIR=$(mktemp -d) python bench/probe_warm_compile.py --mode warmed
NVIDIA: __GL_SHADER_DISK_CACHE_PATH=$(mktemp -d) (or __GL_SHADER_DISK_CACHE=0 for no disk cache at all).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time


def sources():
    from client_gl.gpu import shadergen
    from client_gl.gpu.compute_raster import raster_sources
    from client_gl.gpu.sort import compute_program_source, sort_programs
    from client_gl.gpu.warm_compile import GL_COMPUTE_SHADER, GL_FRAGMENT_SHADER, GL_VERTEX_SHADER

    progs = {}
    for name, src in raster_sources("f4", True, 7).items():
        progs[name] = ((GL_COMPUTE_SHADER, src),)
    for spec in sort_programs(7) + sort_programs(6):
        progs[f"{spec[0]}/{spec[2]}"] = ((GL_COMPUTE_SHADER, compute_program_source(*spec)),)
    vert, frag = shadergen.projected_render_sources("fetch")
    progs["fetch"] = ((GL_VERTEX_SHADER, vert), (GL_FRAGMENT_SHADER, frag))
    return progs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=("cold", "warmed", "twice", "beside"), default="cold")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()
    import moderngl

    from client_gl.gpu.warm_compile import GL_COMPUTE_SHADER, ShaderWarmer

    ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
    progs = sources()

    def compile_main(stages):
        if stages[0][0] == GL_COMPUTE_SHADER:
            return ctx.compute_shader(stages[0][1])
        return ctx.program(vertex_shader=stages[0][1], fragment_shader=stages[1][1])

    out: dict = {"renderer": ctx.info["GL_RENDERER"], "mode": args.mode,
                 "env": {k: v for k, v in os.environ.items() if "SHADER" in k or k.startswith("__GL")}}
    if args.mode == "twice":
        for stages in progs.values():
            compile_main(stages).release()
    if args.mode in ("warmed", "beside"):
        t0 = time.perf_counter()
        warmer = ShaderWarmer(progs.values())
        steps = 0
        while not warmer.finished:
            if args.mode == "beside":
                sum(range(100))
                steps += 1
            else:
                time.sleep(0.001)
        out["warmer_wall_s"] = time.perf_counter() - t0
        out["warmer_failed"] = warmer.failed
        out["warmer_ms"] = {name: round(warmer.seconds.get(stages, float("nan")) * 1e3, 2)
                            for name, stages in progs.items()}
        out["main_python_steps_during_warmer"] = steps
    wall, cpu = {}, {}
    for name, stages in progs.items():
        c0, w0 = time.thread_time(), time.perf_counter()
        prog = compile_main(stages)
        wall[name] = round((time.perf_counter() - w0) * 1e3, 2)
        cpu[name] = round((time.thread_time() - c0) * 1e3, 2)
        prog.release()
    out["main_compile_wall_ms"], out["main_compile_cpu_ms"] = wall, cpu
    out["main_compile_wall_total_ms"] = round(sum(wall.values()), 1)
    out["main_compile_wall_median_ms"] = round(statistics.median(wall.values()), 2)
    out["load"] = os.getloadavg()
    print(json.dumps(out, indent=1))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
