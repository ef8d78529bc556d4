"""bench/rot_choice_table.py and bench/very_low_trade.py (issue 32, cube32): medium-low's row before and after its
measured rotation choice, its neighbours and the rows that changed side of it; very-low's trade against
very-low-rgb127."""
from __future__ import annotations

import json
import math

from conftest import load_bench

T = load_bench("rot_choice_table")
V = load_bench("very_low_trade")


def row(label: str, b: float, psnr: float | None, rotation: str = "norm8x4") -> dict:
    return {"label": label, "preset": label, "kind": "preset", "disk_bytes_per_splat": b, "psnr_mean": psnr,
            "formats": {"rotation": rotation}}


def write(path, rows: list[dict]) -> str:
    path.write_text(json.dumps({"rows": rows}))
    return str(path)


def test_neighbours_skip_twins_and_rows_that_change_side_are_named(tmp_path):
    stored = [row("very-high", 40.0, None), row("medium", 14.0, 62.0), row("medium-low-sh16", 12.42, 60.7),
              row("medium-low", 12.41, 60.6), row("medium-low-12bit", 12.0, 60.0), row("low", 10.0, 55.0)]
    new = [row("medium-low", 12.46, 61.0, "cube8x4")]
    r = T.scene_row(write(tmp_path / "a.json", stored), write(tmp_path / "b.json", new))
    assert r["neighbours"] == ("medium-low-12bit", "medium")  # -sh16 is within 1 % of its bytes: a twin
    assert r["between_before"] and r["between_after"] and r["rotation"] == "cube8x4"
    assert r["crossed"] == ["medium-low-sh16"]  # passed in bytes and PSNR; very-high's null PSNR is +inf
    assert math.isclose(r["psnr_change"], 0.4) and math.isclose(r["bytes_change"], 12.46 / 12.41 - 1)
    # the GL renders' noise is no change of side
    same = [row("medium-low", 12.41, 60.6 + 5e-5)]
    assert T.scene_row(write(tmp_path / "a.json", stored), write(tmp_path / "c.json", same))["crossed"] == []


def test_very_low_trade_is_db_per_e_fold_of_bytes():
    ref, v = row("very-low-rgb127", 10.0, 40.0), row("very-low", 10.0 / math.e, 35.0)
    assert math.isclose(V.trade(ref, v), 5.0)


def test_another_presets_row_is_compared_with_preset(tmp_path):
    """--preset (shvariants32): medium-low-sh16's row against its own neighbours; medium-low, 1.5 % under it in
    bytes, is a neighbour, and the row that changes side of it when -sh16 takes cube8x4 too."""
    stored = [row("medium", 14.0, 62.0), row("medium-low-sh16", 13.07, 52.6), row("medium-low", 12.88, 53.5),
              row("medium-low-12bit", 12.71, 50.3), row("low", 10.0, 45.0)]
    new = [row("medium-low-sh16", 12.80, 53.5, "cube8x4")]
    r = T.scene_row(write(tmp_path / "a.json", stored), write(tmp_path / "b.json", new), "medium-low-sh16")
    assert r["neighbours"] == ("medium-low", "medium") and r["rotation"] == "cube8x4"
    assert not r["between_before"] and not r["between_after"]
    assert r["crossed"] == ["medium-low"]  # passed in bytes, met in PSNR
    assert math.isclose(r["psnr_change"], 0.9)
