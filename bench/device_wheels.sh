#!/usr/bin/env bash
# Wheels that a bare many-core machine with Python 3.12, numpy and msgpack (the GPU machines' image) lacks for
# bench/bench_scale.py --workers: Dask and its pure-Python needs, and zstandard; and moderngl with glcontext for the
# streaming runs (bench/device/run_city.sh stream: the image of 2026-11-29 had none), and the `bc` extra's etcpak and
# texture2ddecoder (decode_quiet's very-low: its BC7 colour). Downloaded here into .whl/
# (.gitignore), carried to the machine and installed there with:
#   python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD
# `device_wheels.sh refine`: gsplat 1.5.3 alone (pure Python; it JIT-compiles its CUDA there, and the image has
# torch, jaxtyping, rich and ninja) and zstandard (the product encoder's, for bench/device/run_refine_encode.sh) into
# .whl_refine/ (.gitignore), for bench/device/run_refine.sh and run_refine_encode.sh: the repository's tracked files
# are ~37 MiB of the 64 MiB that travel, so the refinement carries this ~12 MB folder, not .whl.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = refine ]; then
  python3 -m pip download --no-deps --only-binary=:all: -d .whl_refine gsplat==1.5.3
  # encode --lod-refine (bench/device/run_refine_encode.sh) runs the product encoder, which needs zstandard: the
  # image lacks it. The cp312 wheel of .whl/ where it is there already, else downloaded.
  zst=(.whl/zstandard-0.25.0-cp312-*.whl)
  if [ -f "${zst[0]}" ]; then
    cp "${zst[0]}" .whl_refine/
  else
    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
      --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl_refine zstandard==0.25.0
  fi
  du -sh .whl_refine
  exit 0
fi
python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
  dask==2026.8.0 distributed==2026.8.0 zstandard==0.25.0 tornado==6.6.1 tblib==3.2.2 zict==3.0.0 partd==1.4.2 \
  locket==1.0.0 moderngl==5.12.0 glcontext==3.0.0 etcpak==0.9.15 archspec texture2ddecoder==1.0.6 \
  gsplat==1.5.3
du -sh .whl
