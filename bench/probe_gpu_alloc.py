"""What a large GPU allocation costs the CPU, and when: the pool's atlases and the renderer's work buffers.

On the H100 the first texel upload into a fresh 1 GiB-budget pool took 140-200 ms of the frame loop's CPU (139,521
minor page faults, about the pool's 570 MB), and each growth of the work buffers 30-40 ms: both land in frames (the
first frame with splats, the fly-through's slowest frames). This times, for each allocation method, the creation,
the first small write (with the GPU waited for) and a second one, with the process's minor page faults:

    python bench/probe_gpu_alloc.py --mb 256 1024
    __GL_SHADER_DISK_CACHE_PATH=$(mktemp -d) python bench/probe_gpu_alloc.py --primes --json primes.json   # issue 31

--primes: the ways of priming a fresh atlas (prime_steps), each prime's cost and the first upload after it.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

GL_TEXTURE_2D_ARRAY = 0x8C1A
GL_RGBA32UI = 0x8D70
GL_RGBA_INTEGER = 0x8D99
GL_UNSIGNED_INT = 0x1405
GL_SHADER_STORAGE_BUFFER = 0x90D2
GL_DYNAMIC_STORAGE_BIT = 0x0100
GL_MAP_READ_BIT = 0x0001


def faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def pool_steps(ctx, budget_mb: int) -> list[dict]:
    """A streaming session's pool (the 6M donut's formats, SH0) and its first writes, one step at a time."""
    from client_gl.gpu.gl import GL_PIXEL_UNPACK_BUFFER, StagingBuffer, gl
    from client_gl.gpu.pool import ChunkPool

    formats = {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"}
    rows = []

    def step(label: str, fn) -> None:
        ctx.finish()
        f0, t0 = faults(), time.perf_counter()
        fn()
        ctx.finish()
        row = {"kind": "pool", "method": label, "mb": budget_mb, "ms": round((time.perf_counter() - t0) * 1e3, 2),
               "faults": faults() - f0}
        rows.append(row)
        print(row, flush=True)

    holder = {}
    step("create pool", lambda: holder.setdefault("pool", ChunkPool.for_budget(ctx, budget_mb << 20, formats, 0,
                                                                               host_mirror=False)))
    pool = holder["pool"]
    atlases = list(pool._atlases.items())
    texels = np.zeros(16 * 16, np.uint32)
    staging = StagingBuffer(ctx)
    def client(tex, x):
        tex.write(texels.view(np.uint8).reshape(16, 16, 4)[..., :tex_bytes(tex)], x, 0, 16, 16)

    def staged(tex, x):
        with staging.staged(np.zeros(16 * 16 * 4, np.uint8)):
            tex.write_region(None, 16, 0, 0, x, 0, 16, 16)
        gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)

    # the order of the writes matters on the NVIDIA driver: each texture gets one order
    orders = [("client", "staged", "client"), ("staged", "staged", "client"), ("client", "client", "staged"),
              ("staged", "client", "staged")]
    for (name, tex), order in zip(atlases, orders, strict=False):
        for n, how in enumerate(order):
            step(f"{name} write {n + 1} ({how})", lambda tex=tex, how=how, n=n: (client if how == "client" else
                                                                                 staged)(tex, 16 * n))
    # the atlases written by a compute shader (imageStore, the texture bound as an r32ui image: GL allows an image
    # format of the texture's size class), from a storage buffer
    import ctypes as c

    from client_gl.gpu.gl import gl_function_address as _address
    bind_image = c.CFUNCTYPE(None, c.c_uint, c.c_uint, c.c_int, c.c_ubyte, c.c_int, c.c_uint, c.c_uint)(
        _address("glBindImageTexture"))
    shader = ctx.compute_shader("""#version 430
