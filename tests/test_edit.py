"""The edits of issue 36 (splatstream/edit.py): SH bands rotated exactly (per band, against a numpy reference),
splat-transform's names, frame and results, the same output whether the encoder edits the scene whole or chunk by
chunk (partitioned, Dask), and the CLI's --dry-run."""
from __future__ import annotations

import hashlib
import os
import subprocess

import numpy as np
import pytest
from conftest import real
from test_tool_roundtrip import SOURCE_PLY, splat_transform

from cli.main import main
from splatstream.edit import (
    Box,
    DensityFilter,
    Pipeline,
    Sphere,
    Transform,
    parse_filter,
    quaternion_from_euler,
    quaternion_matrix,
    rotation,
    rotation_quaternion,
    scaling,
    sh_rotation,
    translation,
)
from splatstream.encode import encode_file
from splatstream.encode.options import no_progress
from splatstream.encode.partitioned import ArrayRows, ConcatRows, open_rows
from splatstream.encode.scratch import Scratch
from splatstream.errors import UsageError
from splatstream.gaussians import SH_BAND_COEFFS, SH_BAND_START, Gaussians, covariances
from splatstream.io import open_input, read_gaussians
from splatstream.ply import read_elements, write_gaussians_ply
from splatstream.sh import sh_basis

BANDS = (1, 2, 3)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quaternion_matrix(q / np.linalg.norm(q))


