"""Partitioned encoding (encode/partitioned.py) in this process and on Dask: the output is byte-identical to the
single-process encoder's whatever the number of workers and partitions; a killed worker, object-store outputs,
an interrupted encode."""
from __future__ import annotations

import hashlib
import importlib.util
import os
import socket

import numpy as np
import pytest
from conftest import real, tree_digest

from splatstream import lod
from splatstream.encode import EncodeOptions, encode_file, encode_in_memory
from splatstream.encode.local import LocalEngine
from splatstream.encode.partitioned import ArrayRows, encode_partitioned
from splatstream.encode.scratch import Scratch
from splatstream.errors import InputError
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.ply import write_gaussians_ply
from splatstream.scene_decode import decode_scene
from splatstream.store import FsspecStore, MemoryWriter, load_manifest

# Small leaves so a few thousand splats make a tree of 4 tile levels; a small memory per worker so it is split
# into partitions (8 at 1 MiB: 650 splats each) with two levels of tiles above them. The grid merge named: its output
# is the single-process one for any partitioning (the default, auto, is tests/test_partitioned_auto.py's).
TREE = {"max_leaf_splats": 300, "lod_merge": "grid"}
SMALL_MEMORY = 1 << 20


@pytest.fixture(scope="module")
def scene() -> Gaussians:
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    # Repeated splats: equal centres, so the kd median splits meet ties (resolved by input index).
    return Gaussians.concatenate([g, g.subset(slice(0, 600))])


