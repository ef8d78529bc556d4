#!/bin/bash
# GPU-machine driver for the city-scale run of issue 38 (device `run` tool: the single-GPU 16-core kind or the two-GPU 32-core one), from the repo
# root, carrying .whl (bench/device_wheels.sh: Dask and its needs, plus the client's wheels) and .gl (GL loaders).
# Usage: bash bench/device/run_city.sh make-encode SPLATS   then   bash bench/device/run_city.sh stream
#        bash bench/device/run_city.sh sizes 1000000,6000000,60000000   (each size made, encoded, streamed: the
#        series of first frame and selection time against scene size; results under $OUT/size_N/; SIZE_PASSES=3:
#        three fly-throughs a size;
#        WARM_AB_ROUNDS=N: the shader warmer's first-frame A/B a size)
#   make-encode: the scene (bench/tile_scene.py: copies of the bundled donut, SH0, seed 0) and `encode --workers N`
#                (N: CITY_WORKERS, else the machine's cores, nproc) with the encoder's
#                defaults (medium, pages over 1,024 tiles), timed as bench_scale.py times it
#                (wall, summed PSS of the process tree, the largest process, phases)
#   stream:      the encoded scene served on loopback: the first frame (bench_first_frame.py, twice: cold and warm
#                shader cache), the manifest bytes before it (bench_pages.py --first-frame), and the fly-through
#                (bench_flythrough.py, 3M splat budget), and the first frame with the shader caches off, the sort
#                passes' programs shared and per pass; FLY_ONLY=1: the fly-through only; FLY_ARGS: more of its
#                options, FLY_NAME: its JSON's name under $OUT (default flythrough); FIRST_FRAME_ARGS: more
#                bench_first_frame.py options for the sizes' first frames (e.g. --probe-first-clear)
# The scene stays under /tmp/city while the machine is warm, so the second call must follow the first at once.
set -u
[ -d /tmp/site/distributed ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
# numba and llvmlite for the compiled selection (the `fast` extra): their wheels unpacked, packed as one zstd tar
# (43 MB; 63 MB as wheels) and split in two (.nb1/, .nb2/: `split -b 20000000 -d`), carried by two calls in a row
# (the working tree and the carry make at most 64 MiB a call); the parts wait in /tmp/nbparts while the machine is warm
mkdir -p /tmp/nbparts
for d in .nb1 .nb2; do [ -d $d ] && cp $d/* /tmp/nbparts/; done
if [ ! -d /tmp/site/numba ] && ls /tmp/nbparts/nbpart.00 /tmp/nbparts/nbpart.01 /tmp/nbparts/nbpart.02 >/dev/null 2>&1; then
  cat /tmp/nbparts/nbpart.* > /tmp/nb.tar.zst
  [ "$(sha256sum /tmp/nb.tar.zst | cut -c1-64)" = "$(cat /tmp/nbparts/sha256)" ] || { echo "numba parts: checksum differs"; exit 1; }
  python3 -c "import sys, tarfile, zstandard; tarfile.open(fileobj=zstandard.ZstdDecompressor().stream_reader(open(sys.argv[1], 'rb')), mode='r|').extractall('/tmp/site')" /tmp/nb.tar.zst || exit 1
fi
export NUMBA_CACHE_DIR=/tmp/numba_cache
python3 -c "import numpy, numba; print('numpy', numpy.__version__, 'numba', numba.__version__)" 2>&1 | tail -1
OUT=${OUT:-/tmp/out}
W=/tmp/city
mkdir -p "$OUT" $W
# encode workers: the machine's cores unless CITY_WORKERS says (250M: 198 s on 32, 316 s on 16 with the scene's 70 s
# before it, so make-encode fits one 600 s call on the single-GPU 16-core kind too)
WORKERS=${CITY_WORKERS:-$(nproc)}
what=${1:?make-encode, stream or sizes}
gl_setup() {
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"])'
  python3 -c "$probe" 2>/dev/null || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  python3 -c "$probe" || exit 1
}
fly_summary() {
  python3 -c "import json,sys; d=json.load(open(sys.argv[1]))['streaming']; print({k: d.get(k) for k in \
    ('frames','median_ms','p99_ms','update_ms_median','update_ms_p99','select_ms_median','select_ms_p99', \
     'frame_call_waited_ms_p99','others_cpu_in_p99_frames_ms','growth_frames','converged_after_path_s')}, \
    {k: json.load(open(sys.argv[1])).get(k) for k in ('compiled_selection','decode_jobs','decode_batch', \
     'decode_workers_moving','sort_pass_programs')})" "$1"
}
if [ "$what" = sizes ]; then
  gl_setup
  nproc; free -g | head -2
  for splats in $(echo "${2:?sizes}" | tr , ' '); do
    d=$OUT/size_$splats; s=/tmp/sizes/$splats; mkdir -p "$d" "$s"
    start=$(date +%s)
    python3 bench/tile_scene.py samples/donut.ply --splats "$splats" --out $s/s.ply > /dev/null || exit 1
    python3 -m cli encode $s/s.ply $s/scene --workers "$WORKERS" -q || exit 1
    echo "$splats: made and encoded in $(( $(date +%s) - start )) s"
    python3 bench/bench_pages.py --first-frame $s/scene --runs 5 2>&1 | tail -3 > "$d/first_frame_nogl.txt"
    for run in cold warm; do
      python3 bench/bench_first_frame.py --scene $s/scene ${FIRST_FRAME_ARGS:-} --json "$d/first_frame_$run.json" 2>&1 | tail -3
    done
    # WARM_AB_ROUNDS=N: the shader warmer's A/B on this scene (bench/warm_compile_ab.py: N rounds of the first frame
    # with and without it, each cold on a fresh NVIDIA shader cache and then warm)
    [ -n "${WARM_AB_ROUNDS:-}" ] && python3 bench/warm_compile_ab.py --scene $s/scene --rounds "$WARM_AB_ROUNDS" \
      --cache nvidia --json "$d/warm_ab.json" 2>&1 | tail -12
    # SIZE_PASSES=N: N fly-throughs of each size (flythrough.json, then fly_2.json ...), to tell a change from the
    # spread between passes; FLY_AB_ARGS: every even pass with those bench_flythrough.py options (fly_2_ab.json ...),
    # an A/B alternated within one scene
    for pass in $(seq 1 "${SIZE_PASSES:-1}"); do
      f=flythrough; [ "$pass" -gt 1 ] && f=fly_$pass
      extra=""; if [ -n "${FLY_AB_ARGS:-}" ] && [ $((pass % 2)) = 0 ]; then extra=$FLY_AB_ARGS; f=${f}_ab; fi
      python3 bench/bench_flythrough.py --scene $s/scene --ply $s/s.ply --max-splats 3000000 --breakdown $extra \
        --json "$d/$f.json" > $s/fly.log 2>&1 || tail -20 $s/fly.log
      fly_summary "$d/$f.json"
    done
    rm -rf "$s"
  done
fi
if [ "$what" = make-encode ]; then
  splats=${2:?splats}
  nproc; free -g | head -2; df -h /tmp | tail -1
  start=$(date +%s)
  # A scene already made (a first call that ran out of time in the encode) is kept: the same command again encodes
  # it, so make-encode splits into two calls where one 600 s call is not enough.
  if [ ! -f $W/s.ply ]; then
    python3 bench/tile_scene.py samples/donut.ply --splats "$splats" --out $W/s.part.ply || exit 1
    mv $W/s.part.ply $W/s.ply
  fi
  echo "scene written in $(( $(date +%s) - start )) s: $(du -h $W/s.ply | cut -f1)"
  rm -rf $W/scene
  echo "encode workers: $WORKERS"
  python3 - "$W/s.ply" "$W/scene" "$OUT/encode.json" "$WORKERS" <<'EOF'
import json, pathlib, sys
sys.path.insert(0, "bench")
from bench_scale import run_encode
r = run_encode(pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]),
               ["--workers", sys.argv[4], "--memory-per-worker", "6GB"])
print(json.dumps(r, indent=1))
pathlib.Path(sys.argv[3]).write_text(json.dumps(r, indent=1))
EOF
  python3 -m cli info $W/scene 2>&1 | head -30 | tee "$OUT/info.txt"
  ls $W/scene/data | wc -l
  ls -la $W/scene/manifest.msgpack
fi
if [ "$what" = stream ]; then
  gl_setup
  [ -n "${FLY_ONLY:-}" ] || python3 bench/bench_pages.py --first-frame $W/scene --runs 5 2>&1 | tail -6 | tee "$OUT/first_frame_nogl.txt"
  [ -n "${FLY_ONLY:-}" ] || for run in cold warm; do
    python3 bench/bench_first_frame.py --scene $W/scene --json "$OUT/first_frame_$run.json" 2>&1 | tail -4
  done
  # the first frame with the drivers' shader caches off (every compile cold), the sorts' passes sharing their
  # programs (the default) and each pass its own (--sort-pass-programs): programs_compiled, compile_ms, first_frame_s
  [ -n "${FLY_ONLY:-}" ] || for v in shared perpass; do
    a=""; [ $v = perpass ] && a=--sort-pass-programs
    __GL_SHADER_DISK_CACHE=0 MESA_SHADER_CACHE_DISABLE=true python3 bench/bench_first_frame.py --scene $W/scene $a \
      --json "$OUT/first_frame_nocache_$v.json" 2>&1 | tail -1
  done
  # FLY_ARGS: more bench_flythrough.py options (an A/B: FLY_ARGS="--drain-ms 0" FLY_NAME=fly_drain0)
  fly=${FLY_NAME:-flythrough}
  python3 bench/bench_flythrough.py --scene $W/scene --ply $W/s.ply --max-splats 3000000 --breakdown ${FLY_ARGS:-} \
    --json "$OUT/$fly.json" > $W/fly.log 2>&1 || tail -20 $W/fly.log
  fly_summary "$OUT/$fly.json"
fi
