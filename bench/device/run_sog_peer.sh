#!/bin/bash
# The SOG peer point of s1m_jitter (issue 15), encoded on the GPU machine: splat-transform's SOG encode of a 1M scene
# whose SH rows are all distinct spends its time in the SH k-means (64k centroids of 45 values); on this project's
# 2-core machine it ran over 73 minutes (-g cpu). There, splat-transform runs its k-means on the GPU through WebGPU
# (Dawn on Vulkan), at the tool's defaults (10 SH iterations). From the repo root (device `run` tool), carrying:
#   .gl        GL loader .debs (libvulkan1 among them, amd64)
#   .stcarry   node.xz (this machine's /usr/bin/node, xz), st_nm.tar.xz (node_modules of
#              @playcanvas/splat-transform 3.7.0 without source maps, debug builds and other platforms' Dawn),
#              shared/tools/make_scene.py + shared/data/real/* (the scene's sources), whl/ (msgpack zstandard
#              platformdirs, for bench/transport/make_jitter.py)
# The scene is rebuilt there (make_scene.py --splats 1000000 --seed 0, then make_jitter.py) and its SHA-256 printed, to
# check it against the local copy before its SOG is used. Usage: bash bench/device/run_sog_peer.sh
# Writes $OUT/s1m_jitter.sog and $OUT/sog_peer.log; decode it with `splat-transform -w s1m_jitter.sog dec.ply` anywhere.
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/sog_peer.log") 2>&1
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
c=$PWD/.stcarry
mkdir -p /tmp/node/bin /tmp/st
python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], 'wb'))" \
  "$c/node.xz" /tmp/node/bin/node || exit 1
chmod +x /tmp/node/bin/node
tar -xJf "$c/st_nm.tar.xz" -C /tmp/st || exit 1
st=(/tmp/node/bin/node /tmp/st/node_modules/@playcanvas/splat-transform/bin/cli.mjs)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "$c"/whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
/tmp/node/bin/node --version
"${st[@]}" --version
nproc
python3 "$c/shared/tools/make_scene.py" --splats 1000000 --seed 0 --out /tmp/s1m.ply || exit 1
python3 bench/transport/make_jitter.py /tmp/s1m.ply /tmp/s1m_jitter.ply || exit 1
sha256sum /tmp/s1m_jitter.ply
"${st[@]}" --list-gpus
SECONDS=0
if ! "${st[@]}" -w /tmp/s1m_jitter.ply "$OUT/s1m_jitter.sog"; then
  echo "GPU encode failed; CPU with one worker per core"
  SECONDS=0
  "${st[@]}" -w -g cpu --max-workers "$(nproc)" /tmp/s1m_jitter.ply "$OUT/s1m_jitter.sog" || exit 1
fi
echo "encoded sog: $(stat -c %s "$OUT/s1m_jitter.sog") bytes in $SECONDS s"