@pytest.fixture(scope="module")
def scene_ply(scene, tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("input") / "scene.ply"
    write_gaussians_ply(scene, path)
    return str(path)


def store_digest(files: dict[str, bytes]) -> dict[str, str]:
    return {k: hashlib.sha256(v).hexdigest() for k, v in files.items()}


@pytest.fixture(scope="module")
def reference(scene_ply, tmp_path_factory) -> str:
    """The single-process encode (the whole scene in memory) of the test scene."""
    out = str(tmp_path_factory.mktemp("ref") / "scene")
    encode_file(scene_ply, out, preset="low", **TREE)
    return out


def copy_of(g: Gaussians) -> Gaussians:
    return Gaussians(g.positions.copy(), g.rotations.copy(), g.log_scales.copy(), g.opacity_logits.copy(),
                     g.sh_dc.copy(), g.sh_rest.copy())


@pytest.mark.parametrize("preset", ["medium", "low"])
def test_partitions_of_every_size_give_the_single_process_bytes(scene, tmp_path, preset):
    opts = EncodeOptions(preset=preset, **TREE)
    ref = encode_in_memory(copy_of(scene), opts, name="s")
    tiles = None
    # From one partition (the whole scene) down to partitions that are single leaves.
    for memory in (1 << 40, 4 << 20, SMALL_MEMORY, 200_000):
        writer = MemoryWriter("s")
        space = Scratch.create(str(tmp_path))
        m = encode_partitioned(ArrayRows(scene), writer, opts, LocalEngine(memory), space, source_name="s")
        space.remove()
        got = writer.store()
        assert got.manifest_bytes == ref.manifest_bytes, memory
        assert got.payloads == ref.payloads
        tiles = len(m.tiles)
    assert tiles == 1 + 2 + 4 + 8 + 16 + 32 + 32  # kd depths 0 to 5 and a chain above the 32 leaves
    assert os.listdir(tmp_path) == []  # scratch removed


@pytest.mark.parametrize("constant", ["OPACITY_MATCH_FAR_SSE_PX", "OPACITY_MATCH_FAR_GROWTH"])
def test_partitions_follow_the_far_viewing_scale(scene, tmp_path, monkeypatch, constant):
    """lod.OPACITY_MATCH_FAR_SSE_PX (the levels above the first merged one matched at their own scale: 8 px by
    default, lod.md 6 step 5) and lod.OPACITY_MATCH_FAR_GROWTH (each level above the first merged one at its own
    scale, lod.viewing_scale_px: the level is the tile's level against the tree's leaf level, which the upper tiles
    know) reach the partitioned encoder's upper tiles too: with another value, the same bytes as in memory, and not
    the default's."""
    opts = EncodeOptions(preset="low", **TREE)
    default = encode_in_memory(copy_of(scene), opts, name="s")
    monkeypatch.setattr(lod, constant, 2.0)
    ref = encode_in_memory(copy_of(scene), opts, name="s")
    writer = MemoryWriter("s")
    space = Scratch.create(str(tmp_path))
    encode_partitioned(ArrayRows(scene), writer, opts, LocalEngine(SMALL_MEMORY), space, source_name="s")
    space.remove()
    got = writer.store()
    assert got.manifest_bytes == ref.manifest_bytes
    assert got.payloads == ref.payloads
    assert ref.payloads != default.payloads


def test_ply_read_by_row_ranges_matches(scene_ply, reference, tmp_path):
    out = str(tmp_path / "part")
    encode_file(scene_ply, out, preset="low", memory_per_worker=SMALL_MEMORY, **TREE)
    assert tree_digest(out) == tree_digest(reference)
    assert load_manifest(out).encode_seconds == 0.0
    assert sorted(os.listdir(tmp_path)) == ["part"]


def test_dask_1_2_4_workers_identical(scene_ply, reference, tmp_path):
    pytest.importorskip("distributed")
    want = tree_digest(reference)
    for workers in (1, 2, 4):
        out = str(tmp_path / f"w{workers}")
        encode_file(scene_ply, out, preset="low", workers=workers, memory_per_worker=SMALL_MEMORY, **TREE)
        assert tree_digest(out) == want, workers
    assert sorted(os.listdir(tmp_path)) == ["w1", "w2", "w4"]


def test_a_killed_worker_is_retried_and_the_scene_is_unchanged(scene_ply, reference, tmp_path):
    distributed = pytest.importorskip("distributed")
    from splatstream.encode.distributed import DaskEngine
    from splatstream.encode.partitioned import PlyRows
    from splatstream.ply import vertex_layout
    from splatstream.store import open_writer

    marker = tmp_path / "killed"

    class KillOnFirstPartition(distributed.WorkerPlugin):
        """Kills its worker process (SIGKILL, no clean-up) when the first partition task starts running."""

        def __init__(self, marker: str):
            self.marker = marker

        def transition(self, key, start, finish, **kwargs):
            if finish == "executing" and "build_partition" in str(key) and not os.path.exists(self.marker):
                open(self.marker, "w").close()
                os.kill(os.getpid(), 9)

    engine = DaskEngine(workers=2, memory_per_worker=SMALL_MEMORY)
    try:
        engine.client.register_plugin(KillOnFirstPartition(str(marker)))
        out = str(tmp_path / "scene")
        with open_writer(out) as writer:
            space = Scratch.create(str(tmp_path))
            encode_partitioned(PlyRows(vertex_layout(scene_ply), scene_ply), writer,
                               EncodeOptions(preset="low", **TREE), engine, space, source_name=scene_ply)
            # the deletes run behind the stages (Engine.map_behind) and are settled before the manifest
            left = {os.path.relpath(os.path.join(r, f), space.location).split(os.sep)[0]
                    for r, _, files in os.walk(space.location) for f in files}
            space.remove()
    finally:
        engine.close()
    assert marker.exists()  # a worker did die mid-encode
    assert tree_digest(out) == tree_digest(reference)
    assert not left & {"pos", "node", "route", "originals"}, left


def _fail_on(path: str, bad: str) -> None:
    if path == bad:
        raise InputError(path, None, "cannot delete")
    open(path, "w").close()


def test_tasks_behind_run_and_settle_raises_their_error(tmp_path):
    """Engine.map_behind on Dask: nobody waits for the tasks until settle, which waits for all and raises the
    first error as the task raised it."""
    pytest.importorskip("distributed")
    from splatstream.encode.distributed import DaskEngine

    engine = DaskEngine(workers=2, memory_per_worker=SMALL_MEMORY)
    try:
        paths = [str(tmp_path / f"m{i}") for i in range(6)]
        engine.map_behind(_fail_on, [(p, "") for p in paths], "cleanup")
        assert engine.map(_fail_on, [(str(tmp_path / "x"), "")], "tiles", lambda *a: None) == [None]
        engine.settle()
        assert all(os.path.exists(p) for p in paths)
        engine.map_behind(_fail_on, [(p, paths[3]) for p in paths], "cleanup")
        with pytest.raises(InputError, match="m3.*cannot delete"):
            engine.settle()
        engine.settle()  # settled: nothing left to wait for
    finally:
        engine.close()


def test_interrupted_encode_leaves_no_partial_scene(scene_ply, tmp_path):
    out = tmp_path / "scene"

    def interrupt(stage: str, fraction: float) -> None:
        if stage == "tiles" and fraction > 0.3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        encode_file(scene_ply, out, preset="low", memory_per_worker=SMALL_MEMORY, progress=interrupt, **TREE)
    assert os.listdir(tmp_path) == []  # neither the scene, nor its temporary directory, nor scratch


def test_invalid_rows_are_reported_for_the_whole_file(scene, tmp_path):
    g = copy_of(scene)
    g.positions[[5, 4000], 1] = np.nan
    path = tmp_path / "bad.ply"
    write_gaussians_ply(g, path)
    with pytest.raises(InputError) as single:
        read_gaussians(path)
    with pytest.raises(InputError) as partitioned:
        encode_file(path, tmp_path / "out", memory_per_worker=SMALL_MEMORY, **TREE)
    assert str(partitioned.value) == str(single.value)
    assert "2 of 5,321 splats have non-finite values (NaN or inf) (y: 2)" in str(single.value)
    assert not (tmp_path / "out").exists()
    with pytest.warns(UserWarning, match="2 of 5,321 splats have non-finite values .*; dropped"):
        m = encode_file(path, tmp_path / "out", memory_per_worker=SMALL_MEMORY, drop_invalid=True, **TREE)
    assert m.splats == len(g) - 2


def test_memory_url_output_reads_back_the_same(scene_ply, reference):
    pytest.importorskip("fsspec")
    url = "memory://scenes/fruit"
    encode_file(scene_ply, url, preset="low", memory_per_worker=SMALL_MEMORY, **TREE)
    store = FsspecStore(url)
    files = {"manifest.msgpack": store.read_manifest()}
    m = load_manifest(store)
    for _, _, p in m.payloads():
        files[p.file] = store.read_payload(p)
    assert store_digest(files) == tree_digest(reference)
    a, b = decode_scene(store), decode_scene(reference)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.sh_rest, b.sh_rest)
    # The streaming client reads the same scene from the URL.
    import asyncio

    from client_gl.stream.sources import StoreSource, open_source

    source = open_source(url)
    assert isinstance(source, StoreSource)
    root = m.tiles[0].groups["base"]
    assert asyncio.run(source.fetch_manifest()) == files["manifest.msgpack"]
    assert asyncio.run(source.fetch_payload(root)) == files[root.file]


