"""More SH bands asked for than the scene has (an SH2 scene and --sh-degree 3): every command that takes the option
says so in one warning line and uses the scene's degree, exit 0 (taken without a word before: newuser64)."""
from __future__ import annotations

from pathlib import Path

import pytest
from conftest import real, run_cli

from splatstream.io import read_gaussians
from splatstream.store import load_manifest


def warning(where) -> str:
    return f"splatstream: warning: --sh-degree 3: {where} has SH degree 2; 2 is used"


def warnings_in(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if "warning" in ln]


@pytest.fixture(scope="module")
def sh2(tmp_path_factory) -> tuple[Path, Path]:
    """An SH2 scene (fruit_drops_sh3 encoded at --sh-degree 2) and its decode, an SH2 .ply."""
    base = tmp_path_factory.mktemp("sh2")
    r = run_cli("encode", real("fruit_drops_sh3.ply"), base / "scene", "--sh-degree", "2", "-q")
    assert r.returncode == 0, r.stderr
    assert load_manifest(base / "scene").sh_degree == 2
    r = run_cli("decode", base / "scene", base / "sh2.ply", "-q")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    return base / "scene", base / "sh2.ply"


def test_decode_says_the_scene_has_fewer_bands_and_uses_them(sh2, tmp_path):
    scene, _ = sh2
    for quiet in ((), ("-q",)):  # a warning, not progress: said with -q too
        out = tmp_path / f"d{len(quiet)}.ply"
        r = run_cli("decode", scene, out, "--sh-degree", "3", *quiet)
        assert r.returncode == 0 and warnings_in(r.stderr) == [warning(scene)], r.stderr
        assert read_gaussians(out).sh_degree == 2
    for degree in ("2", "1"):  # as many bands as the scene has, or fewer: no word
        r = run_cli("decode", scene, tmp_path / "e.ply", "--sh-degree", degree)
        assert r.returncode == 0 and warnings_in(r.stderr) == [], r.stderr


def test_encode_and_the_exports_say_it_too(sh2, tmp_path):
    scene, ply = sh2
    r = run_cli("encode", ply, tmp_path / "s", "--sh-degree", "3", "-q")
    assert r.returncode == 0 and warnings_in(r.stderr) == [warning(ply)], r.stderr
    assert load_manifest(tmp_path / "s").sh_degree == 2
    for command, out in (("export-rad", "x.rad"), ("export-sog-lod", "sog"), ("export-3dtiles", "tiles")):
        r = run_cli(command, scene, tmp_path / out, "--sh-degree", "3", "-q")
        assert r.returncode == 0 and warnings_in(r.stderr) == [warning(scene)], (command, r.stderr)
        r = run_cli(command, scene, tmp_path / f"2{out}", "--sh-degree", "2", "-q")
        assert r.returncode == 0 and warnings_in(r.stderr) == [], (command, r.stderr)


def test_eval_says_it_of_a_variant(sh2):
    _, ply = sh2
    r = run_cli("eval", ply, "--presets", "none", "--variants", "x3:low,sh_degree=3", "--views", "1", "--size",
                "64x48", "-q")
    assert r.returncode == 0, r.stderr
    assert warnings_in(r.stderr) == [f"splatstream: warning: variant 'x3': sh_degree=3: {ply} has SH degree 2; 2 is "
                                     "used"], r.stderr


def _headless_available():
    pytest.importorskip("moderngl")
    from client_gl.offscreen import GLUnavailableError, shared_context

    try:
        shared_context()
    except GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")


def test_render_and_view_say_it(sh2, tmp_path):
    _headless_available()
    scene, ply = sh2
    for source in (scene, ply):
        r = run_cli("render", source, "--out", tmp_path / "a.png", "--size", "64x48", "--sh-degree", "3", "-q")
        assert r.returncode == 0 and warnings_in(r.stderr) == [warning(source)], r.stderr
        assert (tmp_path / "a.png").is_file()
    r = run_cli("view", scene, "--headless", "--size", "64x48", "--sh-degree", "3", "--timeout", "120", "-q")
    assert r.returncode == 0 and warnings_in(r.stderr) == [warning(scene)], r.stderr
    r = run_cli("view", scene, "--headless", "--size", "64x48", "--timeout", "120", "-q")  # the default: no word
    assert r.returncode == 0 and warnings_in(r.stderr) == [], r.stderr