def unit_directions(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("band", BANDS)
def test_sh_rotation_of_each_band_against_the_numpy_reference(band):
    """The reference is the definition: a band's function turned by R takes at R d the value it had at d,
    evaluated with the 3DGS basis (sh.sh_basis) at directions the fit never saw."""
    rng = np.random.default_rng(band)
    lo, n = 1 + SH_BAND_START[band], SH_BAND_COEFFS[band]
    for _ in range(5):
        r = random_rotation(rng)
        m = sh_rotation(r, band)
        c = rng.normal(size=(n, 4))
        d = unit_directions(rng)
        before = sh_basis(d, 3)[:, lo:lo + n] @ c
        after = sh_basis(d @ r.T, 3)[:, lo:lo + n] @ (m @ c)  # rows: R d
        np.testing.assert_allclose(after, before, atol=1e-12)
        np.testing.assert_allclose(m @ m.T, np.eye(n), atol=1e-12)  # an orthonormal basis: M is orthogonal
        np.testing.assert_allclose(sh_rotation(r.T, band), m.T, atol=1e-12)  # the inverse turn


def test_band_1_is_the_rotation_matrix_in_the_basis_order():
    """Band 1 of the 3DGS basis is C1 (-y, z, -x): its coefficients turn by P R P^T with P that permutation."""
    p = np.array([[0, -1, 0], [0, 0, 1], [-1, 0, 0]], float)
    r = random_rotation(np.random.default_rng(7))
    np.testing.assert_allclose(sh_rotation(r, 1), p @ r @ p.T, atol=1e-12)


def small_scene() -> Gaussians:
    return read_gaussians(SOURCE_PLY)


def test_a_rotated_scene_shows_the_same_colours_and_shapes():
    g = small_scene()
    t = rotation(30, -40, 75)
    r = quaternion_matrix(np.array(t.rotation))
    out = t.apply(g)
    np.testing.assert_allclose(out.positions, g.positions.astype(np.float64) @ r.T, atol=2e-6)
    np.testing.assert_allclose(covariances(out), r @ covariances(g) @ r.T, rtol=1e-4, atol=1e-9)
    d = unit_directions(np.random.default_rng(0), 50)
    basis = sh_basis(d, 3)[:, 1:]
    turned = sh_basis(d @ r.T, 3)[:, 1:]
    for band in BANDS:  # band by band: each is rotated on its own
        lo, n = SH_BAND_START[band], SH_BAND_COEFFS[band]
        want = np.einsum("dk,nkc->ndc", basis[:, lo:lo + n], g.sh_rest[:, lo:lo + n].astype(np.float64))
        got = np.einsum("dk,nkc->ndc", turned[:, lo:lo + n], out.sh_rest[:, lo:lo + n].astype(np.float64))
        np.testing.assert_allclose(got, want, atol=1e-6)
    np.testing.assert_array_equal(out.sh_dc, g.sh_dc)
    np.testing.assert_array_equal(out.opacity_logits, g.opacity_logits)


def test_coordinates_are_splat_transforms_engine_frame():
    """A PLY's x and y negated (PlayCanvas's frame): --translate 1,2,3 moves a PLY's splats by (-1, -2, 3)."""
    g = small_scene()
    moved = translation(1, 2, 3).apply(g)
    np.testing.assert_allclose(moved.positions - g.positions, np.tile([-1, -2, 3], (len(g), 1)), atol=1e-6)
    # the quaternion of Euler angles is PlayCanvas's (x, then y, then z): 90 about y turns +x to -z
    q = quaternion_from_euler(0, 90, 0)
    np.testing.assert_allclose(quaternion_matrix(q) @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    assert scaling(2).apply(g).log_scales == pytest.approx(g.log_scales + np.log(2), abs=1e-6)


def test_composed_transforms_equal_the_steps_one_by_one():
    g = small_scene()
    steps = [rotation(10, 20, 30), translation(0.5, -1, 2), scaling(1.5), rotation(-5, 0, 45)]
    composed = Pipeline(steps).apply(g)
    assert len(Pipeline(steps).steps) == 1
    one_by_one = g
    for s in steps:
        one_by_one = s.apply(one_by_one)
    for name in ("positions", "rotations", "log_scales", "sh_rest"):
        np.testing.assert_allclose(getattr(composed, name), getattr(one_by_one, name), atol=1e-5)


def test_filters_keep_what_they_say():
    g = small_scene()
    engine = g.positions.astype(np.float64) * [-1, -1, 1]
    box = Box((-0.8, -0.2, -2.2), (-0.6, 0.1, -2.0))
    inside = np.all((engine >= box.lo) & (engine <= box.hi), axis=1)
    np.testing.assert_array_equal(box.keep(g), inside)
    np.testing.assert_array_equal(Box(box.lo, box.hi, keep_inside=False).keep(g), ~inside)
    sphere = Sphere((-0.7, -0.1, -2.1), 0.1)
    np.testing.assert_array_equal(sphere.keep(g), np.linalg.norm(engine - sphere.center, axis=1) < 0.1)
    np.testing.assert_array_equal(parse_filter("opacity>0.3").keep(g), g.opacities.astype(np.float64) > 0.3)
    np.testing.assert_array_equal(parse_filter("scale_1<=0.01").keep(g),
                                  g.log_scales[:, 1].astype(np.float64) <= np.log(0.01))
    np.testing.assert_array_equal(parse_filter("f_dc_0_raw,lte,0.2").keep(g), g.sh_dc[:, 0] <= 0.2)
    assert parse_filter("x != 0.5") == parse_filter("x,neq,0.5")
    for bad, says in (("opacity>>1", "not a number"), ("rot_0>1", "unknown attribute"), ("opacity", "expected"),
                      ("opacity>1.5", "between 0 and 1"), ("opacity,gte,nan", "finite")):
        with pytest.raises(UsageError, match=says):
            parse_filter(bad)


# splat-transform 3.7.0 on tests/fixtures/foreign/fruit_drops_sub16.ply (296 splats): its arguments, our edits
# and the splats it kept (recorded with `splat-transform -g cpu IN ARGS out.ply`).
TOOL_CASES = [
    (["-t", "1,2,3"], [translation(1, 2, 3)], 296),
    (["-r", "30,-40,75", "-t", "1,2,3", "-s", "1.5"], [rotation(30, -40, 75), translation(1, 2, 3), scaling(1.5)],
     296),
    (["-B", "-0.8,-0.2,-2.2,-0.6,0.1,-2.0"], [Box((-0.8, -0.2, -2.2), (-0.6, 0.1, -2.0))], 106),
    (["-S", "-0.7,-0.1,-2.1,0.1"], [Sphere((-0.7, -0.1, -2.1), 0.1)], 80),
    (["-V", "opacity,gt,0.3"], [parse_filter("opacity>0.3")], 61),
    (["-V", "scale_1,lt,0.01"], [parse_filter("scale_1<0.01")], 246),
    (["-V", "f_dc_0,gte,0.5"], [parse_filter("f_dc_0>=0.5")], 41),
    (["-V", "y,gt,-0.1"], [parse_filter("y>-0.1")], 140),
    (["-t", "0.7,0,0", "-V", "x,lt,0"], [translation(0.7, 0, 0), parse_filter("x<0")], 184),
    (["-r", "0,90,0", "-t", "2,0,0", "-B", "-0.11,-1,-1,3,1,1"], [rotation(0, 90, 0), translation(2, 0, 0),
                                                                Box((-0.11, -1, -1), (3, 1, 1))], 246),
]


@pytest.mark.parametrize("case", range(len(TOOL_CASES)))
def test_kept_splats_match_splat_transform(case):
    _, edits, kept = TOOL_CASES[case]
    assert len(Pipeline(edits).apply(small_scene())) == kept


@pytest.mark.parametrize("case", range(len(TOOL_CASES)))
def test_values_match_splat_transform(case, tmp_path):
    tool = splat_transform()
    args, edits, kept = TOOL_CASES[case]
    out = tmp_path / "out.ply"
    r = subprocess.run([tool, "-q", "-w", "-g", "cpu", str(SOURCE_PLY), *args, str(out)], capture_output=True,
                       text=True, timeout=300, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stdout + r.stderr
    v = read_elements(out)[1]["vertex"]
    ours = Pipeline(edits).apply(small_scene())
    assert len(v) == kept == len(ours)

    def cols(*names: str) -> np.ndarray:
        return np.stack([v[n] for n in names], axis=1)

    np.testing.assert_allclose(cols("x", "y", "z"), ours.positions, atol=1e-6)
    np.testing.assert_allclose(cols(*(f"rot_{i}" for i in range(4))), ours.rotations, atol=1e-6)
    np.testing.assert_allclose(cols(*(f"scale_{i}" for i in range(3))), ours.log_scales, atol=1e-6)
    np.testing.assert_array_equal(cols("f_dc_0", "f_dc_1", "f_dc_2"), ours.sh_dc)
    np.testing.assert_array_equal(v["opacity"], ours.opacity_logits)
    k = ours.sh_rest.shape[1]
    rest = cols(*(f"f_rest_{i}" for i in range(3 * k))).reshape(-1, 3, k).transpose(0, 2, 1)
    np.testing.assert_allclose(rest, ours.sh_rest, atol=1e-6)


def tree_digest(path: str) -> str:
    lines = []
    for root, _, files in os.walk(path):
        for f in files:
            with open(os.path.join(root, f), "rb") as fh:
                lines.append(f"{os.path.relpath(os.path.join(root, f), path)} {hashlib.sha256(fh.read()).hexdigest()}")
    return hashlib.sha256("\n".join(sorted(lines)).encode()).hexdigest()


# The scene moved to the origin and turned, then cropped, filtered and holed: 4721 -> 3643 -> 1941 -> 1798 splats.
EDITS = Pipeline([translation(0.75, 0.1, 2.15), rotation(0, 30, 0), Box((-0.1, -0.5, -0.5), (0.5, 0.5, 0.5)),
                  parse_filter("opacity>0.05"), Sphere((0.1, 0, 0), 0.05, keep_inside=False)])


@pytest.fixture(scope="module")
def scene_ply(tmp_path_factory) -> str:
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    path = tmp_path_factory.mktemp("input") / "scene.ply"
    write_gaussians_ply(g, path)
    return str(path)


def test_partitioned_encode_with_edits_is_the_in_memory_one(scene_ply, tmp_path):
    """Crop, filter and transform by chunks (a 1 MiB memory budget: several partitions) give the bytes of the
    scene edited whole in memory, on Dask too."""
    g = read_gaussians(scene_ply)
    kept = len(EDITS.apply(g))
    assert (len(g), kept) == (4721, 1798)
    # the grid named: the same bytes in memory and by partitions for any partitioning (auto: by merge domains)
    tree = {"max_leaf_splats": 300, "preset": "low", "lod_merge": "grid"}
    encode_file(scene_ply, tmp_path / "memory", edits=EDITS, **tree)
    encode_file(scene_ply, tmp_path / "parts", edits=EDITS, memory_per_worker=1 << 20, **tree)
    want = tree_digest(str(tmp_path / "memory"))
    assert tree_digest(str(tmp_path / "parts")) == want
    pytest.importorskip("distributed")
    encode_file(scene_ply, tmp_path / "dask", edits=EDITS, workers=2, memory_per_worker=1 << 20, **tree)
    assert tree_digest(str(tmp_path / "dask")) == want


def test_dry_run_prints_each_step_and_writes_nothing(scene_ply, tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["encode", scene_ply, str(out), "--translate", "0.75,0.1,2.15", "--rotate", "0,30,0", "--crop-box",
                 "-0.1,-0.5,-0.5,0.5,0.5,0.5", "--filter", "opacity>0.05", "--drop-sphere", "0.1,0,0,0.05",
                 "--dry-run"]) == 0
    g = read_gaussians(scene_ply)
    _, counts = EDITS.run(g)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"read {scene_ply}: {len(g):,} splats"
    assert [line.split(": keeps ")[1].split(" of ")[0] for line in lines[1:]] == [f"{n:,}" for _, n in counts]
    assert [n for _, n in counts] == [4721, 3643, 1941, 1798]
    assert lines[1] == "  translate 0.75,0.1,2.15 rotate 0,30,0: keeps 4,721 of 4,721 (0 dropped)"
    assert not out.exists()


def test_convert_applies_the_edits_in_order(tmp_path):
    out = tmp_path / "out.ply"
    assert main(["convert", str(SOURCE_PLY), str(out), "-q", "--filter-value", "opacity,gt,0.1", "--scale", "2",
                 "--crop-sphere", "-1.4,-0.2,-4.2,0.3"]) == 0
    want = Pipeline([parse_filter("opacity>0.1"), scaling(2), Sphere((-1.4, -0.2, -4.2), 0.3)]).apply(small_scene())
    got = read_gaussians(out)
    assert 0 < len(got) == len(want) < len(small_scene())
    np.testing.assert_array_equal(got.positions, want.positions)
    assert isinstance(Pipeline([scaling(2)]).steps[0], Transform)


def test_edit_options_are_checked(tmp_path, capsys):
    for args, says in ((["--filter-box", "1,1,1,0,0,0"], "min corner"), (["--scale-by", "0"], "above 0"),
                       (["--filter-sphere", "0,0,0"], "4 comma-separated numbers"),
                       (["--scale-by", "inf"], "--scale-by: expected a finite number, got 'inf'"),
                       (["--translate", "1,2,3", "--target-psnr", "30"], "without edits")):
        assert main(["encode", str(SOURCE_PLY), str(tmp_path / "out"), "-q", *args]) == 2
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------- merging inputs


@pytest.fixture(scope="module")
def second_ply(tmp_path_factory) -> str:
    """A second input of another SH degree (0), beside scene_ply (3): the first 3000 splats of the fountain."""
    g = read_gaussians(real("winter_fountain_first3000.splat"))
    assert g.sh_degree == 0
    path = tmp_path_factory.mktemp("second") / "fountain.ply"
    write_gaussians_ply(g, path)
    return str(path)


def test_merged_inputs_are_one_after_the_other_with_zero_bands(scene_ply, second_ply, tmp_path):
    """`convert a b out`: the splats of a then b, b's missing SH bands zeros (its colours as they were)."""
    out = tmp_path / "merged.ply"
    assert main(["convert", scene_ply, second_ply, str(out), "-q"]) == 0
    a, b, got = read_gaussians(scene_ply), read_gaussians(second_ply), read_gaussians(out)
    assert (len(a), len(b), len(got), got.sh_degree) == (4721, 3000, 7721, 3)
    np.testing.assert_array_equal(got.positions, np.concatenate([a.positions, b.positions]))
    np.testing.assert_array_equal(got.sh_dc[4721:], b.sh_dc)
    np.testing.assert_array_equal(got.sh_rest[:4721], a.sh_rest)
    assert not got.sh_rest[4721:].any()


def test_partitioned_encode_of_merged_inputs_is_the_in_memory_one(scene_ply, second_ply, tmp_path):
    """Two inputs merged and edited by chunks (chunks of each input in turn, a 1 MiB memory budget) give the bytes
    of the merged scene in memory; on Dask too, where the second input is a .splat spilled to scratch."""
    both = Pipeline([Box((-3, -3, -3), (3, 3, 3)), parse_filter("opacity>0.05")])
    merged = Gaussians.concatenate([read_gaussians(scene_ply), read_gaussians(second_ply)])
    tree = {"max_leaf_splats": 300, "preset": "low", "name": "merged", "lod_merge": "grid"}  # any partitioning
    m = encode_file([scene_ply, second_ply], tmp_path / "memory", edits=both, **tree)
    assert (m.splats, m.sh_degree) == (len(both.apply(merged)), 3)
    assert m.splats == 5471 < len(merged)
    want = tree_digest(str(tmp_path / "memory"))
    encode_file([scene_ply, second_ply], tmp_path / "parts", edits=both, memory_per_worker=1 << 20, **tree)
    assert tree_digest(str(tmp_path / "parts")) == want
    pytest.importorskip("distributed")
    # the .splat itself, not its PLY copy: rotations normalised once, not twice, differ in the last bit
    inputs = [scene_ply, real("winter_fountain_first3000.splat")]
    encode_file(inputs, tmp_path / "memory2", edits=both, **tree)
    encode_file(inputs, tmp_path / "dask", edits=both, workers=2, memory_per_worker=1 << 20, **tree)
    assert tree_digest(str(tmp_path / "dask")) == tree_digest(str(tmp_path / "memory2"))


def test_encode_takes_several_inputs_on_the_command_line(scene_ply, second_ply, tmp_path, capsys):
    assert main(["encode", scene_ply, second_ply, str(tmp_path / "out"), "--filter", "opacity>0.05",
                 "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    kept = len(parse_filter("opacity>0.05").keep(read_gaussians(scene_ply)).nonzero()[0]) + len(
        parse_filter("opacity>0.05").keep(read_gaussians(second_ply)).nonzero()[0])
    assert lines[0] == f"read {scene_ply} + {second_ply}: 7,721 splats"
    assert lines[1] == f"  filter-value opacity,gt,0.05: keeps {kept:,} of 7,721 ({7721 - kept:,} dropped)"
    assert main(["encode", scene_ply, second_ply, str(tmp_path / "out"), "-q", "--target-psnr", "30"]) == 2
    assert "one input" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- floater removal


def test_density_filter_counts_the_neighbours_of_each_cell_exactly():
    """Against brute force: for every splat, the centres whose cell differs from its own by at most 1 on each
    axis; the same kept splats in any order; and a far floater dropped while its far-apart cells stay apart."""
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    f = DensityFilter(0.01, 4)
    cells = np.floor(g.positions.astype(np.float64) / f.size).astype(np.int64)
    want = np.array([np.count_nonzero(np.all(np.abs(cells - c) <= 1, axis=1)) for c in cells])
    np.testing.assert_array_equal(f.neighbour_counts(g), want)
    assert np.count_nonzero(f.keep(g)) == np.count_nonzero(want >= 4) == 4531
    order = np.random.default_rng(1).permutation(len(g))
    np.testing.assert_array_equal(f.keep(g.subset(order)), f.keep(g)[order])
    far = g.subset(np.arange(8))
    far.positions[:] = [[0, 0, 0]] * 4 + [[1000.005, 0, 0], [1000.015, 0, 0], [1000.035, 0, 0], [-1000, 300, 7]]
    np.testing.assert_array_equal(f.neighbour_counts(far), [4, 4, 4, 4, 2, 2, 1, 1])


def test_density_filter_runs_in_memory_and_is_refused_by_partitions(scene_ply, tmp_path, capsys):
    edits = Pipeline([DensityFilter(0.01, 4)])
    m = encode_file(scene_ply, tmp_path / "memory", edits=edits, max_leaf_splats=300, preset="low")
    assert m.splats == 4531
    with pytest.raises(UsageError, match="--filter-density counts each splat's neighbours over the whole scene"):
        encode_file(scene_ply, tmp_path / "parts", edits=edits, memory_per_worker=1 << 20, max_leaf_splats=300)
    assert not (tmp_path / "parts").exists()
    assert main(["encode", scene_ply, str(tmp_path / "out"), "--filter-density", "0.01,4", "--dry-run",
                 "--memory-per-worker", "1MiB"]) == 0
    assert capsys.readouterr().out.splitlines()[1] == "  filter-density 0.01,4: keeps 4,531 of 4,721 (190 dropped)"
    assert main(["convert", scene_ply, str(tmp_path / "c.ply"), "-q", "--filter-density", "0.01,2.5"]) == 2
    assert "whole minimum count" in capsys.readouterr().err


def test_rotate_takes_a_quaternion_in_playcanvas_order(tmp_path):
    """--rotate X,Y,Z,W is the turn of the Euler angles whose quaternion it is (PlayCanvas's x, y, z, w order),
    normalised; a zero quaternion is refused."""
    w, x, y, z = quaternion_from_euler(30, -40, 75)
    g = small_scene()
    want = rotation(30, -40, 75).apply(g)
    got = rotation_quaternion(2 * x, 2 * y, 2 * z, 2 * w).apply(g)
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-12)
    np.testing.assert_allclose(got.rotations, want.rotations, atol=1e-12)
    np.testing.assert_allclose(got.sh_rest, want.sh_rest, atol=1e-9)
    out, ref = tmp_path / "q.ply", tmp_path / "e.ply"
    assert main(["convert", str(SOURCE_PLY), str(out), "-q", "--rotate", "0,0,0.70710678,0.70710678"]) == 0
    assert main(["convert", str(SOURCE_PLY), str(ref), "-q", "--rotate", "0,0,90"]) == 0
    np.testing.assert_allclose(read_gaussians(out).positions, read_gaussians(ref).positions, atol=1e-6)
    with pytest.raises(UsageError, match="length 0"):
        rotation_quaternion(0, 0, 0, 0)


def test_a_value_with_a_leading_minus_is_read_as_the_option_s_value(tmp_path, capsys):
    """splat-transform's users write `-B -1,-1,-1,1,1,1`: the spaced value reads as with `=`."""
    spaced = ["encode", str(SOURCE_PLY), str(tmp_path / "a"), "--filter-box", "-1.4,-0.5,-4.5,-0.8,0.5,-3.5",
              "--translate", "-1,0,0", "--dry-run"]
    assert main(spaced) == 0
    assert main([*spaced[:3], "--filter-box=-1.4,-0.5,-4.5,-0.8,0.5,-3.5", "--translate=-1,0,0", "--dry-run"]) == 0
    first, second = capsys.readouterr().out.split("read ")[1:]
    assert first == second and "filter-box -1.4,-0.5,-4.5,-0.8,0.5,-3.5: keeps" in first


def test_merge_matches_splat_transform_except_its_sh_columns_by_name(tmp_path):
    """splat-transform merges columns by name, zeros where an input lacks one: the same splats and values as ours
    for degrees 3 + 0. For 3 + 1 its by-name f_rest_0..8 (a degree-1 PLY's r, g, b coefficients of band 1) land on
    the first nine red coefficients of degree 3; ours keeps each coefficient where it belongs (zeros padded)."""
    tool = splat_transform()
    a = small_scene()
    low = tmp_path / "deg1.ply"
    write_gaussians_ply(a.with_sh_degree(1), low)
    zero = tmp_path / "deg0.ply"
    write_gaussians_ply(read_gaussians(real("winter_fountain_first3000.splat")), zero)
    for second, same in ((zero, True), (low, False)):
        out = tmp_path / "merged.ply"
        r = subprocess.run([tool, "-q", "-w", "-g", "cpu", str(SOURCE_PLY), str(second), str(out)],
                           capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL)
        assert r.returncode == 0, r.stdout + r.stderr
        v = read_elements(out)[1]["vertex"]
        ours = Gaussians.concatenate([a, read_gaussians(second)])
        assert len(v) == len(ours)
        np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], axis=1), ours.positions)
        flat = np.stack([v[f"f_rest_{i}"] for i in range(45)], axis=1)  # PLY order: channel-major
        np.testing.assert_array_equal(flat[:len(a)], ours.sh_rest[:len(a)].transpose(0, 2, 1).reshape(-1, 45))
        theirs = flat[len(a):]
        if same:
            assert not theirs.any() and not ours.sh_rest[len(a):].any()
        else:
            band1 = a.sh_rest[:, :3].transpose(0, 2, 1).reshape(-1, 9)  # r0 r1 r2 g0 g1 g2 b0 b1 b2
            np.testing.assert_array_equal(theirs[:, :9], band1)  # all nine as red coefficients 0..8
            np.testing.assert_array_equal(ours.sh_rest[len(a):, :3], a.sh_rest[:, :3])
            assert not ours.sh_rest[len(a):, 3:].any()


