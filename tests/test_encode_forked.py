"""The in-memory encode's payloads on forked processes (encode/forked.py): the same bytes with any number of them."""
from __future__ import annotations

import sys
import threading

import numpy as np
import pytest
from conftest import real
from test_encode_bytes import directory_digest

from splatstream.cores import available_cores
from splatstream.encode import EncodeOptions, forked
from splatstream.encode.forked import (
    PayloadChildren,
    _receive_gaussians,
    _send_gaussians,
    encode_tile,
    payload_processes,
)
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
def test_the_bytes_do_not_depend_on_the_payload_processes(tmp_path, options, monkeypatch):
    forks = []
    start = PayloadChildren.start

    def counted(self, tiles):
        threads = threading.active_count()  # before the fork (the feeders start after it)
        forks.append((start(self, tiles), self.processes, threads))
        return forks[-1][0]

    monkeypatch.setattr(PayloadChildren, "start", counted)
    here = encode_with(0, str(tmp_path / "p0"), **options)
    assert encode_with(1, str(tmp_path / "p1"), **options) == here
    assert encode_with(3, str(tmp_path / "p3"), **options) == here
    # forked once per encode, at the leaves, with no other thread running
    assert forks == [(True, 1, 1), (True, 3, 1)]


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


def test_a_tile_crosses_the_pipe_exactly():
    import multiprocessing

    sh3 = read_gaussians(real("fruit_drops_sh3.ply"))
    here, there = multiprocessing.Pipe(duplex=True)
    for g in (sh3, sh3.with_sh_degree(0)):  # SH0: an empty sh_rest (biker's; it failed once)
        sender = threading.Thread(target=_send_gaussians, args=(here, 7, g))
        sender.start()
        kind, tile_id, header = there.recv()
        got = _receive_gaussians(there, header)
        sender.join()
        assert (kind, tile_id) == ("tile", 7)
        for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
            np.testing.assert_array_equal(getattr(got, name), getattr(g, name))


def children_for(tmp_path, processes: int = 1, data: bool = True):
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    plan = plan_encode(g, EncodeOptions(max_leaf_splats=300))
    ctx = plan.context
    root = tmp_path / "out"
    if data:
        (root / "data").mkdir(parents=True)
    return plan, ctx, PayloadChildren(processes, tile_group_names(ctx), ctx, DirectoryPayloads(str(root)))


def test_no_children_while_another_thread_runs(tmp_path):
    plan, ctx, children = children_for(tmp_path)
    release = threading.Event()
    other = threading.Thread(target=release.wait)
    other.start()
    try:
        assert not children.start(plan.tiles)  # a fork beside a running thread: refused
    finally:
        release.set()
        other.join()
    assert children.processes == 0 and not children.children
    payloads = children.finish(plan.tiles, lambda t: {"here": t.id})
    assert payloads == {t.id: {"here": t.id} for t in plan.tiles}  # every tile encoded in this process


def test_children_forked_with_one_thread_share_the_work(tmp_path):
    plan, ctx, children = children_for(tmp_path, processes=2)
    leaves = [t for t in plan.tiles if not t.children]
    try:
        assert threading.active_count() == 1
        assert children.start(leaves)
        assert len(children.children) == 2 and len(children.feeders) == 2
        payloads = children.finish(plan.tiles, lambda t: encode_tile(t.gaussians, tile_group_names(ctx), ctx,
                                                                     children.payloads))
    finally:
        children.close()
    assert sorted(payloads) == sorted(t.id for t in plan.tiles)
    assert threading.active_count() == 1  # the feeders are gone


def test_a_failing_child_fails_the_encode(tmp_path):
    # a directory with no data/ in it: the child's first payload file cannot be made
    plan, ctx, children = children_for(tmp_path, data=False)

    def here(tile):  # this process takes a tile and waits for the child's failure, so the child takes one too
        with children.cond:
            children.cond.wait_for(lambda: children.errors, timeout=60)
        return {}

    try:
        assert children.start(plan.tiles[1:])
        with pytest.raises(RuntimeError, match="payload process failed"):
            children.finish(plan.tiles, here)
    finally:
        children.close()


def test_a_fault_in_a_feeder_fails_the_encode_and_stops_the_child(tmp_path, monkeypatch):
    # the first version hung here: a feeder died on SH0's empty sh_rest, its child waited for a tile forever
    plan, ctx, children = children_for(tmp_path)
    leaves = [t for t in plan.tiles if not t.children]

    def broken(conn, tile_id, g):
        raise ValueError("cannot send")

    monkeypatch.setattr(forked, "_send_gaussians", broken)

    def here(tile):  # wait for the feeder's fault, so that the child asks for a merged tile first
        with children.cond:
            children.cond.wait_for(lambda: children.errors, timeout=60)
        return {}

    try:
        assert children.start(leaves[:1])  # one leaf shared; every merged tile goes down the pipe
        with pytest.raises(RuntimeError, match="cannot send"):
            children.finish(plan.tiles, here)
        assert not children.children  # stopped, not waited for
    finally:
        children.close()
    assert threading.active_count() == 1
