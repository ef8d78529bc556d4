"""Sizes and round-trip errors of our SPZ and GLB writers against @playcanvas/splat-transform (issue 17).

    .venv/bin/python bench/open_formats.py [SCENE.ply ...]   (default: fruit_drops_sh3.ply donut_sh0_no_normals.ply
                                                              from ../shared/data/real)

Needs node and the tool installed by .ci/run into .ci/node (or SPLAT_TRANSFORM=path). For each scene: bytes of our
SPZ v3/v4 and GLB (plain, SPZ-compressed) beside the tool's SPZ v3/v4, GLB and SOG; per-attribute max errors of
our SPZ against the tool's (both decoded by the tool, after undoing the tool's raw SPZ axes), of our SPZ decode
against the input, and of our SOG decode against the tool's; render PSNR (reference renderer, 3 orbit views,
160x120) of each decode against the input. Outputs go to a temporary directory.
"""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import tempfile
import time
import warnings

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_tool_roundtrip import attribute_errors, splat_transform, tool_gaussians  # noqa: E402

from splatstream.axes import RDF_TO_RUB, turn  # noqa: E402
from splatstream.camera import scene_orbit_views  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.metrics import psnr  # noqa: E402
from splatstream.ply import write_gaussians_ply  # noqa: E402
from splatstream.render_ref import render  # noqa: E402
from splatstream.writers.glb import glb_bytes  # noqa: E402
from splatstream.writers.spz import spz_bytes  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"


def tool(*args: object) -> None:
    subprocess.run([splat_transform(), "-q", "-w", "-g", "cpu", *map(str, args)], check=True)


def rounded(errors: dict[str, float]) -> dict[str, float]:
    return {k: float(f"{v:.3g}") for k, v in errors.items()}


def measure(path: pathlib.Path, out: pathlib.Path) -> None:
    src = read_gaussians(path)
    stem = path.name.split("_")[0]
    print(f"== {path.name}: {len(src)} splats, SH {src.sh_degree}, PLY {path.stat().st_size} bytes")
    ply = out / f"{stem}.ply"
    write_gaussians_ply(src, ply, normals=False)
    sizes: dict[str, int] = {}
    for version in (3, 4):
        start = time.perf_counter()
        data = spz_bytes(src, version)
        print(f"  our SPZ v{version}: {time.perf_counter() - start:.2f} s")
        (out / f"ours_v{version}.spz").write_bytes(data)
        sizes[f"spz v{version} ours"] = len(data)
        tool("--spz-version", version, ply, out / f"tool_v{version}.spz")
        sizes[f"spz v{version} tool"] = (out / f"tool_v{version}.spz").stat().st_size
    for compression in ("none", "spz"):
        data = glb_bytes(src, compression)
        (out / f"ours_{compression}.glb").write_bytes(data)
        sizes[f"glb {compression} ours"] = len(data)
    tool(ply, out / "tool.glb")
    tool(ply, out / "tool.sog")
    sizes["glb tool"] = (out / "tool.glb").stat().st_size
    sizes["sog tool"] = (out / "tool.sog").stat().st_size
    print("  bytes:", sizes)
    tool(out / "ours_v4.spz", out / "ours_v4.tool.ply")
    tool(out / "tool_v4.spz", out / "tool_v4.tool.ply")
    ours_by_tool = turn(tool_gaussians(out / "ours_v4.tool.ply"), RDF_TO_RUB)
    print("  SPZ v4, tool's decode of ours vs of its own:",
          rounded(attribute_errors(ours_by_tool, tool_gaussians(out / "tool_v4.tool.ply"))))
    ours = read_gaussians(out / "ours_v4.spz")
    print("  SPZ v4, our decode vs input:", rounded(attribute_errors(ours, src)))
    sog = read_gaussians(out / "tool.sog")
    tool(out / "tool.sog", out / "tool.sog.ply")
    print("  SOG, our decode vs the tool's:", rounded(attribute_errors(sog, tool_gaussians(out / "tool.sog.ply"))))
    views = scene_orbit_views(src.positions, 3, width=160, height=120)
    references = [render(src, camera) for camera in views]
    for label, g in [("SPZ v4 (ours)", ours), ("SOG (tool)", sog),
                     ("GLB spz (ours)", read_gaussians(out / "ours_spz.glb")),
                     ("GLB plain (ours)", read_gaussians(out / "ours_none.glb"))]:
        values = [psnr(render(g, camera), reference) for camera, reference in zip(views, references, strict=True)]
        print(f"  render PSNR {label}: " + ", ".join(f"{v:.1f}" for v in values) + " dB")


def main() -> None:
    scenes = [pathlib.Path(p) for p in sys.argv[1:]] or [REAL / "fruit_drops_sh3.ply",
                                                         REAL / "donut_sh0_no_normals.ply"]
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            out = pathlib.Path(tmp) / scene.stem
            os.makedirs(out)
            measure(scene, out)


if __name__ == "__main__":
    main()