def test_cli_cluster_options_are_checked(scene_ply, tmp_path):
    from conftest import run_cli

    for args, message in ((["--workers", "0"], "--workers: expected a worker count of at least 1 or auto"),
                          (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "give one of them"),
                          (["--memory-per-worker", "lots"], "--memory-per-worker: expected a size")):
        r = run_cli("encode", scene_ply, tmp_path / "out", *args)
        assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def s3_server(monkeypatch):
    """A local S3 server (moto) on loopback with one bucket, and fsspec's s3:// pointed at it."""
    pytest.importorskip("s3fs")
    server_mod = pytest.importorskip("moto.server")
    import fsspec

    port = _free_port()
    server = server_mod.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    endpoint = f"http://127.0.0.1:{port}"
    env = {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1",
           "FSSPEC_S3_ENDPOINT_URL": endpoint}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setitem(fsspec.config.conf, "s3", {"endpoint_url": endpoint})
    fs = fsspec.filesystem("s3", skip_instance_cache=True)
    fs.mkdir("scenes")
    try:
        yield "s3://scenes"
    finally:
        server.stop()


def test_s3_output_on_dask_workers(scene_ply, reference, s3_server):
    pytest.importorskip("distributed")
    import fsspec

    url = f"{s3_server}/fruit"
    encode_file(scene_ply, url, preset="low", workers=2, memory_per_worker=SMALL_MEMORY, **TREE)
    fs = fsspec.filesystem("s3", skip_instance_cache=True)
    names = sorted(p.split("/fruit/", 1)[1] for p in fs.find("scenes/fruit"))
    assert names == sorted(tree_digest(reference))  # no scratch or temporary objects left
    store = FsspecStore(url)
    files = {n: store.fs.cat_file(f"scenes/fruit/{n}") for n in names}
    assert store_digest(files) == tree_digest(reference)
    a, b = decode_scene(store), decode_scene(reference)
    np.testing.assert_array_equal(a.sh_dc, b.sh_dc)


