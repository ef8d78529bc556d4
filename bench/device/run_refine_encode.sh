#!/usr/bin/env bash
# The product's `splatstream encode --lod-refine` (issue 31, phase 2) on the GPU machine, for every lod_vs_peers
# scene in a carried input folder (bench/device/refine_inputs.sh: .refine_statues/, .refine_others/, .refine_flowers/,
# or .refine_in/ = the first two), so that the lead
# measures the real streamed cut of the product's encodes here with bench/lod_vs_peers.py. Run from the repository
# root on the GPU machine:
#
#   bash bench/device/refine_inputs.sh split                             # .refine_statues/ .refine_others/ here
#   bash bench/device/run_refine_encode.sh .refine_statues    # carry [".whl_refine", ".refine_statues"], timeout 600
#   bash bench/device/run_refine_encode.sh .refine_others     # carry [".whl_refine", ".refine_others"], timeout 600
#   BUDGET_S=380 bash bench/device/run_refine_encode.sh .refine_flowers   # carry [".whl_refine", ".refine_flowers"],
#                                                                         # timeout 420
#   SKIP_TESTS=1 ...: the torch tests not run after the encodes (a second run in the same lease)
#   ONLY=biker,guitar bash bench/device/run_refine_encode.sh .refine_others   # a re-run of scenes BUDGET_S cut off
#
# (.whl_refine/ from `bash bench/device_wheels.sh refine`: gsplat and zstandard, 12.1 MB. The tracked files of main
# with this branch are ~37.4 MB, so .refine_in whole (17.5 MB) would make 63.9 of the 64 MiB that travel: the split
# folders, 7.9 and 9.5 MB, leave room; .refine_in works where the tree is smaller.) Per scene, as lod_vs_peers
# encodes it: `python3 -m cli convert SRC full.ply`, then `python3 -m cli encode full.ply OUT/SCENE --lod-refine` (the default
# preset and tree, the refinement's defaults); JOBS scenes at once (default 4: one's CPU work, the tree and the
# payloads, beside another's GPU work), the largest first, after gsplat's CUDA extension is built once alone (its
# import deletes the build lock, so two first importers would break each other's build: ~95 s, kept while the
# machine stays warm). Then the torch tests (tests/test_lod_refine_torch.py as a script: gsplat on CUDA against the
# numpy reference, the refiner end to end). Writes to $OUT: scenes.tar.partNN (one tar of every encoded scene
# directory, split at 15 MiB: ~3 parts for the 11 scenes of .refine_in, ~3 for flowers), refine_encode.log (every
# encode's output: per level the validation PSNR of the level as built and of each variant, what was kept,
# seconds) and summary.json (per scene the manifest's lod.refinement).
#
# Locally, into a --our-scene-dir for bench/lod_vs_peers.py (which reuses a scene directory holding a manifest):
#   mkdir -p /tmp/refined && for d in RUN1_FILES_AT RUN2_FILES_AT RUN3_FILES_AT; do
#     cat "$d"/scenes.tar.part* | tar -xf - -C /tmp/refined; done          # each run's parts are one tar
#   .venv/bin/pip install -e .    # main's editable install predates refine_gpu (only `encode --lod-refine` needs it)
#   .venv/bin/python bench/lod_vs_peers.py --skip-peers --peers-from bench/results/lod_vs_peers_viewscale \
#       --cache-dir /tmp/lvp50/cache --our-scene-dir /tmp/refined --out-dir bench/results/lod_vs_peers_refined
set -uo pipefail
cd "$(dirname "$0")/../.."
IN=${1:?usage: run_refine_encode.sh INPUT_DIR}
OUT=${OUT:-/tmp/refine_encode_out}
SITE=${SITE:-/tmp/site}
WORK=${WORK:-/tmp/refine_encode}
JOBS=${JOBS:-4}
# Every encode ends by this many seconds after the start (SIGTERM: the encoder removes its partial output), so the tar
# of the finished ones always comes back within the command's timeout: BUDGET_S = the timeout less ~40 s.
BUDGET_S=${BUDGET_S:-560}
mkdir -p "$OUT" "$SITE" "$WORK/full" "$WORK/scenes"
start=$(date +%s)
DEADLINE=$((start + BUDGET_S))
ls .whl_refine/gsplat-*.whl .whl_refine/zstandard-*.whl >/dev/null \
  || { echo "gsplat and zstandard wheels missing in .whl_refine/ (bash bench/device_wheels.sh refine)"; exit 1; }
