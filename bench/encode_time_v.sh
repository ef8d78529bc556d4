#!/usr/bin/env bash
# Encode time of presets against `medium` under /usr/bin/time -v (issue 32: every preset within 2x of medium's,
# LOD tree on), optionally against another checkout's code on the same load.
#
#   bench/encode_time_v.sh SCENE LOG ROUNDS PRESET ... (env OLD=path of another checkout, OLD_PRESET=its preset)
#
# Each round runs, one process at a time: medium, then every PRESET with this checkout's code, then OLD_PRESET
# (default: the first PRESET) with OLD's code where OLD is set. One line per run in LOG: user and system CPU seconds,
# wall time, peak RSS, output bytes (du -sb: directory entries included, so equal scenes can differ by 4,096) and
# the load average. CPU seconds are the figure to compare on a shared machine (BENCHMARKS.md, "Encoder").
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
py=${PYTHON:-$here/.venv/bin/python}
scene=$(realpath "$1"); log=$2; rounds=$3; shift 3
old_preset=${OLD_PRESET:-$1}
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
for r in $(seq 1 "$rounds"); do
  specs=("new:medium"); for p in "$@"; do specs+=("new:$p"); done
  [ -n "${OLD:-}" ] && specs+=("old:$old_preset")
  for spec in "${specs[@]}"; do
    code=${spec%%:*}; p=${spec#*:}; root=$here; [ "$code" = old ] && root=$OLD
    rm -rf "$tmp/out"
    (cd "$root" && /usr/bin/time -v -o "$tmp/time.txt" env PYTHONPATH="$root" "$py" -m cli encode "$scene" "$tmp/out" \
      --preset "$p" -q)
    field() { grep "$1" "$tmp/time.txt" | awk '{print $NF}'; }
    echo "round=$r code=$code preset=$p user=$(field 'User time') sys=$(field 'System time') wall=$(field 'Elapsed')" \
      "maxrss_kb=$(field 'Maximum resident') bytes=$(du -sb "$tmp/out" | cut -f1) load=$(cut -d' ' -f1 /proc/loadavg)" \
      "date=$(date -u +%FT%T)" | tee -a "$log"
  done
done
