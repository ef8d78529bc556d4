#!/bin/bash
# GPU-machine driver for the viewer's window path (device `run` tool), from the repo root, carrying:
#   .gl           GL loader .debs (as run_client.sh)
#   .xroot        Xvfb and the X11 client libraries as Debian .debs, unpacked under /tmp/xroot (not into /)
#   .whl          cp312 wheels: run_client.sh's
#   .xwin         winsite.tar.xz: glfw, moderngl-window, pyglm and imgui-bundle unpacked (demos and stubs removed;
#                 xz, to fit the carry limit), and xglx.tar.xz: Mesa's swrast DRI driver built without LLVM
#                 (softpipe), which Xvfb's GLX extension needs to start (the device README: Xvfb, Mesa and the
#                 NVIDIA GLX client library); bench/device/make_xwin.sh makes them and .xroot
# The window is a GLX window on Xvfb drawn by the NVIDIA driver (__GLX_VENDOR_LIBRARY_NAME=nvidia). It streams a
# 6M-splat scene from loopback at 1920x1080, and its converged frames are timed against `view --headless`'s.
# Usage: bash bench/device/run_window.sh [fly]   (results under $OUT; fly: the fly-through A/B of GL calls that
# keep the GIL against calls that release it, with the per-step split of the slowest frames)
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
mkdir -p /tmp/xroot
for f in .xroot/*.deb; do dpkg -x "$f" /tmp/xroot; done
tar -xJf .xwin/xglx.tar.xz -C /tmp/xroot
[ -x /usr/bin/xkbcomp ] || cp /tmp/xroot/usr/bin/xkbcomp /usr/bin/xkbcomp  # Xvfb runs it by this path
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
  .whl/*.whl || exit 1
tar -xJf .xwin/winsite.tar.xz -C /tmp/site
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
W=/tmp/win-work
mkdir -p $W/root
probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"])'
python3 -c "$probe" || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
# PROBE=1: what large GPU allocations cost the CPU, and when (bench/probe_gpu_alloc.py)
[ "${PROBE:-0}" = 1 ] && python3 bench/probe_gpu_alloc.py --mb 256 1024 --json "$OUT/probe_gpu_alloc.json"
[ "${PROBE:-0}" = only ] && python3 bench/probe_gpu_alloc.py --mb 256 --json "$OUT/probe_gpu_alloc.json" && exit
python3 bench/tile_scene.py samples/donut.ply --splats 6000000 --seed 0 --out $W/s6m.ply | tail -1  # no data to carry
python3 -m cli encode $W/s6m.ply $W/root/s6m --up 0,0,1 -q || exit 1
python3 -m cli serve $W/root --port 8765 --no-access-log > $W/serve.log 2>&1 &
SERVE=$!
sleep 2
URL=http://127.0.0.1:8765/scenes/s6m
echo "== headless"
if [ "${FIRST:-${WINDOW:-1}}" = 1 ]; then  # FIRST=1: the first-frame runs even with WINDOW=0
# where the time to the first frame goes: on a fresh machine (the driver compiles every shader), then again
for run in cold warm sync; do  # sync: warm, each renderer and pool step waited for (its GPU work included)
  echo "-- first frame, $run"
  python3 bench/bench_first_frame.py --scene $W/root/s6m --json "$OUT/first_frame_$run.json" \
    $([ $run = sync ] && echo --sync) 2>&1 | grep -v "compile \|alloc buffer" | tail -40
done
fi
if [ "${WINDOW:-1}" = 1 ]; then  # WINDOW=0: the fly-through alone
python3 -m cli view $URL --headless --size 1920x1080 --measure-frames 120 --record "$OUT/headless.json" \
  --screenshot "$OUT/headless.png" --no-cache 2>&1 | tail -2
echo "== window"
LD_LIBRARY_PATH=/tmp/xroot/usr/lib/x86_64-linux-gnu LIBGL_DRIVERS_PATH=/tmp/xroot/usr/lib/x86_64-linux-gnu/dri \
  /tmp/xroot/usr/bin/Xvfb :99 -screen 0 1920x1200x24 \
  -xkbdir /tmp/xroot/usr/share/X11/xkb -nolisten tcp > $W/xvfb.log 2>&1 < /dev/null &
XVFB=$!
sleep 2
export DISPLAY=:99 __GLX_VENDOR_LIBRARY_NAME=nvidia LD_LIBRARY_PATH=/tmp/xroot/usr/lib/x86_64-linux-gnu
echo "xvfb log:"; head -5 $W/xvfb.log
timeout 30 python3 - > $W/probe.log 2>&1 <<'PY'
import glfw
assert glfw.init(), "glfw.init failed"
glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 4); glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 1)
glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
w = glfw.create_window(640, 480, "probe", None, None)
assert w, "no window"
glfw.make_context_current(w)
import moderngl
print("window GL:", moderngl.create_context().info["GL_RENDERER"])
PY
echo "probe rc=$?"; tail -5 $W/probe.log
if [ -n "${OVERLAP:-}" ]; then  # OVERLAP="200 800": bench/probe_window_overlap.py at these iteration counts
  for it in $OVERLAP; do
    timeout 120 python3 bench/probe_window_overlap.py --iterations $it --json "$OUT/overlap_$it.json" 2>&1 | tail -1
  done
  [ "${OVERLAP_ONLY:-0}" = 1 ] && { kill $XVFB $SERVE; exit 0; }
fi
window() {  # window <name> <more view options>: one timed window run, its record as $OUT/<name>.json
  local name=$1
  shift
  timeout 200 python3 -m cli view $URL --size 1920x1080 --exit-when-converged --measure-frames 120 \
    --no-vsync --no-cache --record "$OUT/$name.json" "$@" > $W/$name.log 2>&1 < /dev/null
  echo "$name rc=$?"; tail -5 $W/$name.log
}
window window --screenshot "$OUT/window.png"
window window_no_overlay --no-overlay
# the renderer's image into the window by glBlitFramebuffer instead of a full-window triangle
# frames drawn in the window's own context on its thread (the viewer before its render thread)
SPLATSTREAM_WINDOW_THREAD=0 window window_one_thread --no-overlay
# the NVIDIA driver's own worker thread for GL calls (its swap's copy to the X server may then overlap our next frame)
__GL_THREADED_OPTIMIZATIONS=1 window window_threaded --no-overlay
tail -3 $W/xvfb.log
python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
for name in ("headless", "window", "window_no_overlay", "window_one_thread", "window_threaded"):
    try:
        r = json.load(open(f"{out}/{name}.json"))
    except OSError:
        print(name, "no record"); continue
    print(name, r.get("gl_renderer"), "first frame", r.get("first_frame_s"), "converged", r.get("converged_s"),
          "median converged frame ms", r.get("measured_frame_ms_median"), "of which before the swap",
          r.get("measured_draw_ms_median"), "back to back", r.get("measured_back_to_back_ms"),
          "its split (medians)", r.get("measured_back_to_back_split_median"),
          "first frame split: manifest", r.get("manifest_s"), "pool", r.get("pool_s"), "built", r.get("built_s"))
PY
kill $XVFB 2>/dev/null
fi
if [ "${1:-}" = fly ]; then
  # keep: our GL entry points keeping the GIL (PYFUNCTYPE, the default); release: releasing it in every call
  # (CFUNCTYPE); procN: decoding in N processes instead of 2 threads; si20: a 20 ms interpreter switch interval;
  # presize: work buffers made for the splat budget up front; finishgil: each frame's wait for the GPU with
  # moderngl's finish() (keeps the GIL) instead of wait_for_gpu
  uname -r; echo "THP: $(cat /sys/kernel/mm/transparent_hugepage/enabled) defrag: \
$(cat /sys/kernel/mm/transparent_hugepage/defrag)"; python3 -c "import sys; print(sys.version)"
  for ab in ${FLY_AB:-keep release}; do  # FLY_AB=keep: the default alone
    flag=""; envs=""
    case $ab in
      release) flag=--gl-release-gil ;;
      proc*) flag="--decode-processes ${ab#proc}" ;;
      si20) flag="--switch-interval 0.02" ;;
      si1) flag="--switch-interval 0.001" ;;
      si05) flag="--switch-interval 0.0005" ;;
      dec1) flag="--decode-workers 1" ;;
      finishgil) flag="--finish-keeps-gil" ;;
      nofreeze) flag="--no-gc-freeze" ;;
      profile) flag="--profile" ;;
      presize) flag="--work-splats 2000000" ;;  # the renderer's work buffers made for the 2M budget up front
      blas1) envs="OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1" ;;
      # glibc malloc with fixed thresholds: large arrays stay on the heap, freed memory is not handed back (no page
      # faults for fresh pages in every frame)
      malloc) envs="MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=4294967296 MALLOC_TOP_PAD_=268435456" ;;
    esac
    n=0; while [ -e "$OUT/fly_$ab.json" ]; do n=$((n+1)); ab=${ab%%-*}-$n; done  # a variant named twice: _keep-1
    env $envs python3 bench/bench_flythrough.py --scene $W/root/s6m --ply $W/s6m.ply --json "$OUT/fly_$ab.json" --breakdown \
      $flag > $W/fly_$ab.log 2>&1
    python3 -c "import json,sys; d=json.load(open(sys.argv[1])); s=d['streaming']; print(sys.argv[2], {k: s[k] for k \
      in ('frames','median_ms','p99_ms','p99_ms_with_uploads','p99_ms_without_uploads','update_ms_p99')}, \
      'converged', d['converged_stream_ms'], 'update', d.get('converged_stream_update_ms'), d.get('converged_stream_split'), 'render', d['render_same_set_ms'], d.get('render_same_set_split'), 'threads cpu s', d['thread_cpu_s'], \
      'wall s', d['streaming_wall_s'], 'gc', d.get('gc_pauses'), 'steal s', d.get('machine_steal_s'), \
      {k: v for k, v in s.items() if k.startswith('thread_')}); [print(x) for x in s['slowest'][:4]]" \
      "$OUT/fly_$ab.json" $ab || tail -20 $W/fly_$ab.log
  done
fi
kill $SERVE 2>/dev/null
wait 2>/dev/null
# the device tool brings back a few files only: everything in one archive
(cd "$OUT" && tar -czf /tmp/window_results.tgz -- * && rm -rf -- "${OUT:?}"/* && mv /tmp/window_results.tgz "$OUT/")
