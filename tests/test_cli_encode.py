"""The encode / info / decode commands end to end, as a user runs them."""
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, real, run_cli

from cli.main import COMMANDS, build_parser
from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.ply import read_gaussians_ply
from splatstream.scene_decode import decode_scene


def test_encode_info_decode(tmp_path):
    src = real("fruit_drops_sh3.ply")
    r = run_cli("encode", src, tmp_path / "scene", "--preset", "high")
    assert r.returncode == 0, r.stderr
    assert "encode:" in r.stderr  # progress is shown
    r = run_cli("info", tmp_path / "scene", "--json")
    info = json.loads(r.stdout)
    for key in ("splats", "sh_degree", "preset", "bytes_on_disk", "gpu_bytes_per_splat", "attributes", "tiles",
                "levels", "leaf_splats"):
        assert key in info, key
    assert info["splats"] == 4721 and info["sh_degree"] == 3 and info["preset"] == "high"
    assert info["leaf_splats"] == info["splats"]
    assert set(info["attributes"]) == {"position", "rotation", "scale", "color", "sh"}
    assert info["attributes"]["scale"]["format"] == "norm11"
    disk = sum(f.stat().st_size for f in (tmp_path / "scene").rglob("*") if f.is_file())
    assert info["bytes_on_disk"] == disk
    assert info["bytes_on_disk"] < info["gpu_bytes"]
    r = run_cli("decode", tmp_path / "scene", tmp_path / "out.ply")
    assert r.returncode == 0, r.stderr
    # what is being written is said before the write (a .sog's takes seconds), then what was written
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("decode: ") and lines[0].endswith(
        f"; writing {tmp_path / 'out.ply'} (standard 3DGS PLY)"), r.stderr
    assert lines[1].startswith(f"wrote {tmp_path / 'out.ply'}: "), r.stderr
    back = read_gaussians_ply(tmp_path / "out.ply")
    d = decode_scene(tmp_path / "scene")
    assert np.array_equal(back.positions, d.positions) and np.array_equal(back.sh_rest, d.sh_rest)
    r = run_cli("info", tmp_path / "scene")
    assert "preset high" in r.stdout and "preset     high: 16-bit positions" in r.stdout and "differs" not in r.stdout
    assert info["preset_overrides"] == {} and info["section_filters"]["fields1"] > 0  # format 1.2 transport coding


def test_format_overrides(tmp_path):
    r = run_cli("encode", real("donut_sh0_no_normals.ply"), tmp_path / "s", "--preset", "medium",
                "--position", "f32x4", "--color", "f16x4", "-q")
    assert r.returncode == 0, r.stderr
    info = json.loads(run_cli("info", tmp_path / "s", "--json").stdout)
    assert info["formats"]["position"] == "f32x4" and info["formats"]["color"] == "f16x4"
    assert info["formats"]["rotation"] == "norm10_2"
    assert "sh" not in info["formats"] and "sh" not in info["attributes"]  # an SH0 scene has no SH format
    assert info["preset_overrides"] == {"position": "f32x4", "color": "f16x4"}
    assert "differs from it in: position=f32x4, color=f16x4" in run_cli("info", tmp_path / "s").stdout
    r = run_cli("encode", real("donut_sh0_no_normals.ply"), tmp_path / "t", "--color", "norm565", "-q")
    assert r.returncode == 2 and "4-component" in r.stderr and not (tmp_path / "t").exists()


def test_help_everywhere():
    parser = build_parser()
    registered = next(a for a in parser._actions if a.dest == "command").choices
    assert {"encode", "decode", "info"} <= set(registered) <= set(COMMANDS)
    for command in registered:
        r = run_cli(command, "--help")
        assert r.returncode == 0 and "usage:" in r.stdout, command


# The names a command's description gives its arguments (export-rad's said OUT where its usage line said `output`:
# newuser64)
ARGUMENT_NAMES = {"IN", "INPUT", "OUT", "OUTPUT", "OUT_DIR", "OUTPUT_DIR", "SCENE", "SCENE_DIR", "SOURCE", "ROOT"}


