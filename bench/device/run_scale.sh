#!/bin/bash
# GPU machine (16 cores, CPU only) driver for the Dask scaling of issue 16 (device `run` tool), from the repo root,
# carrying .whl (bench/device_wheels.sh: Dask and its pure-Python needs, zstandard).
# Usage: [LOD_MERGE=auto,grid] bash bench/device/run_scale.sh SPLATS WORKERS [NAME]
#   e.g. run_scale.sh 16000000 16,8,4,1 scale_16m ; run_scale.sh 60000000 16,8,4 scale_60m
# The scene is written once under /tmp/bs and kept (--keep), so a second call on the still-warm machine reuses it.
set -u
# Installed once per machine (a second call on the warm machine would print a warning per package).
[ -d /tmp/site/distributed ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT" /tmp/bs
splats=${1:?splats} workers=${2:?workers} name=${3:-scale}
nproc; free -g | head -2; df -h /tmp | tail -1
lscpu | grep -E "^(Model name|Socket|Core|Thread|NUMA node\(s\)|CPU\(s\)|L3)" || grep -m1 "model name" /proc/cpuinfo
python3 bench/bench_scale.py --splats "$splats" --workers "$workers" --generator synthetic \
  --lod-merge "${LOD_MERGE:-}" --memory-per-worker 3GB --scenes /tmp/bs --keep --json "$OUT/$name.json" 2>&1 | tee "$OUT/$name.log" | tail -40
# (the log under $OUT comes back even when the 10-minute limit cuts the run: `tail` alone then prints nothing)
python3 bench/plot_scale.py "$OUT/$name.json" "$OUT/$name.png" 2>&1 | tail -3
