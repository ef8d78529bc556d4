"""`encode --lod-refine cpu` by partitions (issue 31, city scale; branch partrefine31; format_spec/lod.md 6, "The
refinement by partitions"): each merge domain refined in its own task against its own originals, the levels above
the partitions against the domains' refined roots, one record for the manifest; the bytes the same on every engine
and worker count, the full detail unchanged, the refined levels not the unrefined ones."""
from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest
from conftest import real, run_cli, tree_digest

from splatstream.encode import encode_file
from splatstream.encode.partitioned import routed_row_bytes
from splatstream.errors import UsageError
from splatstream.format.manifest import LevelRefinement, LodRefinement
from splatstream.io import read_gaussians
from splatstream.lod import build_tiles
from splatstream.lod_refine import domains_record, refine_tree
from splatstream.store import open_store, read_manifest

numba = pytest.importorskip("numba")

from refine_cpu import raster  # noqa: E402
from refine_cpu.levels import KERNELS_BYTES, CpuLevelRefiner, CpuRefineSettings  # noqa: E402

# fruit_drops (5,321 splats) in leaves of at most 300: domains of at most 700 splats are the tile level of kd depth
# 3, 8 partitions of 665-666 splats, three levels above them (1, 2 and 4 tiles) refined against their roots.
TREE = {"preset": "low", "max_leaf_splats": 300, "lod_merge_domain_splats": 700}
TIERS = {"lod_upper_domain_roots": 2}
# A domain's task fits (its build 0.84 MiB; with the fit at 32 px, CpuLevelRefiner.peak_bytes, about 72 MiB: 24 and
# the 48 MiB of numba's kernels; the upper domains' the largest), the scene's in-memory encode does not (4.4 MiB, about
# 86 MiB with the fit): partitioned in this process
MEMORY = 74 << 20
PLAIN_MEMORY = 2 << 20  # without the fit: a domain fits (0.84 MiB), the scene (4.4 MiB) does not
# A fit small enough for a test (the defaults' far cameras and camera counts kept)
ITERS, SIZE = 5, 32


def refiner() -> CpuLevelRefiner:
    return CpuLevelRefiner(CpuRefineSettings(iterations=ITERS, size=SIZE))


@pytest.fixture(scope="module")
def encodes(tmp_path_factory) -> dict:
    """The same scene partitioned in this process (refined, and not) and on a local Dask cluster of 2 workers."""
    root = tmp_path_factory.mktemp("partrefine")
    src = real("fruit_drops_sh3.ply")
    out = {}
    for name, kw in [("local", {"memory_per_worker": MEMORY, "lod_refiner": refiner()}),
                     ("dask2", {"workers": 2, "lod_refiner": refiner()}),
                     ("plain", {"memory_per_worker": PLAIN_MEMORY}),
                     # upper domains of 2 roots: the levels above the partitions refined in three tiers (2, 1, 0)
                     ("tiers", {"memory_per_worker": MEMORY, "lod_refiner": refiner(), **TIERS}),
                     ("tiers_dask2", {"workers": 2, "lod_refiner": refiner(), **TIERS})]:
        encode_file(src, root / name, **TREE, **kw)
        out[name] = root / name
    return out


def test_the_bytes_are_the_same_in_this_process_and_on_dask(encodes):
    assert tree_digest(encodes["local"]) == tree_digest(encodes["dask2"])


def test_upper_domains_refine_tier_by_tier_with_the_same_bytes_on_any_engine(encodes):
    assert tree_digest(encodes["tiers"]) == tree_digest(encodes["tiers_dask2"])
    one, tiers = (read_manifest(open_store(encodes[k])) for k in ("local", "tiers"))
    # the domains' own levels (3-5) as before; the levels above grouped and refined per upper domain
    assert [(t.id, t.children) for t in one.tiles] == [(t.id, t.children) for t in tiers.tiles]
    def digests(t) -> dict:
        return {g: e.sha256 for g, e in t.groups.items()}

    for a, b in zip(one.tiles, tiers.tiles, strict=True):
        assert a.level < 3 or digests(a) == digests(b), a.id
    assert any(digests(a) != digests(b) for a, b in zip(one.tiles, tiers.tiles, strict=True) if a.level < 3)
    rec = tiers.lod.refinement
    assert [lv.level for lv in rec.levels] == [0, 1, 2, 3, 4, 5]  # every merged level once, the root's first
    by_id = {t.id: t for t in tiers.tiles}
    for t in tiers.tiles:  # no holes: a parent's bounds cover its children's, refined in another tier or not
        for c in t.children:
            assert all(a <= b for a, b in zip(t.box.min, by_id[c].box.min, strict=True))
            assert all(a >= b for a, b in zip(t.box.max, by_id[c].box.max, strict=True))
            assert by_id[c].geometric_error <= t.geometric_error


