#!/usr/bin/env bash
# The first frame of one client on the same 1M scene written as format 1.16 (the default) and as 1.15
# (`encode --no-relative-boxes`), paired on one GPU machine, with the manifest parse timed alone. Carry .whl_ff
# (zstandard, moderngl, glcontext wheels) and .gl (the EGL debs), as for first_frame_ab.sh.
cd "$(dirname "$0")/../.."
ROUNDS=${ROUNDS:-3}
ROOT=$PWD
OUT=${OUT:-/tmp/out}
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl_ff/*.whl || exit 1
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
probe="import moderngl; moderngl.create_context(standalone=True, backend='egl', require=430)"
PYTHONPATH=/tmp/site python3 -c "$probe" 2>/dev/null || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export NUMBA_CACHE_DIR=/tmp/numba_cache PYTHONPATH=/tmp/site:$ROOT
python3 bench/tile_scene.py samples/donut.ply --splats 1000000 --out /tmp/s.ply || exit 1
mkdir -p /tmp/root
python3 -m cli.main encode /tmp/s.ply /tmp/root/f116 -q || exit 1
python3 -m cli.main encode /tmp/s.ply /tmp/root/f115 --no-relative-boxes -q || exit 1
python3 - <<'PY'
import time
from splatstream.format.manifest import parse_manifest
for v in ("f116", "f115", "f116", "f115"):
    raw = open(f"/tmp/root/{v}/manifest.msgpack", "rb").read()
    t = time.perf_counter(); [parse_manifest(raw) for _ in range(20)]
    print(v, len(raw), "B, parse", round((time.perf_counter() - t) / 20 * 1e3, 2), "ms")
PY
for r in $(seq "$ROUNDS"); do for v in f116 f115; do
  python3 bench/bench_first_frame.py --scene /tmp/root/$v --json $OUT/ff_${v}_$r.json > /tmp/ff_${v}_$r.log 2>&1
  python3 -c "import json;j=json.load(open('$OUT/ff_${v}_$r.json'));print('$v',$r,round(j['first_frame_s'],4),[(e[1][:16],round(e[0],1),round(e[2],1)) for e in j['timeline'] if e[1].startswith(('manifest','gl early','pool','compile','render'))])" || tail -3 /tmp/ff_${v}_$r.log
done; done
