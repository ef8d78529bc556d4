#!/bin/bash
# GPU-machine driver for the renderer on dense scenes (issue 20), one `run` call, about 5 minutes on an H100 or H200
# (guarded to end within 9), from the repo root, carrying (as bench/device/run_bench.sh):
#   .gl           GL loader .debs (libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2, amd64)
#   .whl          cp312 wheels: moderngl glcontext zstandard (+ the client's), and for gsplat 1.5.3 (py3-none-any,
#                 JIT-compiles its CUDA against the machine's torch): gsplat, rich, pygments, markdown-it-py, mdurl,
#                 ninja
#   .bench_carry  tools/make_scene.py and data/real/* (copies of ../shared) so make_scene.py runs there
# Usage: bash bench/device/run_render.sh            (results in $OUT: 5 files, no folders)
#   dense.json          1M and 6M dense scenes (make_scene --spread 0.25), very-high, 1920x1080: the compute draw
#                       and each dense-scene variant (bench_render.py --variants), gsplat wall clock and PSNR
#   default.json        1M and 6M default (sparse) scenes, very-high: the compute draw against gsplat (regression
#                       check against BENCHMARKS.md), and --check (GL against the numpy reference on fruit_drops)
#   dense_medium.json   the dense scenes at medium (the preset): default and the variant VARIANT_MEDIUM
#   render.log          every step's output; the summary tables at the end of each run
#   gsplat_build.log    gsplat's extension build
# Environment: VARIANTS (dense variant flag sets, see DRAW_FLAGS in bench/bench_render.py), VARIANT_MEDIUM,
# FRAMES (40), DEADLINE_S (520: later runs get the time left, each is cut at its share). A dry run of the logic on
# a machine without the GPU (no packages installed, no gsplat, small scenes):
#   LOCAL=1 PY=.venv/bin/python SPLATS="2000 3000" SIZE=96x64 FRAMES=3 GSPLAT= OUT=/tmp/o bash bench/device/run_render.sh
set -u
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
LOG="$OUT/render.log"
exec > >(tee -a "$LOG") 2>&1
PY=${PY:-python3}
if [ -z "${LOCAL:-}" ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
  export PYTHONPATH=/tmp/site:$PWD TORCH_CUDA_ARCH_LIST=9.0 PATH=/tmp/site/bin:$PATH
  export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv
fi
export PYTHONUNBUFFERED=1
SPLATS=${SPLATS:-"1000000 6000000"}
SIZE=${SIZE:-1920x1080}
GSPLAT=${GSPLAT---gsplat}
VARIANTS=${VARIANTS:-"tr8 r8 d16"}
VARIANT_MEDIUM=${VARIANT_MEDIUM:-"d16"}
FRAMES=${FRAMES:-40}
DEADLINE_S=${DEADLINE_S:-520}
W=${WORKDIR:-/tmp/bench}
mkdir -p $W
left() { echo $(( DEADLINE_S - ($(date +%s) - T0) )); }

# gsplat's CUDA extension compiles on first use (~40 s), the scenes are made meanwhile, all in parallel.
gs_pid=
if [ -n "$GSPLAT" ]; then
  $PY -c "from gsplat.cuda._backend import _C; print('gsplat extension ready:', _C is not None)" \
    > "$OUT/gsplat_build.log" 2>&1 &
  gs_pid=$!
fi
# Names as bench_render.py's scene_path(): scene_<n>_seed0.ply (spread 1.0), scene_<n>_seed0_spread0.25.ply.
pids=()
for n in $SPLATS; do
  for spread in 1.0 0.25; do
    f=$W/scene_${n}_seed0.ply
    [ "$spread" = 1.0 ] || f=$W/scene_${n}_seed0_spread${spread}.ply
    [ -f "$f" ] && continue
    ($PY .bench_carry/tools/make_scene.py --splats $n --seed 0 --spread $spread --out "$f.part" > /dev/null \
      && mv "$f.part" "$f") &
    pids+=($!)
  done
done
probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"], c.info["GL_VERSION"])'
if ! $PY -c "$probe"; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  $PY -c "$probe" || exit 1
fi
for p in "${pids[@]}"; do wait "$p" || { echo "make_scene failed"; exit 1; }; done
ls -la $W
echo "scenes made at $(( $(date +%s) - T0 )) s"
if [ -n "$gs_pid" ]; then  # at most 3 more minutes; a failed build leaves gsplat's error in the JSON, GL goes on
  for i in $(seq 1 90); do kill -0 "$gs_pid" 2>/dev/null || break; sleep 2; done
  cat "$OUT/gsplat_build.log"
fi

bench() {  # bench <seconds> <json> <bench_render.py args...>
  local budget=$1 json=$2
  shift 2
  echo "=== $json: $* (at $(( $(date +%s) - T0 )) s, budget $budget s)"
  timeout -k 10 "$budget" $PY bench/bench_render.py --make-scene .bench_carry/tools/make_scene.py --workdir $W \
    --size "$SIZE" --frames "$FRAMES" --color f2 --no-cpu-sort --no-sort-random --json "$OUT/$json" "$@"
  echo "=== $json: rc $? at $(( $(date +%s) - T0 )) s"
}
# 1. dense scenes: every variant, gsplat (wall clock, PSNR at very-high)
bench $(( $(left) * 55 / 100 )) dense.json --splats $SPLATS --spread 0.25 --presets very-high \
  --psnr-preset very-high --draw compute --variants $VARIANTS $GSPLAT
# 2. default scenes: no regression against BENCHMARKS.md, gsplat, correctness on this GL
bench $(( $(left) * 60 / 100 )) default.json --splats $SPLATS --presets very-high --psnr-preset very-high \
  --draw compute $GSPLAT --check
# 3. dense scenes at medium (the table): the default and one variant
bench $(( $(left) - 5 )) dense_medium.json --splats $SPLATS --spread 0.25 --presets medium \
  --psnr-preset medium --draw compute --variants $VARIANT_MEDIUM
echo "total $(( $(date +%s) - T0 )) s"
ls -la "$OUT"
