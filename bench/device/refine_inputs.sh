#!/usr/bin/env bash
# The scene sources bench/device/run_refine.sh reads, copied from the shared data into two ignored folders of the
# repository root (two device runs: the tracked files are ~36 MiB of the 64 MiB that travel):
#   .refine_in/       the 7 statues (.sog), donut, winter_fountain, guitar, biker   (~17.5 MB)
#   .refine_flowers/  flowers_lod/lod-meta.json and its finest level 0_0..0_3       (~13.2 MB; read as `convert` reads
#                     the whole folder: bit-identical to lod_vs_peers' full.ply)
# plus gsplat's wheel: bash bench/device_wheels.sh refine   (.whl_refine/, ~6.5 MB; 12.1 MB with zstandard, which
# bench/device/run_refine_encode.sh needs)
# `refine_inputs.sh split` also splits .refine_in in two for a tree that has grown past what travels beside it and
# .whl_refine (tracked ~36.6 MB + 17.5 + 12.1 = 63.2 MiB of 64): .refine_statues/ (the 7 .sog, 7.9 MB) and
# .refine_others/ (donut, winter_fountain, guitar, biker, 9.5 MB), three device runs instead of two.
set -euo pipefail
cd "$(dirname "$0")/../.."
REAL=${SPLATSTREAM_SHARED:-/work/shared}/data/real
if [ "${1:-}" = split ]; then
  rm -rf .refine_statues .refine_others
  mkdir -p .refine_statues/statues .refine_others
  cp "$REAL"/statues/*.sog .refine_statues/statues/
  cp "$REAL"/donut_sh0_no_normals.ply "$REAL"/winter_fountain.splat "$REAL"/guitar.compressed.ply \
    "$REAL"/biker.compressed.ply .refine_others/
  du -sb .refine_statues .refine_others
  exit 0
fi
rm -rf .refine_in .refine_flowers
mkdir -p .refine_in/statues .refine_flowers/flowers_lod
cp "$REAL"/statues/*.sog .refine_in/statues/
cp "$REAL"/donut_sh0_no_normals.ply "$REAL"/winter_fountain.splat "$REAL"/guitar.compressed.ply \
  "$REAL"/biker.compressed.ply .refine_in/
cp "$REAL"/flowers_lod/lod-meta.json .refine_flowers/flowers_lod/
cp -r "$REAL"/flowers_lod/0_* .refine_flowers/flowers_lod/
du -sb .refine_in .refine_flowers
