#!/usr/bin/env bash
# The scene sources bench/device/run_refine.sh reads, copied from the shared data into two ignored folders of the
# repository root (two device runs: the tracked files are ~36 MiB of the 64 MiB that travel):
#   .refine_in/       the 7 statues (.sog), donut, winter_fountain, guitar, biker   (~17.5 MB)
#   .refine_flowers/  flowers_lod/lod-meta.json and its finest level 0_0..0_3       (~13.2 MB; read as `convert` reads
#                     the whole folder: bit-identical to lod_vs_peers' full.ply)
# plus gsplat's wheel: bash bench/device_wheels.sh refine   (.whl_refine/, ~6.5 MB)
set -euo pipefail
cd "$(dirname "$0")/../.."
REAL=${SPLATSTREAM_SHARED:-/work/shared}/data/real
rm -rf .refine_in .refine_flowers
mkdir -p .refine_in/statues .refine_flowers/flowers_lod
cp "$REAL"/statues/*.sog .refine_in/statues/
cp "$REAL"/donut_sh0_no_normals.ply "$REAL"/winter_fountain.splat "$REAL"/guitar.compressed.ply \
  "$REAL"/biker.compressed.ply .refine_in/
cp "$REAL"/flowers_lod/lod-meta.json .refine_flowers/flowers_lod/
cp -r "$REAL"/flowers_lod/0_* .refine_flowers/flowers_lod/
du -sb .refine_in .refine_flowers
