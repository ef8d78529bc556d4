"""Bytes of an exported 3D Tiles tileset (SPZ and plain content) against our scene and against
@playcanvas/splat-transform's own outputs of the same input (issue 17; results in BENCHMARKS.md).

    .venv/bin/python bench/tiles3d_sizes.py [SCENE ...]   (default: fruit_drops_sh3.ply donut_sh0_no_normals.ply
                                                          winter_fountain.splat from ../shared/data/real)

For each scene: our encode (preset medium, --max-leaf-splats 2000 so that even these small scenes get an LOD tree;
all levels, and the full-detail leaves alone), `export-3dtiles` with SPZ content (v3, what CesiumJS reads) and plain
content, and the tool's SPZ v3 / v4, SOG, GLB, and streamed SOG (lod-meta.json) with three levels (100 %, 25 %,
6.25 % of the splats, decimated by the tool) — the tool's own streamable LOD form. Needs node and the tool
installed by .ci/run into .ci/node (or SPLAT_TRANSFORM=path). Outputs go to a temporary directory.

    PYTHONPATH=. .venv/bin/python bench/tiles3d_sizes.py --json-tree [--splats 6e6,250e6] [--page-levels 6]

The tileset JSON of a paged scene (issue 38, format_spec/tiles3d.md 3.1): on trees of the encoder's exact shape
(bench_pages.synthetic_tree: no splats encoded) paged as the encoder pages them, the bytes of the single-file
tileset.json (`--external-tilesets never`) against the root tileset.json and the external tilesets of the default
(`auto`). Content names are 64-hex names as real ones (the JSON's bytes are those of a real export up to the
digits of the box numbers: boxes are the manifest's, without the growth for SPZ rounding).
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


def json_tree(splat_counts: list[int], page_levels: int) -> None:
    import hashlib
    import json
    import statistics
    import time
    from dataclasses import replace

    import msgpack
    from bench_pages import synthetic_tree, template

    from splatstream.format.manifest import pack_manifest, split_pages
    from splatstream.format.names import tileset_content_name
    from splatstream.tiles3d import ExportOptions, build_tilesets, content_rotation, tile_boxes

    def dumps(d: dict) -> bytes:  # as export_tileset writes them
        return json.dumps(d, separators=(",", ":")).encode("utf-8")

    base = template(0)
    print("| splats | tiles | levels | pages | root manifest | single tileset.json | root tileset.json | external "
          "tilesets | median | max | external total | build s (single, external) |")
    print("|---" * 12 + "|")
    for n in splat_counts:
        whole = synthetic_tree(n, base)
        paged = split_pages(whole, page_levels)
        root_raw = pack_manifest(paged.root)
        # The whole tree as read_manifest gives it for a paged scene: each head tile with its page's entry. (Not
        # read back through resolve_pages: the synthetic tiles' copied payload entries are not checked.)
        refs = {msgpack.unpackb(raw)["parent"]: ref for ref, raw in paged.pages}
        m = replace(whole, tiles=tuple(replace(t, page=refs.get(t.id)) for t in whole.tiles), paged=paged.root.paged)
        pages = paged.pages
        uris = {t.id: tileset_content_name(hashlib.sha256(b"%d" % t.id).hexdigest()) for t in m.tiles}
        boxes = tile_boxes(m, {}, content_rotation(m.up))
        t0 = time.perf_counter()
        single = dumps(build_tilesets(m, uris, boxes, ExportOptions(external_tilesets="never")).root)
        t1 = time.perf_counter()
        split = build_tilesets(m, uris, boxes, ExportOptions())
        root = dumps(split.root)
        t2 = time.perf_counter()
        sizes = [len(v) for v in split.external.values()]
        print(f"| {n / 1e6:g}M | {len(m.tiles):,} | {m.levels} | {len(pages):,} | {len(root_raw):,} | "
              f"{len(single):,} | {len(root):,} | {len(sizes):,} | {statistics.median(sizes):,.0f} | {max(sizes):,} | "
              f"{sum(sizes):,} | {t1 - t0:.1f}, {t2 - t1:.1f} |", flush=True)


def main() -> None:
    if "--json-tree" in sys.argv:
        import argparse

        p = argparse.ArgumentParser()
        p.add_argument("--json-tree", action="store_true")
        p.add_argument("--splats", default="6e6,250e6")
        p.add_argument("--page-levels", type=int, default=6)
        args = p.parse_args()
        sys.path.insert(0, str(ROOT / "bench"))
        json_tree([int(float(v)) for v in args.splats.split(",")], args.page_levels)
        return
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
