"""bench/far31_table.py (issue 31, far31): the budget rows (default, before and after far31, best peer, margins) and
the far-frame rows (the three encodes per factor and the views below the default), on small JSONs."""
from __future__ import annotations

import json

from conftest import load_bench

T = load_bench("far31_table")


def ours(n: int, psnr: float) -> dict:
    return {"budget": n, "psnr_mean": psnr, "splats_drawn": n, "splats_drawn_per_view": [n, n],
            "bytes_downloaded_mean": 1500, "drawn_tile_bytes_mean": 1000}


def test_budget_rows_and_far_rows(tmp_path):
    dd, before, after = (tmp_path / n for n in ("default", "before", "after"))
    for p in (dd, before, after):
        p.mkdir()
    default = {"scene": "guitar", "budgets": [0.02, 3000.0], "budget_splats": [200, 3000],
               "ours": [ours(200, 25.0), ours(3000, 30.0)],
               "peers": [{"budget": 200, "psnr_mean": 24.5, "splats_drawn": 200}],
               "spark": [], "spark_clamp": [], "shipped": [{"level": 2, "splats_drawn": 3000, "psnr_mean": 30.5}]}
    (dd / "guitar.json").write_text(json.dumps(default))
    (before / "guitar.json").write_text(json.dumps({"ours": [ours(200, 26.0), ours(3000, 31.0)]}))
    (after / "guitar.json").write_text(json.dumps({"ours": [ours(3000, 31.25), ours(200, 25.9)]}))
    rows = T.budget_rows("guitar", [str(dd)], [str(before)], [str(after)])
    assert rows == [
        "| guitar | 2 % (200) | 25.00 | 26.00 | 25.90 | -0.10 | 24.50 (splat-transform) | **+1.40** (+1.50) |",
        "|  | 3,000 | 30.00 | 31.00 | 31.25 | +0.25 | 30.50 (shipped L2) | **+0.75** (+0.50) |"]
    assert T.budget_rows("donut", [str(dd)], [str(before)], [str(after)]) == []

    def side(psnr, views):
        return {"psnr": psnr, "psnr_views": views, "drawn_splats": [180, 190]}

    far_before = {"rows": [{"scene": "guitar", "factor": 32.0, "before": side(49.0, [50.0, 48.0]),
                            "after": side(48.9, [50.5, 47.0])}]}
    far_after = {"rows": [{"scene": "guitar", "factor": 32.0, "before": side(48.9, [50.5, 47.0]),
                           "after": side(49.4, [50.6, 47.9])},
                          {"scene": "guitar", "factor": 64.0, "before": side(1, [1, 1]), "after": side(1, [1, 1])}]}
    assert T.far_rows(far_before, far_after) == [
        "| guitar | 32x | 180-190 | 49.00 | 48.90 | 49.40 | +0.50 | -0.10 (1) | **+0.40** (1; worst view -0.10) |"]
