"""bench/preset_dominance.py (issue 32): which preset dominates each peer point, the same with only the presets not
tuned on the point's scene (leave one scene out), the choices checked on other scenes, and the merged plot points."""
from __future__ import annotations

from conftest import load_bench


def load():
    return load_bench("preset_dominance")


D = load()


def row(kind: str, label: str, size: float, psnr: float | None) -> dict:
    return {"kind": kind, "label": label, "disk_bytes_per_splat": size, "psnr_mean": psnr}


def scene(name: str, rows: list[dict]) -> dict:
    s = {"presets": {}, "peers": {}, "input": {"path": f"/x/{name}", "splats": 1000, "sh_degree": 0}}
    for r in rows:
        (s["peers"] if r["kind"] == "compare" else s["presets"])[r["label"]] = r
    return s


def test_verdicts_smallest_preset_at_the_peers_psnr_and_the_goal():
    s = scene("guitar.ply", [row("preset", "medium", 14.0, 60.0), row("preset", "low", 10.0, 50.0),
                             row("preset", "very-high", 40.0, None), row("compare", "st-spz", 12.0, 49.0),
                             row("compare", "st-sog", 12.0, 55.0)])
    spz, sog = D.verdicts(s)
    assert (spz["preset"], spz["met"]) == ("low", True) and abs(spz["ratio"] - 10 / 12) < 1e-12
    # medium is the smallest at >= 55 dB but 14 / 12 > 0.90; at 0.90 of its bytes low is 5 dB short
    assert (sog["preset"], sog["met"]) == ("medium", False)
    assert sog["best_within_goal"] == ("low", 10.0, 50.0)


def test_leave_one_scene_out_keeps_only_presets_not_tuned_on_the_scene():
    rows = [row("preset", "low", 10.0, 50.0), row("preset", "low-plus-9bit-sh5", 9.0, 52.0),
            row("preset", "very-high", 40.0, None)]
    assert set(D.held_out_presets("flowers.ply", scene("flowers.ply", rows)["presets"])) == {"low", "very-high"}
    assert set(D.held_out_presets("guitar.ply", scene("guitar.ply", rows)["presets"])) == \
        {"low", "low-plus-9bit-sh5", "very-high"}
    assert set(D.held_out_presets("donut_sh0_no_normals.ply", scene("d.ply", rows)["presets"])) == {"very-high"}


def test_summary_and_held_out_table_count_points_per_scene_kind():
    scenes = {
        "guitar.ply": scene("guitar.ply", [row("preset", "low", 10.0, 50.0), row("compare", "st-spz", 12.0, 49.0)]),
        "donut_sh0_no_normals.ply": scene("donut_sh0_no_normals.ply", [row("preset", "low", 10.0, 50.0),
                                                                       row("compare", "st-spz", 12.0, 49.0)]),
    }
    n = D.summary(scenes)
    assert n == {"points": 2, "met": 2, "held_out_points": 1, "held_out_met": 1, "loo_met": 1}
    text = D.held_out_markdown(scenes)
    # the choice "low against SPZ" was made on the bench scenes (donut among them) and holds on guitar
    assert "| `low` against st-spz" in text and "donut_sh0_no_normals 0.83, +1.00 dB |" in text
    assert "| 1 of 1 | - |" in text
    assert "every lossy preset was tuned on this scene" in text


def test_merged_points_join_identical_presets_and_sort_by_bytes():
    # guitar (SH0): medium-low and its per-splat SH variants differ only in zstd level (12.88 / 12.97 B)
    presets = {r["label"]: r for r in [row("preset", "medium-low-sh16", 12.97, 70.71),
                                       row("preset", "low", 10.41, 49.47), row("preset", "medium-low", 12.88, 70.71),
                                       row("preset", "medium-high", 17.40, 77.27), row("preset", "high", 17.40, 77.27),
                                       row("preset", "medium", 14.80, 88.26)]}
    merged = D._merged_points(presets)
    assert [r["label"] for r in merged] == ["low", "medium-low = -sh16", "medium", "high = medium-high"]
    assert [r["disk_bytes_per_splat"] for r in merged] == [10.41, 12.88, 14.80, 17.40]


def test_sh0_cells_of_the_per_splat_sh_presets_follow_the_measured_rotation():
    """On an SH0 scene the per-splat SH presets are their base's planes; medium-low's measured cube8x4 is theirs too
    (they measure the same candidates, shvariants32), while a rotation format they do not measure would be named."""
    ml = {**row("preset", "medium-low", 12.0, 60.0), "formats": {"rotation": "cube8x4"}}
    table = D.preset_table({"d.ply": scene("d.ply", [ml])})
    line = next(s for s in table.splitlines() if s.startswith("| medium-low-sh16 |"))
    assert line == "| medium-low-sh16 | = medium-low (no SH bands) |"
    ml["formats"] = {"rotation": "norm565"}
    table = D.preset_table({"d.ply": scene("d.ply", [ml])})
    line = next(s for s in table.splitlines() if s.startswith("| medium-low-sh8 |"))
    assert line == "| medium-low-sh8 | = medium-low with norm8x4 rotations (no SH bands) |"
