"""`splatstream render` end to end (a separate process, as a user runs it)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import real, run_cli

from splatstream import render_ref
from splatstream.camera import look_at
from splatstream.io import read_gaussians
from splatstream.metrics import psnr

pytest.importorskip("moderngl")


@pytest.fixture(scope="module")
def gl_ok(gl_context):
    """The CLI opens its own context; this skips the tests where none opens."""


def _png(path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB")).astype(np.float32) / 255.0


def test_render_encoded_scene_both_sorts(gl_ok, tmp_path):
    scene = tmp_path / "fruit"
    r = run_cli("encode", real("fruit_drops_sh3.ply"), scene, "--preset", "medium", "--no-lod", "-q")
    assert r.returncode == 0, r.stderr
    images = {}
    for sort in ("cpu", "gpu"):
        out = tmp_path / f"{sort}.png"
        r = run_cli("render", scene, "--size", "96x64", "--sort", sort, "--out", out)
        assert r.returncode == 0, r.stderr
        assert f"sort {sort}" in r.stderr
        images[sort] = _png(out)
        assert images[sort].shape == (64, 96, 3) and images[sort].mean() > 0.02
    assert np.abs(images["cpu"] - images["gpu"]).max() <= 2 / 255


def test_render_ply_with_camera(gl_ok, tmp_path):
    out = tmp_path / "a.png"
    r = run_cli("render", real("fruit_drops_sh3.ply"), "--eye", "1,1,1", "--target", "0,0,0", "--up", "0,1,0",
                "--fov-y", "60", "--size", "64x48", "--sh-degree", "1", "--background", "0,0,1", "--out", out)
    assert r.returncode == 0, r.stderr
    # a splat file is encoded in memory first (seconds for a large one): said before it happens
    assert r.stderr.startswith(f"render: 4,721 splats read from {real('fruit_drops_sh3.ply')} ("), r.stderr
    assert "encoding them at very-high for the GPU\nwrote " in r.stderr, r.stderr
    # the count as the line before says it ("4721 splats" after "4,721 splats read": newuser62)
    assert f"wrote {out}: 64x48, 4,721 splats, sort " in r.stderr, r.stderr
    img = _png(out)
    assert img.shape == (48, 64, 3)
    # The camera the command builds from these arguments (near = 1% of the eye's distance: render.py).
    dist = float(np.sqrt(3.0))
    cam = look_at((1, 1, 1), (0, 0, 0), (0, 1, 0), 60, 64, 48, near=min(0.2, 0.01 * dist), far=1000.0)
    ref = render_ref.render(read_gaussians(real("fruit_drops_sh3.ply")), cam, sh_degree=1, background=(0, 0, 1))
    assert np.abs(ref - (0, 0, 1)).max() > 0.2  # the view shows splats
    assert psnr(img, ref) >= 40.0  # 8-bit PNG against the float reference


@pytest.mark.parametrize("args, message", [
    (["--size", "12"], "--size"),
    (["--eye", "1,2"], "--eye"),
    (["--background", "red"], "--background"),
    (["--eye", "0,0,0", "--target", "0,0,0"], "--eye and --target"),
])
def test_bad_arguments(gl_ok, tmp_path, args, message):
    out = tmp_path / "x.png"
    r = run_cli("render", real("fruit_drops_sh3.ply"), *args, "--out", out)
    assert r.returncode == 2
    assert message in r.stderr
    assert not out.exists()


def test_missing_input(tmp_path):
    r = run_cli("render", tmp_path / "nope.ply", "--out", tmp_path / "x.png")
    assert r.returncode == 2
    assert "no such file" in r.stderr


@pytest.mark.parametrize("sort", ["cpu", "gpu"])
def test_view_record_says_the_draw_the_overlay_says(gl_ok, gl_context, tmp_path, sort):
    """The record's `sort` and `draw` and the window overlay's draw path line are the renderer's sort_mode and
    draw_path: with the CPU sort the draw is "raster" (the window's record said "fetch", the headless one "cpu",
    where the overlay said "CPU sort, raster draw")."""
    import json

    from client_gl.offscreen import HeadlessRenderer, RenderOptions
    from client_gl.window import draw_path_line
    from splatstream.io import read_gaussians

    if sort == "gpu" and gl_context.version_code < 430:
        pytest.skip("the GPU sort needs GL 4.3 compute shaders")
    r = run_cli("view", real("fruit_drops_sh3.ply"), "--headless", "--size", "64x48", "--sort", sort, "--record",
                tmp_path / "rec.json", "--no-cache", "-q")
    assert r.returncode == 0, r.stderr
    record = json.loads((tmp_path / "rec.json").read_text())
    assert record["sort"] == sort
    assert record["draw"] == ("raster" if sort == "cpu" else "fetch")  # fetch: the GPU path's draw on a software GL
    h = HeadlessRenderer(RenderOptions(sort=sort), ctx=gl_context)
    try:
        h.load_gaussians(read_gaussians(real("fruit_drops_sh3.ply")))
        assert draw_path_line(h.renderer) == f"{sort.upper()} sort, {record['draw']} draw"
    finally:
        h.unload()


@pytest.mark.parametrize("command", ["render", "view"])
@pytest.mark.parametrize("draw", ["compute", "points"])
def test_draw_with_the_cpu_sort_is_refused_naming_both(tmp_path, command, draw):
    """--draw picks the GPU path's rasterizer: with --sort cpu a raster draw was ignored without a word and compute
    refused in a line naming neither option (newuser61)."""
    out = ["--out", tmp_path / "x.png"] if command == "render" else ["--headless"]
    r = run_cli(command, real("fruit_drops_sh3.ply"), "--sort", "cpu", "--draw", draw, *out)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and f"--draw {draw} and --sort cpu" in lines[0], r.stderr
    assert not (tmp_path / "x.png").exists()


def test_a_named_draw_takes_the_gpu_sort_under_auto(gl_ok, gl_compute_context, tmp_path):
    """`render --draw points` on a software GL (sort auto: the CPU sort there) drew with the CPU sort's raster, the
    draw named ignored without a word; it now takes the GPU path, as --draw compute did."""
    r = run_cli("render", real("fruit_drops_sh3.ply"), "--draw", "points", "--size", "64x48", "--out",
                tmp_path / "x.png")
    assert r.returncode == 0, r.stderr
    assert "sort gpu, draw points" in r.stderr, r.stderr


def test_render_options_for_the_other_kind_of_source_are_refused(tmp_path):
    """--preset sets the formats of a splat file encoded in memory (an encoded scene is drawn in its own) and
    --max-sse draws an encoded scene's streamed tiles (a splat file is drawn whole): each was ignored without a word
    for the other kind of source (newuser61)."""
    scene = tmp_path / "fruit"
    r = run_cli("encode", real("fruit_drops_sh3.ply"), scene, "--preset", "medium", "-q")
    assert r.returncode == 0, r.stderr
    for source, option, said in ((scene, ["--preset", "low"], "--preset low: "),
                                 (real("fruit_drops_sh3.ply"), ["--max-sse", "2"], "--max-sse 2: ")):
        r = run_cli("render", source, *option, "--out", tmp_path / "x.png")
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"splatstream render: error: {said}"), r.stderr
        assert not (tmp_path / "x.png").exists()


def test_view_eye_target_take_the_scenes_up_and_fov_alone_applies(gl_ok, tmp_path):
    """`view SCENE --eye E --target T` took +z as up where the help says 'default: the scene's' (a y-down capture drew
    rolled), and --fov-y or --up without --eye/--target were ignored (newuser61): at the scene's own eye and target
    the view is the scene camera's; --fov-y alone narrows that camera's view, as with --eye/--target."""
    import json

    from PIL import Image

    from splatstream.store import load_manifest

    scene = tmp_path / "fruit"
    r = run_cli("encode", real("fruit_drops_sh3.ply"), scene, "--up", "0,-1,0", "--no-lod", "-q")
    assert r.returncode == 0, r.stderr
    c = load_manifest(scene).camera
    look = ["--eye=" + ",".join(map(repr, c.eye)), "--target=" + ",".join(map(repr, c.target))]

    def shot(name: str, *extra: str) -> np.ndarray:
        r = run_cli("view", scene, "--headless", "--size", "96x64", "--screenshot", tmp_path / f"{name}.png",
                    "--record", tmp_path / f"{name}.json", "--no-cache", "-q", *extra)
        assert r.returncode == 0, r.stderr
        assert json.loads((tmp_path / f"{name}.json").read_text())["converged_s"] is not None
        return np.asarray(Image.open(tmp_path / f"{name}.png"), np.float32)

    home = shot("home")
    assert np.abs(shot("look", *look) - home).max() <= 1.0  # the scene's up, not +z
    narrow = shot("narrow", "--fov-y", "25")
    assert np.abs(narrow - home).mean() > 5.0  # applied
    assert np.abs(narrow - shot("narrow_look", *look, "--fov-y", "25")).max() <= 1.0
