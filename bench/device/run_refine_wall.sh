#!/usr/bin/env bash
# `encode --lod-refine cpu`'s wall clock on a many-core host, this tree's refine_cpu against an older one's (issue 31,
# branch refinewall31: the fit's 16 gradient rows, the backward from the stored transmittance; again for pairwalk31:
# the pair lists in one walk, OLD_COMMIT 1f03469). Before the device call, here, put the older refine_cpu beside the
# tree (untracked and not ignored, so it travels):
#
#   mkdir -p .refine_old && git archive OLD_COMMIT refine_cpu | tar -x -C .refine_old
#   # run (nvidia-h200, 16 cores), carry [".whl_refine"], timeout 600:
#   bash bench/device/run_refine_wall.sh
#
# Per version (old, new, then old, new again: the first of each compiles numba's kernels into its own __pycache__, the
# second is the one to read), `/usr/bin/time` of `python3 -m cli.main encode SCENE OUT --lod-refine cpu -q` run from
# /tmp (so that `-m`'s first sys.path entry, the working directory, does not shadow PYTHONPATH's refine_cpu), then each
# output directory's digest (the bytes must not depend on the version where the sums' order is the same, nor on the
# threads: THREADS="16 8" runs the new version at each). SCENE defaults to samples/donut.ply (45,624 splats, SH0).
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
SCENE=${SCENE:-$ROOT/samples/donut.ply}
SITE=${SITE:-/tmp/site}
THREADS=${THREADS:-}
[ -d .refine_old/refine_cpu ] || { echo ".refine_old/refine_cpu missing (see the header)"; exit 1; }
if [ -d .whl_refine ]; then
  python3 -m pip install -q --no-index --no-deps --target "$SITE" .whl_refine/*.whl || exit 1
fi
digest() { (cd "$1" && find . -type f | LC_ALL=C sort | xargs sha256sum | sha256sum | cut -c1-16); }
run() {  # label pythonpath [env...]
  local label=$1 path=$2; shift 2
  rm -rf "/tmp/rw_$label"
  (cd /tmp && env "$@" PYTHONPATH="$path" /usr/bin/time -f "$label: %e s wall, %U s user, %S s sys, %M KB peak" \
    python3 -c "import sys, runpy, refine_cpu.raster as r; print('$label', r.__file__, 'rows', r.GRADIENT_ROWS, flush=True);
sys.argv = ['cli.main', 'encode', '$SCENE', '/tmp/rw_$label', '-q', '--lod-refine', 'cpu']; runpy.run_module('cli.main', run_name='__main__')")
  echo "$label digest $(digest "/tmp/rw_$label")"
}
nproc
for round in 1 2; do
  run "old$round" "$SITE:$ROOT/.refine_old:$ROOT"
  run "new$round" "$SITE:$ROOT"
done
for t in $THREADS; do
  run "new_t$t" "$SITE:$ROOT" NUMBA_NUM_THREADS="$t"
done
