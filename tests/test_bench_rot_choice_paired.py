"""bench/rot_choice_paired.py (issue 32, cube8x4all32): the half-turn presets' measured rotation choice against their
half turns in one paired report, the stored rows it should reproduce, the ladder before and after, and the rule
that admits a preset on the choice scenes only."""
from __future__ import annotations

import json
import math

from conftest import load_bench

P = load_bench("rot_choice_paired")


def row(label: str, b: float, psnr: float | None, rotation: str = "norm8x4", preset: str | None = None,
        kind: str = "preset", overrides: dict | None = None) -> dict:
    return {"label": label, "preset": preset or label, "kind": kind, "overrides": overrides or {},
            "disk_bytes_per_splat": b, "disk_bytes": round(b * 1000), "psnr_mean": psnr,
            "formats": {"rotation": rotation}}


def half(preset: str, b: float, psnr: float) -> dict:
    return row(f"ht-{preset}", b, psnr, preset=preset, kind="variant", overrides={"rotation": "norm8x4"})


def write(path, rows: list[dict]) -> str:
    path.write_text(json.dumps({"rows": rows}))
    return str(path)


STORED = [row("very-high", 40.0, None), row("medium", 14.0, 62.0), row("medium-low-12bit", 12.0, 60.0),
          row("low-plus", 11.0, 55.0), row("low", 10.0, 54.0)]


def test_a_pair_reproducing_the_stored_row_and_keeping_its_ladder_place(tmp_path):
    paired = [row("low-plus", 11.03, 55.5, "cube8x4"), half("low-plus", 11.0, 55.0 + 5e-4)]
    t = P.scene_table(write(tmp_path / "p.json", paired), write(tmp_path / "s.json", STORED))["low-plus"]
    assert t["rotation"] == "cube8x4" and t["reproduces_stored"]  # the same bytes, the PSNR within GL noise
    assert math.isclose(t["psnr_change"], 0.5 - 5e-4) and math.isclose(t["bytes_change"], 11.03 / 11.0 - 1)
    assert t["between_before"] and t["between_after"] and P.passes(t)


def test_the_rule_needs_every_choice_scene_and_reports_the_held_out_ones(tmp_path):
    up = [row("low-plus", 11.03, 55.5, "cube8x4"), half("low-plus", 11.0, 55.0)]
    down = [row("low-plus", 11.03, 54.9, "cube8x4"), half("low-plus", 11.0, 55.0)]
    too_big = [row("low-plus", 11.4, 55.5, "cube8x4"), half("low-plus", 11.0, 55.0)]  # +3.6 % bytes
    past = [row("low-plus", 11.03, 60.5, "cube8x4"), half("low-plus", 11.0, 55.0)]  # above medium-low-12bit
    kept = [row("low-plus", 11.0, 55.0), half("low-plus", 11.0, 55.0)]  # a SOG-made input: the half turns
    s = write(tmp_path / "s.json", STORED)

    def table(rows, name):
        return P.scene_table(write(tmp_path / f"{name}.json", rows), s)

    assert not P.passes(table(down, "d")["low-plus"]) and not P.passes(table(too_big, "b")["low-plus"])
    assert not P.passes(table(past, "x")["low-plus"])  # it left its place between low and medium-low-12bit
    result = P.tabulate({"a": table(up, "a"), "b": table(up, "u"), "c": table(down, "c"), "d": table(kept, "k")},
                        ["a", "b"])
    v = result["verdict"]["low-plus"]
    assert v["admitted"] and (v["held_out_psnr_up"], v["held_out_psnr_down"], v["held_out_changed"]) == (0, 1, 1)
    assert not P.tabulate({"a": table(up, "a"), "c": table(down, "c")}, ["a", "c"])["verdict"]["low-plus"]["admitted"]
    assert "### low-plus: takes the measured choice" in P.markdown(result)
