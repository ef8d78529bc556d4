#!/bin/bash
# SOG peer points of the SH scenes (issues 15 and 32), encoded on the GPU machine. splat-transform's SOG encode of an
# SH scene spends its time in the SH k-means (64k centroids over every SH row): on this project's 2-core machine
# (-g cpu) flowers (542k splats, SH2) ran over 30 CPU minutes and s1m_jitter over 73 minutes without finishing. On
# the GPU machine splat-transform runs its k-means through WebGPU (Dawn on Vulkan) when a hardware adapter is
# listed, else on the CPU with one worker per core (-g cpu --max-workers $(nproc)); the tool's defaults otherwise
# (10 SH iterations). That machine has no internet and no node: node, splat-transform and the scenes travel in
# .stcarry, and no Python is needed there.
#
# Two steps:
#  1. Here, once, in the repository root: `bash bench/device/run_sog_peer.sh pack` (SOG_SCENES="flowers" by
#     default; also fruit, lodtile, which encode on the CPU here in under a minute each). It writes .stcarry/
#     (ignored through .git/info/exclude), 39.6 MB with flowers:
#       node.xz        this machine's node (v20, x86-64), stripped, xz with the x86 filter (21.09 MB; needs only
#                      glibc and libstdc++)
#       st_nm.tar.xz   what splat-transform 3.7.0's CLI loads (5.3 MB; from $ST_NODE_MODULES, default
#                      .ci/node/node_modules; see below)
#       debs/          libvulkan1 (amd64), the Vulkan loader Dawn needs on the GPU machine
#       scenes/        flowers: the finest level of flowers_lod (0_0..0_3, 13.10 MB; the other levels stay here);
#                      fruit, lodtile: their PLYs
#       sha256.txt     SHA-256 of each scene's input PLY as splat-transform writes it here (flowers: its 4 level-0
#                      SOG chunks merged; it equals bench/run_eval.sh's `splatstream convert` of lod-meta.json to
#                      2.4e-7 in rotations and opacity logits, exactly elsewhere)
#     A device call also sends the repository's working tree: 27.65 MB of tracked files after merging main on
#     2026-11-28, so with .stcarry for flowers (39.54 MB) about 81 KB OVER the 64 MiB (67,108,864 bytes) a call may
#     carry. pack prints the sum. Carry nothing else (.gl is not needed: the Vulkan loader is in .stcarry/debs).
#     Re-encoding flowers' WebP losslessly at effort 6 saves under 1 %; what fits is two calls (SPLIT=1, below).
#     fruit and lodtile alone fit one.
#     SPLIT=1 (with pack) moves the scenes into .stcarry_scenes/ so that each call fits (flowers: 54.6 and 41.3 MB
#     with the tree): a first call carrying [".stcarry", ".gl"] runs `LIST_ONLY=1 bash bench/device/run_sog_peer.sh`
#     (keeps a copy of .stcarry in /tmp/stcarry and lists the adapters), and a second one right after it, while the
#     machine is still held (30 s idle), carries [".stcarry_scenes", ".gl"] and runs the script plainly: the device
#     tool removes ignored paths a call does not name, so the tools come back from /tmp/stcarry. Done so on
#     nvidia-h200 on 2026-11-28: Dawn listed "[0] NVIDIA H200" (with .gl: NVIDIA's Vulkan ICD, libGLX_nvidia,
#     needs libglvnd's libraries, else "vkCreateInstance: Found no drivers") and flowers' SOG took 5 s (k-means
#     1.8 s on the GPU).
#     playbot (issue 32's own scene, held out: PlayCanvas engine examples/assets/splats/playbot, CC-BY-4.0, Stephane
#     Agullo; 500,000 splats, SH2) is outside ../shared/data, named only: `SPLIT=1 SOG_SCENES=playbot bash
#     bench/device/run_sog_peer.sh pack` takes its finest level (one SOG, 0_0, 8.2 MB) from $SPLATSTREAM_HELDOUT
#     (default ../heldout). Packed so on 2026-11-30 with a 38.69 MB tree: the first call (.stcarry, 26 MB, and .gl,
#     0.38 MB) sends about 65.5 MB of the 67.1, the second (.stcarry_scenes and .gl) about 47.6 MB; one call would
#     be about 6.6 MB over.
#  2. One device call (the `run` tool), carrying [".stcarry"]: `bash bench/device/run_sog_peer.sh`, timeout_s 600.
#     It prints the SHA-256 of each input PLY beside the one made here, the adapters Dawn lists, and writes
#     $OUT/<stem>.sog and $OUT/sog_peer.log.
# Then here: copy each <stem>.sog to bench/out/real/peers/<scene>/<stem>.sog and rerun
# `SCENES=<scene> bash bench/run_eval.sh bench/out/real` (bench/eval_peers.sh decodes a given .sog and compares it).
#
# Local test of step 2 (no GPU here: -g cpu on the cores here): `SOG_SCENES=fruit bash bench/device/run_sog_peer.sh
# pack && OUT=/tmp/sogout bash bench/device/run_sog_peer.sh`.
set -u
here=$(cd "$(dirname "$0")/../.." && pwd)
c=$here/.stcarry
stem_of() {
  case "$1" in
    flowers) echo flowers ;; fruit) echo fruit_drops_sh3 ;; lodtile) echo lod_tile_sh3_zero_rest ;;
    playbot) echo playbot ;;
    *) echo "unknown scene $1 (flowers, fruit, lodtile, playbot)" >&2; return 2 ;;
  esac
}
input_ply() {  # SCENE DIR OUT.ply NODE_CMD...: the scene's input PLY from its files under DIR
  local scene=$1 dir=$2 out=$3
  shift 3
  if [ "$scene" = flowers ]; then
    "$@" -q -w "$dir"/flowers_lod/0_*/meta.json "$out"
  elif [ "$scene" = playbot ]; then  # its finest level is one SOG (0_0), all 500,000 splats
    "$@" -q -w "$dir"/playbot/0_0/meta.json "$out"
  else
    cp "$dir/$(stem_of "$scene").ply" "$out"
  fi
}

