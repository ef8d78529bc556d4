#!/usr/bin/env bash
# Rate-distortion numbers of the presets (and of PlayCanvas splat-transform as a peer) on the benchmark scenes.
#
#   bench/run_eval.sh [OUT_DIR]        (default bench/out; env: VIEWS=8 SIZE=512x512 RENDERER=auto PEERS=1
#                                       ATTRIBUTION=low,medium (ATTRIBUTION= for none) PRESETS=all of them
#                                       SCENES="fruit donut s1m" (SCENES=real: every real scene, below)
#                                       VARIANTS="NAME:PRESET,ATTR=FORMAT ..." extra encodes, see eval --help
#                                       SPLAT_TRANSFORM=path of the splat-transform CLI, PEER_FORMATS: see
#                                       bench/eval_peers.sh)
#
# Real scenes (SCENES=real), every file of /work/shared/data/real/: fruit (fruit_drops_sh3.ply, SH3), lodtile
# (lod_tile_sh3_zero_rest.ply, SH3), flowers (the finest level of flowers_lod, SH2, 542k splats), donut
# (donut_sh0_no_normals.ply), biker (biker.compressed.ply), guitar (guitar.compressed.ply), winter_fountain
# (winter_fountain.splat) and the seven statue scans statue-<name> (statues/<name>.sog), all SH0. flowers and the
# statues are streamed SOG: they are converted to PLY once ($OUT/<scene>.ply, `splatstream convert`), so that our
# encoder and the peers read the same decoded values. Synthetic scenes: a 1M-splat make_scene.py scene (python3
# /work/shared/tools/make_scene.py --splats 1000000 --seed 0 --out $OUT/s1m.ply) and s1m_jitter, the same with
# every SH row made distinct (bench/transport/make_jitter.py: make_scene copies a few real scenes, so s1m has only
# 4,517 distinct SH rows and any SH codebook of that size is exact). Per scene it writes <scene>.md (the table),
# <scene>.json (everything, cameras included) and <scene>.png (rate vs PSNR).
# Peers need node (bench/eval_peers.sh: splat-transform from $SPLAT_TRANSFORM, else installed with npm); PEERS=0
# skips them. SOG is encoded with -g cpu, which on an SH scene spends minutes to hours in the SH k-means: flowers'
# SOG is left out here (PEER_FORMATS for flowers is "compressed.ply spz" unless set) and encoded on the GPU machine
# (bench/device/run_sog_peer.sh); put its .sog at $OUT/peers/flowers/flowers.sog and it is decoded and compared.
# RENDERER=auto draws with the GL client when it can (encoded scenes from their own textures, as the client shows
# them; agrees with the reference to ~0.01 dB), else with the numpy reference 3DGS rasterizer (RENDERER=ref forces
# it: exact forward pass, ~25 s/view at 1M).
# Held-out scenes, outside ../shared/data, measured only when named (SCENES=playbot; not part of SCENES=real), their
# sources under $SPLATSTREAM_HELDOUT (default ../heldout): playbot (PlayCanvas engine examples/assets/splats/playbot,
# CC-BY-4.0, Stephane Agullo, https://superspl.at/view?id=ee6d8bc4; 500,000 splats, SH2, a streamed SOG: its finest
# level converted like flowers; its SOG peer is made on the GPU machine like flowers', PEER_FORMATS as flowers').
# playcanvas-logo (PlayCanvas engine examples/assets/splats/playcanvas-logo, engine MIT; 307,128 splats, SH0, a SOG
# version 1 meta.json + WebP planes, converted like the statues; SH0, so its SOG peer is made here with -g cpu).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
out=${1:-$here/bench/out}
py=${PYTHON:-$here/.venv/bin/python}
views=${VIEWS:-8}
size=${SIZE:-512x512}
renderer=${RENDERER:-auto}
attribution=${ATTRIBUTION-low,medium}
shared=${SPLATSTREAM_SHARED:-$here/../shared}
heldout=${SPLATSTREAM_HELDOUT:-$here/../heldout}
mkdir -p "$out"

REAL="fruit lodtile flowers donut biker guitar winter_fountain statue-angel statue-angel-kneeling
statue-angel-with-candlestick statue-massa statue-narcissus statue-st-peter statue-trumpet"

converted() {  # a streamed SOG as one PLY (the finest level), made once
  if [ ! -f "$out/$1.ply" ]; then
    [ -f "$2" ] || { echo "missing $2" >&2; exit 2; }
    (cd "$here" && "$py" -m cli convert "$2" "$out/$1.part.ply" -q >&2)
    mv "$out/$1.part.ply" "$out/$1.ply"
  fi
  echo "$out/$1.ply"
}

scene_path() {
  case "$1" in
    fruit) echo "$shared/data/real/fruit_drops_sh3.ply" ;;
    donut) echo "$shared/data/real/donut_sh0_no_normals.ply" ;;
    biker) echo "$shared/data/real/biker.compressed.ply" ;;
    lodtile) echo "$shared/data/real/lod_tile_sh3_zero_rest.ply" ;;
    guitar) echo "$shared/data/real/guitar.compressed.ply" ;;
    winter_fountain) echo "$shared/data/real/winter_fountain.splat" ;;
    flowers) converted flowers "$shared/data/real/flowers_lod/lod-meta.json" ;;
    statue-*) converted "$1" "$shared/data/real/statues/${1#statue-}.sog" ;;
    playbot) converted playbot "$heldout/playbot/lod-meta.json" ;;
    playcanvas-logo) converted playcanvas-logo "$heldout/playcanvas-logo/meta.json" ;;
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

scenes=${SCENES:-fruit donut s1m}
[ "$scenes" = real ] && scenes=$REAL
for scene in $scenes; do
  input=$(scene_path "$scene")
  compare=()
  if [ "${PEERS:-1}" = 1 ] && { [ -n "${SPLAT_TRANSFORM:-}" ] || command -v npm >/dev/null; }; then
    formats=${PEER_FORMATS:-}
    [ -z "$formats" ] && { [ "$scene" = flowers ] || [ "$scene" = playbot ]; } && formats="compressed.ply spz"
    mapfile -t compare < <(PEER_FORMATS=$formats "$here/bench/eval_peers.sh" "$input" "$out/peers/$scene")
  fi
  echo "== $scene: $input" >&2
  (cd "$here" && "$py" -m cli eval "$input" ${PRESETS:+--presets "$PRESETS"} --views "$views" --size "$size" --renderer "$renderer" \
      --attribution "$attribution" ${VARIANTS:+--variants $VARIANTS} --json "$out/$scene.json" --plot "$out/$scene.png" --markdown "$out/$scene.md" \
      ${compare[@]:+--compare "${compare[@]}"})
done
