"""The exported tileset of a real scene in CesiumJS (npm `cesium`, .ci/node) in headless Chromium (Debian's
`chromium`, software WebGL through SwiftShader), driven by playwright-core: the splats must be drawn where our own
renderer draws them for the same camera.

The page (tests/cesium_page/) is served by a small loopback server here, the tileset by `splatstream serve` on
another loopback port (so the tileset is fetched cross-origin, through our CORS rules). The camera is the scene's
suggested camera, taken from our model coordinates into ECEF with the tileset's transform (format_spec/tiles3d.md
2). Compared: the masks of drawn pixels (any channel above 16/255 on the black background) by intersection over
union, and the PSNR of the two images.

Threshold: IoU >= 0.9 and PSNR >= 25 dB. Measured here (CesiumJS 1.145.0, Chromium 156, 480x360): fruit_drops
(y-down, SH degree 3, default placement) IoU 0.991, PSNR 32.1 dB; donut (z-up, georeferenced at 8.54 E 47.37 N,
height 400 m, heading 30) IoU 0.982, PSNR 29.8 dB; fruit_drops as a paged scene (63 tiles, 2 levels to a page:
a root tileset and 26 external tilesets) IoU 0.992, PSNR 30.3 dB, all 4,721 leaf splats drawn from tiles that only
the external tilesets name. What differs is the soft rims of splats (CesiumJS's kernel and
blending differ from ours). A wrong frame gives far less: the same fruit_drops tileset with SPZ content in the
extension text's axes ("rub") draws nothing inside the view (IoU 0.0), which settles how CesiumJS reads SPZ
content (test_spz_axes_settled_by_cesium); donut content whose splat rotations were composed with its 90-degree
up turn (before the turn went into the root transform) gave IoU 0.84, PSNR 20.7 dB (misoriented splats).
"""
from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
from browser import NODE_MODULES, compare, coverage, keep, render_ours, requirements, serve, shoot, vector_text
from conftest import ROOT, real, run_cli

from splatstream.store import load_manifest
from splatstream.tiles3d import model_to_fixed

CESIUM_BUILD = NODE_MODULES / "cesium" / "Build" / "Cesium"
PAGE_DIR = ROOT / "tests" / "cesium_page"
SIZE = (480, 360)
MIN_IOU = 0.9
MIN_PSNR_DB = 25.0


@pytest.fixture(scope="module")
def page_server():
    """The page's files, and CesiumJS's built files under /cesium/."""
    with serve(PAGE_DIR, {"/cesium/": CESIUM_BUILD}) as (url, _):
        yield url


@pytest.fixture(scope="module")
def tiles_root(tmp_path_factory, page_server):
    """Encoded real scenes and their tilesets; `splatstream serve` of the tilesets (CORS for the page)."""
    requirements(CESIUM_BUILD / "Cesium.js", what="cesium")
    work = tmp_path_factory.mktemp("cesium")
    scenes = {}
    for name, suffix, encode_args, export_args in (
            ("fruit_drops_sh3.ply", "", ["--max-leaf-splats", "2000"], [[], ["--spz-axes", "rub"]]),
            ("donut_sh0_no_normals.ply", "", ["--max-leaf-splats", "2000"],
             [["--longitude", "8.54", "--latitude", "47.37", "--height", "400", "--heading", "30"]]),
            # A paged scene (63 tiles in 7 levels, 2 to a page): a root tileset and 26 external tilesets.
            ("fruit_drops_sh3.ply", "-paged", ["--max-leaf-splats", "300", "--page-tiles", "8", "--page-levels", "2"],
             [[]])):
        stem = name.split(".")[0] + suffix
        scene = work / "scenes" / stem
        r = run_cli("encode", real(name), scene, "--quiet", *encode_args)
        assert r.returncode == 0, r.stderr
        for args in export_args:
            tag = stem + ("-rub" if "rub" in args else "")
            r = run_cli("export-3dtiles", scene, work / "tilesets" / tag, "--quiet", *args)
            assert r.returncode == 0, r.stderr
            scenes[tag] = scene
    proc = subprocess.Popen([sys.executable, "-m", "cli", "serve", str(work / "tilesets"), "--port", "0",
                             "--no-access-log", "--cors-origin", page_server], stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, stdin=subprocess.DEVNULL, text=True)
    line = proc.stderr.readline()
    m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
    try:
        assert m, line
        yield work, scenes, f"http://127.0.0.1:{m.group(1)}"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)


