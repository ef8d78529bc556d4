"""A directory holding both an encoded scene (manifest.msgpack) and a 3D Tiles tileset (tileset.json), e.g. a tileset
copied into a scene: the readers take it as the scene, and no directory output replaces it (export-3dtiles deleted
the scene, as it replaces a directory holding tileset.json; encode would have deleted the tileset). serve's note on
it: tests/test_server.py."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import real, run_cli

from splatstream.atomic import DIRECTORY_OUTPUT_INDEXES
from splatstream.format.names import MANIFEST_NAME, TILESET_NAME
from splatstream.io import read_gaussians
from splatstream.writers.sog_lod import LOD_META_NAME


def test_the_index_names_are_the_formats():
    assert set(DIRECTORY_OUTPUT_INDEXES) == {MANIFEST_NAME, TILESET_NAME, LOD_META_NAME}


@pytest.fixture(scope="module")
def both(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("both")
    r = run_cli("encode", real("fruit_drops_sh3.ply"), base / "scene", "-q")
    assert r.returncode == 0, r.stderr
    r = run_cli("export-3dtiles", base / "scene", base / "tiles", "-q")
    assert r.returncode == 0, r.stderr
    shutil.copytree(base / "scene", base / "both")
    shutil.copytree(base / "tiles", base / "both", dirs_exist_ok=True)
    return base


def listing(path: Path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


def test_no_directory_output_replaces_it(both, tmp_path):
    d = tmp_path / "both"
    shutil.copytree(both / "both", d)
    before = listing(d)
    r = run_cli("export-3dtiles", both / "scene", d, "-q")
    assert r.returncode == 2 and r.stderr.strip() == (
        f"splatstream export-3dtiles: error: {d}: holds an encoded scene (manifest.msgpack) beside tileset.json: "
        "replacing it would delete that encoded scene; give a new or empty directory, or move one of them out")
    r = run_cli("encode", real("fruit_drops_sh3.ply"), d, "-q")
    assert r.returncode == 2 and r.stderr.strip() == (
        f"splatstream encode: error: {d}: holds a 3D Tiles tileset (tileset.json) beside manifest.msgpack: "
        "replacing it would delete that 3D Tiles tileset; give a new or empty directory, or move one of them out")
    assert listing(d) == before
    # a directory of one kind is still replaced by its own kind
    assert run_cli("export-3dtiles", both / "scene", both / "tiles", "-q").returncode == 0
    assert run_cli("encode", real("fruit_drops_sh3.ply"), tmp_path / "s", "-q").returncode == 0
    assert run_cli("encode", real("fruit_drops_sh3.ply"), tmp_path / "s", "-q").returncode == 0


def test_the_readers_take_it_as_the_scene(both, tmp_path):
    r = run_cli("info", both / "both")
    assert r.returncode == 0 and "splats     4,721" in r.stdout, r.stderr
    r = run_cli("decode", both / "both", tmp_path / "d.ply", "-q")
    assert r.returncode == 0 and len(read_gaussians(tmp_path / "d.ply")) == 4721, r.stderr


def test_render_and_view_draw_the_scene(both, tmp_path):
    pytest.importorskip("moderngl")
    from client_gl.offscreen import GLUnavailableError, shared_context

    try:
        shared_context()
    except GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")
    r = run_cli("render", both / "both", "--out", tmp_path / "a.png", "--size", "64x48")
    assert r.returncode == 0 and "4,721 splats" in r.stderr, r.stderr
    r = run_cli("view", both / "both", "--headless", "--size", "64x48", "--timeout", "120")
    assert r.returncode == 0 and "4,721 splats drawn" in r.stderr.splitlines()[-1], r.stderr
