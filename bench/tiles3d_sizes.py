"""Bytes of an exported 3D Tiles tileset (SPZ and plain content) against our scene and against
@playcanvas/splat-transform's own outputs of the same input (issue 17; results in BENCHMARKS.md).

    .venv/bin/python bench/tiles3d_sizes.py [SCENE ...]   (default: fruit_drops_sh3.ply donut_sh0_no_normals.ply
                                                          winter_fountain.splat from ../shared/data/real)

For each scene: our encode (preset medium, --max-leaf-splats 2000 so that even these small scenes get an LOD tree;
all levels, and the full-detail leaves alone), `export-3dtiles` with SPZ content (v3, what CesiumJS reads) and plain
content, and the tool's SPZ v3 / v4, SOG, GLB, and streamed SOG (lod-meta.json) with three levels (100 %, 25 %,
6.25 % of the splats, decimated by the tool) — the tool's own streamable LOD form. Needs node and the tool
installed by .ci/run into .ci/node (or SPLAT_TRANSFORM=path). Outputs go to a temporary directory.
"""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_tool_roundtrip import splat_transform  # noqa: E402

from splatstream.io import read_gaussians  # noqa: E402
from splatstream.ply import write_gaussians_ply  # noqa: E402
from splatstream.store import load_manifest  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"
CLI = [sys.executable, "-m", "cli"]


def tool(*args: object) -> None:
    subprocess.run([splat_transform(), "-q", "-w", "-g", "cpu", *map(str, args)], check=True,
                   stdin=subprocess.DEVNULL)


def ours(*args: object) -> None:
    subprocess.run([*CLI, *map(str, args)], check=True, stdin=subprocess.DEVNULL)


def tree_bytes(path: pathlib.Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def measure(source: pathlib.Path, out: pathlib.Path) -> dict[str, int]:
    g = read_gaussians(source)
    stem = source.name.split(".")[0]
    ply = out / f"{stem}.ply"
    write_gaussians_ply(g, ply, normals=False)
    sizes = {"splats": len(g), "sh": g.sh_degree, "source": source.stat().st_size}
    scene = out / "scene"
    ours("encode", ply, scene, "--max-leaf-splats", "2000", "--quiet")
    m = load_manifest(scene)
    sizes["ours scene"] = m.bytes_on_disk
    sizes["ours leaves"] = m.leaf_bytes_on_disk
    sizes["tiles"] = len(m.tiles)
    for content in ("spz", "plain"):
        ours("export-3dtiles", scene, out / f"tiles-{content}", "--content", content, "--quiet")
        sizes[f"tileset {content}"] = tree_bytes(out / f"tiles-{content}")
    for version in (3, 4):
        tool("--spz-version", version, ply, out / f"tool_v{version}.spz")
        sizes[f"tool spz v{version}"] = tree_bytes(out / f"tool_v{version}.spz")
    tool(ply, out / "tool.sog")
    sizes["tool sog"] = tree_bytes(out / "tool.sog")
    tool(ply, out / "tool.glb")
    sizes["tool glb"] = tree_bytes(out / "tool.glb")
    # The tool's streamed LOD: decimated levels tagged 0 (finest) .. 2, written as lod-meta.json + SOG units.
    tool(ply, "--decimate", "25%", out / "lod1.ply")
    tool(ply, "--decimate", "6.25%", out / "lod2.ply")
    (out / "lod").mkdir()
    tool(ply, "-l", "0", out / "lod1.ply", "-l", "1", out / "lod2.ply", "-l", "2", out / "lod" / "lod-meta.json")
    sizes["tool lod sog"] = tree_bytes(out / "lod")
    return sizes


def main() -> None:
    names = sys.argv[1:] or ["fruit_drops_sh3.ply", "donut_sh0_no_normals.ply", "winter_fountain.splat"]
    columns = ["ours scene", "ours leaves", "tileset spz", "tileset plain", "tool spz v3", "tool spz v4",
               "tool sog", "tool glb", "tool lod sog"]
    print("| scene | splats, SH | tiles | " + " | ".join(columns) + " |")
    print("|---" * (3 + len(columns)) + "|")
    for name in names:
        path = pathlib.Path(name) if os.path.exists(name) else REAL / name
        with tempfile.TemporaryDirectory() as tmp:
            s = measure(path, pathlib.Path(tmp))
        cells = " | ".join(f"{s[c]:,}" for c in columns)
        print(f"| {path.name} | {s['splats']:,}, {s['sh']} | {s['tiles']} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
