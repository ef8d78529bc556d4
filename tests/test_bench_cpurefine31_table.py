"""bench/cpurefine31_table.py (issue 31): the best peer of a budget (a shipped level of exactly that count counts),
the margins, the union of refined rows over directories and the counts of points >= +1 dB, on small JSONs."""
from __future__ import annotations

import json

import pytest
from conftest import load_bench

T = load_bench("cpurefine31_table")


def ours(n: int, psnr: float, drawn=(98, 100)) -> dict:
    return {"budget": n, "psnr_mean": psnr, "splats_drawn": n, "splats_drawn_per_view": [d * n // 100 for d in drawn],
            "bytes_downloaded_mean": 1500, "drawn_tile_bytes_mean": 1000}


def default_json(name: str) -> dict:
    return {"scene": name, "splats": 10000, "sh_degree": 0, "budgets": [0.02, 0.5, 3000.0],
            "budget_splats": [200, 5000, 3000],
            "ours": [ours(200, 25.0), ours(5000, 35.0), ours(3000, 30.0)],
            "peers": [{"budget": 200, "psnr_mean": 24.5, "splats_drawn": 200},
                      {"budget": 5000, "psnr_mean": 36.0, "splats_drawn": 5000},
                      {"budget": 3000, "psnr_mean": None, "splats_drawn": 3000}],
            "spark": [{"budget": 200, "psnr_mean": 24.9, "splats_drawn": 200}],
            "spark_clamp": [],
            "shipped": [{"level": 2, "splats_drawn": 3000, "psnr_mean": 30.5}]}


def test_best_peer_takes_the_highest_level_of_that_count_shipped_levels_included():
    d = default_json("donut")
    assert T.best_peer(d, 200) == (24.9, "Spark")
    assert T.best_peer(d, 5000) == (36.0, "splat-transform")
    assert T.best_peer(d, 3000) == (30.5, "shipped L2")
    assert T.best_peer(d, 7) == (None, "-")


def test_points_margins_fill_and_bytes():
    d = default_json("donut")
    pts = T.points(d, {3000: ours(3000, 31.6), 200: ours(200, 26.0, drawn=(97, 101)), 5000: ours(5000, 37.5)})
    assert [p["budget"] for p in pts] == [200, 5000, 3000]  # the default JSON's budget order
    p200, p5000, p3000 = pts
    assert p200["fraction"] == 0.02 and p3000["fraction"] is None
    assert p200["gain"] == pytest.approx(1.0) and p200["margin"] == pytest.approx(26.0 - 24.9)
    assert p200["margin_default"] == pytest.approx(25.0 - 24.9)
    assert p200["fill"] == (0.97, 1.01) and p200["bytes_ratio"] == 1.5
    assert p5000["margin"] == pytest.approx(1.5) and p5000["margin_default"] == pytest.approx(-1.0)
    assert p3000["margin"] == pytest.approx(1.1) and p3000["who"] == "shipped L2"
    s = T.summary(pts, "x")
    assert "at 3 of 3" in s and "the default at 0 of 3" in s
    assert "(over)" in T.table([("donut", d, pts)], {"statue-st-peter"})


def test_refined_rows_are_the_union_of_directories_and_the_summary_splits_scenes(tmp_path, capsys):
    dd, r1, r2 = (tmp_path / n for n in ("default", "r1", "r2"))
    for p in (dd, r1, r2):
        p.mkdir()
    (dd / "donut.json").write_text(json.dumps(default_json("donut")))
    (dd / "playbot.json").write_text(json.dumps(default_json("playbot")))
    (r1 / "donut.json").write_text(json.dumps({"ours": [ours(200, 26.0), ours(5000, 37.5)]}))
    (r2 / "donut.json").write_text(json.dumps({"ours": [ours(200, 99.0), ours(3000, 29.0)]}))
    (r1 / "playbot.json").write_text(json.dumps({"ours": [ours(200, 24.0), ours(3000, 29.0)]}))
    default, refined = T.load_scene("donut", [str(dd)], [str(r1), str(r2)])
    assert sorted(refined) == [200, 3000, 5000] and refined[200]["psnr_mean"] == 26.0  # the first directory's row
    assert T.load_scene("guitar", [str(dd)], [str(r1)]) is None
    md = tmp_path / "t.md"
    assert T.main(["--default", str(dd), "--refined", str(r1), "--refined", str(r2), "--markdown", str(md),
                   "--plot", str(tmp_path / "t.png")]) == 0
    text = md.read_text()
    assert "the scenes of ../shared/data, budgets of 2 / 6 / 25 / 50 %: 2 points; refined >= +1 dB above the best " \
           "peer at 2 of 2" in text
    assert "outside it (playbot), 2 / 6 / 25 / 50 %: 1 points; refined >= +1 dB above the best peer at 0 of 1" in text
    assert "at the counts of its shipped levels: 1 points; refined >= +1 dB above the best peer at 0 of 1" in text
    assert (tmp_path / "t.png").stat().st_size > 0
