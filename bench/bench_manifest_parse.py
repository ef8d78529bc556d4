"""Time parse_manifest on real manifests: eager, lazy (the streaming client's first frame) and lazy with every payload
entry read afterwards, as in-process medians.

    PYTHONPATH=. python bench/bench_manifest_parse.py SCENE_DIR [SCENE_DIR ...] [--repeat 15] [--json out.json]

Run it once with the code under test on PYTHONPATH and once with another checkout's (the A/B of BENCHMARKS.md,
"Manifest parse"): the script only imports `splatstream.format.manifest.parse_manifest`, which every version has.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import time

from splatstream.format.manifest import parse_manifest


def _read_all(m) -> None:
    for t in m.tiles:
        for name in t.groups:
            t.groups[name]


def time_parse(data: bytes, repeat: int) -> dict[str, float]:
    """Median milliseconds of each mode over `repeat` runs (after one untimed run)."""
    modes = {
        "eager": lambda: parse_manifest(data),
        "lazy": lambda: parse_manifest(data, lazy_payloads=True),
        "lazy_then_all": lambda: _read_all(parse_manifest(data, lazy_payloads=True)),
    }
    out = {}
    for name, run in modes.items():
        run()
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            run()
            times.append((time.perf_counter() - t0) * 1e3)
        out[name] = round(statistics.median(times), 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=pathlib.Path)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--json", type=pathlib.Path)
    args = ap.parse_args()
    rows = {}
    for scene in args.scenes:
        data = (scene / "manifest.msgpack").read_bytes()
        m = parse_manifest(data)
        sections = sum(len(p.sections) for _, _, p in m.payloads())
        rows[scene.name] = {"bytes": len(data), "tiles": len(m.tiles), "sections": sections,
                            **time_parse(data, args.repeat)}
        r = rows[scene.name]
        print(f"{scene.name:28s} {r['bytes']:>9,d} B {r['tiles']:>5d} tiles {sections:>6d} sections  eager "
              f"{r['eager']:8.2f} ms  lazy {r['lazy']:8.2f} ms  lazy+all {r['lazy_then_all']:8.2f} ms", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
