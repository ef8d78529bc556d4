#!/usr/bin/env bash
# Produce peer encodings of a scene with PlayCanvas splat-transform (npm @playcanvas/splat-transform), and
# decode each back to a standard PLY with the same tool, so `splatstream eval --compare` can read them:
#
#   bench/eval_peers.sh INPUT.ply OUT_DIR
#
# Writes OUT_DIR/<stem>.compressed.ply, .spz, .sog (the encodings whose sizes count) and OUT_DIR/<stem>.<fmt>.dec.ply
# (decoded by splat-transform), and prints the matching `--compare LABEL=DECODED@ENCODED` arguments on stdout
# (one per line). The tool is installed under $PEERS_PREFIX (default /tmp/peers-VERSION) on first use; node >= 18.
# SOG is encoded on the CPU (-g cpu: no WebGPU here), with the tool's default 10 SH k-means iterations (1M splats:
# ~7 minutes on 2 cores; on an SH scene of 500k splats over 30 CPU minutes). Existing outputs newer than the input
# are reused unless PEERS_FORCE=1; an encoding present without its decoded PLY (a .sog made on the GPU machine by
# bench/device/run_sog_peer.sh, copied to OUT_DIR/<stem>.sog) is decoded and used as it is.
# Env: SPLAT_TRANSFORM=the tool's CLI (e.g. .ci/node/node_modules/.bin/splat-transform; else npm installs it),
# PEER_FORMATS="compressed.ply spz sog" (the formats encoded; one missing from it is still used when its encoding is
# already in OUT_DIR).
set -euo pipefail
in=${1:?usage: eval_peers.sh INPUT.ply OUT_DIR}
out=${2:?usage: eval_peers.sh INPUT.ply OUT_DIR}
version=${SPLAT_TRANSFORM_VERSION:-3.7.0}  # the newest on npm when measured (npm view @playcanvas/splat-transform)
prefix=${PEERS_PREFIX:-/tmp/peers-$version}
st=${SPLAT_TRANSFORM:-$prefix/node_modules/.bin/splat-transform}
if [ ! -x "$st" ]; then
  mkdir -p "$prefix"
  (cd "$prefix" && npm install --silent "@playcanvas/splat-transform@$version" >&2)
fi
mkdir -p "$out"
stem=$(basename "$in")
stem=${stem%.ply}; stem=${stem%.splat}; stem=${stem%.sog}
echo "splat-transform $("$st" --version 2>&1 | tail -1) ($st) on $in" >&2
formats=" ${PEER_FORMATS:-compressed.ply spz sog} "
for fmt in compressed.ply spz sog; do
  enc="$out/$stem.$fmt"
  dec="$out/$stem.$fmt.dec.ply"
  if [ "${PEERS_FORCE:-0}" != 1 ] && [ -s "$dec" ] && [ "$enc" -nt "$in" ] && [ "$dec" -nt "$enc" ]; then
    echo "reusing $enc ($(stat -c %s "$enc") bytes; PEERS_FORCE=1 re-encodes)" >&2
    echo "st-$fmt=$dec@$enc"
    continue
  fi
  if [ -s "$enc" ] && [ ! -s "$dec" ] && { [ "$formats" = "${formats/ $fmt /}" ] || [ "$enc" -nt "$in" ]; }; then
    echo "decoding the given $enc ($(stat -c %s "$enc") bytes)" >&2
    "$st" -q -w "$enc" "$dec" >&2
    echo "st-$fmt=$dec@$enc"
    continue
  fi
  if [ "$formats" = "${formats/ $fmt /}" ]; then
    echo "$fmt: not encoded (PEER_FORMATS=${formats# })" >&2
    continue
  fi
  extra=()
  [ "$fmt" = sog ] && extra=(-g cpu)
  start=$(date +%s.%N)
  "$st" -q -w "${extra[@]}" "$in" "$enc" >&2
  end=$(date +%s.%N)
  "$st" -q -w "$enc" "$dec" >&2
  printf 'encoded %s: %d bytes in %.2f s\n' "$fmt" "$(stat -c %s "$enc")" "$(echo "$end - $start" | bc)" >&2
  echo "st-$fmt=$dec@$enc"
done