def test_every_merged_level_is_refined_and_recorded_and_the_leaves_stay(encodes):
    plain, refined = read_manifest(open_store(encodes["plain"])), read_manifest(open_store(encodes["local"]))
    rec = refined.lod.refinement
    assert plain.lod.refinement is None and rec is not None
    assert rec.variants == (("A", ("opacity_logits", "sh_dc")),) and (rec.size_px, rec.iterations) == (SIZE, ITERS)
    # the levels above the partitions (0-2) and those inside the domains (3-5): every merged level, once
    assert [lv.level for lv in rec.levels] == sorted({t.level for t in refined.tiles if t.children}) == [0, 1, 2, 3, 4,
                                                                                                          5]
    kept = {lv.level: lv.kept for lv in rec.levels}
    assert kept[0] == kept[1] == kept[2] == "A"
    for lv in rec.levels:
        psnr = dict(lv.validation_psnr)
        assert set(psnr) == {"none", "A"} and (lv.kept == "none" or psnr["A"] >= psnr["none"])
    changed = 0
    for a, b in zip(plain.tiles, refined.tiles, strict=True):
        assert (a.id, a.level, a.children, a.splats, a.geometric_error) == (b.id, b.level, b.children, b.splats,
                                                                            b.geometric_error)
        same = {g: e.sha256 for g, e in a.groups.items()} == {g: e.sha256 for g, e in b.groups.items()}
        if not a.children:
            assert same  # the full detail: byte for byte
        elif kept[a.level] == "none":
            pass  # a level some domain kept as built may still differ in another domain
        else:
            changed += not same
    assert changed >= len([t for t in refined.tiles if t.children and kept[t.level] == "A"]) // 2
    assert not {g: e.sha256 for g, e in plain.tiles[0].groups.items()} == {
        g: e.sha256 for g, e in refined.tiles[0].groups.items()}  # the root, refined above the partitions


FRAMES: list = []  # the frames a RecordingRefiner was called with (module-level: the engine may copy the refiner)


class RecordingRefiner(CpuLevelRefiner):
    """The CPU refiner, noting where each fit's cameras were placed from (its `frame`) and its full detail's size."""

    def __call__(self, g, tiles, up, progress, frame=None):
        FRAMES.append((len(g), frame))
        return super().__call__(g, tiles, up, progress, frame=frame)


