"""Vector and number options take negative values as typed (`--eye -2.9,-1.7,0`), in every command that has them:
argparse alone would take such a value for an unknown option and stop with a usage error."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT, run_cli

from cli.main import build_parser, join_negative_values
from splatstream.io import read_gaussians
from splatstream.ply import write_gaussians_ply
from splatstream.store import load_manifest

DONUT = ROOT / "samples" / "donut.ply"


def parse(*argv: str):
    return build_parser().parse_args(list(argv))


@pytest.mark.parametrize("argv, expected", [
    (["encode", "a.ply", "out", "--up", "-1,0,0"], {"up": "-1,0,0"}),
    (["eval", "a.ply", "--up", "0,-1,0"], {"up": "0,-1,0"}),
    (["render", "a.ply", "--out", "x.png", "--eye", "-2.9,-1.7,0", "--target", "-1,-2,-3", "--up", "-0,0,-1",
      "--background", "-0,0,0"], {"eye": "-2.9,-1.7,0", "target": "-1,-2,-3", "up": "-0,0,-1",
                                  "background": "-0,0,0"}),
    (["view", "scene", "--eye", "-2.9,-1.7,0", "--target", "-1e-3,0,0", "--up", "0,0,-1"],
     {"eye": "-2.9,-1.7,0", "target": "-1e-3,0,0", "up": "0,0,-1"}),
    (["export-3dtiles", "scene", "tiles", "--longitude", "-122.4", "--latitude", "-33.9", "--height", "-1e2",
      "--heading", "-30"], {"longitude": -122.4, "latitude": -33.9, "height": -100.0, "heading": -30.0}),
])
def test_negative_values_are_taken_as_typed(argv, expected):
    args = parse(*argv)
    for name, value in expected.items():
        assert getattr(args, name) == value, name


def test_only_number_lists_after_value_options_are_joined():
    opts = {"--eye", "--out"}
    assert join_negative_values(["--eye", "-1,2,-3", "--out", "x"], opts) == ["--eye=-1,2,-3", "--out", "x"]
    # not a number list: left for argparse (an unknown option, a usage error)
    assert join_negative_values(["--eye", "-q"], opts) == ["--eye", "-q"]
    assert join_negative_values(["--eye", "-1,x,0"], opts) == ["--eye", "-1,x,0"]
    # a flag (no value) is never joined, nor anything after `--`
    assert join_negative_values(["-q", "-1,0,0"], opts) == ["-q", "-1,0,0"]
    assert join_negative_values(["--", "--eye", "-1,0,0"], opts) == ["--", "--eye", "-1,0,0"]


def test_a_bad_vector_is_still_a_one_line_usage_error():
    r = run_cli("render", DONUT, "--out", "x.png", "--eye", "-1,-2")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "--eye" in r.stderr and "-1,-2" in r.stderr


@pytest.mark.parametrize("colour", ["2,0,0", "-1,0,0", "255,255,255"])
def test_a_background_outside_0_1_is_refused_as_the_help_says(colour, tmp_path):
    # render --help says 'R,G,B in [0, 1]'; these drew without a word (newuser58)
    r = run_cli("render", DONUT, "--out", tmp_path / "x.png", "--background", colour)
    assert r.returncode == 2 and not (tmp_path / "x.png").exists()
    assert r.stderr.strip() == (f"splatstream render: error: --background {colour}: expected R,G,B each in [0, 1] "
                                "(1,1,1 is white)")


@pytest.fixture(scope="module")
def small_ply(tmp_path_factory):
    g = read_gaussians(DONUT)
    keep = np.arange(0, len(g.positions), 15)  # about 3,000 splats of the bundled sample
    path = tmp_path_factory.mktemp("vec") / "small.ply"
    write_gaussians_ply(g.subset(keep), path)
    return path


def test_encode_up_negative(small_ply, tmp_path):
    r = run_cli("encode", small_ply, tmp_path / "s", "--up", "-1,0,0", "-q")
    assert r.returncode == 0, r.stderr
    assert load_manifest(tmp_path / "s").up == (-1.0, 0.0, 0.0)


def test_render_negative_camera_is_the_same_picture_as_with_equals(small_ply, tmp_path, gl_context):
    from PIL import Image

    cam = ["--target", "-0.01,-0.02,0", "--up", "0,0,1", "--size", "96x64"]
    a = run_cli("render", small_ply, "--eye", "-0.3,-0.3,0.2", *cam, "--out", tmp_path / "a.png")
    assert a.returncode == 0, a.stderr
    b = run_cli("render", small_ply, "--eye=-0.3,-0.3,0.2", *cam, "--out", tmp_path / "b.png")
    assert b.returncode == 0, b.stderr
    pa, pb = (np.asarray(Image.open(tmp_path / n)) for n in ("a.png", "b.png"))
    assert pa.std() > 1  # the scene is in the picture
    assert np.array_equal(pa, pb)


def test_view_headless_negative_eye(small_ply, tmp_path, gl_context):
    r = run_cli("view", small_ply, "--headless", "--eye", "-0.3,-0.3,0.2", "--target", "0,0,0", "--up", "0,0,1",
                "--size", "96x64", "--screenshot", tmp_path / "v.png", "--no-cache", "-q")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "v.png").stat().st_size > 0
