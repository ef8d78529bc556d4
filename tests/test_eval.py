import json
import math
import os

import numpy as np
import pytest
from conftest import ROOT, real, run_cli
from PIL import Image

from cli.main import main
from splatstream.camera import Camera
from splatstream.evaluate import EvalOptions, cameras_from_report, evaluate, parse_compare, seed_bytes_per_splat
from splatstream.io import read_gaussians
from splatstream.render_ref import render


def test_eval_cli_table_json_plot(tmp_path):
    src = real("fruit_drops_sh3.ply")
    out_json, out_png, out_md = tmp_path / "r.json", tmp_path / "r.png", tmp_path / "r.md"
    res = run_cli("eval", src, "--presets", "medium,low", "--views", "2", "--size", "128x96", "--renderer", "ref",
                  "--json", out_json, "--plot", out_png, "--markdown", out_md, "--compare", f"self={src}")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    header = "| Quality | Pos | Rot | Scl | Col | SH | bytes/splat GPU | disk | Compr | PSNR | SSIM | encode s |"
    assert header in lines
    medium = next(line for line in lines if line.startswith("| medium |"))
    assert "| norm11 | norm10_2 | norm11 | norm8x4 | norm565 |" in medium
    assert any(line.startswith("| self |") and "inf (inf)" in line for line in lines)
    assert out_md.read_text() == res.stdout
    assert "Seed" not in res.stdout and "goal" not in res.stdout.lower() and "MISSED" not in res.stdout
    report = json.loads(out_json.read_text())
    rows = {r["label"]: r for r in report["rows"]}
    assert set(rows) == {"medium", "low", "self"}
    assert len(report["cameras"]) == 2 and report["size"] == [128, 96]
    assert rows["medium"]["psnr_mean"] > rows["low"]["psnr_mean"] > 20
    assert rows["medium"]["ssim_mean"] > 0.99
    assert rows["self"]["psnr_mean"] is None and rows["self"]["identical_views"] == 2  # inf is not JSON
    assert rows["self"]["ssim_mean"] == pytest.approx(1.0)
    for label in ("medium", "low"):
        r = rows[label]
        assert 0 < r["disk_bytes_per_splat"] < 60 and 0 < r["gpu_bytes_per_splat"] < 60
        assert r["compression"] == pytest.approx(os.path.getsize(src) / r["disk_bytes"])
        assert r["encode_seconds"] > 0 and len(r["psnr_per_view"]) == 2
    assert "goals" not in report and set(report["reference_table"]["presets"]) == {"very-high", "high", "medium",
                                                                                   "low", "very-low"}
    with Image.open(out_png) as im:
        assert im.size == (900, 600)
        assert len(im.getcolors(100000)) > 10  # something was drawn
    # the cameras in the JSON reproduce the reference renders
    cams = cameras_from_report(report)
    assert all(isinstance(c, Camera) and (c.width, c.height) == (128, 96) for c in cams)


def test_eval_api_reproducible_cameras_and_encoded_dir(tmp_path):
    src = real("donut_sh0_no_normals.ply")
    opts = EvalOptions(presets=["high"], views=1, width=48, height=40, encoded_dir=str(tmp_path))
    rep = evaluate(str(src), opts)
    (row,) = rep["rows"]
    assert row["formats"]["position"] == "f16x4"
    assert os.path.isfile(tmp_path / "high" / "manifest.msgpack")  # --encoded keeps the scenes
    assert rep["input"]["sh_degree"] == 0
    # PSNR recomputed from the JSON camera matches the report
    g = read_gaussians(src)
    from splatstream.metrics import psnr
    from splatstream.scene_decode import decode_scene

    cam = cameras_from_report(rep)[0]
    p = psnr(render(g, cam), render(decode_scene(tmp_path / "high"), cam))
    assert p == pytest.approx(row["psnr_mean"], abs=1e-4)