def test_spilled_and_merged_rows_read_any_range(tmp_path):
    """The rows an encoder chunk asks for, whatever the spill's chunk size and across the inputs of a merge (the
    partitioned encoder's chunks are sized by the memory per worker, not by the spill)."""
    splat = read_gaussians(real("winter_fountain_first3000.splat"))
    ply = small_scene()
    space = Scratch.create(str(tmp_path))
    try:
        spilled = open_rows(open_input(real("winter_fountain_first3000.splat")), None, space, 700, False,
                            no_progress, "input1")
        for start, stop in ((0, 700), (500, 2500), (2999, 5000), (1400, 1400)):
            g, stats = spilled.read(start, stop)
            np.testing.assert_array_equal(g.positions, splat.positions[start:stop])
            assert stats.rows == len(g)
        merged = ConcatRows([ArrayRows(ply), spilled])
        whole = Gaussians.concatenate([ply, splat])
        assert (merged.rows, merged.sh_degree) == (len(ply) + 3000, 3)
        for start, stop in ((0, 100), (250, 1900), (len(ply) - 5, len(ply) + 10), (len(ply) + 2990, 10 ** 6)):
            g, _ = merged.read(start, stop)
            np.testing.assert_array_equal(g.positions, whole.positions[start:stop])
            np.testing.assert_array_equal(g.sh_rest, whole.sh_rest[start:stop])
    finally:
        space.remove()
