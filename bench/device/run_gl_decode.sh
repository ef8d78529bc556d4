#!/bin/bash
# GPU-machine check of the texel formats of format 1.3 (norm16x4, norm9x3; issue 15) on the NVIDIA GL driver (EGL): the shader
# decode of every texel format against the numpy reference (tests/test_gl_decode.py; norm16x4 = GL_RGBA16 unorm
# read through a sampler2D, norm9x3 = R32UI unpacked in the shader), the SH codebook in them
# (tests/test_gl_codebook.py), and the formats' own tests (tests/test_format_1_3.py: bit layouts, scenes encoded and
# decoded), and tile steps (format.md 4.3.1, preset medium-low-12bit: widened ranges;
# tests/test_gl_decode.py::test_shader_decode_equals_numpy_on_tile_steps and tests/test_tile_steps.py). About a minute. From the repo root (device `run` tool), carrying as
# bench/device/run_client.sh does:
#   .gl           GL loader .debs (libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2, amd64)
#   .whl          cp312 wheels: moderngl glcontext zstandard msgpack platformdirs, and pytest with its
#                 dependencies (pytest iniconfig pluggy packaging)
#   .bench_carry  data/real/* (a copy of ../shared/data/real) for the tests' real scenes
# Usage: bash bench/device/run_gl_decode.sh      (log in $OUT/gl_decode.log)
# What to look for: every test passes (the GPU's unorm16 -> float conversion within 1 ulp of value / 65535); a
# failure in test_shader_decode_equals_numpy[FORMAT] names the plane and the largest difference. The BC formats' cases
# skip where etcpak is not carried.
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/gl_decode.log") 2>&1
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 SPLATSTREAM_SHARED=$PWD/.bench_carry
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
probe='import moderngl; c = moderngl.create_context(standalone=True, backend="egl", require=430); print(c.info["GL_RENDERER"], c.info["GL_VERSION"])'
if ! python3 -c "$probe"; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  python3 -c "$probe" || exit 1
fi
python3 -m pytest --version || { echo "pytest is not in .whl: add pytest iniconfig pluggy packaging wheels"; exit 1; }
# -rs: a skipped test (no GL context, no real scene) is reported, not taken for a pass
python3 -m pytest -q -rs -p no:cacheprovider tests/test_gl_decode.py tests/test_format_1_3.py tests/test_tile_steps.py \
  "tests/test_gl_codebook.py::test_shader_decode_equals_numpy"