if [ "${1:-}" = pack ]; then
  set -euo pipefail
  real=${SPLATSTREAM_SHARED:-$here/../shared}/data/real
  heldout=${SPLATSTREAM_HELDOUT:-$here/../heldout}  # scenes outside ../shared/data (playbot), named only
  nm=${ST_NODE_MODULES:-$here/.ci/node/node_modules}
  [ -d "$nm/@playcanvas/splat-transform" ] || { echo "no splat-transform under $nm (ST_NODE_MODULES)"; exit 1; }
  exclude=$(git -C "$here" rev-parse --git-path info/exclude)
  grep -qxF '/.stcarry*/' "$exclude" 2>/dev/null || echo '/.stcarry*/' >> "$exclude"  # .stcarry and .stcarry.part
  rm -rf "$c.part" && mkdir -p "$c.part/scenes"
  tmp=$(mktemp -d)
  cp "$(command -v node)" "$tmp/node" && strip "$tmp/node"
  xz -T1 --x86 --lzma2=preset=9e,dict=128MiB -c "$tmp/node" > "$c.part/node.xz"  # BCJ: 21.09 MB, not 21.85
  mkdir -p "$c.part/debs"  # the Vulkan loader Dawn needs there (the device README's apt-get download, amd64)
  o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
  mkdir -p /tmp/amd64/partial
  (apt-get "${o[@]}" update -qq >/dev/null 2>&1; cd "$c.part/debs" && apt-get "${o[@]}" download -qq libvulkan1) \
    || echo "apt-get download libvulkan1 failed: carry .gl with it, or the GPU encode falls back to the CPU"
  # what the CLI loads: its bundle (dist/cli.mjs, worker.mjs, the SPZ chunk it imports, which bundles @adobe/spz,
  # lib/webp.wasm), webgpu's Linux x86-64 Dawn (symbols stripped), debug, ms; not the library builds (index.mjs /
  # .cjs and their SPZ chunk), @adobe/spz, source maps, TypeScript types or other platforms' Dawn. Checked here: a
  # SOG encode of fruit_drops with -g cpu --max-workers 2 and --list-gpus run from this set.
  # NO_DAWN=1: without webgpu's Dawn (about 4 MB of the carry): the k-means then runs on the CPU there (-g cpu,
  # one worker per core), for a carry that would otherwise be over the limit. Tried with flowers on nvidia-h200-x2
  # (32 cores, 2026-11-28): the CPU k-means had not finished when the call's 600 s ran out, so flowers' SOG point
  # was then still missing; with Dawn it was made in 5 s on the GPU, in two calls (SPLIT=1, above).
  for p in @playcanvas/splat-transform $([ -n "${NO_DAWN:-}" ] || echo webgpu) debug ms; do
    mkdir -p "$tmp/node_modules/$(dirname "$p")"
    cp -r "$nm/$p" "$tmp/node_modules/$p"
  done
  d=$tmp/node_modules/@playcanvas/splat-transform/dist
  spz_cli=$(grep -o "import('./spz-[A-Za-z0-9_-]*\.js')" "$d/cli.mjs" | head -1 | sed "s/.*'\.\/\(.*\)')/\1/")
  find "$d" -maxdepth 1 -name 'spz-*.js' ! -name "$spz_cli" -delete
  rm -f "$d/index.mjs" "$d/index.cjs"
  find "$tmp/node_modules" \( -name '*.map' -o -name '*.d.ts' -o -name '*.d.cts' \) -delete
  if [ -z "${NO_DAWN:-}" ]; then
    find "$tmp/node_modules/webgpu/dist" -type f ! -name 'linux-x64.dawn.node' ! -name '*.js' -delete
    strip --strip-unneeded "$tmp/node_modules/webgpu/dist/linux-x64.dawn.node"
  else  # the CLI imports webgpu at start; without Dawn it gets a module that has no adapter to offer
    mkdir -p "$tmp/node_modules/webgpu"
    printf '%s\n' '{"name": "webgpu", "version": "0.0.0-no-dawn", "type": "module", "main": "index.js"}' \
      > "$tmp/node_modules/webgpu/package.json"
    printf '%s\n' 'export const globals = {};' \
      'export function create() { throw new Error("this carry has no Dawn (NO_DAWN=1): use -g cpu"); }' \
      > "$tmp/node_modules/webgpu/index.js"
  fi
  tar -cf - -C "$tmp" node_modules | xz -T1 -9e > "$c.part/st_nm.tar.xz"
  : > "$c.part/sha256.txt"
  for s in ${SOG_SCENES:-flowers}; do
    stem=$(stem_of "$s")
    if [ "$s" = flowers ]; then
      mkdir -p "$c.part/scenes/flowers_lod"
      cp -r "$real"/flowers_lod/0_* "$c.part/scenes/flowers_lod/"
    elif [ "$s" = playbot ]; then
      mkdir -p "$c.part/scenes/playbot"
      cp -r "$heldout"/playbot/0_0 "$heldout"/playbot/playbot.txt "$c.part/scenes/playbot/"
    else
      cp "$real/$stem.ply" "$c.part/scenes/"
    fi
    chmod -R u+w "$c.part/scenes"
    input_ply "$s" "$c.part/scenes" "$tmp/$stem.ply" "$(command -v node)" "$tmp/node_modules/@playcanvas/splat-transform/bin/cli.mjs"
    echo "$(sha256sum < "$tmp/$stem.ply" | cut -d' ' -f1)  $stem" >> "$c.part/sha256.txt"
  done
  echo "${SOG_SCENES:-flowers}" > "$c.part/scenes.txt"
  rm -rf "$tmp" "$c" "$c"_scenes
  if [ -n "${SPLIT:-}" ]; then
    mkdir -p "$c"_scenes && mv "$c.part/scenes" "$c.part/sha256.txt" "$c.part/scenes.txt" "$c"_scenes/
    du -sh "$c"_scenes
  fi
  mv "$c.part" "$c"
  du -sh "$c" "$c"/*
  # what a device call carrying only .stcarry sends: the tracked and untracked-not-ignored files, and .stcarry
  tree=$(git -C "$here" ls-files -co --exclude-standard -z | (cd "$here" && xargs -0 du -cb 2>/dev/null) \
    | awk '$2 == "total" {s += $1} END {print s}')
  total=$((tree + $(du -sb "$c" | cut -f1)))
  [ -z "${SPLIT:-}" ] || echo "the second call (.stcarry_scenes) sends about $((tree + $(du -sb "$c"_scenes | cut -f1))) bytes"
  echo "a call carrying .stcarry sends about $total bytes (tree $tree); the limit is 67108864 (64 MiB)"
  [ "$total" -le 67108864 ] || echo "OVER the limit: pack fewer scenes (SOG_SCENES) or leave untracked files out"
  exit 0
fi

OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/sog_peer.log") 2>&1
if [ ! -f "$c/node.xz" ] && [ -f /tmp/stcarry/node.xz ]; then c=/tmp/stcarry; fi  # the second call of SPLIT=1
if [ -d /usr/local/nvidia ]; then  # the GPU machine only: it unpacks into /
  for f in "$c"/debs/*.deb "$here"/.gl/*.deb; do [ -f "$f" ] && dpkg -x "$f" /; done
  ldconfig
fi
[ -d /usr/local/nvidia/share/vulkan ] && export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
sc=$c  # where the scenes are: .stcarry, or .stcarry_scenes after pack with SPLIT=1
[ -d "$here/.stcarry_scenes/scenes" ] && sc=$here/.stcarry_scenes
[ -f "$c/node.xz" ] || { echo "no .stcarry: run 'bash bench/device/run_sog_peer.sh pack' here and carry .stcarry"; exit 1; }
w=$(mktemp -d)
mkdir -p "$w/bin" "$w/st"
python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], 'wb'))" \
  "$c/node.xz" "$w/bin/node" || exit 1
chmod +x "$w/bin/node"
tar -xJf "$c/st_nm.tar.xz" -C "$w/st" || exit 1
st=("$w/bin/node" "$w/st/node_modules/@playcanvas/splat-transform/bin/cli.mjs")
echo "node $("$w/bin/node" --version), splat-transform $("${st[@]}" --version 2>&1 | tail -1), $(nproc) cores"
# A hardware adapter listed ("[N] NAME", Dawn's software ones left out) means the WebGPU k-means on it; none (or a
# failed GPU encode) the CPU with one worker per core.
"${st[@]}" --list-gpus > "$w/gpus.txt" 2>&1
cat "$w/gpus.txt"
idx=$(grep -E '^\[[0-9]+\] ' "$w/gpus.txt" | grep -v -i -E 'swiftshader|llvmpipe|software' | head -1 \
  | sed 's/^\[\([0-9]*\)\].*/\1/')
