#!/usr/bin/env bash
# RenderOptions.warm_first, the first frame's two compiles side by side (issue 31; BENCHMARKS.md, "The first frame's
# two compiles side by side"): paired A/B against --no-warm-first on the NVIDIA driver, each cold run on a fresh
# __GL_SHADER_DISK_CACHE_PATH and then once more on it warm (bench/warm_compile_ab.py --cache nvidia), a 1M copy of
# the donut served on loopback at 1920x1080; then the 14-program probe (is the fetch draw's pair now a hit?).
# Beside the device call, as for first_frame_ab.sh: .whl_ff (zstandard, moderngl, glcontext wheels) and .gl (the EGL
# debs); run (nvidia-h200), carry [".whl_ff", ".gl"]: bash bench/device/first_compiles_ab.sh   (ROUNDS=5 default)
cd "$(dirname "$0")/../.."
ROUNDS=${ROUNDS:-5}
ROOT=$PWD
OUTDIR=${OUT:-/tmp/first_compiles_out}
mkdir -p "$OUTDIR"
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl_ff/*.whl || exit 1
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
probe="import moderngl; moderngl.create_context(standalone=True, backend='egl', require=430)"
PYTHONPATH=/tmp/site python3 -c "$probe" 2>/dev/null || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export NUMBA_CACHE_DIR=/tmp/numba_cache PYTHONPATH=/tmp/site:$ROOT
python3 bench/tile_scene.py samples/donut.ply --splats 1000000 --out /tmp/s.ply || exit 1
mkdir -p /tmp/root && python3 -m cli.main encode /tmp/s.ply /tmp/root/scene -q || exit 1
python3 bench/warm_compile_ab.py --scene /tmp/root/scene --rounds "$ROUNDS" --frames-after 0 --cache nvidia \
    --toggle=--no-warm-first --json "$OUTDIR/warm_first_ab.json" | tee "$OUTDIR/warm_first_ab.log"
for m in cold warmed; do __GL_SHADER_DISK_CACHE_PATH=$(mktemp -d) python3 bench/probe_warm_compile.py --mode $m \
    --json "$OUTDIR/probe_$m.json" > "$OUTDIR/probe_$m.log" 2>&1
  python3 -c "import json; j = json.load(open('$OUTDIR/probe_$m.json')); print('$m', 'total ms', \
j['main_compile_wall_total_ms'], 'fetch ms', j['main_compile_wall_ms']['fetch'], 'warmer', j.get('warmer_ms'))"
done
