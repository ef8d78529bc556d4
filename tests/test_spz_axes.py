"""An SPZ stored without the format's RUB axis turn (what splat-transform 3.x writes) reads turned 180 degrees about
x; `eval --compare` warns about it (and measures it turned back with --spz-axes auto or rdf), and `convert
--spz-axes rdf` reads it upright."""
from __future__ import annotations

import json

import numpy as np
from conftest import real, run_cli

from splatstream.axes import RDF_TO_RUB, turn, turned_against
from splatstream.io import read_gaussians, write_gaussians


def spz_pair(tmp_path):
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    ours, theirs = tmp_path / "ours.spz", tmp_path / "theirs.spz"
    write_gaussians(g, ours)  # RUB, as the format says
    write_gaussians(turn(g, RDF_TO_RUB), theirs)  # the PLY's RDF values stored as they are
    return g, ours, theirs


def test_a_turned_spz_is_recognised_against_its_scene(tmp_path):
    g, ours, theirs = spz_pair(tmp_path)
    assert not turned_against(read_gaussians(ours), g, RDF_TO_RUB)
    assert turned_against(read_gaussians(theirs), g, RDF_TO_RUB)


def test_convert_reads_an_rdf_spz_upright(tmp_path):
    g, _, theirs = spz_pair(tmp_path)
    r = run_cli("convert", theirs, tmp_path / "back.ply", "--spz-axes", "rdf", "-q")
    assert r.returncode == 0, r.stderr
    back = read_gaussians(tmp_path / "back.ply")
    assert np.abs(back.positions - g.positions).max() < 1e-3  # SPZ's 12-bit fixed point, not a turn
    r = run_cli("convert", real("fruit_drops_sh3.ply"), tmp_path / "x.ply", "--spz-axes", "rdf")
    assert r.returncode == 2 and "is not an SPZ file" in r.stderr


def test_eval_warns_about_a_turned_spz_and_measures_it_turned_back_on_request(tmp_path):
    _, ours, theirs = spz_pair(tmp_path)
    src = real("fruit_drops_sh3.ply")
    common = ["--presets", "none", "--views", "2", "--size", "96x96"]
    r = run_cli("eval", src, *common, "--compare", f"ours={ours}", f"theirs={theirs}", "--json", tmp_path / "a.json")
    assert r.returncode == 0, r.stderr
    warned = [line for line in r.stderr.splitlines() if "warning" in line]
    assert len(warned) == 1 and str(theirs) in warned[0] and "turned 180 degrees about x" in warned[0], r.stderr
    rows = {row["label"]: row for row in json.loads((tmp_path / "a.json").read_text())["rows"]}
    r = run_cli("eval", src, *common, "--compare", f"theirs={theirs}", "--spz-axes", "auto", "--json",
                tmp_path / "b.json")
    assert r.returncode == 0, r.stderr
    fixed = json.loads((tmp_path / "b.json").read_text())["rows"][0]
    assert fixed["spz_turned_back"] is True
    assert fixed["psnr_mean"] > rows["theirs"]["psnr_mean"] + 10
    # as good as the file written with the turn (within the rounding of values quantised in the other axes)
    assert abs(fixed["psnr_mean"] - rows["ours"]["psnr_mean"]) < 3.0
