#!/usr/bin/env bash
# Preset exploration: `splatstream eval` of the presets and candidate variants on one scene (kept encoded; the
# encoder writes the fields1 transport coding itself), the table as OUT_DIR/NAME.md.
#
#   bench/transport/eval_variants.sh INPUT NAME OUT_DIR [PEER_ARGS_FILE]
#   env: VIEWS (8), SIZE (512x512), PRESETS (very-high,high,medium,medium-low,medium-low-9bit,low-plus,low,very-low), VARIANTS (space-separated
#        NAME:PRESET,ATTR=FORMAT,... as for eval --variants)
set -euo pipefail
here=$(cd "$(dirname "$0")/../.." && pwd)
in=$1; name=$2; out=$3; peers=${4:-}
py=${PYTHON:-$here/.venv/bin/python}
mkdir -p "$out"
compare=()
if [ -n "$peers" ] && [ -s "$peers" ]; then mapfile -t compare < "$peers"; fi
(cd "$here" && "$py" -m cli eval "$in" --views "${VIEWS:-8}" --size "${SIZE:-512x512}" \
    --presets "${PRESETS:-very-high,high,medium,medium-low,medium-low-9bit,low-plus,low,very-low}" --encoded "$out/$name.encoded" \
    ${VARIANTS:+--variants $VARIANTS} ${compare[@]:+--compare "${compare[@]}"} --json "$out/$name.json" \
    --markdown "$out/$name.md" -q)
