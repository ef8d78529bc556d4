#!/usr/bin/env bash
# Issue 31's encode bound as a user sees it: the default encode's wall clock on 2 cores (and on 1), 60c1b51 (the
# encoder the issue was filed against: "old") against main before this branch ("base") and this tree ("new"), on
# the quiet 16-core GPU machine: `taskset`-like pinning (bench/encode_wall.py --cores) to cores 0,1 and to core 0;
# the 1M scene (make_scene.py --splats 1000000 --seed 0, SH3) at medium, biker at medium, low and very-high; the
# three versions' order turned each round. Wall, CPU (the encode and its forked children), ru_maxrss and the tree's
# peak PSS per run, appended to $OUT/encode_wall.json, then a table of medians; base's and new's output digests
# must agree.
#
# The device call carries the working tree but not git's history, so the older trees travel in .enc_carry/:
#   old/splatstream       git archive 60c1b51 splatstream
#   base/splatstream, base/cli   git archive BASE_COMMIT splatstream cli (encproc31: main 7909191)
#   tools/make_scene.py   ../shared/tools/make_scene.py
#   data/real/biker.compressed.ply   (the biker cases)
#   data/real/fruit_drops_sh3.ply lod_tile_sh3_zero_rest.ply donut_sh0_no_normals.ply winter_fountain.splat
#                         (make_scene.py's sources, for the 1M scene)
# (about 15 MB). The lead's /work/main/.enc_carry holds old/, base/ (= 7909191's files), tools/, biker and donut,
# but not the other three sources (make_scene.py fails without them). In the root of the tree to measure:
#
#   rm -rf .enc_carry && cp -r /work/main/.enc_carry .enc_carry    # or make it with the git archive lines above
#   (cd /work/shared/data/real && cp fruit_drops_sh3.ply lod_tile_sh3_zero_rest.ply winter_fountain.splat \
#     "$OLDPWD/.enc_carry/data/real/")
#   # device run (nvidia-h200), carry [".whl", ".enc_carry"], timeout_s 600:
#   ONLY_1M=1 ROUNDS=2 bash bench/device/encode_wall_2core.sh
#
# Where .git does travel and .enc_carry/old or base is missing, they are made with git archive here. ROUNDS (3),
# CORESETS ("0,1 0"), ONLY_1M=1 / ONLY_BIKER=1 narrow it. ONLY_1M=1 ROUNDS=2 is 12 encodes of the 1M scene: about
# 350-420 s there by enc2core31's run (old 13-14 s, base 47-50 s, new 33-46 s on its cores), under the call's 600 s;
# the whole default run does not fit one call (biker adds about 60 s a round). CORESETS takes taskset's CPU lists,
# ranges too: CORESETS="0-7 0-15" ONLY_1M=1 ROUNDS=2 measures 8 and 16 cores (new forks at most 2 children,
# forked.MAX_PAYLOAD_PROCESSES, whatever the cores). VERSIONS="old new" leaves base out (this tree against 60c1b51).
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
CARRY=${CARRY:-$ROOT/.enc_carry}
ROUNDS=${ROUNDS:-3}
CORESETS=${CORESETS:-"0,1 0"}
OUT=${OUT:-/tmp/encode_wall_out}
SCRATCH=${SCRATCH:-/tmp/ew}
mkdir -p "$OUT" "$SCRATCH"
if [ -d .whl ]; then
  [ -d /tmp/site/zstandard ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1
versions=(${VERSIONS:-old base new})
for v in old base; do
  [[ " ${versions[*]} " == *" $v "* ]] || continue
  if [ ! -d "$CARRY/$v/splatstream" ]; then
    commit=60c1b51; [ $v = base ] && commit=${BASE_COMMIT:-main}
    mkdir -p "$CARRY/$v" && git archive "$commit" splatstream cli | tar -x -C "$CARRY/$v" \
      || { echo ".enc_carry/$v missing and no git history to make it (see the header)"; exit 1; }
  fi
done
nproc; python3 -c "import numpy, zstandard; print('numpy', numpy.__version__, 'zstandard', zstandard.__version__)" || exit 1
S1M=$SCRATCH/s1m.ply
if [ "${ONLY_BIKER:-0}" != 1 ] && [ ! -f $S1M ]; then
  python3 "$CARRY/tools/make_scene.py" --splats 1000000 --seed 0 --out $S1M || exit 1
fi
BIKER=$CARRY/data/real/biker.compressed.ply
declare -A CODE=([old]="$CARRY/old:splatstream.cli" [base]="$CARRY/base:cli" [new]="$ROOT:cli")
cases=()
[ "${ONLY_BIKER:-0}" = 1 ] || cases+=("$S1M medium")
if [ "${ONLY_1M:-0}" != 1 ]; then
  for p in medium low very-high; do cases+=("$BIKER $p"); done
fi
t0=$SECONDS
for round in $(seq 1 "$ROUNDS"); do
  for cores in $CORESETS; do
    for c in "${cases[@]}"; do
      set -- $c
      k=$(( (round - 1) % ${#versions[@]} ))
      for v in "${versions[@]:$k}" "${versions[@]:0:$k}"; do
        python3 bench/encode_wall.py --label "$v" --code "${CODE[$v]}" --cores "$cores" --tag "round$round" \
          --json "$OUT/encode_wall.json" "$1" --preset "$2" | cut -c1-400
      done
    done
  done
  echo "round $round done at $((SECONDS - t0)) s"
done
python3 - "$OUT/encode_wall.json" <<'EOF'
import collections, json, statistics, sys
rows = [r for r in json.load(open(sys.argv[1])) if r["rc"] == 0]
by = collections.defaultdict(list)
for r in rows:
    by[(r["scene"], r["args"], r["cores"], r["label"])].append(r)
print("scene | args | cores | version | wall s (median) | CPU s | maxrss MB | tree PSS MB | digests")
for key in sorted(by):
    rs = by[key]
    med = lambda k: statistics.median(r[k] for r in rs)
    print(" | ".join(map(str, key)), "|", round(med("wall_s"), 2), "|", round(med("cpu_s"), 2), "|",
          round(med("maxrss_mb")), "|", round(med("tree_pss_peak_mb")), "|", sorted({r["digest"] for r in rs}))
EOF
