"""The streaming client's fetcher against real servers on loopback (no mocks): a fault-injecting aiohttp server
(tests/fault_server.py) and `splatstream serve` killed and restarted mid-fetch. Every payload must arrive with
exactly the right bytes, never a corrupt one; the disk cache, cancellation, priority order and close() are
checked on the way. Timeouts and backoffs are made small through the constructor so every test is bounded."""
from __future__ import annotations

import hashlib
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import pytest
from conftest import real_path
from fault_server import FaultServer

from client_gl.stream.cache import DiskCache
from client_gl.stream.fetch import (
    MANIFEST_LOCAL,
    MANIFEST_NETWORK,
    MANIFEST_OFFLINE,
    MANIFEST_REVALIDATED,
    Fetcher,
    RetryPolicy,
)
from client_gl.stream.sources import NOT_A_SCENE, FetchError, HttpSource, StoreSource, open_source
from splatstream.errors import InputError
from splatstream.format.container import VerifiedPayload
from splatstream.format.manifest import Manifest
from splatstream.store import DirectoryStore, MemoryStore, load_manifest

REPO = Path(__file__).resolve().parents[1]
SCENE = "fruit"
T = TypeVar("T")


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A root with one real encoded scene: fruit_drops (4721 splats, SH degree 3) in tiles of at most 1000 splats
    (11 tiles, 44 payloads); the spec's test vector when the real data is not here."""
    root = tmp_path_factory.mktemp("stream-root")
    ply = real_path("fruit_drops_sh3.ply")
    if ply is not None:
        from splatstream.encode import encode_file

        encode_file(ply, root / SCENE, max_leaf_splats=1000)
    else:
        shutil.copytree(REPO / "format_spec" / "vectors" / "low", root / SCENE,
                        ignore=shutil.ignore_patterns("expected.json"))
    return root


@pytest.fixture(scope="module")
def manifest(root) -> Manifest:
    return load_manifest(root / SCENE)


@pytest.fixture
def server(root):
    srv = FaultServer(root).start()
    yield srv
    srv.stop()


def fetcher(source, **kw) -> Fetcher:
    kw.setdefault("request_timeout_s", 1.0)
    kw.setdefault("stall_timeout_s", 0.4)
    kw.setdefault("retry", RetryPolicy(base_s=0.02, cap_s=0.2))
    kw.setdefault("manifest_timeout_s", 3.0)
    kw.setdefault("seed", 0)
    return Fetcher(source, **kw).start()


def requests_of(m: Manifest) -> list:
    """Every payload of the scene as (priority, key, entry), tiles in id order then the codebook."""
    return [(-float(i), (t.id if t is not None else None, g), p) for i, (t, g, p) in enumerate(m.payloads())]


def collect(f: Fetcher, count: int, timeout_s: float = 20.0) -> list:
    """done() results until `count` arrived (or the deadline); asserts that no key arrives twice."""
    out, seen = [], set()
    deadline = time.monotonic() + timeout_s
    while len(out) < count and time.monotonic() < deadline:
        for key, entry, data in f.done():
            assert key not in seen, f"{key} delivered twice"
            seen.add(key)
            out.append((key, entry, data))
        time.sleep(0.005)
    return out


