# vhdec4 device A/B: bench/decode_quiet.py of main (.oldvh: a `git archive` of main's commit) and of this tree
# (branch vhdec4, merged or checked out), alternated in one lease on the same pinned cores, JSONs to $OUT.
#
# Run from the repository root of the tree under test (main with vhdec4 merged, or the branch): copy this script
# into .oldvh, then with the run tool:
#   carry: [".whl", ".oldvh"]     command: bash .oldvh/vhdec4_ab.sh
# .whl holds zstandard-*.whl (cp312; as /work/main/.whl does); .oldvh is made here, before the run, from main's commit
# before the merge (the base; vhdec4 was branched from a3259bd, and main's decode code is the same at 292580e):
#   rm -rf .oldvh && mkdir .oldvh && git archive <base commit> splatstream client_gl cli bench tests | tar -x -C .oldvh
#   cp bench/device/decode_ab_old_new.sh .oldvh/vhdec4_ab.sh   (and drop .oldvh/bench/results and all of .oldvh/tests/data but guitar and winter_fountain: 61 of the 64 MiB)
# vhdec5 (very-high's payloads above 256 KB join their zstd blocks): guitar and winter_fountain have no such payload;
# keep tests/data/real/fruit_drops_sh3.ply (1.2 MB) in .oldvh too and run with SCENES=fruit_drops_sh3 PRESETS=very-high.
# dec32 (fields1's packed texels stored two at a time, the lossy presets): .oldvh from this branch's base, bf3f94e
# (`git archive bf3f94e splatstream client_gl cli bench tests | tar -x -C .oldvh`), with this branch's
# bench/decode_quiet.py copied into .oldvh/bench/ and tests/data/real's guitar, winter_fountain and fruit_drops_sh3
# kept; then four calls of about 5-7 minutes each (ROUNDS=1: new, old), the preset sets swapped:
#   SCENES=guitar,winter_fountain,fruit_drops_sh3 PRESETS=medium,medium-low,low-plus-9bit,very-high ROUNDS=1
#   SCENES=guitar,winter_fountain,fruit_drops_sh3 PRESETS=low,very-low,medium-12bit,medium ROUNDS=1
# (medium in both: four of its pairs). The bundled scenes are SH0 small tiles and one SH3 tile; the 1M SH3 LOD tree
# this change helps most (decode_quiet --scenes s1m=PATH) needs make_scene.py's source scenes, not in the repo.
# If a call nears the run tool's 600 s, run it as two calls with ROUNDS=1 (the order then: new, old) or PRESETS fewer.
# Knobs (environment; defaults are the device's): PY (python3), CORES (2-5), ROUNDS (2), RUNS (3), JOBS (8),
# SCENES (guitar,winter_fountain), PRESETS (very-high,medium,high). About 4-5 minutes a round on the H200 host.
# Tested on the 2-core VM with PY=<venv python> CORES=1 ROUNDS=1 RUNS=1 JOBS=2 SCENES=guitar PRESETS=very-high.
set -e
PY=${PY:-python3}
CORES=${CORES:-2-5}
ROUNDS=${ROUNDS:-2}
OUT=${OUT:-/tmp/vhdec4_ab_out}
mkdir -p "$OUT"
export OUT
SITE=/tmp/site
if ! $PY -c "import zstandard" 2>/dev/null; then
  mkdir -p $SITE && $PY -m pip install -q --no-index --no-deps --target $SITE .whl/zstandard-*.whl
fi
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/numba_cache}
test -f .oldvh/bench/decode_quiet.py || { echo "no .oldvh/bench/decode_quiet.py: make .oldvh first (see the top)"; exit 2; }
nproc; PYTHONPATH=$SITE $PY -c "import numba, zstandard, numpy; print('numba', numba.__version__, 'zstandard', zstandard.__version__, 'numpy', numpy.__version__)"
A="--scenes ${SCENES:-guitar,winter_fountain} --presets ${PRESETS:-very-high,medium,high} --jobs ${JOBS:-8} --runs ${RUNS:-3} --no-fit --kernels numba"
for r in $(seq 1 "$ROUNDS"); do
  # the order swapped each round (new first in odd rounds), so a drift in the host's speed falls on both alike
  for side in $( [ $((r % 2)) = 1 ] && echo "new old" || echo "old new"); do
    if [ $side = new ]; then
      PYTHONPATH=$SITE:$PWD taskset -c "$CORES" $PY bench/decode_quiet.py $A --json "$OUT/new_$r.json" > /dev/null 2>"$OUT/new_$r.err" || tail -5 "$OUT/new_$r.err"
    else
      (cd .oldvh && PYTHONPATH=$SITE:$PWD taskset -c "$CORES" $PY bench/decode_quiet.py $A --json "$OUT/old_$r.json" > /dev/null 2>"$OUT/old_$r.err") || tail -5 "$OUT/old_$r.err"
    fi
    echo "round $r $side done $(date -u +%H:%M:%S) load $(cut -d' ' -f1-3 /proc/loadavg)"
  done
done
$PY - <<'PY'
import glob, json, os
rows = {}
for f in sorted(glob.glob(os.path.join(os.environ["OUT"], "*.json"))):
    d = json.load(open(f))
    side = os.path.basename(f).split("_")[0]
    for c in d["cases"]:
        rows.setdefault((c["scene"], c["preset"]), {}).setdefault(side, []).append(c["numba"]["verified"])
    print(os.path.basename(f), {p: (v["numba"]["verified"], v["numba"]["slowest_scene_verified"])
                                for p, v in d["by_preset"].items()})
print("verified median M splats/s, old -> new (each round), new/old of the medians' median:")
for (scene, preset), v in sorted(rows.items()):
    old, new = v.get("old", []), v.get("new", [])
    ratio = (sorted(new)[len(new) // 2] / sorted(old)[len(old) // 2]) if old and new else float("nan")
    print(f"  {scene:16s} {preset:10s} {old} -> {new}  x{ratio:.3f}")
PY
