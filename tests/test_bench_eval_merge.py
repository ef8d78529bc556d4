"""bench/eval_merge.py (issue 32): a preset or a peer point measured alone is merged into a scene's report only when
both measured the same scene the same way (input, cameras, size, renderer), replacing a row of the same label."""
from __future__ import annotations

import json
import pathlib

from conftest import load_bench


def load():
    return load_bench("eval_merge")


M = load()


def report(commit: str, rows: list[dict], cameras=((0.0, 1.0, 2.0),)) -> dict:
    return {"source": {"commit": commit}, "input": {"path": "/a/flowers.ply", "bytes": 10, "splats": 2},
            "cameras": [list(c) for c in cameras], "size": [64, 64], "renderer": "gl", "rows": rows}


def row(kind: str, label: str, psnr: float) -> dict:
    return {"kind": kind, "label": label, "psnr_mean": psnr}


def write(path: pathlib.Path, data: dict) -> str:
    path.write_text(json.dumps(data))
    return str(path)


def test_peer_rows_merge_only_with_peers_and_replace_their_label(tmp_path):
    target = write(tmp_path / "t.json", report("a", [row("preset", "medium", 50.0), row("compare", "st-spz", 40.0),
                                                     row("compare", "st-sog", 1.0)]))
    source = write(tmp_path / "s.json", report("b", [row("preset", "new", 45.0), row("compare", "st-sog", 44.9)]))
    assert M.main([target, source]) == 0
    rows = json.loads(pathlib.Path(target).read_text())["rows"]
    # without --peers the peer row stays as measured; the preset goes before the peers
    assert [(r["label"], r["psnr_mean"]) for r in rows] == [("medium", 50.0), ("new", 45.0), ("st-spz", 40.0),
                                                            ("st-sog", 1.0)]
    assert M.main([target, source, "--peers", "--only", "st-sog"]) == 0
    rows = json.loads(pathlib.Path(target).read_text())["rows"]
    assert [(r["label"], r["psnr_mean"]) for r in rows] == [("medium", 50.0), ("new", 45.0), ("st-spz", 40.0),
                                                            ("st-sog", 44.9)]
    assert rows[-1]["merged_from"] == {"commit": "b"}


def test_other_cameras_are_refused_and_the_target_is_untouched(tmp_path, capsys):
    before = report("a", [row("compare", "st-spz", 40.0)])
    target = write(tmp_path / "t.json", before)
    source = write(tmp_path / "s.json", report("b", [row("compare", "st-sog", 44.9)], cameras=((0.0, 1.0, 2.5),)))
    assert M.main([target, source, "--peers"]) == 1
    assert "cameras differ" in capsys.readouterr().err
    assert json.loads(pathlib.Path(target).read_text()) == before


def test_cameras_an_ulp_apart_are_the_same_views(tmp_path):
    """step32: camera.look_at_near_far's refactor moved fruit_drops' eyes and near planes by an ulp (every view's PSNR
    the same to the last digit); such cameras are the same views, a real difference is still refused."""
    target = write(tmp_path / "t.json", report("a", [row("preset", "medium", 50.0)], cameras=((0.35712093311489490,
                                                                                             -2.5069121102696568),)))
    source = write(tmp_path / "s.json", report("b", [row("preset", "new", 45.0)], cameras=((0.35712093311489485,
                                                                                          -2.506912110269657),)))
    assert M.main([target, source]) == 0
    assert [r["label"] for r in json.loads(pathlib.Path(target).read_text())["rows"]] == ["medium", "new"]
    assert not M.same_cameras([{"eye": [0.0, 1.0], "up": [0, -1, 0]}], [{"eye": [0.0, 1.0 + 1e-9], "up": [0, -1, 0]}])
    assert not M.same_cameras([{"eye": [0.0, 1.0]}], [{"eye": [0.0, 1.0], "near": 0.1}])
