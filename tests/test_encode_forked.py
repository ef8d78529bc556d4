"""The in-memory encode's payloads on forked processes (encode/forked.py): the same bytes with any number of them."""
from __future__ import annotations

import os
import pathlib
import signal
import subprocess
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

# The children are forked only where this process runs no other thread (forked.only_thread). In the whole suite
# earlier tests leave idle threads behind (executors, servers' loops: 4 threads at this module in CI), so the tests
# that need a fork run in a fresh interpreter of their own (test_the_fork_tests_in_a_fresh_process), and are skipped
# in any other.
FRESH = os.environ.get("SPLATSTREAM_FORK_TESTS") == "1"
forks = pytest.mark.skipif(not FRESH, reason="needs a process with one thread: run by "
                                             "test_the_fork_tests_in_a_fresh_process")


def test_the_fork_tests_in_a_fresh_process():
    if FRESH:
        pytest.skip("this is the fresh process")
    root = pathlib.Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(pathlib.Path(__file__))],
                       cwd=root, env={**os.environ, "SPLATSTREAM_FORK_TESTS": "1"}, capture_output=True, text=True,
                       check=False)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-2000:]
    assert " passed" in r.stdout and " failed" not in r.stdout


def encode_with(processes: int, out: str, **options) -> str:
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    opts = EncodeOptions(max_leaf_splats=300, reorder_input=True, **options)
    with DirectoryWriter(out) as writer:
        encode_to(g, writer, opts, processes=processes)
    return directory_digest(out)


@forks
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


@forks
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
        assert payload_processes(writer, cores=3) == 2
        assert payload_processes(writer, cores=16) == forked.MAX_PAYLOAD_PROCESSES == 2  # the tree feeds only so many
        assert payload_processes(writer) == min(2, available_cores() - 1)
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


@forks
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


@forks
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


@forks
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


@forks
def test_the_bar_counts_the_childrens_payloads_and_ends_at_one(tmp_path):
    plan, ctx, children = children_for(tmp_path, processes=1)
    leaves = [t for t in plan.tiles if not t.children]
    shares: list[float] = []
    try:
        assert children.start(leaves)
        payloads = children.finish(plan.tiles, lambda t: encode_tile(t.gaussians, tile_group_names(ctx), ctx,
                                                                     children.payloads), shares.append)
    finally:
        children.close()
    assert children.done  # the child encoded some tiles, and the bar reached 1.0 only by counting them
    assert sorted(payloads) == sorted(t.id for t in plan.tiles)
    assert shares == sorted(shares) and len(set(shares)) == len(shares)  # it only moves forward
    assert shares[-1] == 1.0 and all(0.0 <= s < 1.0 for s in shares[:-1])


@forks
def test_the_encodes_progress_with_a_child(tmp_path):
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    opts = EncodeOptions(max_leaf_splats=300)
    stages = {}
    for processes in (0, 1):
        events: list[tuple[str, float]] = stages.setdefault(processes, [])
        with DirectoryWriter(str(tmp_path / f"p{processes}")) as writer:
            encode_to(g, writer, opts, lambda stage, f, events=events: events.append((stage, f)),
                      processes=processes)
    bar = [f for stage, f in stages[1] if stage == "encode"]
    assert bar == sorted(bar) and bar[0] == 0.0 and bar[-1] == 1.0
    assert len(set(bar)) > 2 and all(f < 1.0 for f in bar[:bar.index(1.0)])  # moves, and 1.0 only at the end
    # the stages before the payloads report as they do without children
    assert [e for e in stages[1] if e[0] != "encode"] == [e for e in stages[0] if e[0] != "encode"]


@forks
def test_a_child_killed_mid_encode_fails_it_in_one_line(tmp_path, monkeypatch, capsys):
    import splatstream.encode.local as local
    from cli.main import main

    monkeypatch.setattr(local, "payload_processes", lambda writer, cores=None: 1)
    start = PayloadChildren.start
    killed = []

    def start_then_kill(self, tiles):  # the child is killed once the tree is under way, as the OOM killer would
        started = start(self, tiles)
        for proc, _ in self.children:
            os.kill(proc.pid, signal.SIGKILL)
            killed.append(proc.pid)
        return started

    monkeypatch.setattr(PayloadChildren, "start", start_then_kill)
    out = tmp_path / "scene"
    rc = main(["encode", str(real("fruit_drops_sh3.ply")), str(out), "-q", "--max-leaf-splats", "300"])
    err = capsys.readouterr().err
    assert killed and rc == 1
    assert err.strip().splitlines() == [
        f"splatstream encode: error: payload process {killed[0]} was killed by SIGKILL before its payloads were "
        "done"]
    assert os.listdir(tmp_path) == []  # neither the scene nor its temporary directory
    assert threading.active_count() == 1


@forks
def test_a_dead_child_is_seen_though_its_pipe_stays_open(tmp_path):
    # The pipe's far end kept open here: no EOF comes, the liveness check (waitid, not a time limit) finds it.
    import multiprocessing

    plan, ctx, children = children_for(tmp_path)
    here, there = multiprocessing.Pipe(duplex=True)
    proc = multiprocessing.get_context("fork").Process(target=os._exit, args=(3,))
    proc.start()
    try:
        with pytest.raises(EOFError):
            children._receive(proc, here)
        assert forked._exit_status(proc.pid) == "exited with status 3"
    finally:
        proc.join()
        here.close()
        there.close()
