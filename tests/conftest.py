import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("SPLATSTREAM_SHARED", ROOT.parent / "shared"))
REAL = SHARED / "data" / "real"
REAL_PLYS = ["fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply", "donut_sh0_no_normals.ply"]


def real(name: str) -> pathlib.Path:
    path = REAL / name
    if not path.exists():
        pytest.skip(f"real scene {path} not available")
    return path


def run_cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    """Run the installed CLI the way a user does (a separate process, no stdin)."""
    return subprocess.run([sys.executable, "-m", "splatstream.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, stdin=subprocess.DEVNULL, timeout=600)
