#!/bin/bash
# GPU-machine driver for bench/bench_render.py (device `run` tool), from the repo root, carrying:
#   .gl           GL loader .debs (libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2, amd64)
#   .whl          cp312 wheels: moderngl, glcontext, zstandard, gsplat (py3-none-any, JIT-compiles its CUDA)
#   .bench_carry  tools/make_scene.py and data/real/* (copies of ../shared) so make_scene.py runs there
# Usage: bash bench/device/run_bench.sh [bench_render.py args...]   (results in $OUT/bench.json, PNGs in $OUT)
# BENCH=bench/device/bench_compute.py: the same with the compute rasterizer's stages (binning, tile sort).
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv
# gsplat's CUDA extension compiles on first use (~40 s): build it in the background meanwhile.
(python3 -c "from gsplat.cuda._backend import _C; print('gsplat extension ready:', _C is not None)" \
  > "$OUT/gsplat_build.log" 2>&1 &)
probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"], c.info["GL_VERSION"])'
if ! python3 -c "$probe"; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  python3 -c "$probe" || exit 1
fi
python3 "${BENCH:-bench/bench_render.py}" --make-scene .bench_carry/tools/make_scene.py --workdir /tmp/bench \
  --json "$OUT/bench.json" --images "$OUT" "$@"
rc=$?
tail -3 "$OUT/gsplat_build.log"
exit $rc
