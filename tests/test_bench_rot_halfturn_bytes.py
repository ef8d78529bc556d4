"""bench/rot_halfturn_bytes.py (issue 32, evalrefresh32): a preset's bytes with and without the half-turn rotation
gauge, encoded as `evaluate` encodes it, and the report rows rewritten from that A/B (bytes only, quality kept)."""
from __future__ import annotations

import copy

import pytest
from conftest import load_bench, real

from splatstream.format import presets as P
from splatstream.io import read_gaussians

H = load_bench("rot_halfturn_bytes")
UP = [0.0, -1.0, 0.0]


def test_every_smallest_three_preset_is_measured_and_none_other():
    names = H.smallest_three_presets()
    assert {"high", "medium", "medium-low", "low-plus", "medium-low-palette"} <= set(names)
    assert not {"very-high", "low", "very-low", "very-low-rgb127"} & set(names)


def test_both_encodes_leave_the_preset_table_as_it_was(tmp_path):
    path = real("fruit_drops_sh3.ply")
    g = read_gaussians(path)
    report = {"input": {"path": str(path), "bytes": path.stat().st_size}, "camera_rule": {"up": UP},
              "encode_options": {"lod": False, "zstd_level": None}}
    table = dict(P.PRESET_ROTATION_GAUGE)
    # low-plus-9bit: low-plus measures cube8x4 on fruit_drops since cube8x4all32, whose gauge is the cube in both arms
    off = H.encoded_bytes(g, "low-plus-9bit", report, None, str(tmp_path / "off"))
    half = H.encoded_bytes(g, "low-plus-9bit", report, "half-turns", str(tmp_path / "half"))
    assert P.PRESET_ROTATION_GAUGE == table
    # the same texel formats and GPU bytes; the rotation plane's bytes move (its values in another order)
    assert {a: s["format"] for a, s in half["attributes"].items()} == {a: s["format"] for a, s in
                                                                         off["attributes"].items()}
    assert half["attributes"]["rotation"]["disk_bytes"] != off["attributes"]["rotation"]["disk_bytes"]
    assert half["gpu_bytes"] == off["gpu_bytes"]
    assert half["disk_bytes"] == half["bytes_on_disk_total"]


def ab_row(scene: str, preset: str, off: int, half: int) -> dict:
    return {"scene": scene, "preset": preset, "splats": 100, "off": off, "half_turns": half,
            "half_turns_fields": {"disk_bytes": half, "disk_bytes_per_splat": half / 100, "compression": 2.0,
                                  "bytes_on_disk_total": half, "leaf_bytes_on_disk": half - 50, "gpu_bytes": 1600,
                                  "attributes": {"rotation": {"disk_bytes": 7}}}}


def report_of(rows: list[dict]) -> dict:
    return {"rows": [{"label": label, "kind": "preset", "preset": label, "overrides": {}, "gpu_bytes": 1600,
                      "disk_bytes": disk, "psnr_mean": 50.0, "psnr_per_view": [49.0, 51.0]} for label, disk in rows]
            + [{"label": "st-sog", "kind": "compare", "disk_bytes": 999}]}


def test_apply_rewrites_only_the_named_presets_bytes():
    results = [ab_row("donut", "high", 2000, 1900), ab_row("donut", "low-plus", 1200, 1180),
               ab_row("fruit", "high", 3000, 2950)]
    report = report_of([("high", 2000), ("low-plus", 1200), ("low", 1000)])
    before = copy.deepcopy(report)
    changed = H.apply(report, H.scene_of("bench/results/eval_heldout/donut_4x384.json"), results, ["high"], "abc")
    assert changed == [("high", 2000, 1900)]
    high = report["rows"][0]
    assert high["disk_bytes"] == 1900 and high["leaf_bytes_on_disk"] == 1850
    assert high["bytes_refreshed"]["disk_bytes_before"] == 2000 and high["bytes_refreshed"]["commit"] == "abc"
    assert high["psnr_mean"] == 50.0 and high["gpu_bytes"] == 1600
    assert report["rows"][1:] == before["rows"][1:]
    # applied again: nothing left to do (within the manifest's few bytes)
    assert H.apply(report, "donut", results, ["high"], "abc") == []


def test_apply_refuses_rows_stale_for_another_reason():
    results = [ab_row("donut", "high", 2000, 1900)]
    with pytest.raises(ValueError, match="stale for another reason"):
        H.apply(report_of([("high", 2500)]), "donut", results, ["high"], "abc")
    with pytest.raises(ValueError, match="not in the A/B"):
        H.apply(report_of([("high", 2000)]), "fruit", results, ["high"], "abc")


def test_scene_names():
    assert H.scene_of("a/playcanvas-logo_4x384.json") == "playcanvas-logo"
    assert H.scene_of("a/statue-angel-with-candlestick.json") == "statue-angel-with-candlestick"
    assert H.scene_of("a/winter_fountain.json") == "winter_fountain"
