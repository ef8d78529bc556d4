"""Lossless WebP effort of our SOG writers (writers/sog.py: `export-sog-lod` and `convert` to .sog): bytes against
encoding time for libwebp's (method, quality) pairs (issue 35; results in BENCHMARKS.md).

    .venv/bin/python bench/sog_webp_effort.py [SCENE ...]   (default: fruit_drops_sh3.ply donut_sh0_no_normals.ply
                                                            winter_fountain.splat from ../shared/data/real)

For each scene: our encode (preset medium, --max-leaf-splats 2000), then its streamed SOG written in this process
once per pair (writers/sog.py's WEBP_METHOD and WEBP_QUALITY set for the run). Prints the bytes of all files and
the CPU seconds of the whole export (process time: the machine is shared, wall time is not the export's).
"""
from __future__ import annotations

import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]

from splatstream.sog_export import export_streamed_sog  # noqa: E402
from splatstream.writers import sog  # noqa: E402

REAL = ROOT.parent / "shared" / "data" / "real"
PAIRS = ((4, 100), (4, 50), (2, 50), (1, 50), (0, 100))


def main() -> None:
    scenes = sys.argv[1:] or ["fruit_drops_sh3.ply", "donut_sh0_no_normals.ply", "winter_fountain.splat"]
    default = (sog.WEBP_METHOD, sog.WEBP_QUALITY)
    print(f"default (method, quality): {default}")
    print("| scene | method | quality | bytes | vs (4, 100) | export CPU s |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in scenes:
            path = pathlib.Path(name) if pathlib.Path(name).exists() else REAL / name
            scene = pathlib.Path(tmp) / path.stem
            subprocess.run([sys.executable, "-m", "cli", "encode", str(path), str(scene), "--max-leaf-splats", "2000",
                            "-q"], check=True, stdin=subprocess.DEVNULL)
            base = None
            for method, quality in PAIRS:
                sog.WEBP_METHOD, sog.WEBP_QUALITY = method, quality
                out = pathlib.Path(tmp) / f"{path.stem}-{method}-{quality}"
                t = time.process_time()
                report = export_streamed_sog(scene, out)
                cpu = time.process_time() - t
                base = base or report.bytes
                print(f"| {path.name} | {method} | {quality} | {report.bytes:,} | {report.bytes / base:.4f} | "
                      f"{cpu:.2f} |", flush=True)
    sog.WEBP_METHOD, sog.WEBP_QUALITY = default


if __name__ == "__main__":
    main()