def wait_for(read: Callable[[], T], ok: Callable[[T], bool], timeout_s: float = 30.0) -> T:
    """read() until ok(value) holds (a generous bound: a loaded machine only makes it later), the value that
    held; a test asserts on it, never on a count read at one moment."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = read()
        if ok(value) or time.monotonic() > deadline:
            return value
        time.sleep(0.01)


def assert_exact(root: Path, results: list, reqs: list) -> None:
    by_key = {k: d for k, _, d in results}
    assert set(by_key) == {k for _, k, _ in reqs}
    for _, key, entry in reqs:
        # handed on as checked: a VerifiedPayload of its entry (decoding does not hash it again)
        assert isinstance(by_key[key], VerifiedPayload) and by_key[key].matches(entry), key
        assert by_key[key].data == (root / SCENE / entry.file).read_bytes(), key


def shas_by_size(m: Manifest) -> list[str]:
    """Distinct payloads, largest first."""
    sizes = {p.sha256: p.bytes for _, _, p in m.payloads()}
    return sorted(sizes, key=lambda s: (-sizes[s], s))


# -- faults -------------------------------------------------------------------------------------------------------


def test_faults_are_retried_and_only_verified_bytes_are_delivered(root, manifest, server):
    shas = shas_by_size(manifest)
    server.add_fault(shas[0], "500", "500")
    server.add_fault(shas[1], "corrupt")
    server.add_fault(shas[2], "stall")
    server.add_fault(shas[3], "truncate")
    server.add_fault(shas[4], "hang")
    server.add_fault("manifest", "500")
    reqs = requests_of(manifest)
    f = fetcher(HttpSource(server.url(SCENE)))
    try:
        f.manifest()
        assert f.manifest_bytes == (root / SCENE / "manifest.msgpack").read_bytes()
        f.want(reqs)
        results = collect(f, len(reqs))
        assert_exact(root, results, reqs)
        s = f.stats()
    finally:
        f.close()
    assert s.failures == {"http_5xx": 3, "checksum": 1, "stall": 1, "truncated": 1, "timeout": 1}
    assert s.retries == 7 and s.delivered == len(reqs) and not s.offline
    assert s.in_flight == 0 and s.queued == 0 and s.manifest_source == MANIFEST_NETWORK
    assert [st for _, st in server.requests(shas[0])] == [500, 500, 200]
    assert [st for _, st in server.requests(shas[1])] == [200, 200]  # the corrupt answer, then the right one
    payload_requests = [r for r in server.requests("/data/")]
    assert len(payload_requests) == len({p.sha256 for _, _, p in reqs}) + 6


def test_a_payload_that_stays_corrupt_is_never_delivered(root, manifest, server):
    shas = shas_by_size(manifest)
    server.add_fault(shas[0], *["corrupt"] * 1000)
    reqs = requests_of(manifest)
    f = fetcher(HttpSource(server.url(SCENE)))
    try:
        f.manifest()
        f.want(reqs)
        bad = [k for _, k, e in reqs if e.sha256 == shas[0]]
        results = collect(f, len(reqs) - len(bad), timeout_s=20)
        s = wait_for(f.stats, lambda s: s.failures.get("checksum", 0) >= 3)  # several more corrupt answers
        results += f.done()
    finally:
        f.close()
    assert {k for k, _, _ in results} == {k for _, k, _ in reqs} - set(bad)
    assert_exact(root, results, [r for r in reqs if r[1] not in bad])
    assert s.failures["checksum"] >= 3 and s.queued + s.in_flight == len(bad)
    assert "checksum mismatch" in s.last_error and shas[0] in s.last_error


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_serve(root: Path, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "cli", "serve", str(root), "--port", str(port),
                             "--throttle-mbps", "1.5", "--no-access-log"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, stdin=subprocess.DEVNULL, text=True)
    line = proc.stderr.readline()
    assert f":{port}/" in line, line
    return proc


def test_server_killed_and_restarted_mid_fetch(root, manifest):
    """`splatstream serve` on a 1.5 Mbit/s link (the scene takes about 2 s), killed with SIGKILL while payloads
    are in flight and restarted on the same port: streaming resumes and every payload arrives exactly."""
    port = _free_port()
    proc = _start_serve(root, port)
    reqs = requests_of(manifest)
    f = fetcher(HttpSource(f"http://127.0.0.1:{port}/scenes/{SCENE}/"), retry=RetryPolicy(base_s=0.05, cap_s=0.3))
    try:
        f.manifest()
        f.want(reqs)
        results = collect(f, 3)  # done() hands over what has arrived: 3 or a few more under load
        assert 3 <= len(results) < len(reqs) and f.stats().in_flight > 0
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
        # The fetcher notices the dead server when its loop thread next runs: wait for that (however loaded the
        # machine), not for a fixed time.
        down = wait_for(f.stats, lambda s: s.offline and s.failures.get("connection", 0) >= 1)
        results += f.done()
        assert down.offline and down.failures.get("connection", 0) >= 1 and down.delivered < len(reqs)
        proc = _start_serve(root, port)
        results += collect(f, len(reqs) - len(results), timeout_s=30)
        s = f.stats()
    finally:
        f.close()
        proc.terminate()
        proc.wait(10)
    assert len(results) == len(reqs)
    assert_exact(root, results, reqs)
    assert not s.offline and s.delivered == len(reqs)


# -- disk cache ---------------------------------------------------------------------------------------------------


def test_a_warm_cache_only_revalidates_the_manifest(root, manifest, server, tmp_path):
    reqs = requests_of(manifest)
    f = fetcher(HttpSource(server.url(SCENE)), cache=DiskCache(tmp_path / "cache"))
    try:
        f.manifest()
        f.want(reqs)
        assert_exact(root, collect(f, len(reqs)), reqs)
    finally:
        f.close()
    first = len(server.requests())
    assert server.requests("manifest") == [(f"/scenes/{SCENE}/manifest.msgpack", 200)]

    f = fetcher(HttpSource(server.url(SCENE)), cache=DiskCache(tmp_path / "cache"))
    try:
        f.manifest()
        data = f.manifest_bytes
        f.want(reqs)
        results = collect(f, len(reqs))
        s = f.stats()
    finally:
        f.close()
    assert data == (root / SCENE / "manifest.msgpack").read_bytes()
    assert_exact(root, results, reqs)
    assert server.requests()[first:] == [(f"/scenes/{SCENE}/manifest.msgpack", 304)]  # and nothing else
    assert s.bytes_downloaded == 0 and s.requests == 1 and s.manifest_source == MANIFEST_REVALIDATED
    distinct = {e.sha256: e.bytes for _, _, e in reqs}
    assert s.cache_hits == len(distinct) and s.delivered == len(reqs)
    assert s.bytes_from_cache == sum(distinct.values()) + len(data)


def test_offline_with_a_warm_cache(root, manifest, tmp_path):
    reqs = requests_of(manifest)
    srv = FaultServer(root).start()
    url = srv.url(SCENE)
    try:
        with fetcher(HttpSource(url), cache=DiskCache(tmp_path / "c")) as f:
            f.manifest()
            f.want(reqs)
            assert len(collect(f, len(reqs))) == len(reqs)
    finally:
        srv.stop()
    with fetcher(HttpSource(url), cache=DiskCache(tmp_path / "c")) as f:
        f.manifest()
        data = f.manifest_bytes
        f.want(reqs)
        results = collect(f, len(reqs))
        s = f.stats()
    assert data == (root / SCENE / "manifest.msgpack").read_bytes()
    assert_exact(root, results, reqs)
    assert s.offline and s.manifest_source == MANIFEST_OFFLINE and s.bytes_downloaded == 0
    assert s.failures == {"connection": 1}


def test_a_damaged_cache_file_is_refetched(root, manifest, server, tmp_path):
    reqs = requests_of(manifest)
    cache = DiskCache(tmp_path / "cache")
    with fetcher(HttpSource(server.url(SCENE)), cache=cache) as f:
        f.manifest()
        f.want(reqs)
        assert len(collect(f, len(reqs))) == len(reqs)
    victim = shas_by_size(manifest)[0]
    path = Path(cache.payload_path(victim))
    wait_for(path.exists, bool)  # the cache is written right after delivery, in a worker thread
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 1
    path.write_bytes(bytes(data))
    before = len(server.requests(victim))
    cache2 = DiskCache(tmp_path / "cache")
    with fetcher(HttpSource(server.url(SCENE)), cache=cache2) as f:
        f.manifest()
        f.want(reqs)
        results = collect(f, len(reqs))
    assert_exact(root, results, reqs)
    assert len(server.requests(victim)) == before + 1
    assert cache2.stats.corrupt == 1


# -- scheduling ---------------------------------------------------------------------------------------------------


def test_priority_order_with_one_request_in_flight(root, manifest, server):
    reqs = requests_of(manifest)
    random.Random(5).shuffle(reqs)
    distinct = {}
    for r in reqs:  # one key per payload: shared payloads would be delivered together
        distinct.setdefault(r[2].sha256, r)
    reqs = list(distinct.values())
    with fetcher(HttpSource(server.url(SCENE)), max_in_flight=1) as f:
        f.manifest()
        f.want(reqs)
        results = collect(f, len(reqs))
    assert [k for k, _, _ in results] == [k for _, k, _ in reqs]
    payload_paths = [p for p, _ in server.requests("/data/")]
    assert payload_paths == [f"/scenes/{SCENE}/{e.file}" for _, _, e in reqs]


def test_a_new_list_reorders_the_queue(root, manifest, server):
    reqs = list({r[2].sha256: r for r in requests_of(manifest)}.values())[:10]
    server.slow_bytes_per_s = max(e.bytes for _, _, e in reqs) / 0.1  # each payload takes up to 0.1 s
    for _, _, e in reqs:
        server.add_fault(e.sha256, "slow")
    with fetcher(HttpSource(server.url(SCENE)), max_in_flight=1) as f:
        f.manifest()
        f.want(reqs)
        got = collect(f, 2)
        rest = [r for r in reqs if r[1] not in {k for k, _, _ in got}]
        f.want(list(reversed(rest)))
        got += collect(f, len(rest))
    keys = [k for k, _, _ in got]
    assert keys[:2] == [k for _, k, _ in reqs[:2]]
    # after the switch, the request in flight (the old list's third, unless it had not started yet) finishes
    # first, then the new order
    reordered = [k for _, k, _ in reversed(rest)]
    assert keys[2:] in ([reqs[2][1]] + [k for k in reordered if k != reqs[2][1]], reordered)


def test_cancelled_keys_are_never_delivered(root, manifest, server):
    shas = shas_by_size(manifest)[:3]
    entries = {e.sha256: e for _, _, e in manifest.payloads()}
    server.slow_bytes_per_s = entries[shas[0]].bytes / 4.0  # each payload takes about 4 s (they are alike in size)
    for sha in shas:
        server.add_fault(sha, "slow")
    reqs = [(3.0 - i, ("k", i), entries[sha]) for i, sha in enumerate(shas)]
    with fetcher(HttpSource(server.url(SCENE)), stall_timeout_s=2.0) as f:
        f.manifest()
        f.want(reqs)
        # all three bodies started (the server logs each as its headers go out) and none has finished
        started = wait_for(lambda: (len(server.requests("/data/")), f.stats().in_flight), lambda v: v[0] >= 3)
        assert started == (3, 3)
        f.want(reqs[:1])
        s = f.stats()
        assert s.cancelled == 2 and s.in_flight == 1 and s.queued == 0
        got = collect(f, 1, timeout_s=30)
        time.sleep(1.5)  # the cancelled bodies, started together with this one, would have finished by now
        got += f.done()
        assert [k for k, _, _ in got] == [("k", 0)]
        assert got[0][2].data == (root / SCENE / entries[shas[0]].file).read_bytes()
        f.want(reqs[1:2])  # wanted again: a new request
        again = collect(f, 1)
    assert [k for k, _, _ in again] == [("k", 1)]
    assert len(server.requests(shas[1])) == 2


def test_close_with_requests_in_flight_is_quick_and_quiet(root, manifest, server, capfd):
    reqs = requests_of(manifest)
    for sha in {e.sha256 for _, _, e in reqs}:
        server.add_fault(sha, "hang")
    f = fetcher(HttpSource(server.url(SCENE)), request_timeout_s=30)
    f.manifest()
    f.want(reqs)
    # Six requests (max_in_flight) reach the server and hang there: the server's log only grows, so this is an
    # event to wait for, not a count read at one moment.
    hanging = wait_for(lambda: [r for r in server.requests("/data/") if r[1] == 0], lambda h: len(h) >= 6)
    assert len(hanging) >= 6
    s = f.stats()
    assert s.delivered == 0 and 1 <= s.in_flight <= 6
    t0 = time.monotonic()
    f.close()
    # quick: close() gives up within about a second by design; the bound is loose for a loaded machine and still
    # far below the 30 s the hanging requests would take
    assert time.monotonic() - t0 < 5.0
    assert not f._thread.is_alive()
    assert f.done() == []
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Unclosed" not in err


def test_close_while_manifest_waits_for_a_server_that_does_not_answer(server, capfd):
    server.add_fault("manifest", "hang")
    f = fetcher(HttpSource(server.url(SCENE)), manifest_timeout_s=30)
    import threading

    outcome = []

    def ask():
        try:
            f.manifest()
        except FetchError as exc:
            outcome.append(str(exc))

    t = threading.Thread(target=ask)
    t.start()
    time.sleep(0.3)
    t0 = time.monotonic()
    f.close()
    t.join(2)
    assert time.monotonic() - t0 < 5.0 and not t.is_alive()  # not the 30 s manifest timeout
    assert outcome and "closed" in outcome[0]
    assert "Traceback" not in capfd.readouterr().err


# -- manifest errors ----------------------------------------------------------------------------------------------


def test_manifest_errors_are_one_line_and_name_the_url(root, server, tmp_path):
    port = _free_port()
    url = f"http://127.0.0.1:{port}/scenes/nothing"
    with fetcher(HttpSource(url), manifest_timeout_s=0.3) as f:
        with pytest.raises(FetchError) as exc:
            f.manifest()
    msg = str(exc.value)
    assert msg.startswith(f"{url}/manifest.msgpack: cannot connect to 127.0.0.1:{port}")
    assert "refused" in msg and "\n" not in msg and exc.value.kind == "connection"

    with fetcher(HttpSource(server.url("nosuch"))) as f:
        with pytest.raises(FetchError, match=r"/scenes/nosuch/manifest.msgpack: no such scene \(the server answered "
                                             r"404"):
            f.manifest()
        s = f.stats()
    assert s.requests == 1 and s.retries == 0  # permanent: not retried

    (root / "broken").mkdir(exist_ok=True)
    (root / "broken" / "manifest.msgpack").write_bytes(b"<html>captive portal</html>")
    with fetcher(HttpSource(server.url("broken")), cache=DiskCache(tmp_path / "c")) as f:
        with pytest.raises(FetchError, match="/scenes/broken/manifest.msgpack: not a splatstream manifest"):
            f.manifest()
    assert DiskCache(tmp_path / "c").get_manifest(server.url("broken") + "/manifest.msgpack") is None


def test_a_local_manifest_that_does_not_parse_is_named_as_the_file(tmp_path):
    # `view DIR` named the directory ('bad/tm: not a splatstream manifest ...') where `info` and `decode` name
    # DIR/manifest.msgpack (newuser58)
    scene = tmp_path / "tm"
    scene.mkdir()
    (scene / "manifest.msgpack").write_bytes(b"\x8f\xa6format")  # a map cut short
    with fetcher(open_source(scene)) as f:
        with pytest.raises(FetchError) as exc:
            f.manifest()
    assert str(exc.value).startswith(f"{scene / 'manifest.msgpack'}: not a splatstream manifest ("), str(exc.value)


def test_a_local_manifest_with_a_flipped_byte_is_named_corrupt(tmp_path, root):
    # `view SCENE` said 'not a splatstream manifest (checksum: checksum mismatch: the manifest is corrupt ...)' of a
    # manifest with one byte flipped, where info and decode say it is corrupt (newuser64)
    scene = tmp_path / "flipped"
    shutil.copytree(root / SCENE, scene)
    path = scene / "manifest.msgpack"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 1
    path.write_bytes(bytes(data))
    with fetcher(open_source(scene)) as f:
        with pytest.raises(FetchError) as exc:
            f.manifest()
    assert str(exc.value).startswith(f"{path}: checksum: checksum mismatch: the manifest is corrupt ("), str(exc.value)
    assert exc.value.kind == NOT_A_SCENE and not exc.value.transient
    assert "not a splatstream manifest" not in str(exc.value)


def test_an_exported_3d_tiles_tileset_is_named_as_one(tmp_path):
    # `view TILES_DIR` said 'not a scene directory ... pass the splat file itself', and `view TILES_DIR/tileset.json`
    # 'unrecognised file format' (newuser58)
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    (tiles / "tileset.json").write_text('{"asset": {"version": "1.1"}}')
    for given in (tiles, tiles / "tileset.json"):
        with pytest.raises(InputError) as exc:
            open_source(str(given))
        assert str(exc.value) == (f"{given}: a 3D Tiles tileset (`splatstream export-3dtiles`), which CesiumJS draws "
                                  "(`splatstream serve` serves it); `view` streams the scene directory it was "
                                  "exported from")


def test_an_unreachable_server_is_reported_at_once(tmp_path):
    """Connection refused or an unknown host, nothing cached: one line at once, not after the manifest timeout."""
    port = _free_port()
    for url, expected in [(f"http://127.0.0.1:{port}/scenes/x", f"cannot connect to 127.0.0.1:{port} (connection "
                                                                 f"refused)"),
                          ("http://no-such-host.invalid/scenes/x", "unknown host 'no-such-host.invalid'")]:
        with fetcher(HttpSource(url), manifest_timeout_s=30, cache=DiskCache(tmp_path / "c")) as f:
            t0 = time.monotonic()
            with pytest.raises(FetchError) as exc:
                f.manifest()
            assert time.monotonic() - t0 < 10  # DNS of a .invalid name may take a moment; never the 30 s
        msg = str(exc.value)
        assert msg.startswith(url + "/manifest.msgpack: ") and expected in msg and "\n" not in msg, msg
        assert "unknown error" not in msg


def test_a_dripping_manifest_ends_at_the_manifest_deadline(root, server):
    server.slow_bytes_per_s = 20
    server.add_fault("manifest", "slow")
    with fetcher(HttpSource(server.url(SCENE)), manifest_timeout_s=1.5, stall_timeout_s=5) as f:
        t0 = time.monotonic()
        with pytest.raises(FetchError, match=r"/scenes/fruit/manifest.msgpack: no complete manifest within 1.5 s: "
                                             r"not complete in time \(\d+ bytes received in the last attempt"):
            f.manifest()
        assert time.monotonic() - t0 < 5


def test_manifest_is_retried_through_server_errors(root, server):
    server.add_fault("manifest", "500", "500", "500")
    with fetcher(HttpSource(server.url(SCENE))) as f:
        f.manifest()
        assert f.manifest_bytes == (root / SCENE / "manifest.msgpack").read_bytes()
        s = f.stats()
    assert s.failures == {"http_5xx": 3} and s.retries == 3 and s.requests == 4


# -- local sources ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["directory", "memory"])
def test_local_stores_stream_the_same_bytes(root, manifest, kind, tmp_path):
    if kind == "directory":
        source = open_source(root / SCENE)
        assert isinstance(source, StoreSource) and isinstance(source.store, DirectoryStore)
    else:
        d = root / SCENE
        payloads = {f"data/{p.name}": p.read_bytes() for p in (d / "data").iterdir()}
        source = StoreSource(MemoryStore((d / "manifest.msgpack").read_bytes(), payloads))
    reqs = requests_of(manifest)
    cache = DiskCache(tmp_path / "unused")
    with fetcher(source, cache=cache) as f:
        f.manifest()
        assert f.manifest_bytes == (root / SCENE / "manifest.msgpack").read_bytes()
        f.want(reqs)
        results = collect(f, len(reqs))
        s = f.stats()
    assert_exact(root, results, reqs)
    assert s.manifest_source == MANIFEST_LOCAL and s.cache_hits == 0 and cache.size_bytes() == 0
    assert s.bytes_downloaded == len((root / SCENE / "manifest.msgpack").read_bytes()) + sum(
        e.bytes for _, _, e in reqs)


@pytest.mark.parametrize("damage", ["flipped", "short", "missing"])
def test_a_damaged_local_payload_fails_permanently_after_two_reads(root, manifest, tmp_path, damage):
    """A local store reads the same bytes again: a payload whose SHA-256 or size differs from the manifest, or
    whose file is missing, is read twice (a re-encode may rename the file in mid-read), then reported by damaged()
    and never requested again; the other payloads all arrive. (Over HTTP the same failure is retried while wanted:
    test_a_payload_that_stays_corrupt_is_never_delivered.)"""
    scene = tmp_path / "copy"
    shutil.copytree(root / SCENE, scene)
    victim = shas_by_size(manifest)[0]
    path = scene / "data" / f"{victim}.bin"
    data = bytearray(path.read_bytes())
    if damage == "flipped":
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    elif damage == "short":
        path.write_bytes(bytes(data[:-1]))
    else:
        path.unlink()
    kind, field = {"flipped": ("checksum", "sha256"), "short": ("checksum", "bytes"),
                   "missing": ("missing", None)}[damage]
    reqs = requests_of(manifest)
    with fetcher(open_source(scene)) as f:
        f.manifest()
        f.want(reqs)
        bad = [k for _, k, e in reqs if e.sha256 == victim]
        results = collect(f, len(reqs) - len(bad))
        damaged = wait_for(f.damaged, lambda d: len(d) >= 1)
        f.want([r for r in reqs if r[1] in bad])  # still wanted: it is not read a third time
        wait_for(f.stats, lambda s: s.in_flight > 0, timeout_s=0.5)  # (it never is: a pump had its chance)
        s = f.stats()
        assert f.done() == []
    assert_exact(root, results, [r for r in reqs if r[1] not in bad])
    assert s.failures == {kind: 2} and s.retries == 1 and s.in_flight == 0
    assert len(damaged) == 1 and damaged[0].kind == kind and damaged[0].field == field
    assert damaged[0].path == str(path)
    message = str(damaged[0])
    assert "\n" not in message and message.startswith(str(path))
    if damage == "flipped":
        assert message == (f"{path}: sha256: SHA-256 {hashlib.sha256(data).hexdigest()}, the manifest says "
                           f"{victim} (the file is damaged or was replaced)")
    elif damage == "short":
        assert message == f"{path}: bytes: payload is {len(data) - 1} bytes, the manifest says {len(data)}"
    else:
        assert message == f"{path}: payload file named in the manifest is missing"


def test_io_waits_for_the_frame_loop_when_asked(root, manifest, server):
    """Fetcher.yield_to: while the frame loop is in its CPU work (the event clear), responses are not handled; they
    are once it waits for the GPU (the event set), and the bytes are exact. A gate that stays closed only delays
    (each wait is bounded)."""
    import threading

    idle = threading.Event()
    reqs = requests_of(manifest)[:4]
    f = fetcher(HttpSource(server.url(SCENE)))
    try:
        f.manifest()
        f.yield_to(idle, timeout_s=5.0)
        f.want(reqs)
        time.sleep(0.3)
        assert f.done() == [] and f.stats().delivered == 0  # the loop is waiting at the gate
        idle.set()
        results = collect(f, len(reqs), timeout_s=10.0)
        assert_exact(root, results, reqs)
        idle.clear()
        f.yield_to(idle, timeout_s=0.01)  # never opened: every wait times out, the fetch still completes
        more = requests_of(manifest)[4:8]
        f.want(more)
        assert_exact(root, collect(f, len(more), timeout_s=10.0), more)
    finally:
        f.close()


def test_the_queued_count_is_the_wanted_keys_not_in_flight():
    """stats().queued counted over the keys in flight (a few) is the count over the wanted keys (hundreds) it replaced,
    whatever the two hold: keys in flight that are wanted, and some that no longer are."""
    fetcher = Fetcher(StoreSource(MemoryStore(b"")))  # never started: only its bookkeeping
    rnd = random.Random(3)
    for _ in range(50):
        keys = [(rnd.randrange(1000), rnd.choice(["base", "sh1", "page"])) for _ in range(rnd.randrange(0, 300))]
        fetcher._wanted = {k: (1.0, None) for k in keys}
        fetcher._jobs = {k: None for k in rnd.sample(keys, min(len(keys), rnd.randrange(0, 9)))}
        fetcher._jobs.update({(2000 + i, "base"): None for i in range(rnd.randrange(0, 3))})  # no longer wanted
        assert fetcher.stats().queued == sum(1 for k in fetcher._wanted if k not in fetcher._jobs)
        assert fetcher.stats().in_flight == len(fetcher._jobs)
    fetcher._wanted, fetcher._jobs = {}, {}


def test_retry_delay_stays_capped_after_thousands_of_failures():
    """A manifest or payload retried for minutes counts thousands of failures: the backoff stays within its cap (2.0
    to the power of a failure count past 1024 overflowed, and the fetcher's thread raised OverflowError)."""
    import random

    policy, rng = RetryPolicy(base_s=0.02, cap_s=0.2), random.Random(0)
    delays = [policy.delay(n, rng) for n in (1, 2, 10, 1025, 5000, 10**6)]
    assert all(0.0 <= d <= 0.2 for d in delays)
    assert policy.delay(1, random.Random(1)) <= 0.02