class _CountingEngine(LocalEngine):
    def __init__(self):
        super().__init__(threads=1)
        self.calls: list[str] = []

    def map(self, fn, args, stage, progress, heavy=False, task_progress=False):
        self.calls.append(fn.__name__)
        return super().map(fn, args, stage, progress, heavy, task_progress)


def test_bracketed_kd_splits_are_the_exact_medians(tmp_path):
    """The top kd splits from one bracketed pass per level (brackets from a sample) equal lod.kd_split's on the
    whole scene; a sample too thin gathers whole nodes, and a misleading one falls back to the radix selection."""
    from splatstream.encode.partitioned import _top_splits
    from splatstream.lod import kd_split

    rng = np.random.default_rng(3)
    n, depth = 60_000, 4
    p = (rng.normal(size=(n, 3)) * [4.0, 2.0, 1.0]).astype(np.float32)
    p[:700] = p[0]  # ties, resolved by input index
    idx = np.arange(n, dtype=np.int64)
    scratch = Scratch.create(str(tmp_path))
    spans = [(s, min(s + 7_000, n)) for s in range(0, n, 7_000)] + [(n, n)]  # and an empty chunk
    for i, (s, e) in enumerate(spans):
        scratch.save(f"pos/{i}", p=p[s:e])
    expected, nodes = [], [idx]
    for _ in range(depth):
        parts = [kd_split(p, idx, rows) for rows in nodes]
        expected.append((np.array([a for _, _, a, _ in parts]), np.array([k for _, _, _, k in parts], np.uint64)))
        nodes = [half for lo, hi, _, _ in parts for half in (lo, hi)]
    bounds = (p.min(axis=0), p.max(axis=0))
    samples = {"good": ((p[::5], idx[::5]), "chunk_bracket"), "thin": ((p[::4_000], idx[::4_000]), "chunk_bracket"),
               "misleading": ((p[::5] * 0.5, idx[::5]), "chunk_select")}
    for name, (sample, used) in samples.items():
        engine = _CountingEngine()
        splits = _top_splits(engine, scratch, spans, depth, n, bounds, sample, lambda *a: None)
        for (axes, pivots), (want_axes, want_pivots) in zip(splits, expected, strict=True):
            np.testing.assert_array_equal(axes, want_axes, err_msg=name)
            np.testing.assert_array_equal(pivots, want_pivots, err_msg=name)
        assert used in engine.calls, (name, engine.calls)
    assert _CountingEngine().calls == []
    engine = _CountingEngine()
    _top_splits(engine, scratch, spans, depth, n, bounds, samples["good"][0], lambda *a: None)
    assert engine.calls == ["chunk_bracket"] * depth  # one pass per level, no box or radix passes
    scratch.remove()


