"""The in-memory encode's payloads on forked processes (encode/forked.py): the same bytes with any number of them."""
from __future__ import annotations

import sys

import pytest
from conftest import real
from test_encode_bytes import directory_digest

from splatstream.encode import EncodeOptions
from splatstream.encode.forked import ForkedPayloads, available_cores, balanced_split, encode_tiles, payload_processes
from splatstream.encode.jobs import tile_group_names
from splatstream.encode.local import encode_to
from splatstream.encode.plan import plan_encode
from splatstream.io import read_gaussians
from splatstream.store import DirectoryPayloads, DirectoryWriter, MemoryWriter

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked payloads on Linux only")


def encode_with(processes: int, out: str, **options) -> str:
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    opts = EncodeOptions(max_leaf_splats=300, reorder_input=True, **options)
    with DirectoryWriter(out) as writer:
        encode_to(g, writer, opts, processes=processes)
    return directory_digest(out)


@pytest.mark.parametrize("options", [{}, {"lod_merge": "grid", "preset": "low"}], ids=["auto-medium", "grid-low"])
def test_the_bytes_do_not_depend_on_the_payload_processes(tmp_path, options):
    here = encode_with(0, str(tmp_path / "p0"), **options)
    assert encode_with(1, str(tmp_path / "p1"), **options) == here
    assert encode_with(3, str(tmp_path / "p3"), **options) == here


def test_a_tree_handed_in_is_encoded_by_the_processes_alike(tmp_path):
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    opts = EncodeOptions(max_leaf_splats=300)
    tiles = plan_encode(g, opts).tiles
    digests = []
    for processes in (0, 2):
        out = str(tmp_path / f"p{processes}")
        with DirectoryWriter(out) as writer:
            encode_to(g, writer, opts, tiles=tiles, processes=processes)
        digests.append(directory_digest(out))
    assert digests[0] == digests[1]


def test_processes_only_for_a_directory_and_more_than_one_core(tmp_path):
    with DirectoryWriter(str(tmp_path / "d")) as writer:
        assert payload_processes(writer, cores=1) == 0
        assert payload_processes(writer, cores=2) == 1
        assert payload_processes(writer, cores=16) == 15
        assert payload_processes(writer) == available_cores() - 1
    assert payload_processes(MemoryWriter(), cores=16) == 0  # a child's payloads would stay in the child


def test_balanced_split_keeps_order_and_evens_the_splats():
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    tiles = plan_encode(g, EncodeOptions(max_leaf_splats=300)).tiles
    parts = balanced_split(tiles, 3)
    assert sorted(t.id for p in parts for t in p) == sorted(t.id for t in tiles)
    for p in parts:
        assert [t.id for t in p] == sorted(t.id for t in p)  # breadth-first order kept within a part
    loads = [sum(len(t.gaussians) for t in p) for p in parts]
    assert max(loads) - min(loads) <= max(len(t.gaussians) for t in tiles)
    assert balanced_split(tiles[:1], 4) == [tiles[:1]]  # no empty parts


def test_a_failing_child_fails_the_encode(tmp_path):
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    plan = plan_encode(g, EncodeOptions(max_leaf_splats=300))
    ctx = plan.context
    # a directory with no data/ in it: the child's first payload file cannot be made
    forked = ForkedPayloads(1, tile_group_names(ctx), ctx, DirectoryPayloads(str(tmp_path)))
    try:
        forked.offer(plan.tiles[1:])
        with pytest.raises(RuntimeError, match="payload process failed"):
            forked.finish(lambda part: encode_tiles(part, tile_group_names(ctx), ctx, None))
    finally:
        forked.close()
