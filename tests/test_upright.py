"""Every real scene opens upright and wholly framed from its default camera (issue 34): the up axis each scene
really has is detected (or read from the PLY header when it names one), the image's up is the scene's up, and the
scene's box (the central 99 % of its splats that are not nearly transparent) projects inside the image. Each scene
is also rendered from that camera (`splatstream render FILE`, the command a user runs), and the picture holds the
scene near its middle."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, real, real_path, run_cli, with_shared

from splatstream.camera import framing_box, suggested_camera
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians, scene_up, up_from_comments
from splatstream.orientation import Y_DOWN_UP, Z_UP, view_side
from splatstream.ply import write_gaussians_ply
from splatstream.store import load_manifest

# The up axis each scene has (looked at in the pictures `splatstream render FILE` makes of each).
EXPECTED_UP = {
    "fruit_drops_sh3.ply": Y_DOWN_UP,
    "lod_tile_sh3_zero_rest.ply": Z_UP,
    "donut_sh0_no_normals.ply": Z_UP,
    "guitar.compressed.ply": Y_DOWN_UP,
    "winter_fountain.splat": Y_DOWN_UP,
    "biker.compressed.ply": Y_DOWN_UP,
    "statues/massa.sog": Y_DOWN_UP,
    "statues/st-peter.sog": Y_DOWN_UP,
    "flowers_lod/3_0/meta.json": Y_DOWN_UP,  # its coarsest level (26,895 splats), bundled
}
SIZE = (320, 180)


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def check_upright_and_framed(cam, g: Gaussians, up) -> None:
    _, true_up, _ = cam.basis()
    assert float(true_up @ np.array(up)) > 0.85  # the image's up is the scene's up (the view is raised ~20-25 deg)
    uv, depth = cam.project(box_corners(*framing_box(g.positions, g.opacity_logits)))
    assert (depth > 0).all()
    assert (uv[:, 0] >= 0).all() and (uv[:, 0] <= cam.width).all(), uv
    assert (uv[:, 1] >= 0).all() and (uv[:, 1] <= cam.height).all(), uv
    # and not lost in the middle: the box spans a good part of the image
    span = uv.max(axis=0) - uv.min(axis=0)
    assert max(span[0] / cam.width, span[1] / cam.height) > 0.5, span


def check_render(path, tmp_path, up_arg: str | None = None) -> None:
    """`splatstream render FILE` with no camera option: the scene is in the picture, around its middle."""
    from PIL import Image

    out = tmp_path / "default.png"
    extra = ["--up", up_arg] if up_arg else []
    r = run_cli("render", path, "--size", f"{SIZE[0]}x{SIZE[1]}", "--out", out, "-q", *extra)
    assert r.returncode == 0, r.stderr
    img = np.asarray(Image.open(out), np.float64).mean(axis=2)
    lit = img > 0.1 * img.max()
    assert lit.mean() > 0.02  # something is drawn
    rows, cols = np.nonzero(lit)
    weight = img[rows, cols]
    cy, cx = np.average(rows, weights=weight), np.average(cols, weights=weight)
    assert abs(cx / SIZE[0] - 0.5) < 0.25 and abs(cy / SIZE[1] - 0.5) < 0.25, (cx, cy)


@pytest.mark.parametrize("name", with_shared(list(EXPECTED_UP)))
def test_real_scene_opens_upright_and_wholly_framed(name, tmp_path, gl_context):
    path = real(name)
    g = read_gaussians(path)
    up = scene_up(path, g).up
    assert up == EXPECTED_UP[name]
    cam = suggested_camera(g.positions, up=up, width=SIZE[0], height=SIZE[1], side=view_side(g, up),
                           opacity_logits=g.opacity_logits)
    check_upright_and_framed(cam, g, up)
    check_render(path, tmp_path)


def test_the_encoded_scene_camera_frames_the_whole_guitar(tmp_path):
    """The manifest's suggested camera (what `view` opens with): the guitar's head is in view, not cut off."""
    path = real("guitar.compressed.ply")
    r = run_cli("encode", path, tmp_path / "g", "-q")
    assert r.returncode == 0, r.stderr
    m = load_manifest(tmp_path / "g")
    from splatstream.camera import Camera

    c = m.camera
    cam = Camera(c.eye, c.target, c.up, c.fov_y, *SIZE)
    check_upright_and_framed(cam, read_gaussians(path), m.up)


def ground_layout(seed: int = 1) -> Gaussians:
    """A small z-up scene laid out as make_scene.py does (copies of the real z-up objects spread over a ground in
    x and y, each turned about z), from the bundled scenes only."""
    rng = np.random.default_rng(seed)
    parts = []
    for name in ["donut_sh0_no_normals.ply", "lod_tile_sh3_zero_rest.ply"] * 5:
        g = read_gaussians(real(name))
        g = g.subset(np.arange(0, len(g), 8))
        g = Gaussians(g.positions, g.rotations, g.log_scales, g.opacity_logits, g.sh_dc,
                      np.zeros((len(g), 0, 3), np.float32))
        centre = np.median(g.positions, axis=0)
        size = np.percentile(np.linalg.norm(g.positions - centre, axis=1), 95)
        k = rng.uniform(0.5, 2.5) / size
        a = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], np.float32)
        q = np.array([np.cos(a / 2), 0, 0, np.sin(a / 2)], np.float32)
        w1, v1 = q[0], q[1:]
        w2, v2 = g.rotations[:, 0], g.rotations[:, 1:]
        quats = np.concatenate([(w1 * w2 - v2 @ v1)[:, None], w1 * v2 + w2[:, None] * v1 + np.cross(v1, v2)], 1)
        off = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), k * size], np.float32)
        parts.append(Gaussians(((g.positions - centre) * k) @ rot.T + off, quats.astype(np.float32),
                               g.log_scales + np.float32(np.log(k)), g.opacity_logits, g.sh_dc, g.sh_rest))
    return Gaussians.concatenate(parts)


def test_a_ground_layout_is_z_up_and_seen_from_above(tmp_path, gl_context):
    g = ground_layout()
    path = tmp_path / "layout.ply"
    write_gaussians_ply(g, path)
    choice = scene_up(path, g)
    assert choice.up == Z_UP and "ground plane" in choice.reason
    cam = suggested_camera(g.positions, up=Z_UP, width=SIZE[0], height=SIZE[1], opacity_logits=g.opacity_logits)
    check_upright_and_framed(cam, g, Z_UP)
    assert cam.eye[2] > np.percentile(g.positions[:, 2], 99)  # from above the ground, not from under it
    check_render(path, tmp_path)


def with_comment(src, dst, comment: str) -> None:
    data = open(src, "rb").read()
    at = data.index(b"\n") + 1  # after "ply"
    open(dst, "wb").write(data[:at] + f"comment {comment}\n".encode() + data[at:])


def test_a_ply_header_comment_naming_up_is_honoured(tmp_path):
    assert up_from_comments(["up 0 0 1"]) == (0.0, 0.0, 1.0)
    assert up_from_comments(["Z-up"]) == up_from_comments(["up_axis: z"]) == (0.0, 0.0, 1.0)
    assert up_from_comments(["up = -y"]) == (0.0, -1.0, 0.0)
    assert up_from_comments(["written by splatstream", "setup: y", "x-ray"]) is None
    # the bundled card is y-down by its shape; a header that says z up wins, in encode and in render
    src = real("fruit_drops_sh3.ply")
    dst = tmp_path / "zup.ply"
    with_comment(src, dst, "up_axis z")
    choice = scene_up(dst, read_gaussians(dst))
    assert choice.up == Z_UP and "header" in choice.reason
    r = run_cli("encode", dst, tmp_path / "s")
    assert r.returncode == 0, r.stderr
    assert "up 0,0,1: 0,0,1 as the PLY header's comment says" in r.stderr
    assert load_manifest(tmp_path / "s").up == Z_UP
    r = run_cli("encode", dst, tmp_path / "t", "--up", "0,-1,0", "-q")  # --up still overrides it
    assert r.returncode == 0 and load_manifest(tmp_path / "t").up == Y_DOWN_UP
    # `view FILE` encodes the file in memory the same way
    from client_gl.stream.sources import encode_splat_file
    from splatstream.format.manifest import parse_manifest

    assert parse_manifest(encode_splat_file(str(dst)).read_manifest()).up == Z_UP


def make_scene(tmp_path, splats: int, *args: str):
    """Run the shared make_scene.py (its copy in tests/tools/, byte for byte) over the bundled scenes: it reads
    ../data/real/ beside its resolved path, so it runs as a copy in that layout, made of links to the scenes."""
    layout = tmp_path / "shared"
    (layout / "tools").mkdir(parents=True)
    (layout / "data" / "real").mkdir(parents=True)
    shutil.copy(ROOT / "tests" / "tools" / "make_scene.py", layout / "tools" / "make_scene.py")
    for name in ("fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply", "donut_sh0_no_normals.ply",
                 "winter_fountain.splat"):
        (layout / "data" / "real" / name).symlink_to(real_path(name))
    tool = layout / "tools" / "make_scene.py"
    out = tmp_path / "scene.ply"
    subprocess.run([sys.executable, os.fspath(tool), "--splats", str(splats), "--out", os.fspath(out), *args],
                   check=True, capture_output=True, timeout=300)
    return out


def test_a_make_scene_scene_opens_upright_and_wholly_framed(tmp_path, gl_context):
    """make_scene.py's layout (z up, ground in x and y): 50,000 splats, seed 1, spread 4 (several objects; a
    smaller spread holds one object, a copy of the y-down fountain)."""
    path = make_scene(tmp_path, 50_000, "--seed", "1", "--spread", "4")
    g = read_gaussians(path)
    assert scene_up(path, g).up == Z_UP
    cam = suggested_camera(g.positions, up=Z_UP, width=SIZE[0], height=SIZE[1], opacity_logits=g.opacity_logits)
    check_upright_and_framed(cam, g, Z_UP)
    assert cam.eye[2] > np.percentile(g.positions[:, 2], 99)
    check_render(path, tmp_path)