def test_scratch_of_a_killed_encode_is_removed_by_the_next(tmp_path):
    """Issue 37: SIGKILL of an encode left its .splatstream-scratch-* directory beside the output for good. A
    scratch directory is locked by its process (flock, dropped by the kernel when it dies): the next encode's
    Scratch.create removes those nobody holds, never one of a running encode nor a directory without the lock."""
    import signal
    import subprocess
    import sys

    code = ("import os, signal, sys; from splatstream.encode.scratch import Scratch; "
            "s = Scratch.create(sys.argv[1]); s.save('pos/0', p=__import__('numpy').zeros(10)); "
            "print(s.location, flush=True); os.kill(os.getpid(), signal.SIGKILL)")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == -signal.SIGKILL
    dead = r.stdout.strip()
    assert os.path.isdir(dead) and os.path.isfile(os.path.join(dead, "pos", "0"))
    foreign = tmp_path / ".splatstream-scratch-foreign"  # no owner lock: not known to be ours, kept
    foreign.mkdir()
    live = Scratch.create(str(tmp_path))  # this process holds it
    assert not os.path.exists(dead)
    again = Scratch.create(str(tmp_path))
    assert os.path.isdir(live.location) and foreign.is_dir()
    again.remove()
    live.remove()
    assert sorted(os.listdir(tmp_path)) == [foreign.name]


PAGED = {"page_tiles": 4, "page_levels": 2}