if [ -n "$idx" ]; then gpu=(-g "$idx"); else gpu=(-g cpu --max-workers "$(nproc)"); fi
echo "SOG k-means on: ${gpu[*]}"
if [ -n "${LIST_ONLY:-}" ]; then
  [ "$c" = /tmp/stcarry ] || { rm -rf /tmp/stcarry && cp -r "$c" /tmp/stcarry; }
  rm -rf "$w"; exit 0
fi
status=0
for s in ${SOG_SCENES:-$(cat "$sc/scenes.txt")}; do
  stem=$(stem_of "$s") || { status=2; continue; }
  input_ply "$s" "$sc/scenes" "$w/$stem.ply" "${st[@]}" || { status=1; continue; }
  echo "== $s: input sha256 $(sha256sum < "$w/$stem.ply" | cut -d' ' -f1) (here: $(grep " $stem\$" "$sc/sha256.txt" \
    | cut -d' ' -f1))"
  SECONDS=0
  if ! "${st[@]}" -w "${gpu[@]}" "$w/$stem.ply" "$OUT/$stem.sog"; then
    echo "$s: encode with ${gpu[*]} failed; CPU with one worker per core"
    SECONDS=0
    "${st[@]}" -w -g cpu --max-workers "$(nproc)" "$w/$stem.ply" "$OUT/$stem.sog" || { status=1; continue; }
  fi
  echo "$s: encoded $stem.sog, $(stat -c %s "$OUT/$stem.sog") bytes in $SECONDS s (${gpu[*]})"
done
rm -rf "$w"
exit $status
