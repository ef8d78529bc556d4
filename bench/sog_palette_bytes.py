"""Disk bytes of preset variants on one-tile encodes, counted as `splatstream eval` counts them (the payloads and
the manifest over the splats), without rendering: for variants whose PSNR an eval report already has (the same
quantisation with another transport, issue 32: `transport=keyed` stores the same texels in another order, so the
eval's PSNR is unchanged; checked on statue-massa, BENCHMARKS.md).

    python bench/sog_palette_bytes.py INPUT --json OUT.json -- CONFIG [CONFIG ...]

CONFIG as bench/eval_probe.py's ("LABEL:PRESET[,ATTR=FORMAT][,pos_g=G][,transport=keyed]...").
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from sh_coding_probe import parse_config, register  # noqa: E402

from splatstream.encode import EncodeOptions, encode_gaussians  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402


def scene_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(path) for f in files)


def main() -> None:
    argv = sys.argv[1:]
    cut = argv.index("--")
    ap = argparse.ArgumentParser()
    ap.add_argument("input")
    ap.add_argument("--json", required=True)
    args = ap.parse_args(argv[:cut])
    g = read_gaussians(args.input)
    out = {"input": os.path.basename(args.input), "splats": len(g), "rows": {}}
    for config in argv[cut + 1:]:
        name = register(*parse_config(config))
        with tempfile.TemporaryDirectory() as tmp:
            m = encode_gaussians(g, os.path.join(tmp, "s"), EncodeOptions(preset=name, lod=False))
            b = scene_bytes(os.path.join(tmp, "s"))
        out["rows"][name] = {"disk_bytes": b, "disk_bytes_per_splat": b / len(g), "version": list(m.version),
                             "position_filter": next(s.filter for s in m.tiles[0].groups["base"].sections
                                                     if s.name == "position")}
        print(f"{name}: {b / len(g):.3f} B/splat, version {m.version}, position {out['rows'][name]['position_filter']}")
    with open(args.json, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