python3 -m pip install -q --no-index --no-deps --target "$SITE" .whl_refine/*.whl || exit 1
export PYTHONPATH=$SITE:$PWD
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-12}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
python3 -c "import torch, gsplat; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'gsplat', gsplat.__version__)"
# gsplat's CUDA extension, built (or found) once, alone, before any encode imports it.
python3 -c "
import sys
from refine_gpu.levels import missing
lack = missing()
print('lod-refine ready' if lack is None else 'lod-refine: ' + lack)
sys.exit(lack is not None)" || exit 1
echo "extension ready after $(( $(date +%s) - start )) s"

# The scenes lod_vs_peers knows whose source is in the folder, the largest source first.
mapfile -t SCENES < <(python3 - "$IN" <<'EOF'
import os, sys
sys.path.insert(0, "bench")
import lod_vs_peers as lvp
root = sys.argv[1]
def size(p):
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(os.path.dirname(p)) for f in fs) \
        if p.endswith(".json") else os.path.getsize(p)
only = [n for n in os.environ.get("ONLY", "").split(",") if n]  # ONLY=a,b: those scenes alone (a re-run)
found = [(size(os.path.join(root, s.source)), n) for n, s in lvp.SCENES.items()
         if os.path.exists(os.path.join(root, s.source)) and (not only or n in only)]
for _, n in sorted(found, reverse=True):
    print(n, lvp.SCENES[n].source)
EOF
)
echo "scenes: ${#SCENES[@]}"

encode_one() {  # NAME SOURCE: convert, encode --lod-refine, a line of seconds; its output in WORK/NAME.log
  local name=$1 src=$2 t0 t1 t2 rc left
  t0=$(date +%s)
  left=$((DEADLINE - t0))
  [ "$left" -gt 30 ] || { echo "$name: rc 124, not started (BUDGET_S spent)"; return 124; }
  python3 -m cli convert "$IN/$src" "$WORK/full/$name.ply" -q || { echo "$name: convert failed"; return 1; }
  t1=$(date +%s)
  # not -q: the per-level lines (lod-refine: level ...) go to the log; the progress lines do not
  left=$((DEADLINE - $(date +%s)))
  timeout "$left" python3 -m cli encode "$WORK/full/$name.ply" "$WORK/scenes/$name" --lod-refine 2>&1 \
    | grep -v "^encode: "
  rc=${PIPESTATUS[0]}
  t2=$(date +%s)
  if [ "$rc" -eq 0 ]; then  # what bench/lod_vs_peers.py records of an encode it made itself
    python3 -c "import json, sys; json.dump({'command': 'splatstream encode full.ply OUT --lod-refine',
    'seconds': $((t2 - t1)), 'machine': 'H200, bench/device/run_refine_encode.sh'}, open(sys.argv[1], 'w'), indent=1)" \
      "$WORK/scenes/$name/lod_vs_peers_encode.json"
  fi
  echo "$name: rc $rc, convert $((t1 - t0)) s, encode --lod-refine $((t2 - t1)) s"
  rm -f "$WORK/full/$name.ply"
  return "$rc"
}
export -f encode_one
export IN WORK DEADLINE
# The first JOBS start 6 s apart: each encode imports gsplat's built extension (torch re-checks it with a no-op ninja
# run under a lock file that gsplat's import removes), so simultaneous first imports are avoided where it is cheap.
i=0
for line in "${SCENES[@]}"; do
  echo "$(( i < JOBS ? i * 6 : 0 )) $line"
  i=$((i + 1))
done | xargs -P "$JOBS" -L 1 bash -c 'sleep "$0"; encode_one "$1" "$2" > "$WORK/$1.log" 2>&1; tail -1 "$WORK/$1.log"'

# What each scene kept (from the manifests) and the logs, in the order of the scenes.
for line in "${SCENES[@]}"; do
  name=${line%% *}
  echo "=== $name"; cat "$WORK/$name.log"
done > "$OUT/refine_encode.log"
grep -h "^===\|lod-refine: level\|: rc " "$OUT/refine_encode.log" | sed "s/^lod-refine: /  /"
python3 - "$WORK/scenes" "$OUT/summary.json" <<'EOF'
import json, os, sys
from splatstream.format.manifest import parse_manifest
root, out = sys.argv[1:]
summary = {}
for name in sorted(os.listdir(root)):
    path = os.path.join(root, name, "manifest.msgpack")
    if not os.path.exists(path):
        continue
    m = parse_manifest(open(path, "rb").read())
    r = m.lod.refinement
    summary[name] = {"version": list(m.version), "splats": m.splats, "bytes_on_disk": m.bytes_on_disk,
                     "refinement": r.to_dict() if r else None}
    kept = " ".join(f"{lv.level}:{lv.kept}" for lv in r.levels) if r else "NOT REFINED"
    print(f"{name}: {m.splats:,} splats, {m.bytes_on_disk / 2**20:.1f} MiB, kept {kept}")
json.dump(summary, open(out, "w"), indent=1)
EOF
tar -cf - -C "$WORK/scenes" . | split -b 15M -d -a 2 - "$OUT/scenes.tar.part"
echo "encodes done after $(( $(date +%s) - start )) s"

# The torch tests on the GPU (gsplat on CUDA against the numpy reference, the refiner end to end), as a script: the
# image has no pytest.
left=$((DEADLINE + 30 - $(date +%s)))
if [ -n "${SKIP_TESTS:-}" ]; then
  echo "SKIP_TESTS: tests/test_lod_refine_torch.py not run"
elif [ "$left" -gt 10 ]; then
  timeout "$left" python3 tests/test_lod_refine_torch.py 2>&1 | tail -8
else
  echo "no time left for tests/test_lod_refine_torch.py"
fi
ls -la "$OUT"
echo "total $(( $(date +%s) - start )) s"
