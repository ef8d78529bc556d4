"""bench/preset_summary_ranges.py (issue 32, tidy32): every B/splat figure a preset's summary quotes (what
`encode --help` and `info` print) lies within the committed real-scene eval reports' range at its SH degree, to 3 %."""
from __future__ import annotations

import glob
import json

from conftest import ROOT, load_bench

from splatstream.format.presets import PRESET_SUMMARY

S = load_bench("preset_summary_ranges")
REPORTS = [json.load(open(p)) for p in sorted(glob.glob(str(ROOT / "bench" / "results" / "eval_real" / "*.json")))]


def test_quoted_figures_parse_ranges_single_figures_and_their_sh_degree():
    text = "x; about 13-15.5 B/splat at SH3, 12 at SH0 (statues, 61 dB), 45.6 at SH3 (fruit_drops, 64 dB); 11-bit SH"
    assert S.quoted(text) == [(13.0, 15.5, 3), (12.0, 12.0, 0), (45.6, 45.6, 3)]


def test_a_zero_rest_sh3_scene_counts_as_sh0_and_an_sh_preset_takes_its_base_there():
    rows = [{"kind": "preset", "label": p, "preset": p, "overrides": {}, "splats": 100, "disk_bytes_per_splat": b,
             "psnr_mean": 60.0, "attributes": {"sh": {"disk_bytes": 20}}} for p, b in (("high", 17.0), ("low", 9.0))]
    report = {"input": {"sh_degree": 3}, "rows": rows}
    assert S.scene_sh(report) == 0
    table = S.ranges([report])
    assert table["medium-high"][0]["bytes"] == (17.0, 17.0) and table["low"][0]["psnr"] == (60.0, 60.0)
    rows[0]["attributes"]["sh"]["disk_bytes"] = 5000  # 50 B/splat of SH: an SH3 scene
    assert S.scene_sh(report) == 3 and "medium-high" not in S.ranges([report])
    assert S.mismatches({"low": "about 9.2 at SH3, 8 at SH0"}, S.ranges([report]), 0.03) == [
        "low: 8-8 B/splat at SH0: no report measures it at SH0"]
    assert S.mismatches({"low": "about 9.2 at SH3"}, S.ranges([report]), 0.03) == []
    assert S.mismatches({"low": "about 8.5-9.5 at SH3"}, S.ranges([report]), 0.03)[0].startswith("low: 8.5-9.5")


def test_every_summary_figure_is_within_the_reports_range():
    assert len(REPORTS) >= 14
    table = S.ranges(REPORTS)
    assert table["high"][3]["scenes"] >= 1 and table["high"][0]["scenes"] >= 12  # lod_tile's empty SH3 counts as SH0
    assert sum(len(S.quoted(t)) for t in PRESET_SUMMARY.values()) >= 30
    assert S.mismatches(PRESET_SUMMARY, table, 0.03) == []
