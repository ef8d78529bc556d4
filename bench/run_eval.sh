#!/usr/bin/env bash
# Rate-distortion numbers of the presets (and of PlayCanvas splat-transform as a peer) on the benchmark scenes.
#
#   bench/run_eval.sh [OUT_DIR]        (default bench/out; env: VIEWS=8 SIZE=512x512 RENDERER=auto PEERS=1
#                                       ATTRIBUTION=low,medium (ATTRIBUTION= for none) PRESETS=all of them
#                                       SCENES="fruit donut s1m" (also: biker lodtile s1m_jitter)
#                                       VARIANTS="NAME:PRESET,ATTR=FORMAT ..." extra encodes, see eval --help)
#
# Scenes: /work/shared/data/real/fruit_drops_sh3.ply, donut_sh0_no_normals.ply, biker.compressed.ply,
# lod_tile_sh3_zero_rest.ply, a 1M-splat make_scene.py scene (python3 /work/shared/tools/make_scene.py --splats
# 1000000 --seed 0 --out $OUT/s1m.ply) and s1m_jitter, the same with every SH row made distinct
# (bench/transport/make_jitter.py: make_scene copies a few real scenes, so s1m has only 4,517 distinct SH rows and
# any SH codebook of that size is exact). Per scene it writes <scene>.md (the table), <scene>.json (everything,
# cameras included) and <scene>.png (rate vs PSNR).
# Peers need node + npm (bench/eval_peers.sh); PEERS=0 skips them. RENDERER=auto draws with the GL client when it
# can (encoded scenes from their own textures, as the client shows them; agrees with the reference to ~0.01 dB),
# else with the numpy reference 3DGS rasterizer (RENDERER=ref forces it: exact forward pass, ~25 s/view at 1M).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
out=${1:-$here/bench/out}
py=${PYTHON:-$here/.venv/bin/python}
views=${VIEWS:-8}
size=${SIZE:-512x512}
renderer=${RENDERER:-auto}
attribution=${ATTRIBUTION-low,medium}
shared=${SPLATSTREAM_SHARED:-$here/../shared}
mkdir -p "$out"

scene_path() {
  case "$1" in
    fruit) echo "$shared/data/real/fruit_drops_sh3.ply" ;;
    donut) echo "$shared/data/real/donut_sh0_no_normals.ply" ;;
    biker) echo "$shared/data/real/biker.compressed.ply" ;;
    lodtile) echo "$shared/data/real/lod_tile_sh3_zero_rest.ply" ;;
    s1m)
      if [ ! -f "$out/s1m.ply" ]; then
        python3 "$shared/tools/make_scene.py" --splats 1000000 --seed 0 --out "$out/s1m.ply" >&2
      fi
      echo "$out/s1m.ply" ;;
    s1m_jitter)
      if [ ! -f "$out/s1m_jitter.ply" ]; then
        "$py" "$here/bench/transport/make_jitter.py" "$(scene_path s1m)" "$out/s1m_jitter.ply" >&2
      fi
      echo "$out/s1m_jitter.ply" ;;
    *) echo "unknown scene $1" >&2; exit 2 ;;
  esac
}

for scene in ${SCENES:-fruit donut s1m}; do
  input=$(scene_path "$scene")
  compare=()
  if [ "${PEERS:-1}" = 1 ] && command -v npm >/dev/null; then
    mapfile -t compare < <("$here/bench/eval_peers.sh" "$input" "$out/peers/$scene")
  fi
  echo "== $scene: $input" >&2
  (cd "$here" && "$py" -m cli eval "$input" ${PRESETS:+--presets "$PRESETS"} --views "$views" --size "$size" --renderer "$renderer" \
      --attribution "$attribution" ${VARIANTS:+--variants $VARIANTS} --json "$out/$scene.json" --plot "$out/$scene.png" --markdown "$out/$scene.md" \
      ${compare[@]:+--compare "${compare[@]}"})
done