def camera_query(scene: Path, tileset: dict, tileset_url: str) -> tuple[str, list[str]]:
    """The page's query for the scene's suggested camera, and the same camera as `splatstream render` options."""
    manifest = load_manifest(scene)
    cam = manifest.camera
    eye, target, up = (np.asarray(v, np.float64) for v in (cam.eye, cam.target, cam.up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    true_up = up - (up @ forward) * forward
    true_up /= np.linalg.norm(true_up)
    m = model_to_fixed(tileset, manifest.up)
    rot = m[:3, :3]
    text = vector_text
    query = urllib.parse.urlencode({
        "tileset": tileset_url, "eye": text(m[:3, :3] @ eye + m[:3, 3]), "dir": text(rot @ forward),
        "up": text(rot @ true_up), "fovy": cam.fov_y, "near": 0.01 * float(np.linalg.norm(target - eye)),
    })
    # (--opt=value: a vector may start with a minus sign)
    ours = [f"--eye={text(eye)}", f"--target={text(target)}", f"--up={text(up)}", f"--fov-y={cam.fov_y}"]
    return query, ours


def shoot_tileset(tiles_root, page_server, tag: str, tmp_path: Path,
                  splats: int = 0) -> tuple[float, float, dict, float]:
    """splats: the page waits until that many are drawn (besides its own wait for a still splat count)."""
    work, scenes, tiles_url = tiles_root
    scene = scenes[tag]
    tileset = json.loads((work / "tilesets" / tag / "tileset.json").read_text())
    query, ours = camera_query(scene, tileset, f"{tiles_url}/scenes/{tag}/tileset.json")
    if splats:
        query += f"&splats={splats}"
    theirs_png, ours_png = tmp_path / f"cesium-{tag}.png", tmp_path / f"ours-{tag}.png"
    report = shoot(f"{page_server}/index.html?{query}", theirs_png, SIZE)
    render_ours(scene, ours_png, SIZE, ours)
    keep(theirs_png, ours_png)
    iou, psnr = compare(ours_png, theirs_png)
    return iou, psnr, report, coverage(ours_png)


@pytest.mark.parametrize("tag", ["fruit_drops_sh3", "donut_sh0_no_normals", "fruit_drops_sh3-paged"])
def test_cesium_draws_the_splats_where_we_do(tiles_root, page_server, tmp_path, tag):
    work, scenes, _ = tiles_root
    # The paged scene: every leaf (all below the root manifest's levels) must be drawn, so the page waits for them.
    every = load_manifest(scenes[tag]).splats if tag.endswith("-paged") else 0
    iou, psnr, report, drawn = shoot_tileset(tiles_root, page_server, tag, tmp_path, every)
    result = report["result"]
    print(f"{tag}: IoU {iou:.3f}, PSNR {psnr:.1f} dB, {result['splats']} splats in {result['selected']} tiles, "
          f"{report['gl']}")
    assert "refused" not in " ".join(report["logs"]), report["logs"]  # nothing asked for the internet
    assert result["loadedTiles"] >= result["selected"] > 0 and result["splats"] > 0
    assert drawn > 0.05  # the camera sees the scene (our render is not empty)
    assert iou >= MIN_IOU and psnr >= MIN_PSNR_DB, (iou, psnr)
    externals = {p.name for p in (work / "tilesets" / tag / "tiles").glob("*.json")}
    read = {path.rsplit("/", 1)[-1] for path in report["fetched"] if path.endswith(".json")}
    if tag.endswith("-paged"):
        # CesiumJS went down through the external tilesets (format_spec/tiles3d.md 3.1) and loaded content that
        # only they name (the tiles below the root manifest's levels), and drew it where we draw the scene.
        assert externals and read & externals, (sorted(externals)[:3], report["fetched"][:20])
        below = set()
        for name in read & externals:
            below |= _content_names(json.loads((work / "tilesets" / tag / "tiles" / name).read_text())["root"])
        root = json.loads((work / "tilesets" / tag / "tileset.json").read_text())["root"]
        glbs = {path.rsplit("/", 1)[-1] for path in report["fetched"] if path.endswith(".glb")}
        assert glbs & (below - _content_names(root)), sorted(glbs)[:5]
        assert result["splats"] == every, (result, every)
    else:
        assert not externals


def _content_names(tile: dict) -> set[str]:
    names = {tile["content"]["uri"].rsplit("/", 1)[-1]} if "content" in tile else set()
    for child in tile.get("children", []):
        names |= _content_names(child)
    return names


def test_spz_axes_settled_by_cesium(tiles_root, page_server, tmp_path):
    """SPZ content in the axes the extension's text describes ("rub") is drawn turned 180 degrees about the up
    axis by CesiumJS (its loader decodes SPZ without conversion), so our default stores glTF's axes ("luf")."""
    iou, _, report, _ = shoot_tileset(tiles_root, page_server, "fruit_drops_sh3-rub", tmp_path)
    assert report["result"]["splats"] > 0  # loaded and drawn, only elsewhere
    assert iou < 0.5, iou
