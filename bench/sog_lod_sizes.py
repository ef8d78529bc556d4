"""Bytes of our streamed-SOG export (`export-sog-lod`) against @playcanvas/splat-transform's streamed SOG of the
same levels (issue 35; results in BENCHMARKS.md).

    .venv/bin/python bench/sog_lod_sizes.py [SCENE ...]   (default: fruit_drops_sh3.ply donut_sh0_no_normals.ply
                                                          winter_fountain.splat from ../shared/data/real)

For each scene: our encode (preset medium, --max-leaf-splats 2000), `export-sog-lod` of it, and the tool given the
very same levels (our tiles of each depth decoded to a PLY, tagged `-l L`: level 0 the leaves) writing
`lod-meta.json` + SOG units with its default unit size, so both hold the same splats and only the writers differ.
Prints bytes (all files), bytes per stored splat, and the largest position error of level 0 against our decoded
leaves (matched by nearest centre). Also writes the commands' directories under OUT (default: a temporary one)
for timing them. Needs node and the tool installed by .ci/run into .ci/node (or SPLAT_TRANSFORM=path).
"""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_tool_roundtrip import splat_transform  # noqa: E402

from splatstream.ply import write_gaussians_ply  # noqa: E402
from splatstream.readers.sog import read_streamed_sog  # noqa: E402
from splatstream.scene_decode import decode_scene  # noqa: E402
from splatstream.store import load_manifest  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"
CLI = [sys.executable, "-m", "cli"]


def run(*args: object) -> None:
    subprocess.run(list(map(str, args)), check=True, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)


def tree_bytes(path: pathlib.Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def level0_error(directory: pathlib.Path, leaves) -> float:
    from scipy.spatial import cKDTree  # bench extra (pyproject [bench])

    g = read_streamed_sog(directory).level(0)
    return float(cKDTree(leaves.positions.astype(np.float64)).query(g.positions.astype(np.float64))[0].max())


def measure(source: pathlib.Path, out: pathlib.Path) -> dict:
    scene = out / "scene"
    run(*CLI, "encode", source, scene, "--max-leaf-splats", "2000", "--quiet")
    m = load_manifest(scene)
    depth = max(t.level for t in m.tiles)
    run(*CLI, "export-sog-lod", scene, out / "ours", "--quiet")
    inputs = []
    for level in range(depth + 1):
        ply = out / f"level{level}.ply"
        write_gaussians_ply(decode_scene(scene, tiles=[t.id for t in m.tiles if t.level == depth - level]), ply,
                            normals=False)
        inputs += [ply, "-l", level]  # an action applies to the input before it
    (out / "tool").mkdir()
    # The tool's command, saved for timing it beside ours.
    (out / "tool_command.txt").write_text(" ".join(map(str, [splat_transform(), "-q", "-w", "-g", "cpu", *inputs,
                                                             out / "tool" / "lod-meta.json"])))
    run(splat_transform(), "-q", "-w", "-g", "cpu", *inputs, out / "tool" / "lod-meta.json")
    stored = sum(t.splats for t in m.tiles)
    leaves = decode_scene(scene)
    return {"splats": m.splats, "levels": depth + 1, "stored": stored, "ours": tree_bytes(out / "ours"),
            "tool": tree_bytes(out / "tool"), "ours err": level0_error(out / "ours", leaves),
            "tool err": level0_error(out / "tool", leaves)}


def main() -> None:
    names = [a for a in sys.argv[1:] if not a.startswith("--out=")] or \
        ["fruit_drops_sh3.ply", "donut_sh0_no_normals.ply", "winter_fountain.splat"]
    keep = next((a[len("--out="):] for a in sys.argv[1:] if a.startswith("--out=")), None)
    print("| scene | splats | levels | splats stored | ours bytes | B/stored splat | tool bytes | B/stored splat | "
          "ours / tool | level-0 position error ours, tool |")
    print("|---" * 10 + "|")
    for name in names:
        path = pathlib.Path(name) if os.path.exists(name) else REAL / name
        with tempfile.TemporaryDirectory() as tmp:
            out = pathlib.Path(keep) / path.name.split(".")[0] if keep else pathlib.Path(tmp)
            out.mkdir(parents=True, exist_ok=True)
            s = measure(path, out)
        print(f"| {path.name} | {s['splats']:,} | {s['levels']} | {s['stored']:,} | {s['ours']:,} | "
              f"{s['ours'] / s['stored']:.2f} | {s['tool']:,} | {s['tool'] / s['stored']:.2f} | "
              f"{s['ours'] / s['tool']:.3f} | {s['ours err']:.2e}, {s['tool err']:.2e} |", flush=True)


if __name__ == "__main__":
    main()