def test_every_fit_is_seen_from_the_whole_scenes_cameras(tmp_path):
    """Each domain (and the levels above) is fitted from the camera rule of the WHOLE scene (lod_refine.CameraFrame
    of the scene's sample of centres: here every centre, the in-memory encode's frame), not around its own splats:
    so the domain alone in the frame the in-memory encode fits the whole tree in (BENCHMARKS.md, "Closing the
    partitioned refinement's gap": cameras around each domain cost 0.2-1.2 dB streamed on 3 of 4 scenes)."""
    from splatstream.io import read_gaussians
    from splatstream.lod_refine import CameraFrame, far_level_cameras, orbit_distance_and_focal, refine_cameras

    src = real("fruit_drops_sh3.ply")
    g = read_gaussians(src)
    FRAMES.clear()
    encode_file(src, tmp_path / "a", memory_per_worker=MEMORY, lod_refiner=RecordingRefiner(
        CpuRefineSettings(iterations=ITERS, size=SIZE)), **TREE)
    scene = CameraFrame.of(g.positions)
    # 8 domains, then the levels above against the 8 refined roots
    assert len(FRAMES) == 9, [n for n, _ in FRAMES]
    for _, frame in FRAMES:
        assert all(np.array_equal(a, b) for a, b in ((frame.median, scene.median), (frame.lo, scene.lo),
                                                     (frame.hi, scene.hi)))
    # a domain's cameras: the whole scene's rule, as the in-memory encode's from all of the positions
    up = (0.0, -1.0, 0.0)
    assert refine_cameras(scene, up, 6, 32, 3) == refine_cameras(g.positions, up, 6, 32, 3)
    assert orbit_distance_and_focal(scene, up, 32) == orbit_distance_and_focal(g.positions, up, 32)
    assert far_level_cameras(scene, up, 4, 32, 9, (2.0, 8.0)) == far_level_cameras(g.positions, up, 4, 32, 9,
                                                                                    (2.0, 8.0))
    # and not those around a domain's own splats (today's before partgap31): another orbit
    part = g.positions[: len(g) // 8]
    assert refine_cameras(part, up, 6, 32, 3) != refine_cameras(g.positions, up, 6, 32, 3)


def test_the_record_of_the_domains():
    def rec(levels):
        return LodRefinement("render-fit", (("A", ("opacity_logits", "sh_dc")),), 256, 60, 32, 1000, 16, 1001,
                             tuple(levels))

    a = rec([LevelRefinement(3, "A", (("none", 20.0), ("A", 21.0))), LevelRefinement(4, "none",
                                                                                   (("none", 30.0), ("A", 29.0)))])
    b = rec([LevelRefinement(3, "none", (("none", 30.0), ("A", 29.0))), LevelRefinement(4, "none",
                                                                                      (("none", 30.0), ("A", 29.5)))])
    above = rec([LevelRefinement(0, "A", (("none", 18.0), ("A", 19.0)))])
    r = domains_record([a, b], above)
    assert [lv.level for lv in r.levels] == [0, 3, 4] and r.levels[0] == above.levels[0]
    three, four = dict(r.levels[1].validation_psnr), dict(r.levels[2].validation_psnr)
    # level 3: kept where one domain kept it; "none" the domains' mean MSE as built, "A" as written (A in the first
    # domain, as built in the second)
    assert r.levels[1].kept == "A" and r.levels[2].kept == "none"
    assert three["none"] == pytest.approx(-10 * np.log10((10 ** -2.0 + 10 ** -3.0) / 2), abs=1e-3)
    assert three["A"] == pytest.approx(-10 * np.log10((10 ** -2.1 + 10 ** -3.0) / 2), abs=1e-3)
    assert four["A"] == pytest.approx(-10 * np.log10((10 ** -2.9 + 10 ** -2.95) / 2), abs=1e-3)
    assert domains_record([a], None).levels == a.levels  # one domain: its own record


def test_a_domain_over_the_memory_and_a_refiner_that_does_not_run_by_partitions_are_refused(tmp_path):
    src = real("fruit_drops_sh3.ply")
    with pytest.raises(UsageError, match=r"--lod-refine by partitions refines each merge domain .* give more "
                                         r"--memory-per-worker"):
        encode_file(src, tmp_path / "a", memory_per_worker=1 << 19, lod_refiner=refiner(), **TREE)

    class InMemoryOnly:
        name = "--lod-refine gpu"

        def __call__(self, g, tiles, up, progress):
            raise AssertionError("not called")

    with pytest.raises(UsageError, match="--lod-refine gpu refines in-memory encodes only, not a partitioned one"):
        encode_file(src, tmp_path / "b", memory_per_worker=PLAIN_MEMORY, lod_refiner=InMemoryOnly(), **TREE)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_the_fit_memory_is_counted_in_what_a_domain_needs(tmp_path):
    """A worker that holds a domain's build (0.84 MiB) but not its fit (CpuLevelRefiner.peak_bytes: about 72 MiB at
    32 px) is refused, in one line naming the domain, the setting and the fit's share, before anything is written:
    before the route pass where even the fit without its pairs does not fit ("at least", 62 MiB), after it with the
    pairs a pixel estimated from the scene's sample (72 MiB: the levels above the domains, at the refiner's constant
    32 pairs a pixel, which the scene's estimate passes at 32 px); the fit's model bounds what a real fit of the
    whole scene takes (tracemalloc: the pair lists and targets are numpy arrays)."""
    src = real("fruit_drops_sh3.ply")
    with pytest.raises(UsageError, match=r"a subtree of at most 700 splats\) in one task, which needs at least 62 MiB "
                                         r"per worker \(the refiner's renders, targets and pair lists 61 MiB of it: a "
                                         r"smaller --lod-refine-size takes less\), more than the memory per worker "
                                         r"\(20 MiB\): give more --memory-per-worker"):
        encode_file(src, tmp_path / "a", memory_per_worker=20 << 20, lod_refiner=refiner(), **TREE)
    with pytest.raises(UsageError, match=r"a subtree of at most 700 splats\) in one task, which needs 72 MiB per "
                                         r"worker \(the refiner's renders, targets and pair lists 70 MiB of it: a "
                                         r"smaller --lod-refine-size takes less\), more than the memory per worker "
                                         r"\(64 MiB\): give more --memory-per-worker"):
        encode_file(src, tmp_path / "a", memory_per_worker=64 << 20, lod_refiner=refiner(), **TREE)
    assert not (tmp_path / "a").exists()
    g = read_gaussians(src)
    tiles = build_tiles(g, 300, 2.0, merge="auto")
    fit = refiner()
    tracemalloc.start()
    try:
        refine_tree(g, tiles, (0.0, 0.0, 1.0), fit, lambda stage, fraction: None)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # tracemalloc sees numpy's arrays, not numba's kernels (the model's KERNELS_BYTES: RSS, bench/refiner_memory.py)
    model = fit.peak_bytes(len(g), routed_row_bytes(g.sh_degree)) - KERNELS_BYTES
    # measured: 14.4 MiB against 31.6 (30.4 on a first fit, numba compiling: the model's splat term fitted there)
    assert model / 4 <= peak <= model, (peak, model)
    assert CpuLevelRefiner(CpuRefineSettings(size=64)).peak_bytes(1000, 64) > fit.peak_bytes(1000, 64)


def test_the_fit_is_the_same_on_any_number_of_threads():
    """The gradient rows are a constant (raster.GRADIENT_ROWS), so a Dask worker's threads and this process's give
    the same floats."""
    from conftest import real as real_path

    from splatstream.camera import scene_orbit_views
    from splatstream.io import read_gaussians

    g = read_gaussians(real_path("fruit_drops_sh3.ply"))
    views = scene_orbit_views(g.positions, 3, 40, 40, elevation_deg=25.0)
    pl = raster.pair_lists(g, views, g.sh_degree)
    target = np.full((3, 40, 40, 3), 0.25, np.float32)
    op, dc = g.opacities.astype(np.float64), raster.SH_C0 * g.sh_dc.astype(np.float64)
    before = numba.get_num_threads()
    try:
        out = []
        for n in sorted({1, before}):
            numba.set_num_threads(n)
            out.append(raster.loss_and_grad(pl, op, dc, target))
    finally:
        numba.set_num_threads(before)
    for loss, g_op, g_dc in out[1:]:
        assert loss == out[0][0] and np.array_equal(g_op, out[0][1]) and np.array_equal(g_dc, out[0][2])


def test_cli_refines_by_partitions_with_any_workers_as_in_memory(tmp_path):
    """Through the CLI: --workers 1 and 2 (a local Dask cluster) refine a scene of one merge domain to the bytes of
    the in-memory encode (the partition is the whole tree); progress and the refiner's lines shown; the record
    lists every merged level."""
    src = real("fruit_drops_sh3.ply")
    args = ("--preset", "low", "--max-leaf-splats", "256", "--lod-refine", "cpu", "--lod-refine-iters", str(ITERS),
            "--lod-refine-size", str(SIZE))
    digests = {}
    for name, extra in [("memory", ()), ("w1", ("--workers", "1")), ("w2", ("--workers", "2"))]:
        r = run_cli("encode", src, tmp_path / name, *args, *extra)
        assert r.returncode == 0, r.stderr
        # the refiner's lines (from the Dask workers too) and the progress
        assert "lod-refine: level 0 (" in r.stderr and "encode: tiles 100%" in r.stderr, r.stderr
        digests[name] = tree_digest(tmp_path / name)
    assert digests["memory"] == digests["w1"] == digests["w2"]
    info = json.loads(run_cli("info", tmp_path / "w2", "--json").stdout)
    m = read_manifest(open_store(tmp_path / "w2"))
    assert [lv["level"] for lv in info["lod"]["refinement"]["levels"]] == sorted(
        {t.level for t in m.tiles if t.children})


def test_partitions_of_single_leaves_are_refined_above_against_the_originals(tmp_path):
    """Domains smaller than a leaf: the partitions are the leaves, with no merged level of their own, so the task
    above refines every merged level, its leaves the originals; recorded, and the same bytes with other memory."""
    src = real("fruit_drops_sh3.ply")
    kw = {**TREE, "lod_merge_domain_splats": 200}
    digests = []
    # (not 2x MEMORY: the whole scene fits there and is encoded in memory, every level grouped whole, where the
    # partitioned encode groups the levels above the partitions by upper domains)
    for name, memory in (("a", MEMORY), ("b", MEMORY + (4 << 20))):
        encode_file(src, tmp_path / name, memory_per_worker=memory, lod_refiner=refiner(), **kw)
        digests.append(tree_digest(tmp_path / name))
    assert digests[0] == digests[1]
    m = read_manifest(open_store(tmp_path / "a"))
    assert [lv.level for lv in m.lod.refinement.levels] == sorted({t.level for t in m.tiles if t.children})
