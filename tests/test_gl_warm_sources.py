"""The shader warmer links the very sources moderngl compiles (warm_compile.ShaderWarmer, renderer.program_stages):
the drivers' shader caches are keyed by the text, and moderngl's Context.program strips a vertex and fragment
program's sources, so an unstripped copy linked ahead was a miss (the fetch draw's program "not helped" on llvmpipe
and NVIDIA: BENCHMARKS.md, "The first frame's two compiles side by side"). Real GL (EGL, llvmpipe here), each step a
process of its own over a Mesa disk cache of its own; no timings asserted."""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pytest
from conftest import real

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians
from splatstream.store import load_manifest

pytest.importorskip("moderngl")

ROOT = pathlib.Path(__file__).resolve().parents[1]

CACHE_PROBE = r"""
import json, sys
from client_gl.offscreen import create_context
from client_gl.gpu.renderer import program_stages
from client_gl.gpu import warm_compile
vert, frag, how = json.load(open(sys.argv[1]))
ctx = create_context()
if how == "moderngl":
    ctx.program(vertex_shader=vert, fragment_shader=frag).release()
elif how == "warmer":  # the raw calls the warmer's thread makes, on the sources it is given
    warm_compile._compile_and_link(warm_compile._gl_functions(), program_stages("raster", (vert, frag)))
else:  # the sources as given, unstripped (what the warmer linked before it stripped them)
    warm_compile._compile_and_link(warm_compile._gl_functions(), ((0x8B31, vert), (0x8B30, frag)))
ctx.release()
"""


def _cache_entries(directory: pathlib.Path) -> set[tuple[str, int]]:
    """The cache's files and sizes (a miss adds a file, or grows one where the cache is a single file; its LRU index
    is rewritten on every use, so it is left out)."""
    return {(str(p.relative_to(directory)), p.stat().st_size) for p in directory.rglob("*")
            if p.is_file() and p.name != "index"}


def _run_probe(tmp_path, cache, vert, frag, how) -> set[tuple[str, int]]:
    spec = tmp_path / "probe.json"
    spec.write_text(json.dumps([vert, frag, how]))
    env = dict(os.environ, MESA_SHADER_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    env.pop("MESA_SHADER_CACHE_DISABLE", None)
    subprocess.run([sys.executable, "-c", CACHE_PROBE, str(spec)], env=env, check=True, cwd=tmp_path, timeout=300)
    return _cache_entries(cache)


def test_a_pair_the_warmer_linked_is_the_one_moderngl_finds_in_the_cache(gl_compute_context, tmp_path):
    """moderngl's compile of splat.vert's program adds no cache entry after program_stages' sources were linked by
    the warmer's raw calls (the cache's hit), where it adds entries after a link of the unstripped sources (a miss)."""
    from client_gl.gpu import shadergen
    from client_gl.gpu.residency_layout import PoolLayout

    if "llvmpipe" not in gl_compute_context.info.get("GL_RENDERER", "").lower():
        pytest.skip("counts the entries of Mesa's disk cache")
    scene = tmp_path / "fruit"
    encode_gaussians(read_gaussians(real("fruit_drops_sh3.ply")), scene,
                     EncodeOptions(preset="medium", max_leaf_splats=256))
    m = load_manifest(scene)
    vert, frag = shadergen.render_sources(shadergen.decode_header(PoolLayout(m.formats, m.sh_degree, None)), 430)
    assert vert != vert.strip()  # moderngl's strip changes the text
    for how, hit in (("warmer", True), ("unstripped", False)):
        cache = tmp_path / how
        ahead = _run_probe(tmp_path, cache, vert, frag, how)
        if not ahead:
            pytest.skip("Mesa's disk cache wrote nothing here (switched off by its configuration)")
        after = _run_probe(tmp_path, cache, vert, frag, "moderngl")
        assert (after == ahead) == hit, (how, sorted(after - ahead))
