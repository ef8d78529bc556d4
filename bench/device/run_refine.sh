#!/usr/bin/env bash
# The device run of bench/device/refine_lod_levels.py (issue 31, phase 1: the merged LOD levels refined against
# gsplat renders of the full-detail scene). Run from the repository root on the GPU machine, carrying the scene
# sources (a folder laid out as the shared data/real) and gsplat's wheel (bench/device_wheels.sh refine: .whl_refine/):
#
#   bash bench/device/run_refine.sh .refine_in [refine_lod_levels.py options]
#
# The lead's two runs (the tracked files are ~36 MiB of the 64 MiB that travel; bench/device/refine_inputs.sh and
# bench/device_wheels.sh refine make the folders): `BUDGET_S=360 bash bench/device/run_refine.sh .refine_in`, carry
# [".whl_refine", ".refine_in"], timeout 450; then `BUDGET_S=200 bash bench/device/run_refine.sh .refine_flowers`,
# carry [".whl_refine", ".refine_flowers"], timeout 290 (at once: a warm machine keeps gsplat's build).
#
# Installs gsplat (--no-deps: the image has torch, jaxtyping, rich, ninja, nvcc), JIT-builds its CUDA extension while
# the trees are built on the CPUs (refine_lod_levels.py does both), then refines every scene found in the folder
# within BUDGET_S seconds of wall clock (default 480) and writes refine_<variant>_<k>.npz + refine_report.json to
# $OUT (at most 8 files of 16 MiB). The tiles kept are those today's default encode's streamed cut drew
# (bench/results/lod_vs_peers_px28, tracked in the repository).
set -euo pipefail
cd "$(dirname "$0")/../.."
IN=${1:?usage: run_refine.sh INPUT_DIR [options]}
shift
OUT=${OUT:-/tmp/refine_out}
SITE=${SITE:-/tmp/site}
mkdir -p "$OUT" "$SITE"
start=$(date +%s)
whl=
for f in .whl_refine/gsplat-*.whl .whl/gsplat-*.whl; do [ -f "$f" ] && whl=$f && break; done
[ -n "$whl" ] || { echo "no gsplat wheel in .whl_refine/ or .whl/ (bench/device_wheels.sh refine)"; exit 1; }
python3 -m pip install -q --no-index --no-deps --target "$SITE" "$whl"
export PYTHONPATH=$SITE:$PWD
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-12}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
command -v nvcc || ls /usr/local/cuda/bin/nvcc || echo "no nvcc: gsplat cannot JIT-compile"
# One process only imports gsplat's extension: its import deletes the build lock and, with no .so yet, the build
# directory (gsplat/cuda/_backend.py), so a second importer would break the first one's build. The refinement
# imports it (the JIT build, ~1 min) while its worker processes build the trees.
budget=$(( ${BUDGET_S:-480} - ($(date +%s) - start) ))
status=0
python3 bench/device/refine_lod_levels.py --inputs "$IN" --out "$OUT" --drawn bench/results/lod_vs_peers_px28 \
  --budget-s "$budget" "$@" || status=$?
ls -la "$OUT"
echo "total $(( $(date +%s) - start )) s"
exit $status
