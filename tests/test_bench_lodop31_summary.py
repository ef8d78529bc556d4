"""bench/lodop31_summary.py (issue 31, branch lodop31): per-level changes against `base`, ranked from the first
merged level, and the brief's gate."""
from __future__ import annotations

import json

from conftest import load_bench

S = load_bench("lodop31_summary")


def write(path, scene, variants):
    path.write_text(json.dumps({"scene": scene, "splats": 1000, "variants": variants}))
    return str(path)


def levels(psnrs):
    return [{"level": 3 + i, "count": 10 * 2 ** i, "share": 0.016 * 2 ** i, "psnr": p} for i, p in enumerate(psnrs)]


def test_deltas_rank_levels_from_the_first_merged_one_and_merge_a_scenes_files(tmp_path, capsys):
    a = write(tmp_path / "a.json", "s", {"base": levels([20, 22, 24, 26, 28, 30])})
    b = write(tmp_path / "b.json", "s", {"opmax=2": levels([19, 21.5, 24.5, 26.5, 29, 30])})
    rows = S.deltas([a, b])["opmax=2"]
    assert [(lv, k) for _s, lv, k, _d in rows] == [(3, 5), (4, 4), (5, 3), (6, 2), (7, 1), (8, 0)]
    assert [round(d, 2) for *_x, d in rows] == [-1.0, -0.5, 0.5, 0.5, 1.0, 0.0]
    assert S.main([a, b]) == 0
    out = capsys.readouterr().out
    # k >= 2: -1.0, -0.5, +0.5, +0.5 -> median 0.0; worst -1.0: the gate fails
    assert "k >= 2 median +0.00 (2/4 >= +0.3); worst level -1.00 (2/6 below -0.3): fails" in out
    assert "| s | -1.00 | -0.50 | +0.50 | +0.50 | +1.00 | +0.00 |" in out
