"""Can a window's swap overlap the next frame's GPU work when they are in two GL contexts on two threads?

On the GPU machine's virtual display (Xvfb, NVIDIA GLX client library) the swap copies every frame to the X server
on the CPU and waits for all the work queued in its context: within one context, nothing we queue overlaps it
(BENCHMARKS.md, "Window against headless"). This probe draws a synthetic frame of about the streamed scene's GPU
time (a compute shader writing a 1920x1080 image, repeated) and shows it in a window three ways:

  render   the frames alone, no window work (what `view --headless` measures)
  serial   one context: frame, full-window triangle sampling it, swap (what the viewer does)
  threads  a render thread with its own context (a hidden window sharing objects with the visible one) draws
           frame N+1 into one of two textures while the main thread shows frame N: fence, wait, triangle, swap

and prints the median frame interval of each. Run under a display (xvfb-run locally, the device's carried Xvfb):

    python bench/probe_window_overlap.py --frames 200 --iterations 40
"""
from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np

_HEAVY = """#version 430
layout(local_size_x = 16, local_size_y = 16) in;
layout(rgba8, binding = 0) writeonly uniform image2D u_out;
uniform int u_iterations;
uniform float u_frame;
void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    vec2 uv = vec2(p) / vec2(imageSize(u_out));
    vec3 c = vec3(uv, 0.5 + 0.5 * sin(u_frame * 0.1));
    for (int i = 0; i < u_iterations; ++i) c = fract(c * 1.0001 + sin(c.yzx * 3.1 + float(i)) * 0.01);
    imageStore(u_out, p, vec4(c, 1.0));
}
"""
class Frames:
    """The synthetic frame: `iterations` steps of a compute shader over a width x height RGBA8 image."""

    def __init__(self, ctx, size, iterations: int):
        self.ctx, self.size = ctx, size
        self.prog = ctx.compute_shader(_HEAVY)
        self.prog["u_iterations"] = iterations
        self.targets = [ctx.texture(size, 4) for _ in range(2)]
        self.n = 0

    def draw(self) -> object:
        tex = self.targets[self.n % 2]
        tex.bind_to_image(0, read=False, write=True)
        self.prog["u_frame"] = float(self.n)
        self.prog.run((self.size[0] + 15) // 16, (self.size[1] + 15) // 16)
        self.ctx.memory_barrier()
        self.n += 1
        return tex


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--iterations", type=int, default=40, help="the synthetic frame's work (about 3.5 ms on the H100 "
                                                               "at 40 is the aim: check the `render` line)")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()
    import glfw
    import moderngl

    w, h = (int(v) for v in args.size.split("x"))
    if not glfw.init():
        raise SystemExit("glfw.init failed (no display?)")
    for hint, value in ((glfw.CONTEXT_VERSION_MAJOR, 4), (glfw.CONTEXT_VERSION_MINOR, 3),
                        (glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)):
        glfw.window_hint(hint, value)
    window = glfw.create_window(w, h, "overlap probe", None, None)
    glfw.window_hint(glfw.VISIBLE, glfw.FALSE)
    hidden = glfw.create_window(64, 64, "render context", None, window)  # shares textures and syncs with `window`
    glfw.make_context_current(window)
    glfw.swap_interval(0)
    ctx = moderngl.create_context()
    from client_gl.gpu.gl import fence, gpu_wait
    from client_gl.window import _BLIT_FS, _BLIT_VS

    blit = ctx.program(vertex_shader=_BLIT_VS, fragment_shader=_BLIT_FS)
    vao = ctx.vertex_array(blit, [])
    frames = Frames(ctx, (w, h), args.iterations)
    out: dict = {"gl_renderer": ctx.info["GL_RENDERER"], "size": [w, h], "iterations": args.iterations}

    def show(tex) -> None:
        ctx.screen.use()
        ctx.viewport = (0, 0, w, h)
        tex.use(0)
        blit["u_image"] = 0
        vao.render(vertices=3)

    def timed(step, n: int) -> float:
        for _ in range(10):
            step()
        ctx.finish()
        t = time.perf_counter()
        for _ in range(n):
            step()
        ctx.finish()
        return (time.perf_counter() - t) * 1e3 / n

    out["render_ms"] = timed(frames.draw, args.frames)
    out["serial_ms"] = timed(lambda: (show(frames.draw()), glfw.swap_buffers(window)), args.frames)

    # threads: frames drawn in the hidden window's context on a render thread, shown by this one
    ready: list = []  # (texture glo, sync) of finished-submitting frames, newest last
    lock = threading.Condition()
    stop = threading.Event()
    drawn = [0]

    def render_thread() -> None:
        glfw.make_context_current(hidden)
        rctx = moderngl.create_context()
        rframes = Frames(rctx, (w, h), args.iterations)
        while not stop.is_set():
            with lock:  # at most two frames ahead of the display (two targets)
                while len(ready) >= 1 and not stop.is_set():
                    lock.wait(0.05)
            tex = rframes.draw()
            sync = fence()
            drawn[0] += 1
            with lock:
                ready.append((tex.glo, sync))
                lock.notify_all()
        rctx.finish()
        glfw.make_context_current(None)

    shown = {}

    def show_next() -> None:
        with lock:
            while not ready:
                lock.wait(0.05)
            glo, sync = ready.pop(0)
            lock.notify_all()
        gpu_wait(sync)  # the GPU waits for the render context's frame, not this thread
        tex = shown.get(glo)
        if tex is None:
            tex = shown[glo] = ctx.external_texture(glo, (w, h), 4, 0, "f1")
        show(tex)
        glfw.swap_buffers(window)

    worker = threading.Thread(target=render_thread, daemon=True)
    worker.start()
    out["threads_ms"] = timed(show_next, args.frames)
    stop.set()
    with lock:
        lock.notify_all()
    worker.join(5)
    out["threads_frames_drawn"] = drawn[0]
    img = np.frombuffer(ctx.screen.read(components=3), np.uint8)
    out["last_frame_mean"] = float(img.mean())  # not black: the shown frames carry the render thread's image
    glfw.terminate()
    print(json.dumps(out, indent=1))
    print(f"render {out['render_ms']:.2f} ms, serial {out['serial_ms']:.2f} ms, threads {out['threads_ms']:.2f} ms "
          f"(a frame: the synthetic one alone, then shown in one context, then drawn on a render thread)")
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