@pytest.mark.parametrize("args, message", [
    (["--presets", "ultra"], "unknown preset"),
    (["--size", "big"], "--size"),
    (["--views", "0"], "--views"),
    (["--views", "8000"], "--views must be at most 1024"),
    (["--compare", "/nonexistent/x.ply"], "no such file"),
    # taken without a word (newuser61): no --compare file to apply to; an orbit over the pole
    (["--spz-axes", "rdf"], "--spz-axes rdf: the axes of SPZ files given to --compare, and none is given"),
    (["--elevation", "95"], "--elevation 95: expected degrees in (-90, 90)"),
    (["--elevation", "-90"], "--elevation -90: expected degrees in (-90, 90)"),
])
def test_eval_cli_bad_arguments(args, message, capsys):
    rc = main(["eval", str(real("fruit_drops_sh3.ply")), "--renderer", "ref", "--size", "32x32", "-q", *args])
    assert rc == 2
    assert message in capsys.readouterr().err


def test_eval_cli_missing_input(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nope.ply")]) == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.parametrize("flag, name", [("--json", "r.json"), ("--plot", "p.png"), ("--markdown", "t.md")])
def test_eval_outputs_that_cannot_be_written_are_refused_before_measuring(flag, name, tmp_path, capsys):
    # --json into a read-only directory was found after every encode and render: exit 1 and the system's words
    # ('ro/x.json: Read-only file system'); /proc takes no new file, whoever runs the test (root included)
    rc = main(["eval", str(real("fruit_drops_sh3.ply")), "--renderer", "ref", "--size", "32x32", "--views", "1",
               "--presets", "low", flag, f"/proc/{name}"])
    assert rc == 2
    captured = capsys.readouterr()
    assert f"/proc/{name}: cannot write in /proc" in captured.err
    assert "| low |" not in captured.out and "low:" not in captured.err  # nothing measured
    assert main(["eval", str(real("fruit_drops_sh3.ply")), "--presets", "low", "--encoded", "/proc/enc"]) == 2
    assert "/proc/enc/low: cannot write in /proc" in capsys.readouterr().err
    (tmp_path / "d.json").mkdir()
    assert main(["eval", str(real("fruit_drops_sh3.ply")), "--presets", "low", "--json", str(tmp_path / "d.json")]) == 2
    assert "is a directory, expected a file name" in capsys.readouterr().err


def test_parse_compare_and_seed_sizes(tmp_path):
    f = tmp_path / "a.ply"
    f.write_bytes(b"x")
    d = tmp_path / "a.sog"
    d.write_bytes(b"yy")
    assert parse_compare(str(f)) == ("a.ply", str(f), str(f))
    assert parse_compare(f"peer={f}@{d}") == ("peer", str(f), str(d))
    assert seed_bytes_per_splat("medium", 3) == pytest.approx(248 / 5.2)
    assert seed_bytes_per_splat("medium", 0) == pytest.approx(248 / 5.2 - 15 * 2)
    assert math.isclose(seed_bytes_per_splat("low", 3) - seed_bytes_per_splat("low", 0), 7.5)
    assert np.isfinite(seed_bytes_per_splat("very-high", 1))


def test_eval_gl_agrees_with_reference():
    from cli.commands.renderers import gl_renderer, pick_renderer

    if gl_renderer() is None:
        pytest.skip("no GL context here")
    src = str(real("donut_sh0_no_normals.ply"))
    reps = {kind: evaluate(src, EvalOptions(presets=["low"], views=1, width=64, height=64),
                           renderer=pick_renderer(kind))
            for kind in ("gl", "ref")}
    assert reps["gl"]["renderer"].startswith("gl")
    gl_row, ref_row = reps["gl"]["rows"][0], reps["ref"]["rows"][0]
    # GL draws the encoded textures, the reference renders the decoded splats: the same scene either way
    assert gl_row["psnr_mean"] == pytest.approx(ref_row["psnr_mean"], abs=1.0)
    assert gl_row["disk_bytes"] == ref_row["disk_bytes"]


def test_attribution_rows_and_markdown():
    from splatstream.evaluate import report_markdown

    rep = evaluate(str(real("fruit_drops_sh3.ply")),
                   EvalOptions(presets=["low"], attribution=["low"], views=1, width=32, height=32))
    labels = [r["label"] for r in rep["rows"]]
    assert labels[0] == "low"
    for attr in ("position", "rotation", "scale", "color", "sh"):
        assert f"low {attr}=f32x4" in labels and f"low only {attr}" in labels
    only_color = next(r for r in rep["rows"] if r["label"] == "low only color")
    assert only_color["formats"]["color"] == "norm8x4" and only_color["formats"]["position"] == "f32x4"
    md = report_markdown(rep)
    assert "Error attribution for low" in md
    assert "| color | norm8x4 |" in md


def test_read_compare_clamps_infinite_opacity(tmp_path):
    from splatstream.evaluate import read_compare
    from splatstream.gaussians import Gaussians, normalize_quaternions
    from splatstream.ply import gaussians_ply_dtype, read_header, write_gaussians_ply

    rng = np.random.default_rng(5)
    n = 20
    g = Gaussians(rng.normal(size=(n, 3)), normalize_quaternions(rng.normal(size=(n, 4))), rng.normal(size=(n, 3)),
                  rng.normal(size=n), rng.normal(size=(n, 3)), rng.normal(size=(n, 15, 3)))
    path = tmp_path / "peer.ply"
    write_gaussians_ply(g, path)
    header = read_header(path)
    data = np.memmap(path, dtype=gaussians_ply_dtype(3), mode="r+", offset=header.size, shape=(n,))
    data["opacity"][[1, 4]] = [np.inf, -np.inf]
    data.flush()
    del data
    got, clamped = read_compare(str(path))
    assert clamped == 2
    np.testing.assert_array_equal(got.sh_rest, g.sh_rest)
    np.testing.assert_array_equal(got.positions, g.positions)
    np.testing.assert_allclose(got.rotations, g.rotations, atol=1e-7)
    limit = np.log((1 - 1e-6) / 1e-6)  # the PLY reader's finite logit for alpha 1 (issue 17)
    assert got.opacity_logits[1] == pytest.approx(limit, rel=1e-6) and got.opacity_logits[4] == pytest.approx(-limit,
                                                                                                           rel=1e-6)
    np.testing.assert_array_equal(np.delete(got.opacity_logits, [1, 4]), np.delete(g.opacity_logits, [1, 4]))


def test_variants_parse_and_run():
    from splatstream.errors import UsageError
    from splatstream.evaluate import parse_variant, report_markdown

    assert parse_variant("x:low,rotation=norm565,sh_degree=2") == ("x", "low", {"rotation": "norm565"}, 2, None)
    assert parse_variant("y:medium,sh_codebook=256") == ("y", "medium", {}, None, "256")
    for bad in ("x", "x:", "x:ultra", "x:low,rotation", "x:low,colour=bc7", "x:low,sh_degree=5", "x:low,scale=nope"):
        with pytest.raises(UsageError):
            parse_variant(bad)
    rep = evaluate(str(real("fruit_drops_sh3.ply")),
                   EvalOptions(presets=[], variants=["low-sh1:low,sh_degree=1"], views=1, width=32, height=32))
    (row,) = rep["rows"]
    assert row["kind"] == "variant" and row["sh_degree"] == 1
    assert "| low-sh1 | norm8x4 | cube565 | norm8x4 | norm8x4 | norm565 VQ64 (SH1) |" in report_markdown(rep)


def test_a_codebook_variant_where_no_sh_band_is_kept_is_refused_before_any_run():
    """`--variants cb:low,sh_codebook=auto` on an SH0 scene (or with sh_degree=0) failed after the presets' runs,
    naming encode's --sh-codebook (newuser62): refused at once, naming the variant, before a reference view."""
    from splatstream.errors import UsageError

    said = []
    donut = str(real("donut_sh0_no_normals.ply"))
    with pytest.raises(UsageError, match=r"variant 'cb': sh_codebook=auto needs SH bands 1..3, and .* keeps none "
                                         r"\(SH degree 0\); leave sh_codebook out"):
        evaluate(donut, EvalOptions(presets=["low"], variants=["cb:low,sh_codebook=auto"], views=1, width=32,
                                    height=32), log=said.append)
    assert not any("rendered" in line or "low:" in line for line in said), said
    with pytest.raises(UsageError, match=r"variant 'cb0': sh_codebook=64 .* \(SH degree 3, sh_degree=0\)"):
        evaluate(str(real("fruit_drops_sh3.ply")),
                 EvalOptions(presets=[], variants=["cb0:low,sh_degree=0,sh_codebook=64"], views=1, width=32, height=32))
    rep = evaluate(donut, EvalOptions(presets=[], variants=["off:low,sh_codebook=off"], views=1, width=32, height=32))
    assert [r["label"] for r in rep["rows"]] == ["off"]


def test_reference_table_only_on_request(tmp_path):
    src = real("fruit_drops_sh3.ply")
    res = run_cli("eval", src, "--presets", "medium", "--views", "1", "--size", "32x32", "--renderer", "ref",
                  "--reference-table", "-q")
    assert res.returncode == 0, res.stderr
    assert "Reference, not measured here" in res.stdout and "| medium | " in res.stdout
    assert " 4,721 splats, SH3, " in res.stdout and ". 1 view at 32x32, " in res.stdout  # it said '1 views'


def test_a_compare_of_another_splat_count_is_said():
    # `eval logo.ply --compare other=guitar.spz` (another scene by mistake): 11.7 dB and 15.44 B/splat, no word
    res = run_cli("eval", real("fruit_drops_sh3.ply"), "--presets", "none", "--views", "1", "--size", "32x32",
                  "--renderer", "ref", "--compare", f"other={real('winter_fountain_first3000.splat')}")
    assert res.returncode == 0, res.stderr
    assert "read " in res.stderr and ": 4,721 splats, SH degree 3 (" in res.stderr  # with separators
    assert ("other: 3,000 splats, the input 4,721: another scene, or a decimated one? (its B/splat is per its own "
            "splats)") in res.stderr, res.stderr


def test_eval_lod_counts_one_tile_in_the_singular():
    # a one-tile scene's shared tree was logged as '1 tiles' (encode --target-size on fruit_drops: newuser58)
    res = run_cli("eval", real("fruit_drops_sh3.ply"), "--presets", "low", "--views", "1", "--size", "32x32",
                  "--renderer", "ref", "--lod")
    assert res.returncode == 0, res.stderr
    assert "built the LOD tree every encode takes: 1 tile (" in res.stderr, res.stderr


@pytest.mark.parametrize("scene", ["fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply"])
def test_low_meets_its_bound_on_real_sh3(scene):
    """Issue 15: `low` at 35 dB or more with 12 B/splat or fewer on disk on the real SH3 scenes (measured at 8 views
    of 512x512: fruit_drops 37.6 dB at 11.67 B, lod_tile 37.3 dB at 10.77 B). Here 2 small views with the reference
    rasterizer, which measured 37.9 and 41.4 dB; the bound keeps the issue's 35 dB."""
    from cli.commands.renderers import pick_renderer

    rep = evaluate(str(real(scene)), EvalOptions(presets=["low"], views=2, width=96, height=96),
                   renderer=pick_renderer("ref"))
    (row,) = rep["rows"]
    assert row["disk_bytes_per_splat"] <= 12.0 and row["psnr_mean"] >= 35.0, row
    assert row["sh_codebook_entries"] is not None and row["formats"]["color"] == "norm8x4"


def _preset_row(label: str, size: float, db: float | None) -> dict:
    return {"label": label, "kind": "preset", "disk_bytes_per_splat": size, "psnr_mean": db}


def test_preset_for_target_picks_smallest_meeting_psnr_and_best_under_size():
    from splatstream.errors import UsageError
    from splatstream.evaluate import preset_for_target

    rows = [_preset_row("very-high", 43.1, None), _preset_row("medium", 15.1, 60.4),
            _preset_row("medium-low", 13.0, 60.0), _preset_row("low-plus", 11.9, 52.1),
            _preset_row("low", 10.6, 49.2), _preset_row("very-low", 7.7, 41.9),
            {"label": "spz", "kind": "compare", "disk_bytes_per_splat": 5.0, "psnr_mean": 70.0}]
    assert preset_for_target(rows, target_psnr=50)["label"] == "low-plus"
    assert preset_for_target(rows, target_psnr=60)["label"] == "medium-low"  # 60.0 meets 60: the smaller files
    assert preset_for_target(rows, target_psnr=61)["label"] == "very-high"  # identical (None) meets any target
    assert preset_for_target(rows, target_bytes=12)["label"] == "low-plus"
    assert preset_for_target(rows, target_bytes=100)["label"] == "very-high"
    assert preset_for_target(rows, target_bytes=7.7)["label"] == "very-low"
    # a preset that is larger and worse than another never wins either way
    rows.append(_preset_row("odd", 14.0, 59.0))
    assert preset_for_target(rows, target_psnr=59)["label"] == "medium-low"
    assert preset_for_target(rows, target_bytes=14.5)["label"] == "medium-low"
    with pytest.raises(UsageError, match="smallest: very-low at 7.70"):
        preset_for_target(rows, target_bytes=5)
    with pytest.raises(UsageError, match="one target"):
        preset_for_target(rows, target_psnr=50, target_bytes=12)
    with pytest.raises(UsageError, match="highest: medium at 60.40"):
        preset_for_target(rows[1:], target_psnr=70)


def test_high_sh255_is_measured_by_default_and_targets_between_medium_high_and_high_pick_it():
    """Issue 32, hole32: eval (and so --target-psnr / --target-size, which measure eval's presets) takes high-sh255
    between high and medium-high; on fruit_drops' stored report (8 views at 512 px) a target between its
    neighbours' points picks it."""
    from splatstream.evaluate import PRESET_ORDER, preset_for_target

    assert PRESET_ORDER.index("high") + 1 == PRESET_ORDER.index("high-sh255") == PRESET_ORDER.index("medium-high") - 1
    rows = json.loads((ROOT / "bench" / "results" / "eval_real" / "fruit.json").read_text())["rows"]
    points = {r["label"]: (r["disk_bytes_per_splat"], r["psnr_mean"]) for r in rows if r["kind"] == "preset"}
    assert points["medium-high"][0] < points["high-sh255"][0] < points["high"][0]  # 45.05 < 55.66 < 70.55 B
    assert points["medium-high"][1] < points["high-sh255"][1] < points["high"][1]  # 63.32 < 63.65 < 63.66 dB
    assert preset_for_target(rows, target_psnr=63.5)["label"] == "high-sh255"
    assert preset_for_target(rows, target_bytes=60)["label"] == "high-sh255"
    assert preset_for_target(rows, target_bytes=50)["label"] == "medium-high"


def test_encode_target_size_is_the_size_of_the_scene_written_with_its_lod_tree(tmp_path):
    """`encode --target-size B` with the LOD tree on (the default) writes a scene of at most B bytes per splat on disk,
    every level counted, and reports that size: the presets are measured as the encode writes them (its LOD options
    too), not at full detail only, which picked presets whose scene on disk was larger than B (issue 32)."""
    from cli.commands.renderers import pick_renderer
    from splatstream.evaluate import path_size, preset_for_target

    src = real("fruit_drops_sh3.ply")
    leaf = {"max_leaf_splats": 1024}  # 4,803 splats: leaves of at most 1,024 make a tree with coarse levels

    def rows(lod: bool) -> list[dict]:
        opts = EvalOptions(views=1, width=512, height=512, lod=lod, encode_options=leaf)
        return evaluate(str(src), opts, renderer=pick_renderer("auto"))["rows"]

    full, tree = rows(False), rows(True)
    size_of = {r["label"]: r["disk_bytes_per_splat"] for r in tree}
    assert all(size_of[r["label"]] > 1.1 * r["disk_bytes_per_splat"] for r in full)  # the coarse levels' bytes
    # a target the full-detail measure answers with a preset whose scene on disk is larger than the target
    target = next(t for t in sorted(r["disk_bytes_per_splat"] + 0.01 for r in tree)
                  if size_of[preset_for_target(full, target_bytes=t)["label"]] > t)
    want = preset_for_target(tree, target_bytes=target)
    res = run_cli("encode", src, tmp_path / "s", "--target-size", target, "--target-views", "1", "--max-leaf-splats",
                  1024)
    assert res.returncode == 0, res.stderr
    info = json.loads(run_cli("info", tmp_path / "s", "--json").stdout)
    assert info["preset"] == want["label"] and len(info["bytes_per_level"]) > 1
    written = path_size(str(tmp_path / "s")) / info["splats"]
    assert written == pytest.approx(want["disk_bytes_per_splat"], abs=1e-6) and written <= target
    assert f"<= {target:g} B/splat: preset {want['label']} ({written:.2f} B/splat on disk with all LOD levels, " \
        in res.stderr


def test_encode_target_psnr_and_size_pick_what_eval_measures(tmp_path):
    """`encode --target-psnr` / `--target-size` encode with the preset eval's numbers pick (same views, same
    renderer), and refuse what cannot work together or cannot be met, in one line."""
    src = real("fruit_drops_sh3.ply")
    res = run_cli("eval", src, "--views", "2", "--size", "512x512", "--json", tmp_path / "r.json")
    assert res.returncode == 0, res.stderr
    rows = json.loads((tmp_path / "r.json").read_text())["rows"]
    from splatstream.evaluate import preset_for_target

    target_db = 40.0
    want = preset_for_target(rows, target_psnr=target_db)["label"]
    res = run_cli("encode", src, tmp_path / "a", "--target-psnr", target_db, "--target-views", "2", "--no-lod")
    assert res.returncode == 0, res.stderr
    assert f"PSNR >= 40 dB: preset {want} (" in res.stderr
    # each preset's numbers in one column (the rows were ragged, their labels' padding stripped: newuser63)
    measured = [line for line in res.stderr.splitlines() if "B/splat disk" in line]
    assert len(measured) == len(rows)
    assert len({line.index("B/splat disk") for line in measured}) == 1, measured
    assert min(len(line) - len(line.lstrip()) for line in (m.removeprefix("target:") for m in measured)) == 1
    assert json.loads(run_cli("info", tmp_path / "a", "--json").stdout)["preset"] == want
    size = preset_for_target(rows, target_psnr=target_db)["disk_bytes_per_splat"] - 0.01
    want_small = preset_for_target(rows, target_bytes=size)["label"]
    assert want_small != want
    res = run_cli("encode", src, tmp_path / "b", "--target-size", size, "--target-views", "2", "-q")
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""
    assert json.loads(run_cli("info", tmp_path / "b", "--json").stdout)["preset"] == want_small
    for args, message in ((["--target-size", "1", "--target-views", "1"], "B/splat), all LOD levels counted (--no-lod"),
                          (["--target-psnr", "40", "--preset", "low"], "choose the preset"),
                          (["--target-psnr", "40", "--target-size", "9"], "not allowed with argument"),
                          (["--target-psnr", "-3"], "expected a PSNR above 0"),
                          (["--target-size", "9", "--target-views", "0"], "expected at least 1")):
        res = run_cli("encode", src, tmp_path / "c", *args, "-q")
        assert res.returncode == 2 and message in res.stderr and "Traceback" not in res.stderr, (args, res.stderr)
        assert len(res.stderr.strip().splitlines()) <= 3  # argparse's usage lines, or our one line
        assert not (tmp_path / "c").exists()


def test_target_presets_are_measured_on_the_merge_the_encode_builds():
    """--target-size must compare the bytes of the tree the encode builds: auto by default on either engine (a
    distributed encode runs it inside its partitions since branch partauto31); a named merge is kept either way."""
    from cli.commands.encode import target_lod_merge
    from splatstream.encode.options import IN_MEMORY_LOD_MERGE, PARTITIONED_LOD_MERGE

    assert target_lod_merge(None, distributed=True) == PARTITIONED_LOD_MERGE == "auto"
    assert target_lod_merge(None, distributed=False) == IN_MEMORY_LOD_MERGE == "auto"
    assert target_lod_merge("grid", distributed=False) == "grid"
    assert target_lod_merge("grid", distributed=True) == "grid"


def test_a_streamed_sog_is_sized_by_its_finest_level_not_its_index(tmp_path):
    """eval of playbot/lod-meta.json said '1,040 bytes (0.0 B/splat)' and a compression of 0.0x: the index alone.
    The input's bytes are the index and the units of the level eval reads (level 0: 0_0/ here, not 1_0/)."""
    from conftest import ROOT

    from splatstream.evaluate import path_size, report_markdown
    sog = ROOT / "tests" / "fixtures" / "foreign" / "fruit_drops_lod"
    files = lambda d: sum(f.stat().st_size for f in d.rglob("*") if f.is_file())  # noqa: E731
    finest = (sog / "lod-meta.json").stat().st_size + files(sog / "0_0")
    assert path_size(str(sog / "lod-meta.json")) == path_size(str(sog)) == finest
    assert path_size(str(sog / "0_0" / "meta.json")) == files(sog / "0_0")  # an unbundled SOG: its directory
    rep = evaluate(str(sog / "lod-meta.json"), EvalOptions(presets=["low"], views=1, width=48, height=40))
    assert rep["input"]["bytes"] == finest and rep["input"]["splats"] == 74
    assert rep["rows"][0]["compression"] == pytest.approx(finest / rep["rows"][0]["disk_bytes"], rel=1e-6)
    assert report_markdown(rep).startswith(f"Scene `fruit_drops_lod/lod-meta.json`: 74 splats, SH3, {finest:,} bytes")


def test_very_low_rgb127_is_measured_by_default_and_targets_between_very_low_and_low_pick_it():
    """Issue 32, step32: eval (and so --target-psnr / --target-size) takes very-low-rgb127 between low and very-low;
    on fruit_drops' stored report (8 views at 512 px) targets between its neighbours' points pick it."""
    from splatstream.evaluate import PRESET_ORDER, preset_for_target

    assert PRESET_ORDER.index("low") + 1 == PRESET_ORDER.index("very-low-rgb127") == PRESET_ORDER.index("very-low") - 1
    rows = json.loads((ROOT / "bench" / "results" / "eval_real" / "fruit.json").read_text())["rows"]
    points = {r["label"]: (r["disk_bytes_per_splat"], r["psnr_mean"]) for r in rows if r["kind"] == "preset"}
    # cube565 rotations since rotrange32 (format 1.13): 9.35 < 10.03 < 11.67 B, 36.01 < 37.70 < 42.63 dB
    assert points["very-low"][0] < points["very-low-rgb127"][0] < points["low"][0]
    assert points["very-low"][1] < points["very-low-rgb127"][1] < points["low"][1]
    assert preset_for_target(rows, target_psnr=37)["label"] == "very-low-rgb127"
    assert preset_for_target(rows, target_bytes=10.1)["label"] == "very-low-rgb127"
    assert preset_for_target(rows, target_bytes=9.5)["label"] == "very-low"


def test_eval_reads_a_sog_directory_as_convert_does(tmp_path, capsys):
    # `eval /work/heldout/playcanvas-logo` (a SOG v1 directory, which convert, encode and render read) was refused:
    # 'is a directory; eval takes ... another format `convert` reads'. Its input bytes are the planes' (13.2 B/splat
    # for the whole logo), as for its meta.json.
    sog_dir = ROOT / "tests" / "fixtures" / "foreign" / "logo_v1_sub300"
    common = ["--presets", "low", "--views", "1", "--size", "32x32", "--renderer", "ref", "-q", "--json"]
    assert main(["eval", str(sog_dir), *common, str(tmp_path / "dir.json")]) == 0, capsys.readouterr().err
    assert main(["eval", str(sog_dir / "meta.json"), *common, str(tmp_path / "meta.json")]) == 0
    by_dir, by_meta = (json.loads((tmp_path / n).read_text()) for n in ("dir.json", "meta.json"))
    assert by_dir["input"]["splats"] == by_meta["input"]["splats"] == 300
    assert by_dir["input"]["bytes"] == by_meta["input"]["bytes"] > 1000  # the planes, not the meta.json alone
    # a splatstream scene's directory is still refused, saying what gives its splats
    scene = tmp_path / "scene"
    assert main(["encode", str(sog_dir), str(scene), "-q"]) == 0
    capsys.readouterr()
    assert main(["eval", str(scene), "--presets", "low"]) == 2
    err = capsys.readouterr().err
    assert "is a directory; eval takes the original splat file" in err and "`splatstream decode`" in err, err