def test_a_paged_scene_is_the_same_on_every_engine(scene_ply, tmp_path):
    """Manifest pages (format.md 6.1) are written by the client after the tiles, from the same manifest: in
    process, partitioned in process, on Dask and to an fsspec URL, the same files."""
    reference = str(tmp_path / "ref")
    encode_file(scene_ply, reference, preset="low", **PAGED, **TREE)
    want = tree_digest(reference)
    assert load_manifest(reference).paged.pages > 1
    out = str(tmp_path / "local")
    encode_file(scene_ply, out, preset="low", memory_per_worker=SMALL_MEMORY, **PAGED, **TREE)
    assert tree_digest(out) == want
    if importlib.util.find_spec("distributed") is not None:
        out = str(tmp_path / "dask")
        encode_file(scene_ply, out, preset="low", workers=2, memory_per_worker=SMALL_MEMORY, **PAGED, **TREE)
        assert tree_digest(out) == want
    if importlib.util.find_spec("fsspec") is not None:
        url = "memory://scenes/fruit-paged"
        encode_file(scene_ply, url, preset="low", memory_per_worker=SMALL_MEMORY, **PAGED, **TREE)
        m = load_manifest(FsspecStore(url))  # the pages read back from the store
        assert m.paged is not None and len(m.tiles) == m.paged.tiles


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None, reason="needs dask.distributed")
def test_ctrl_c_from_a_terminal_reaches_the_workers_and_says_one_line(tmp_path):
    """A terminal's Ctrl-C goes to the whole foreground process group, the local cluster's workers included: each
    printed its KeyboardInterrupt traceback (about 60 lines) under 'splatstream encode: interrupted' (newuser64). The
    workers ignore SIGINT now (encode/dask_worker_setup.py) and the encode answers it: one line, exit 130, nothing
    left. The signal is sent once the workers are writing payloads (a file in the temporary scene), not at a time."""
    import signal
    import subprocess
    import sys
    import time

    from conftest import ROOT

    out = tmp_path / "scene"
    proc = subprocess.Popen([sys.executable, "-m", "cli", "encode", "-q", "--workers", "2", "--preset", "very-high",
                             "--zstd-level", "19", "--max-leaf-splats", "2048", str(ROOT / "samples" / "donut.ply"),
                             str(out)], cwd=ROOT, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
                            start_new_session=True,  # its own process group, as a shell's foreground job
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        temps = [p for p in tmp_path.iterdir() if p.name.startswith(f".{out.name}.{proc.pid}.")]
        if temps and any(temps[0].glob("data/*.bin")):
            break
        time.sleep(0.01)
    if proc.poll() is not None:
        pytest.fail(f"the encode ended before its workers wrote a payload: {proc.communicate()[1]}")
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip() == "splatstream encode: interrupted", err
    assert list(tmp_path.iterdir()) == []


def _group_processes(group: int) -> list[str]:
    """The command lines of the live (not zombie) processes of a process group, from /proc."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            if int(fields[2]) == group and fields[0] != "Z":
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    found.append(f.read().replace(b"\0", b" ").decode(errors="replace"))
        except (OSError, IndexError, ValueError):
            pass  # gone meanwhile
    return found


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None or not os.path.isdir("/proc"),
                    reason="needs dask.distributed and /proc")
@pytest.mark.parametrize("state, forked", [
    ("its resource tracker runs", 0),          # the encode is starting the cluster, no fork server yet
    ("its fork server runs", 1),               # the server imports Dask's preloads, no worker yet
    ("its first worker process runs", 2),      # a worker in its own start-up
    ("both worker processes run", 3),
])
def test_ctrl_c_while_the_local_cluster_starts_says_one_line(tmp_path, state, forked):
    """A terminal's Ctrl-C in the local cluster's first second (the fork server importing Dask, a worker in its own
    start) printed the fork server's and Dask's start-up tracebacks (30 to 180 lines: newuser64). The fork server and
    its workers ignore SIGINT from their start (encode/forkserver_setup.py) and the encode holds it until the cluster
    has started, then closes it: one line, exit 130, nothing left, no process. The signal goes to the process group
    once the start has reached `state` (polled in /proc, not timed)."""
    import signal
    import subprocess
    import sys
    import time

    from conftest import ROOT

    out = tmp_path / "scene"
    proc = subprocess.Popen([sys.executable, "-m", "cli", "encode", "-q", "--workers", "2",
                             str(ROOT / "samples" / "donut.ply"), str(out)], cwd=ROOT, stderr=subprocess.PIPE,
                            text=True, stdin=subprocess.DEVNULL, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            running = _group_processes(proc.pid)
            servers = sum("multiprocessing.forkserver" in c for c in running)  # its workers share its command line
            if any("multiprocessing.resource_tracker" in c for c in running) and servers >= forked:
                break
            time.sleep(0.005)
        if proc.poll() is not None:
            pytest.fail(f"the encode ended before {state}: {proc.communicate()[1]}")
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130 and err.strip() == "splatstream encode: interrupted", (state, err)
    assert list(tmp_path.iterdir()) == []
    while _group_processes(proc.pid) and time.monotonic() < deadline:  # the cluster's processes end with it
        time.sleep(0.05)
    assert _group_processes(proc.pid) == []


def test_the_local_cluster_takes_a_free_local_port(scene_ply, tmp_path):
    """With Dask's usual dashboard port held (another cluster, another program), `encode --workers` still prints
    nothing but its result: the scheduler's HTTP server takes a free port on 127.0.0.1 (it bound 0.0.0.0:8787, and
    a held port printed Dask's 'Port 8787 is already in use' warning into the CLI's stderr)."""
    pytest.importorskip("distributed")
    from conftest import run_cli

    holder = socket.socket()
    try:
        holder.bind(("0.0.0.0", 8787))
        holder.listen(1)
    except OSError:
        pass  # held already by someone else: the case itself
    try:
        r = run_cli("encode", "-q", "--workers", "2", scene_ply, tmp_path / "scene")
    finally:
        holder.close()
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert load_manifest(tmp_path / "scene").leaf_splats > 0
