#!/usr/bin/env bash
# Issue 31, the cold first frame's start-up work (BENCHMARKS.md, "The first frame's prime and framebuffer off the
# serial path"): RenderOptions.atlas_prime ("clear": glClearTexSubImage, no compile, against main's "compute") and
# RenderOptions.early_target (the headless session's framebuffer made and cleared while the manifest is fetched),
# on the NVIDIA driver, from a fresh machine:
#   1. the machine's first GL process that draws: one first frame with both switches on (one sample of a fresh
#      machine's cold driver; r24/r25: 0.276 / 0.279 s with main's behaviour);
#   2. bench/probe_gpu_alloc.py --primes on a fresh shader cache: per prime variant its own cost (the compute
#      prime's first round a cold compile) and the first upload from a pixel-unpack buffer into each fresh atlas of a
#      1 GiB pool after it (ms and page faults: does the driver still move the atlas through host memory?);
#   3. bench/first_frame_variants_ab.py: main (compute prime, framebuffer made by the first frame), both, the early
#      target alone, the clear prime alone; ROUNDS rounds (default 4), the order rotated each round, each run cold on
#      a fresh __GL_SHADER_DISK_CACHE_PATH and then warm on it; a 1M copy of the donut on loopback at 1920x1080.
# Beside the device call, as for first_frame_ab.sh: .whl_ff (zstandard, moderngl, glcontext wheels; else .whl) and
# .gl (the EGL debs); run (nvidia-h200), carry [".whl_ff", ".gl"]: bash bench/device/first_frame_prime_ab.sh
# About 3-4 minutes. JSON and logs under $OUT: first_process.json, primes.json, prime_ab.json.
# Here, on llvmpipe (its timings are not the target: what runs and what comes out):
#   INSTALL=0 CACHE=mesa PY=.venv/bin/python SPLATS=100000 PROBE_MB=128 ROUNDS=2 \
#     FF_ARGS="--as-hardware --size 640x360 --gpu-mem-mb 64" OUT=/tmp/x bash bench/device/first_frame_prime_ab.sh
cd "$(dirname "$0")/../.."
ROUNDS=${ROUNDS:-4}
ROOT=$PWD
OUTDIR=${OUT:-/tmp/first_frame_prime_out}
PY=${PY:-python3}
CACHE=${CACHE:-nvidia}  # nvidia | mesa: whose disk cache each cold run gets fresh
SPLATS=${SPLATS:-1000000}
PROBE_MB=${PROBE_MB:-1024}
FF_ARGS=${FF_ARGS:-}  # more bench_first_frame.py options of every run
W=$(mktemp -d)
mkdir -p "$OUTDIR"
if [ "${INSTALL:-1}" = 1 ]; then
  WHL=.whl_ff; [ -d $WHL ] || WHL=.whl
  $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site $WHL/*.whl || exit 1
  for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  export PYTHONPATH=/tmp/site:$ROOT
else
  export PYTHONPATH=$ROOT
fi
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/numba_cache}
CACHE_VAR=__GL_SHADER_DISK_CACHE_PATH; [ "$CACHE" = mesa ] && CACHE_VAR=MESA_SHADER_CACHE_DIR
$PY bench/tile_scene.py samples/donut.ply --splats "$SPLATS" --out $W/s.ply || exit 1
$PY -m cli.main encode $W/s.ply $W/scene -q || exit 1
# EGL's vendor file where the debs' loader does not find NVIDIA's by itself (a context made, nothing cleared or
# compiled: the driver's start-up work is left to step 1)
probe="import moderngl; moderngl.create_context(standalone=True, backend='egl', require=430)"
$PY -c "$probe" 2>/dev/null || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
summary() {
  $PY -c "import json, sys; j = json.load(open(sys.argv[1])); print(sys.argv[2], {k: j.get(k) for k in \
('first_frame_s', 'manifest_s', 'pool_s', 'built_s', 'compile_ms', 'early_target_ms', 'prime_ms', 'first_clear_ms', \
'first_join_ms', 'context_ms')})" "$1" "$2"
}
# shellcheck disable=SC2086
env $CACHE_VAR="$(mktemp -d)" $PY bench/bench_first_frame.py --scene $W/scene --atlas-prime clear $FF_ARGS \
  --json "$OUTDIR/first_process.json" > "$OUTDIR/first_process.log" 2>&1 \
  && summary "$OUTDIR/first_process.json" "first process (both)" || tail -5 "$OUTDIR/first_process.log"
env $CACHE_VAR="$(mktemp -d)" $PY bench/probe_gpu_alloc.py --primes --pool-mb "$PROBE_MB" \
  --json "$OUTDIR/primes.json" > "$OUTDIR/primes.log" 2>&1; tail -7 "$OUTDIR/primes.log"
# shellcheck disable=SC2086
$PY bench/first_frame_variants_ab.py --scene $W/scene --rounds "$ROUNDS" --cache "$CACHE" \
  --json "$OUTDIR/prime_ab.json" -- $FF_ARGS > "$OUTDIR/prime_ab.log" 2>&1 || { tail -5 "$OUTDIR/prime_ab.log"; exit 1; }
$PY -c "import json, sys; s = json.load(open(sys.argv[1]))['summary']; [print(k, {m: v for m, v in e.items() \
if m.startswith(('first_frame_s', 'built_s', 'compile_ms', 'early_target_ms', 'prime_ms', 'first_clear_ms', \
'first_join_ms'))}) for k, e in s.items()]" "$OUTDIR/prime_ab.json"
rm -rf "$W"
