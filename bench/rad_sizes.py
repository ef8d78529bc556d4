"""Bytes and time of our RAD export (`export-rad`, issue 35; results in BENCHMARKS.md), beside our scene and our
streamed-SOG export of the same tree.

    .venv/bin/python bench/rad_sizes.py [SCENE ...]   (default: fruit_drops_sh3.ply donut_sh0_no_normals.ply
                                                      winter_fountain.splat from ../shared/data/real)

For each scene: our encode (preset medium, --max-leaf-splats 2000), then `export-rad` (both encodings: exact, and
Spark's 8-bit `--encoding spark`) and `export-sog-lod` of it,
each run as its own process three times (medians of wall and CPU time of the child, after one warm-up). Prints
splats, tree depth, splats stored in the .rad (every level plus its root splat), bytes of the scene, the .rad and
the streamed SOG, bytes per stored splat, and the times.
"""
from __future__ import annotations

import os
import pathlib
import resource
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from splatstream.readers.rad import read_rad_tree  # noqa: E402
from splatstream.store import load_manifest  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"
CLI = [sys.executable, "-m", "cli"]


def run(*args: object) -> tuple[float, float]:
    """Wall and CPU seconds of one child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(list(map(str, args)), check=True, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def timed(*args: object) -> tuple[float, float]:
    run(*args)
    runs = [run(*args) for _ in range(3)]
    return statistics.median(w for w, _ in runs), statistics.median(c for _, c in runs)


def tree_bytes(path: pathlib.Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    names = sys.argv[1:] or ["fruit_drops_sh3.ply", "donut_sh0_no_normals.ply", "winter_fountain.splat"]
    print("| scene | splats | levels | splats in the .rad | scene bytes | .rad bytes | B/stored splat | .rad bytes, "
          "spark encoding | B/stored splat | streamed SOG bytes | export-rad wall, CPU | with --encoding spark | "
          "export-sog-lod wall, CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        with tempfile.TemporaryDirectory() as tmp:
            out = pathlib.Path(tmp)
            source = pathlib.Path(name) if os.path.exists(name) else REAL / name
            run(*CLI, "encode", source, out / "scene", "--max-leaf-splats", "2000", "--quiet")
            rad_wall, rad_cpu = timed(*CLI, "export-rad", out / "scene", out / "scene.rad", "--quiet")
            sp_wall, sp_cpu = timed(*CLI, "export-rad", out / "scene", out / "spark.rad", "--encoding", "spark",
                                    "--quiet")
            sog_wall, sog_cpu = timed(*CLI, "export-sog-lod", out / "scene", out / "sog", "--quiet")
            tree = read_rad_tree(out / "scene.rad")
            m = load_manifest(out / "scene")
            rad, spark = tree_bytes(out / "scene.rad"), tree_bytes(out / "spark.rad")
            print(f"| {source.name} | {m.splats:,} | {max(t.level for t in m.tiles) + 1} | {len(tree.splats):,} | "
                  f"{tree_bytes(out / 'scene'):,} | {rad:,} | {rad / len(tree.splats):.2f} | {spark:,} | "
                  f"{spark / len(tree.splats):.2f} | {tree_bytes(out / 'sog'):,} | {rad_wall:.2f} s, {rad_cpu:.2f} s | "
                  f"{sp_wall:.2f} s, {sp_cpu:.2f} s | {sog_wall:.2f} s, {sog_cpu:.2f} s |", flush=True)


if __name__ == "__main__":
    main()