def test_every_help_names_its_arguments_as_its_usage_line_does():
    parser = build_parser()
    registered = next(a for a in parser._actions if a.dest == "command").choices
    for command, sub in registered.items():
        positionals = [a for a in sub._actions if not a.option_strings]
        metavars = {a.metavar for a in positionals}
        usage = sub.format_usage()
        # every positional is named in capitals on the usage line, and so in the list below it
        assert all(isinstance(m, str) and m.isupper() and m in usage.split() for m in metavars), (command, usage)
        named = set(re.findall(r"\b[A-Z][A-Z_]*\b", sub.description or "")) & ARGUMENT_NAMES
        assert named <= metavars, (command, named, metavars)
    assert "SCENE_DIR OUT" in registered["export-rad"].format_usage()


def test_failed_encode_leaves_old_scene_and_no_temporaries(tmp_path, monkeypatch):
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    encode_gaussians(g, tmp_path / "scene", EncodeOptions(preset="medium"))
    before = sorted(p.name for p in (tmp_path / "scene" / "data").iterdir())

    import splatstream.encode.local as enc

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(enc, "encode_group", boom)
    with pytest.raises(RuntimeError):
        encode_gaussians(g, tmp_path / "scene", EncodeOptions(preset="high"))
    assert sorted(p.name for p in (tmp_path / "scene" / "data").iterdir()) == before
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]


def test_reencode_replaces_scene(tmp_path):
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    encode_gaussians(g, tmp_path / "scene", EncodeOptions(preset="medium"))
    m = encode_gaussians(g, tmp_path / "scene", EncodeOptions(preset="high"))
    files = {p.name for p in (tmp_path / "scene" / "data").iterdir()}
    assert files == {e.file.split("/")[1] for t in m.tiles for e in t.groups.values()}
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]


def test_encoding_is_deterministic(tmp_path):
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    a = encode_gaussians(g, tmp_path / "a", EncodeOptions(preset="medium"))
    b = encode_gaussians(g, tmp_path / "b", EncodeOptions(preset="medium"))
    assert [t.groups for t in a.tiles] == [t.groups for t in b.tiles]


def test_wrong_paths_give_clear_errors(tmp_path):
    (tmp_path / "file.ply").write_text("x")
    r = run_cli("info", tmp_path / "file.ply")
    assert r.returncode == 2 and "not a directory" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("info", tmp_path / "missing")
    assert r.returncode == 2 and "no such directory" in r.stderr
    r = run_cli("encode", real("donut_sh0_no_normals.ply"), tmp_path / "s", "-q")
    assert r.returncode == 0, r.stderr
    r = run_cli("decode", tmp_path / "s", tmp_path / "nodir" / "out.ply")
    assert r.returncode == 2 and "output directory" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("given", ["fruit_drops_lod/lod-meta.json", "fruit_drops_lod", "fruit_drops_lod/0_0/meta.json"])
def test_streamed_sog_scene_is_named_after_its_directory(tmp_path, given):
    """A streamed SOG's index is lod-meta.json and an unbundled SOG's meta.json, whatever the scene: a new user's
    playbot/lod-meta.json became a scene named "lod-meta" in info and the server's /api/scenes."""
    from conftest import ROOT
    src = ROOT / "tests" / "fixtures" / "foreign" / given
    r = run_cli("encode", src, tmp_path / "scene", "-q")
    assert r.returncode == 0, r.stderr
    info = json.loads(run_cli("info", tmp_path / "scene", "--json").stdout)
    assert info["name"] == ("0_0" if given.endswith("0_0/meta.json") else "fruit_drops_lod")
    r = run_cli("encode", src, tmp_path / "named", "-q", "--name", "mine")  # --name still wins
    assert json.loads(run_cli("info", tmp_path / "named", "--json").stdout)["name"] == "mine"


def test_scene_name_from_a_url_and_a_plain_file():
    from splatstream.encode.plan import scene_name
    opts = EncodeOptions()
    assert scene_name(opts, "s3://bucket/scenes/garden/lod-meta.json", "out") == "garden"
    assert scene_name(opts, "captures/garden.ply", "out") == "garden"
    assert scene_name(opts, None, "out") == "out"


