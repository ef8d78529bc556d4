#!/bin/bash
# Same-run fly-through A/B at 6M on the GPU machine: this tree's client against an older one (.oldr16), alternated,
# two passes each, on a scene the OLD encoder writes (a newer format may not be readable by the old client).
# Make the old tree here, then run with the run tool (carry [".whl", ".gl", ".oldr16"]; command: bash .oldr16/ab.sh):
#   rm -rf .oldr16 && mkdir .oldr16 && git archive <old commit> bench cli client_gl splatstream server | tar -x -C .oldr16
#   rm -rf .oldr16/bench/results .oldr16/bench/device .oldr16/bench/peers   (3 MB left)
#   cp bench/device/ab6m_vs_old.sh .oldr16/ab.sh
# Used for r17 (BENCHMARKS.md, "Today's code on the GPU machine (r17)": old = fb97426, r16's client). JSONs in $OUT/ab6m.
set -u
[ -d /tmp/site/distributed ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba_cache
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"])'
python3 -c "$probe" 2>/dev/null || export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
python3 -c "$probe" || exit 1
s=/tmp/ab6m; mkdir -p $s $OUT/ab6m
[ -f $s/s.ply ] || python3 bench/tile_scene.py samples/donut.ply --splats 6000000 --out $s/s.ply > /dev/null || exit 1
rm -rf $s/scene; (cd .oldr16 && PYTHONPATH=/tmp/site:$PWD python3 -m cli encode $s/s.ply $s/scene --workers 16 -q) || exit 1
for pass in 1 2; do
  for v in new old; do
    if [ $v = old ]; then (cd .oldr16 && PYTHONPATH=/tmp/site:$PWD python3 bench/bench_flythrough.py --scene $s/scene --ply $s/s.ply --max-splats 3000000 --breakdown --json $OUT/ab6m/${v}_$pass.json > $s/fly_$v.log 2>&1 || tail -5 $s/fly_$v.log)
    else python3 bench/bench_flythrough.py --scene $s/scene --ply $s/s.ply --max-splats 3000000 --breakdown --json $OUT/ab6m/${v}_$pass.json > $s/fly_$v.log 2>&1 || tail -5 $s/fly_$v.log; fi
    python3 -c "import json,sys; d=json.load(open(sys.argv[1]))['streaming']; print(sys.argv[1].split('/')[-1], {k: d.get(k) for k in ('frames','median_ms','p99_ms','update_ms_median','update_ms_p99','select_ms_median','select_ms_p99')})" $OUT/ab6m/${v}_$pass.json
  done
done
