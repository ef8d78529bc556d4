"""`splatstream convert`: every readable format to .ply and .splat, and bad inputs end with a message, exit 2,
no traceback and no output file (not even a temporary one)."""
from __future__ import annotations

import pathlib

import numpy as np
import pytest
from conftest import real, run_cli

from cli.main import main
from splatstream.io import read_gaussians

FIXTURES = pathlib.Path(__file__).parent / "fixtures" / "foreign"


@pytest.mark.parametrize("name", ["fruit_drops_v2.spz", "fruit_drops_v4.spz", "fruit_drops.compressed.ply",
                                  "fruit_drops_sub16.ply"])
def test_convert_to_ply_is_lossless(tmp_path, capsys, name):
    out = tmp_path / "out.ply"
    assert main(["convert", str(FIXTURES / name), str(out)]) == 0
    err = capsys.readouterr().err
    assert "read 296 splats, SH degree 3" in err  # progress goes to stderr
    # the last line says what was written, and where (it said 'done': newuser63)
    assert err.strip().splitlines()[-1].startswith(f"convert: wrote {out}: 296 splats, SH degree 3, "
                                                   f"{out.stat().st_size:,} bytes ("), err
    a, b = read_gaussians(FIXTURES / name), read_gaussians(out)
    for field in ("positions", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    # The PLY reader renormalises quaternions, which moves already-unit float32 ones by an ulp or so.
    np.testing.assert_allclose(a.rotations, b.rotations, rtol=0, atol=3e-7)
    assert [p.name for p in tmp_path.iterdir()] == ["out.ply"]


def test_convert_real_to_splat_and_back(tmp_path, capsys):
    src = real("guitar.compressed.ply")
    out = tmp_path / "guitar.splat"
    assert main(["convert", str(src), str(out), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    assert out.stat().st_size == 90854 * 32
    back = read_gaussians(out)
    orig = read_gaussians(src)
    np.testing.assert_array_equal(back.positions, orig.positions)
    assert np.abs(back.opacities - orig.opacities).max() <= 0.5 / 255 + 1e-6


def test_convert_sh_to_splat_notes_the_loss(tmp_path, capsys):
    assert main(["convert", str(FIXTURES / "fruit_drops_v3.spz"), str(tmp_path / "x.splat")]) == 0
    assert "bands 1..3 are dropped" in capsys.readouterr().err


def test_decode_to_splat_says_the_sh_degree_written(tmp_path):
    """decode said 'wrote x.splat: ... SH degree 3' of a .splat, which holds no SH bands: it says 0 and what is
    dropped, as convert does."""
    r = run_cli("encode", FIXTURES / "fruit_drops_v4.spz", tmp_path / "scene", "--no-lod", "--quiet")
    assert r.returncode == 0, r.stderr
    r = run_cli("decode", tmp_path / "scene", tmp_path / "x.splat")
    assert r.returncode == 0, r.stderr
    assert "bands 1..3 are dropped" in r.stderr and "296 splats, SH degree 0" in r.stderr, r.stderr
    assert read_gaussians(tmp_path / "x.splat").sh_degree == 0
    r = run_cli("decode", tmp_path / "scene", tmp_path / "x.spz")  # a format that keeps the bands says them
    assert "296 splats, SH degree 3" in r.stderr and "dropped" not in r.stderr, r.stderr


def assert_clean_failure(result, out: pathlib.Path, *phrases: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert "splatstream convert: error:" in result.stderr
    for phrase in phrases:
        assert phrase in result.stderr
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary file left


@pytest.mark.parametrize("name", ["fruit_drops_v2.spz", "fruit_drops_v4.spz", "fruit_drops.compressed.ply"])
def test_truncated_input_fails_cleanly(tmp_path, name):
    data = (FIXTURES / name).read_bytes()
    bad = tmp_path / "in" / name
    bad.parent.mkdir()
    bad.write_bytes(data[:len(data) * 2 // 3])
    out = tmp_path / "out" / "x.ply"
    out.parent.mkdir()
    assert_clean_failure(run_cli("convert", bad, out), out, str(bad))


def test_corrupt_splat_and_bad_arguments(tmp_path, capsys):
    bad = tmp_path / "in.splat"
    bad.write_bytes(bytes(range(256)) * 3 + b"x")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "x.ply"
    assert main(["convert", str(bad), str(out)]) == 2
    assert "not a multiple of 32" in capsys.readouterr().err
    assert not out.exists() and not list(out_dir.iterdir())
    assert main(["convert", str(FIXTURES / "fruit_drops_v4.spz"), str(out_dir / "x.rad")]) == 2
    assert "cannot write .rad files" in capsys.readouterr().err
    # a .compressed.ply output was written as a standard 3DGS PLY under PlayCanvas's compressed PLY name (newuser58)
    for command in (["convert", str(FIXTURES / "fruit_drops_v4.spz")], ["decode", str(tmp_path / "no_scene")]):
        assert main([*command, str(out_dir / "x.compressed.ply")]) == 2
        assert "x.compressed.ply: cannot write PlayCanvas compressed PLY" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "missing.ply"), str(out)]) == 2
    assert "no such file" in capsys.readouterr().err
    assert not list(out_dir.iterdir())


def test_failed_conversion_keeps_existing_output(tmp_path):
    out = tmp_path / "x.ply"
    out.write_bytes(b"previous")
    bad = tmp_path / "bad.spz"
    bad.write_bytes(b"NGSP" + bytes(40))
    result = run_cli("convert", bad, out)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "version 0 is not supported" in result.stderr
    assert out.read_bytes() == b"previous"


def test_convert_to_sog_shows_the_writing_progress(tmp_path):
    """The SOG writer's SH palette fit (5.6 s on playbot) was one silent step: its share is reported, the file the
    same as without progress."""
    out = tmp_path / "fd.sog"
    r = run_cli("convert", real("fruit_drops_sh3.ply"), out)
    assert r.returncode == 0, r.stderr
    shares = [line for line in r.stderr.splitlines() if line.startswith("convert: writing ") and "%" in line]
    assert shares and shares[-1].startswith("convert: writing 100%")
    quiet = tmp_path / "q.sog"
    r = run_cli("convert", real("fruit_drops_sh3.ply"), quiet, "--quiet")
    assert r.returncode == 0 and "writing" not in r.stderr
    assert out.read_bytes() == quiet.read_bytes()
    assert len(read_gaussians(str(out))) == 4721


@pytest.mark.parametrize("output, option", [("x.ply", ["--spz-version", "3"]),
                                            ("x.sog", ["--glb-compression", "spz"]),
                                            ("x.spz", ["--glb-compression", "none"]),
                                            ("x.glb", ["--spz-version", "4"])])
def test_an_output_option_for_another_format_is_refused(tmp_path, capsys, output, option):
    """`convert logo x.ply --spz-version 3` wrote a PLY and `x.sog --glb-compression spz` a SOG, the option taken
    without a word (newuser61); --lod-level and --spz-axes rdf were already refused for an input they do not fit."""
    out = tmp_path / output
    assert main(["convert", str(FIXTURES / "fruit_drops_sub16.ply"), str(out), *option]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{option[0]} {option[1]}: only for" in err[0] and output in err[0], err
    assert not out.exists()