def test_streamed_sog_merged_with_another_input_says_its_tree_is_not_kept(tmp_path):
    # several inputs are one splat set with our tree: a streamed SOG among them gives its finest level only, and
    # says so (it was dropped without a word: newuser58)
    sog = Path(__file__).parent / "fixtures" / "foreign" / "fruit_drops_lod" / "lod-meta.json"
    r = run_cli("encode", sog, real("fruit_drops_sh3.ply"), tmp_path / "scene", "--preset", "low")
    assert r.returncode == 0, r.stderr
    assert f"encode: {sog} holds its own LOD tree; merged with the other inputs its finest level is read" in r.stderr
    info = json.loads(run_cli("info", tmp_path / "scene", "--json").stdout)
    assert info["splats"] == 4721 + 74


def test_target_on_a_kept_tree_names_both_ways_out(tmp_path):
    # `encode playbot --target-size 20` said only 'add --rebuild-lod'; --no-lod (its finest level alone) is the
    # other way the README gives, and a target is then measured (newuser60)
    sog = Path(__file__).parent / "fixtures" / "foreign" / "fruit_drops_lod" / "lod-meta.json"
    r = run_cli("encode", sog, tmp_path / "scene", "--target-size", "20")
    assert r.returncode == 2 and not (tmp_path / "scene").exists(), r.stderr
    assert r.stderr.strip().endswith("add --rebuild-lod to build ours from its finest level, or --no-lod for its "
                                     "finest level alone"), r.stderr
    assert "--target-psnr/--target-size applies only to a tree we build" in r.stderr, r.stderr


def test_rebuild_lod_where_no_input_has_a_tree_is_refused(tmp_path):
    """`encode logo/meta.json --rebuild-lod` (a SOG v1, no tree of its own) was taken without a word (newuser62):
    refused in one line naming the option, the input and what it is; a streamed SOG still takes it."""
    sog_v1 = ROOT / "tests" / "fixtures" / "foreign" / "logo_v1_sub300"
    for inputs in ([sog_v1], [real("fruit_drops_sh3.ply"), sog_v1]):
        r = run_cli("encode", *inputs, tmp_path / "scene", "--rebuild-lod")
        assert r.returncode == 2 and not (tmp_path / "scene").exists(), r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1, r.stderr
        assert lines[0].startswith("splatstream encode: error: --rebuild-lod builds our LOD tree"), r.stderr
        assert f"{sog_v1} is a PlayCanvas SOG" in lines[0] and "leave the option out" in lines[0], r.stderr
    streamed = ROOT / "tests" / "fixtures" / "foreign" / "fruit_drops_lod"
    r = run_cli("encode", streamed, tmp_path / "scene", "--rebuild-lod", "-q")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("options", [["--lod-merge", "cost"], ["--max-leaf-splats", "4096", "--page-tiles", "3"],
                                     ["--reduction", "3"], ["--page-levels", "2"], ["--rebuild-lod"]])
def test_no_lod_with_the_tree_options_is_refused_naming_both(tmp_path, options):
    """`encode --no-lod --lod-merge cost` (or --max-leaf-splats, --reduction, the page options) wrote one tile and took
    the tree's option without a word (newuser61)."""
    r = run_cli("encode", real("fruit_drops_sh3.ply"), tmp_path / "scene", "--no-lod", *options)
    assert r.returncode == 2 and not (tmp_path / "scene").exists(), r.stderr
    lines = r.stderr.strip().splitlines()
    flags = ", ".join(o for o in options if o.startswith("--"))
    assert len(lines) == 1 and f"--no-lod and {flags}: --no-lod writes one tile" in lines[0], r.stderr


