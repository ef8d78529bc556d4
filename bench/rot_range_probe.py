"""`bench/eval_probe.py` with two bench-only rotation formats: the cube gauge's ranged x, y, z (format.md 4.5,
`cube565`'s rule) in the texels of the smallest-three presets (issue 32, rotrange32, part 3; not in the format).

    python bench/rot_range_probe.py SCENE --json OUT.json [eval options] -- CONFIG [CONFIG ...]
    python bench/rot_range_probe.py table NAME=OUT.json ... [--markdown T.md]   (the probes' A/B table)

The table pairs `probe-m` with `probe-mc` (`medium`: half turns, the cube in cube10_2) and `probe-ml` with
`probe-mlc` (`medium-low`: half turns, the cube in cube8x4): B/splat and mean PSNR each, and the change.

`cube10_2`: norm10_2's texels, x, y, z in its three 10-bit fields over [-tan(pi/8), tan(pi/8)] (1.7x finer than
smallest three's [-0.707, 0.707]), the 2-bit field unused (no index); `cube8x4`: norm8x4's, x, y, z in three bytes.
Both decode as `cube565` does (xyz mode, w derived) and make the encoder store the cube gauge (presets.rotation_gauge),
e.g. `mc:medium,rotation=cube10_2 mlc:medium-low,rotation=cube8x4` against `m:medium ml:medium-low` (half turns).
The formats are registered in this process only (texformats, transport, the validator's and presets' format lists,
written as version 1.13 like cube565): no file written here is a valid scene for any other reader.
"""
from __future__ import annotations

import importlib
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from splatstream.format import presets, texformats, transport  # noqa: E402

validate = importlib.import_module("splatstream.format.manifest.validate")
versions = importlib.import_module("splatstream.format.manifest.versions")

PROBE_FORMATS = {"cube10_2": "norm10_2", "cube8x4": "norm8x4"}


def register() -> None:
    for name, texels in PROBE_FORMATS.items():
        base = texformats.FORMATS[texels]
        texformats.FORMATS[name] = texformats.TexelFormat(
            name, base.bits_per_texel, base.components, base.levels, base.gl_internal, base.block, base.shuffle,
            same_texels_as=texels, rotation_range=texformats.CUBE_GAUGE_RANGE)
        texformats.TEXEL_DTYPES[name] = texformats.TEXEL_DTYPES[texels]
        transport.FIELD_LAYOUTS[name] = transport.FIELD_LAYOUTS[texels]
    names = tuple(PROBE_FORMATS)
    for module in (texformats, validate, presets):
        if hasattr(module, "VALUE_FORMATS"):
            module.VALUE_FORMATS = module.VALUE_FORMATS + names
        if hasattr(module, "ROTATION_ONLY_FORMATS"):
            module.ROTATION_ONLY_FORMATS = module.ROTATION_ONLY_FORMATS + names
    for module in (versions, validate):
        module.FORMATS_1_13 = module.FORMATS_1_13 + names


PAIRS = (("medium", "probe-m", "probe-mc"), ("medium-low", "probe-ml", "probe-mlc"))


def table(argv: list[str]) -> str:
    import json

    markdown = None
    if "--markdown" in argv:
        i = argv.index("--markdown")
        markdown = argv[i + 1]
        argv = argv[:i] + argv[i + 2:]
    lines = ["| scene | " + " | ".join(f"`{p}`: half turns -> cube ({'cube10_2' if p == 'medium' else 'cube8x4'})"
                                      for p, _, _ in PAIRS) + " |", "|---|" + "---|" * len(PAIRS)]
    for arg in argv:
        name, path = arg.split("=", 1)
        rows = {r["label"]: r for r in json.load(open(path))["rows"]}
        cells = []
        for _, a, b in PAIRS:
            ra, rb = rows[a], rows[b]
            ba, bb = ra["disk_bytes_per_splat"], rb["disk_bytes_per_splat"]
            cells.append(f"{ba:.2f} -> {bb:.2f} B ({100 * (bb / ba - 1):+.1f}%), {ra['psnr_mean']:.2f} -> "
                         f"{rb['psnr_mean']:.2f} dB ({rb['psnr_mean'] - ra['psnr_mean']:+.2f})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    if markdown:
        open(markdown, "w").write(text)
    return text


if __name__ == "__main__":
    if sys.argv[1:2] == ["table"]:
        print(table(sys.argv[2:]))
        sys.exit(0)
    register()
    from eval_probe import run  # noqa: E402

    sys.exit(run(sys.argv[1:]))
