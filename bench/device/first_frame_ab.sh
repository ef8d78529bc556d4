#!/usr/bin/env bash
# The first frame (bench/bench_first_frame.py: warm, with its steps timed), this tree against older ones, paired on
# one machine (BENCHMARKS.md, r23). Here, before the device call, export each older tree beside this one (ignored,
# carried by name) and a wheel folder with zstandard, moderngl and glcontext:
#
#   mkdir .ab_before && git archive OLD splatstream cli client_gl server bench/bench_first_frame.py \
#       bench/bench_stream.py pyproject.toml | tar -x -C .ab_before          # and .ab_REV for more trees (VARIANTS)
#   # run (nvidia-h200), carry [".whl_ff", ".gl", ".ab_before", ...]: bash bench/device/first_frame_ab.sh
cd "$(dirname "$0")/../.."
VARIANTS=${VARIANTS:-new old}
ROUNDS=${ROUNDS:-3}
ROOT=$PWD
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl_ff/*.whl || exit 1
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
probe="import moderngl; moderngl.create_context(standalone=True, backend='egl', require=430)"
PYTHONPATH=/tmp/site python3 -c "$probe" 2>/dev/null || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export NUMBA_CACHE_DIR=/tmp/numba_cache
PYTHONPATH=/tmp/site:$ROOT python3 bench/tile_scene.py samples/donut.ply --splats 1000000 --out /tmp/s.ply || exit 1
mkdir -p /tmp/root && PYTHONPATH=/tmp/site:$ROOT python3 -m cli.main encode /tmp/s.ply /tmp/root/scene -q || exit 1
for r in $(seq "$ROUNDS"); do for v in $VARIANTS; do
  D=$ROOT; [ $v = old ] && D=$ROOT/.ab_before; [ -d $ROOT/.ab_$v ] && D=$ROOT/.ab_$v
  (cd $D && PYTHONPATH=/tmp/site:$D python3 bench/bench_first_frame.py --scene /tmp/root/scene --json /tmp/ff_${v}_$r.json > /tmp/ff_${v}_$r.log 2>&1)
  python3 -c "import json;j=json.load(open('/tmp/ff_${v}_$r.json'));print('$v',$r,round(j['first_frame_s'],4),[(e[1][:16],round(e[2],1)) for e in j['timeline'] if e[1] in ('engine.update','pool','decode (thread)','render','engine.take_arrived')])" || tail -3 /tmp/ff_${v}_$r.log
done; done