layout(local_size_x = 16, local_size_y = 16) in;
layout(r32ui, binding = 0) writeonly uniform uimage2D atlas;
layout(std430, binding = 0) readonly buffer Src { uint words[]; };
uniform ivec2 u_at;
void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    imageStore(atlas, u_at + p, uvec4(words[p.y * 16 + p.x]));
}""")
    src = ctx.buffer(np.arange(256, dtype=np.uint32).tobytes())
    fresh = {}
    for name in ("position", "rotation"):  # R32UI and RGB10_A2, fresh ones
        old = pool._atlases[name]
        fresh[name] = type(old)(old.internal, old.width, old.height, old.layers)

    def compute(tex, x):
        bind_image(0, tex.glo, 0, 0, 0, 0x88B9, 0x8236)  # GL_WRITE_ONLY, GL_R32UI
        src.bind_to_storage_buffer(0)
        shader["u_at"] = (x, 0)
        shader.run(1, 1)
        ctx.memory_barrier()

    reader = ctx.compute_shader("""#version 430
layout(local_size_x = 1) in;
uniform usampler2D u_tex;
layout(std430, binding = 1) buffer Out { uint sum; };
void main() { sum += texelFetch(u_tex, ivec2(0), 0).x; }""")
    sink = ctx.buffer(reserve=16)

    def read(tex, x):  # the first time a shader samples the texture (the cull pass's texelFetch)
        tex.bind(0)
        reader["u_tex"] = 0
        sink.bind_to_storage_buffer(1)
        reader.run(1)

    for name, tex in fresh.items():
        for n, how in enumerate(("compute", "compute", "client", "compute", "staged", "read", "read")):
            fn = {"compute": compute, "client": client, "staged": staged, "read": read}[how]
            step(f"fresh {name} write {n + 1} ({how})", lambda tex=tex, fn=fn, n=n: fn(tex, 16 * n))
        tex.release()
    for name, tex in pool._atlases.items():
        step(f"pool {name} first read", lambda tex=tex: read(tex, 0))
    step("range records", lambda: pool._write_records(np.arange(4)))
    step("bind (state upload)", pool.bind)
    gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)
    pool.release()
    return rows


PRIME_VARIANTS = ("none", "clear", "clear-layers", "fbo-clear", "copy", "compute")
GL_COLOR = 0x1800
GL_COLOR_ATTACHMENT0 = 0x8CE0
GL_SCISSOR_TEST = 0x0C11
INTEGER_FORMATS = (0x8236, 0x8234, 0x8D70, 0x8238)  # R32UI, R16UI, RGBA32UI, RG8UI: glClearBuffer*uiv


def prime_steps(ctx, budget_mb: int, variants: list[str], rounds: int) -> list[dict]:
    """What each way of making a fresh atlas GPU-written costs, and whether the driver then still moves the atlas
    through host memory at its first upload from a pixel-unpack buffer (the pool's uploads; BENCHMARKS.md, "The first
    frame's prime and framebuffer off the serial path"). Per variant and round: a streaming session's pool of
    `budget_mb` (the 6M donut's formats, SH0) made unprimed; the prime of its uncompressed atlases timed with the GPU
    waited for ("prime": its first round is the cold one, a compute prime's compile included where the shader cache
    is fresh); then per atlas the first upload from the staging buffer (a run of 16 slots, 256x16 texels, as a
    join's) and a second one, each waited for, with the process's minor page faults (a move through host memory:
    one a 4 KB page of the atlas). Variants (PRIME_VARIANTS):
      none          nothing (the problem: 40-90 ms a 128 MB atlas on the H100 at the first client upload)
      clear         glClearTexSubImage of texel (0, 0), layer 0 (ChunkPool's prime="clear")
      clear-layers  the same texel on every layer of an array atlas
      fbo-clear     layer 0 attached to a framebuffer, a 1x1 scissored glClearNamedFramebuffer (render target path)
      copy          glCopyImageSubData of one texel from a small texture of the same format uploaded from memory
      compute       prime_texels.comp's imageStore (ChunkPool's prime="compute", main's; a compile)
    Round r runs the variants in turn, in reverse order on odd rounds (an order effect shows as a difference)."""
    import ctypes as c

    from client_gl.gpu.gl import GL_PIXEL_UNPACK_BUFFER, RawTexture, StagingBuffer, gl
    from client_gl.gpu.gl import gl_function_address as _address
    from client_gl.gpu.pool import ChunkPool

    u, i, p = c.c_uint, c.c_int, c.c_void_p
    fn = {name: c.PYFUNCTYPE(None, *sig)(_address(name)) for name, sig in {
        "glCreateFramebuffers": (i, p), "glDeleteFramebuffers": (i, p),
        "glNamedFramebufferTextureLayer": (u, u, u, i, i), "glNamedFramebufferTexture": (u, u, u, i),
        "glClearNamedFramebufferfv": (u, u, i, p), "glClearNamedFramebufferuiv": (u, u, i, p),
        "glEnable": (u,), "glDisable": (u,), "glScissor": (i, i, i, i),
        "glCopyImageSubData": (u, u, i, i, i, i, u, u, i, i, i, i, i, i, i)}.items()}
    formats = {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"}
    staging = StagingBuffer(ctx)
    run = np.zeros(16 * 16 * 16 * 4, np.uint8)  # 16 slots' blocks, 4 bytes a texel at most

    def fbo_clear(tex) -> None:
        name = c.c_uint(0)
        fn["glCreateFramebuffers"](1, c.byref(name))
        if tex.layers:
            fn["glNamedFramebufferTextureLayer"](name.value, GL_COLOR_ATTACHMENT0, tex.glo, 0, 0)
        else:
            fn["glNamedFramebufferTexture"](name.value, GL_COLOR_ATTACHMENT0, tex.glo, 0)
        fn["glEnable"](GL_SCISSOR_TEST)
        fn["glScissor"](0, 0, 1, 1)
        zero = (c.c_uint * 4)() if tex.internal in INTEGER_FORMATS else (c.c_float * 4)()
        key = "glClearNamedFramebufferuiv" if tex.internal in INTEGER_FORMATS else "glClearNamedFramebufferfv"
        fn[key](name.value, GL_COLOR, 0, zero)
        fn["glDisable"](GL_SCISSOR_TEST)
        fn["glDeleteFramebuffers"](1, c.byref(name))

    sources: dict[int, RawTexture] = {}

    def copy(tex) -> None:
        src = sources.get(tex.internal)
        if src is None:
            src = sources[tex.internal] = RawTexture(tex.internal, 16, 16)
            src.write(np.zeros(16 * 16 * tex.texel_bytes, np.uint8), 0, 0, 16, 16)
        fn["glCopyImageSubData"](src.glo, src.target, 0, 0, 0, 0, tex.glo, tex.target, 0, 0, 0, 0, 1, 1, 1)

    def prime(pool, how: str) -> None:
        atlases = [t for t in pool._atlases.values() if not t.compressed]
        if how in ("clear", "compute"):
            pool._prime_atlases(how)
        elif how == "clear-layers":
            for tex in atlases:
                for layer in range(max(1, tex.layers)):
                    tex.clear_texel(0, 0, layer)
        elif how == "fbo-clear":
            for tex in atlases:
                fbo_clear(tex)
        elif how == "copy":
            for tex in atlases:
                copy(tex)

    def staged(tex, n: int) -> None:
        with staging.staged(run[:16 * 16 * 16 * tex.texel_bytes]):
            tex.write_region(None, 16 * 16, 0, 0, 16 * 16 * n, 16, 16 * 16, 16)
        gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)

    def timed(fn_) -> tuple[float, int]:
        ctx.finish()
        f0, t0 = faults(), time.perf_counter()
        fn_()
        ctx.finish()
        return round((time.perf_counter() - t0) * 1e3, 3), faults() - f0

    rows = []
    # the process's first GL work (a driver's start-up, tens of ms cold on the H200: BENCHMARKS.md r25) paid here,
    # not by the first variant's prime
    ms, f = timed(lambda: ctx.framebuffer([ctx.texture((64, 64), 4)]).clear(0.0, 0.0, 0.0, 0.0))
    rows.append({"kind": "prime", "variant": "first GL work (a 64x64 clear)", "ms": ms, "faults": f})
    print(rows[-1], flush=True)
    for r in range(rounds):
        for how in (variants if r % 2 == 0 else variants[::-1]):
            holder = {}
            create_ms, _ = timed(lambda holder=holder: holder.setdefault("pool", ChunkPool.for_budget(
                ctx, budget_mb << 20, formats, 0, host_mirror=False, prime="none")))
            pool = holder["pool"]
            prime_ms, prime_faults = timed(lambda pool=pool, how=how: prime(pool, how))
            row = {"kind": "prime", "variant": how, "round": r, "mb": budget_mb, "create_ms": create_ms,
                   "prime_ms": prime_ms, "prime_faults": prime_faults, "atlases": {}}
            for name, tex in pool._atlases.items():
                if tex.compressed:
                    continue
                first = timed(lambda tex=tex: staged(tex, 0))
                second = timed(lambda tex=tex: staged(tex, 1))
                row["atlases"][name] = {"mb": round(tex.nbytes / (1 << 20), 1), "first_upload_ms": first[0],
                                        "first_upload_faults": first[1], "second_upload_ms": second[0],
                                        "second_upload_faults": second[1]}
            row["first_uploads_ms"] = round(sum(a["first_upload_ms"] for a in row["atlases"].values()), 3)
            row["first_uploads_faults"] = sum(a["first_upload_faults"] for a in row["atlases"].values())
            rows.append(row)
            print({k: v for k, v in row.items() if k != "atlases"}, flush=True)
            pool.release()
    for src in sources.values():
        src.release()
    staging.release()
    gl.glBindBuffer(GL_PIXEL_UNPACK_BUFFER, 0)
    return rows


def tex_bytes(tex) -> int:
    from client_gl.gpu.gl import PIXEL_TRANSFER
    return PIXEL_TRANSFER[tex.internal][2]


def summarize_primes(rows: list[dict]) -> None:
    """One line a variant: its prime's ms (cold round, then the others) and the first uploads' ms and faults."""
    by: dict[str, list[dict]] = {}
    for row in rows:
        if "round" in row:
            by.setdefault(row["variant"], []).append(row)
    for how, sel in by.items():
        print(f"{how:13s} prime ms {[r['prime_ms'] for r in sel]}  first uploads ms "
              f"{[r['first_uploads_ms'] for r in sel]}  faults {[r['first_uploads_faults'] for r in sel]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mb", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--pool-mb", type=int, default=1024, help="GPU budget of the pool whose first uploads are timed")
    ap.add_argument("--primes", action="store_true",
                    help="only the atlas primes' probe (prime_steps: each prime's cost and the first upload after "
                         "it); run with a fresh shader cache (__GL_SHADER_DISK_CACHE_PATH=$(mktemp -d)) so that the "
                         "compute prime's first round compiles cold")
    ap.add_argument("--prime-variants", default=",".join(PRIME_VARIANTS),
                    help=f"comma-separated, in order (of {', '.join(PRIME_VARIANTS)})")
    ap.add_argument("--prime-rounds", type=int, default=2)
    args = ap.parse_args()
    variants = [v for v in args.prime_variants.split(",") if v]
    unknown = set(variants) - set(PRIME_VARIANTS)
    if unknown:
        ap.error(f"unknown prime variants {sorted(unknown)} (choose from {', '.join(PRIME_VARIANTS)})")
    from client_gl.gpu.gl import gl_function_address as _address
    from client_gl.offscreen import create_context

    ctx = create_context()
    if args.primes:
        out = {"gl_renderer": ctx.info.get("GL_RENDERER"), "gl_version": ctx.info.get("GL_VERSION"),
               "rows": prime_steps(ctx, args.pool_mb, variants, args.prime_rounds)}
        summarize_primes(out["rows"])
        if args.json_out:
            with open(args.json_out, "w") as f:
                json.dump(out, f, indent=1)
        return
    u, i, p = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
    fn = {name: ctypes.CFUNCTYPE(None, *sig)(_address(name)) for name, sig in {
        "glGenTextures": (i, p), "glBindTexture": (u, u), "glDeleteTextures": (i, p),
        "glTexImage3D": (u, i, i, i, i, i, i, u, u, p), "glTexStorage3D": (u, i, u, i, i, i),
        "glTexSubImage3D": (u, i, i, i, i, i, i, i, u, u, p), "glGenBuffers": (i, p), "glBindBuffer": (u, u),
        "glBufferStorage": (u, ctypes.c_ssize_t, p, u), "glBufferSubData": (u, ctypes.c_ssize_t, ctypes.c_ssize_t, p),
        "glDeleteBuffers": (i, p), "glClearTexImage": (u, i, u, u, p)}.items()}
    texel = np.arange(16 * 16 * 4, dtype=np.uint32)

    def texture(method: str, mb: int):
        layers = 4
        side = int((mb * (1 << 20) / (16 * layers)) ** 0.5) // 16 * 16
        name = ctypes.c_uint(0)
        fn["glGenTextures"](1, ctypes.byref(name))
        fn["glBindTexture"](GL_TEXTURE_2D_ARRAY, name.value)
        if method == "teximage":
            fn["glTexImage3D"](GL_TEXTURE_2D_ARRAY, 0, GL_RGBA32UI, side, side, layers, 0, GL_RGBA_INTEGER,
                               GL_UNSIGNED_INT, None)
        else:
            fn["glTexStorage3D"](GL_TEXTURE_2D_ARRAY, 1, GL_RGBA32UI, side, side, layers)
            if method == "texstorage+clear":
                fn["glClearTexImage"](name.value, 0, GL_RGBA_INTEGER, GL_UNSIGNED_INT, None)

        def write():
            fn["glBindTexture"](GL_TEXTURE_2D_ARRAY, name.value)
            fn["glTexSubImage3D"](GL_TEXTURE_2D_ARRAY, 0, 16, 16, 1, 16, 16, 1, GL_RGBA_INTEGER, GL_UNSIGNED_INT,
                                  texel.ctypes.data_as(p))

        def free():
            fn["glDeleteTextures"](1, ctypes.byref(name))
        return write, free

    def buffer(method: str, mb: int):
        size = mb << 20
        if method == "moderngl reserve":
            buf = ctx.buffer(reserve=size)
            return (lambda: buf.write(texel.tobytes(), offset=4096)), buf.release
        name = ctypes.c_uint(0)
        fn["glGenBuffers"](1, ctypes.byref(name))
        fn["glBindBuffer"](GL_SHADER_STORAGE_BUFFER, name.value)
        flags = GL_DYNAMIC_STORAGE_BIT | (GL_MAP_READ_BIT if method.endswith("+read") else 0)
        fn["glBufferStorage"](GL_SHADER_STORAGE_BUFFER, size, None, flags)

        def write():
            fn["glBindBuffer"](GL_SHADER_STORAGE_BUFFER, name.value)
            fn["glBufferSubData"](GL_SHADER_STORAGE_BUFFER, 4096, texel.nbytes, texel.ctypes.data_as(p))
        return write, (lambda: fn["glDeleteBuffers"](1, ctypes.byref(name)))

    rows = []
    for mb in args.mb:
        for kind, make, methods in (("texture", texture, ("teximage", "texstorage", "texstorage+clear")),
                                    ("buffer", buffer, ("moderngl reserve", "bufferstorage", "bufferstorage+read"))):
            for method in methods:
                ctx.finish()
                f0, t0 = faults(), time.perf_counter()
                write, free = make(method, mb)
                ctx.finish()
                f1, t1 = faults(), time.perf_counter()
                write()
                ctx.finish()
                f2, t2 = faults(), time.perf_counter()
                write()
                ctx.finish()
                t3 = time.perf_counter()
                free()
                ctx.finish()
                row = {"kind": kind, "method": method, "mb": mb, "create_ms": round((t1 - t0) * 1e3, 2),
                       "create_faults": f1 - f0, "first_write_ms": round((t2 - t1) * 1e3, 2),
                       "first_write_faults": f2 - f1, "second_write_ms": round((t3 - t2) * 1e3, 2)}
                rows.append(row)
                print(row, flush=True)
    rows += pool_steps(ctx, args.pool_mb)
    out = {"gl_renderer": ctx.info.get("GL_RENDERER"), "rows": rows}
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
