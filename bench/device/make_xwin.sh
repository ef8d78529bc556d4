#!/usr/bin/env bash
# Makes what bench/device/run_window.sh carries besides .gl, .xroot and .whl (all under .git/info/exclude):
#   .xroot/*.deb        Xvfb and the X11 client libraries (Debian 12 packages, unpacked on the GPU machine under
#                       /tmp/xroot, never into /)
#   .xwin/winsite.tar.xz  glfw, moderngl-window, pyglm, imgui-bundle and what they import for CPython 3.12 unpacked, demos, stubs and
#                       tests removed, xz: as wheels they would not fit the 64 MiB carry limit beside the rest
#   .xwin/xglx.tar.xz   Mesa 22.3.6's swrast DRI driver built without LLVM (softpipe) and what it links that the
#                       GPU machine lacks. Xvfb's GLX extension loads swrast_dri.so to start at all (without it
#                       clients see "GLX extension not found"); Debian's driver links libLLVM-15 (117 MB) and so
#                       cannot be carried. The window's GL is the NVIDIA driver's (__GLX_VENDOR_LIBRARY_NAME=nvidia);
#                       softpipe only has to be there.
# Usage: bash bench/device/make_xwin.sh   (needs apt-get source access and Mesa's build dependencies: a few minutes)
set -euo pipefail
cd "$(dirname "$0")/../.."
mkdir -p .xroot .xwin
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64'
(cd .xroot && apt-get $o download xvfb xserver-common x11-xkb-utils xkb-data libxfont2 libfontenc1 libfreetype6 \
  libpng16-16 libbrotli1 libpixman-1-0 libunwind8 libxkbfile1 libxau6 libxdmcp6 libbsd0 libmd0 libdrm2 \
  libglapi-mesa libglx-mesa0 libx11-6 libx11-data libx11-xcb1 libxcb1 libxcb-dri2-0 libxcb-dri3-0 libxcb-glx0 \
  libxcb-present0 libxcb-randr0 libxcb-shm0 libxcb-sync1 libxcb-xfixes0 libxcursor1 libxext6 libxfixes3 libxi6 \
  libxinerama1 libxrandr2 libxrender1 libxshmfence1 libxxf86vm1)

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$work/w" \
  glfw==2.11.0 moderngl-window==3.1.1 pyglm==2.8.3 imgui-bundle==1.6.3 pydantic==2.14.3 pydantic-core==2.50.4 \
  munch==4.0.0 typing-inspection==0.4.5 typing-extensions==4.16.0 annotated-types==0.8.0
mkdir -p "$work/site"
for w in "$work"/w/*.whl; do python3 -m zipfile -e "$w" "$work/site"; done
find "$work/site" \( -name demos_* -o -name '*.pyi' -o -name tests -o -name __pycache__ \) -prune -exec rm -rf {} +
rm -rf "$work"/site/imgui_bundle/demos* "$work"/site/imgui_bundle/assets/fonts/Font_Awesome*
tar -C "$work/site" -cJf .xwin/winsite.tar.xz .

(cd "$work" && apt-get source --download-only mesa=22.3.6-1+deb12u2 && dpkg-source -x mesa_22.3.6-1+deb12u2.dsc mesa)
(cd "$work/mesa" && meson setup build -Dllvm=disabled -Dgallium-drivers=swrast -Dvulkan-drivers= -Dplatforms=x11 \
  -Dglx=dri -Degl=disabled -Dgles1=disabled -Dgles2=disabled -Dshared-glapi=enabled -Dgbm=disabled -Dglvnd=false \
  -Dosmesa=false -Dzstd=disabled -Dshader-cache=disabled -Dvalgrind=disabled -Dlibunwind=disabled \
  -Dlmsensors=disabled -Dgallium-vdpau=disabled -Dgallium-va=disabled -Dgallium-xa=disabled -Dgallium-omx=disabled \
  -Dgallium-nine=false -Dgallium-opencl=disabled -Dvideo-codecs= -Dbuildtype=release -Dstrip=true -Db_ndebug=true \
  -Dprefix=/usr -Dlibdir=lib/x86_64-linux-gnu && ninja -C build src/gallium/targets/dri/swrast_dri.so)
lib="$work/xglx/usr/lib/x86_64-linux-gnu"
mkdir -p "$lib/dri"
cp "$work/mesa/build/src/gallium/targets/dri/swrast_dri.so" "$lib/dri/"
cp -L "$work/mesa/build/src/mapi/shared-glapi/libglapi.so.0" /lib/x86_64-linux-gnu/libexpat.so.1 "$lib/"
strip --strip-unneeded "$lib/dri/swrast_dri.so" "$lib/libglapi.so.0"
tar -C "$work/xglx" -cJf .xwin/xglx.tar.xz usr
du -sh .xroot .xwin/*
