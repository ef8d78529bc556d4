"""Time parse_manifest on real manifests: eager, lazy (the streaming client's, before its first frame) and lazy with
every payload entry read afterwards; medians of in-process runs.

    PYTHONPATH=. python bench/bench_manifest_parse.py SCENE_DIR [SCENE_DIR ...] [--repeat 31] [--json out.json]
    git show 615105a:splatstream/format/manifest.py > /tmp/ref_manifest.py
    PYTHONPATH=. python bench/bench_manifest_parse.py SCENE_DIR ... --ref /tmp/ref_manifest.py

With --ref, a manifest module of another version (a single file that imports its siblings relatively, as
splatstream/format/manifest.py did before issue 33) is loaded beside this tree's, and each run of this tree's
parse is paired with one of the reference's, in alternating order: the figures are medians of CPU time of this
process (a shared machine's other work moves wall time by more than the difference), and the ratio is the median
of the pairs' ratios (BENCHMARKS.md, "Manifest parse").
"""
from __future__ import annotations

import argparse
import gc
import importlib.util
import json
import pathlib
import statistics
import sys
import time
from collections.abc import Callable

from splatstream.format.manifest import parse_manifest

MODES = ("eager", "lazy", "lazy_then_all")


def load_reference(path: pathlib.Path):
    """A manifest module of another version, as splatstream.format._reference_manifest (its relative imports find
    this tree's format modules)."""
    spec = importlib.util.spec_from_file_location("splatstream.format._reference_manifest", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def run_once(parse: Callable, data: bytes, mode: str) -> float:
    """CPU milliseconds of one parse in `mode` (lazy_then_all: every payload entry read after a lazy parse). Each
    run starts from a collected heap: otherwise whichever run crosses the collector's thresholds pays for a
    collection of the runs before it (paired runs alternate, and the thresholds' period can favour one side)."""
    gc.collect()
    t0 = time.process_time()
    m = parse(data, lazy_payloads=mode != "eager")
    if mode == "lazy_then_all":
        for t in m.tiles:
            for name in t.groups:
                t.groups[name]
    return (time.process_time() - t0) * 1e3


def time_modes(data: bytes, repeat: int, ref=None) -> dict[str, dict[str, float]]:
    out = {}
    for mode in MODES:
        run_once(parse_manifest, data, mode)
        if ref is None:
            out[mode] = {"ms": round(statistics.median(run_once(parse_manifest, data, mode)
                                                       for _ in range(repeat)), 2)}
            continue
        run_once(ref.parse_manifest, data, mode)
        new, old = [], []
        for i in range(repeat):
            pair = [(parse_manifest, new), (ref.parse_manifest, old)]
            for parse, times in pair if i % 2 else pair[::-1]:
                times.append(run_once(parse, data, mode))
        out[mode] = {"ms": round(statistics.median(new), 2), "ref_ms": round(statistics.median(old), 2),
                     "ratio": round(statistics.median(a / b for a, b in zip(new, old, strict=True)), 3)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=pathlib.Path)
    ap.add_argument("--repeat", type=int, default=31)
    ap.add_argument("--ref", type=pathlib.Path, help="a manifest.py of another version to pair each run with")
    ap.add_argument("--json", type=pathlib.Path)
    args = ap.parse_args()
    ref = load_reference(args.ref) if args.ref else None
    rows = {}
    for scene in args.scenes:
        data = (scene / "manifest.msgpack").read_bytes()
        m = parse_manifest(data)
        sections = sum(len(p.sections) for _, _, p in m.payloads())
        times = time_modes(data, args.repeat, ref)
        rows[scene.name] = {"bytes": len(data), "tiles": len(m.tiles), "sections": sections, **times}
        cells = "  ".join(f"{mode} {t['ms']:7.2f} ms" + (f" (ref {t['ref_ms']:7.2f}, x{t['ratio']:.3f})" if ref else "")
                          for mode, t in times.items())
        print(f"{scene.name:24s} {len(data):>9,d} B {len(m.tiles):>5d} tiles {sections:>6d} sections  {cells}",
              flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
