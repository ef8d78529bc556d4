#!/bin/bash
# GPU-machine driver for the streaming client's benchmarks (device `run` tool), from the repo root, carrying:
#   .gl           GL loader .debs (libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2, amd64)
#   .whl          cp312 wheels: moderngl glcontext zstandard msgpack aiohttp (+ its deps) platformdirs
#   .bench_carry  tools/make_scene.py and data/real/* (copies of ../shared) so make_scene.py runs there
# Usage: bash bench/device/run_client.sh [stream|first|levels|fly|flyab|oracle|all]   (results under $OUT)
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 SPLATSTREAM_SHARED=$PWD/.bench_carry
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"], c.info["GL_VERSION"])'
if ! python3 -c "$probe"; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  python3 -c "$probe" || exit 1
fi
what=${1:-all}
W=/tmp/stream-work
mkdir -p $W
lscpu | grep -E "^(Model name|Socket|Core|Thread|CPU\(s\))" || true
if [ "$what" = stream ] || [ "$what" = first ] || [ "$what" = all ]; then
  # first frames on loopback (a first run compiles the driver's shaders: run once before, as a user's second start)
  python3 bench/bench_stream.py --splats 1000000 --links loopback --cameras overview --modes need \
    --workdir $W --out /tmp/warmup > /dev/null 2>&1
  python3 bench/bench_stream.py --splats 1000000,6000000 --links loopback --modes need --frame-every 4 \
    --workdir $W --out "$OUT/stream_loopback" 2>&1 | tail -8
  if [ "$what" = first ]; then rm -rf "$OUT/stream_loopback"/*/; exit 0; fi
  # SH bands by need (default shares and two others) against every band: bytes (the link does not change them)
  # and PSNR against the all-bands frame and the full-detail render
  python3 bench/bench_stream.py --splats 1000000,6000000 --links 100:0 \
    --modes need,all,share0.99-0.97-0.95,share0.95-0.85-0.7 --frame-every 8 --workdir $W \
    --out "$OUT/stream_bands" 2>&1 | tail -20
  # at most 8 files come back: keep stream.json, stream.md and stream.png of each run, not the per-run folders
  for d in stream_loopback stream_bands; do
    find "$OUT/$d" -mindepth 1 -maxdepth 1 -type d -exec rm -rf {} +
    rm -f "$OUT/$d"/full_*.png
  done
fi
if [ "$what" = levels ]; then
  # coarse to fine through every level against skipping to the cut, at 20 Mbit/s + 40 ms
  python3 bench/bench_stream.py --splats 1000000,6000000 --links 20:40 --modes need,skip --frame-every 2 \
    --workdir $W --out "$OUT/levels" 2>&1 | tail -12
  find "$OUT/levels" -mindepth 1 -maxdepth 1 -type d -exec rm -rf {} +
fi
if [ "$what" = flyab ] || [ "$what" = levels ]; then
  # the frame loop's switch interval: 0.5 ms (the client's) against CPython's 5 ms, with the per-step split
  [ -d $W/root/s6000000 ] || python3 bench/bench_stream.py --splats 6000000 --links loopback --cameras overview \
    --modes need --workdir $W --out /tmp/prep > /dev/null 2>&1
  for si in 0.0005 0.005; do
    python3 bench/bench_flythrough.py --scene $W/root/s6000000 --ply $W/s6000000.ply --breakdown \
      --switch-interval $si --json "$OUT/fly_si$si.json" > $W/fly_$si.log 2>&1
    python3 -c "import json,sys; d=json.load(open(sys.argv[1]))['streaming']; print(sys.argv[2], {k: d[k] for k in \
      ('frames','median_ms','p99_ms','p99_ms_with_uploads','p99_ms_without_uploads','update_ms_p99')})" \
      "$OUT/fly_si$si.json" "$si" || tail -5 $W/fly_$si.log
  done
fi
if [ "$what" = oracle ]; then
  # how many SH-band bytes any per-tile band rule could save, and at what PSNR (bench/probe_band_oracle.py)
  for n in 1000000 6000000; do
    python3 -c "import sys; sys.path.insert(0, 'bench'); from bench_stream import make_scene, encode; \
encode(make_scene($n, 0, '$W'), '$W/root/s$n', 'medium')" || exit 1
    for cam in overview close-up; do
      python3 bench/probe_band_oracle.py --scene $W/root/s$n --ply $W/s$n.ply --camera $cam --full-detail \
        --json "$OUT/band_oracle_${n}_$cam.json" 2>&1 | grep "tiles,\|renders\|shares\|'target': 0.3\|Error" | cut -c1-210
    done
  done
fi
if [ "$what" = fly ] || [ "$what" = all ]; then
  python3 bench/bench_flythrough.py --scene $W/root/s6000000 --ply $W/s6000000.ply --json "$OUT/flythrough.json" \
    2>&1 | tail -30
fi
