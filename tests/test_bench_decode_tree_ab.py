"""bench/decode_tree_ab.py (issue 32, vhdec33): a tree against itself decodes the same texels in both workers and
reports every case asked for. No timing is asserted."""
from __future__ import annotations

import json
import subprocess
import sys

from conftest import ROOT


def test_a_tree_against_itself_reports_each_case_with_equal_texels(tmp_path):
    out = tmp_path / "ab.json"
    subprocess.run([sys.executable, str(ROOT / "bench" / "decode_tree_ab.py"), "--before", str(ROOT), "--scenes",
                    "lod_tile_sh3_zero_rest", "--presets", "medium,very-high", "--runs", "2", "--kernels", "numpy",
                    "--cache", str(tmp_path / "cache"), "--json", str(out)], check=True, cwd=ROOT,
                   capture_output=True, timeout=600)
    report = json.loads(out.read_text())
    assert [(c["scene"], c["preset"]) for c in report["cases"]] == [("lod_tile_sh3_zero_rest", "medium"),
                                                                     ("lod_tile_sh3_zero_rest", "very-high")]
    for case in report["cases"]:
        assert len(case["texels_sha256"]) == 64  # both workers' digests, equal (else the script exits non-zero)
        assert case["splats"] > 0 and case["payloads"] > 0
        assert set(case["pass_ms"]) == {"before", "after"}
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["lod_tile_sh3_zero_rest__medium.pkl",
                                                                      "lod_tile_sh3_zero_rest__very-high.pkl"]