def test_a_kept_tree_refuses_the_options_of_a_tree_we_build(tmp_path):
    """A streamed SOG's tree is kept as read: --max-leaf-splats, --reduction and --lod-merge were taken without a
    word (the help says they 'then follow it'); refused as edits and --lod-refine are (newuser61)."""
    sog = Path(__file__).parent / "fixtures" / "foreign" / "fruit_drops_lod" / "lod-meta.json"
    r = run_cli("encode", sog, tmp_path / "scene", "--max-leaf-splats", "4096", "--lod-merge", "grid")
    assert r.returncode == 2 and not (tmp_path / "scene").exists(), r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--max-leaf-splats, --lod-merge apply only to a tree we build" in lines[0], r.stderr
    assert lines[0].endswith("add --rebuild-lod to build ours from its finest level"), r.stderr
    r = run_cli("encode", sog, tmp_path / "scene", "--max-leaf-splats", "4096", "--rebuild-lod", "-q")
    assert r.returncode == 0, r.stderr


def test_a_one_splat_scene_is_said_in_the_singular_and_decode_takes_quiet(tmp_path):
    """newuser63: a 1-splat scene went through every command, but each said '1 splats'; `decode -q` was refused as
    an unknown option where encode, convert and the exports take it."""
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    from splatstream.ply import write_gaussians_ply

    write_gaussians_ply(g.subset(np.arange(1)), tmp_path / "one.ply")
    r = run_cli("encode", tmp_path / "one.ply", tmp_path / "one")
    assert r.returncode == 0, r.stderr
    assert f"wrote {tmp_path / 'one'}: 1 splat, SH degree 3" in r.stderr, r.stderr
    r = run_cli("decode", tmp_path / "one", tmp_path / "back.ply")
    assert r.returncode == 0 and "decode: 1 splat decoded" in r.stderr, r.stderr
    assert ": 1 splat, SH degree 3" in r.stderr, r.stderr
    r = run_cli("decode", tmp_path / "one", tmp_path / "quiet.ply", "-q")
    assert r.returncode == 0 and r.stderr == "" and r.stdout == "", r.stderr
    assert read_gaussians_ply(tmp_path / "quiet.ply").positions.tolist() == read_gaussians_ply(
        tmp_path / "back.ply").positions.tolist()
    r = run_cli("convert", tmp_path / "one.ply", tmp_path / "c.ply", "--filter-box", "-1e9,-1e9,-1e9,1e9,1e9,1e9")
    assert r.returncode == 0 and "read 1 splat, SH degree 3" in r.stderr and ": 1 splat kept" in r.stderr, r.stderr
    r = run_cli("convert", tmp_path / "one.ply", tmp_path / "d.ply", "--dry-run", "--translate", "1,0,0")
    assert r.returncode == 0 and f"read {tmp_path / 'one.ply'}: 1 splat\n" in r.stdout, r.stdout
    r = run_cli("export-rad", tmp_path / "one", tmp_path / "one.rad")
    assert r.returncode == 0 and ", 1 splat of full detail (1 over all levels)" in r.stderr, r.stderr
    r = run_cli("export-sog-lod", tmp_path / "one", tmp_path / "one_sog")
    assert r.returncode == 0 and ", 1 splat at level 0 (1 over all levels)" in r.stderr, r.stderr
    r = run_cli("render", tmp_path / "one.ply", "--out", tmp_path / "one.png", "--size", "64x48")
    assert r.returncode == 0 and "render: 1 splat read from" in r.stderr, r.stderr
    assert "64x48, 1 splat, sort" in r.stderr, r.stderr
    r = run_cli("eval", tmp_path / "one.ply", "--presets", "medium", "--views", "1", "--size", "32x32")
    assert r.returncode == 0 and f"read {tmp_path / 'one.ply'}: 1 splat, SH degree 3" in r.stderr, r.stderr
    assert "Scene `one.ply`: 1 splat, SH3, " in r.stdout, r.stdout


def test_ctrl_c_while_the_commands_are_imported_says_one_line(monkeypatch, capsys):
    """build_parser imports every command's modules (a second on a busy machine): a Ctrl-C meanwhile printed the
    import's traceback (polish64). The KeyboardInterrupt is raised where the import would take it."""
    import cli.main as cli_main

    def interrupted_import():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_main, "build_parser", interrupted_import)
    assert cli_main.main(["encode", "-q", "--workers", "2", "in.ply", "out"]) == 130
    assert capsys.readouterr().err == "splatstream encode: interrupted\n"
    assert cli_main.main(["--version"]) == 130
    assert capsys.readouterr().err == "splatstream: interrupted\n"
