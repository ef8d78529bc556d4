"""`splatstream serve --throttle-mbps R --latency-ms L`: the simulated link (server/throttle.py) over real loopback
sockets. The rates are long-run averages over seconds, so the tolerances (15 %) are far above timer noise."""
from __future__ import annotations

import http.client
import threading
import time
from pathlib import Path

import pytest
from conftest import run_cli

from server.testing import ServerThread, write_fake_scene
from server.throttle import MBIT, Link

FOUR_MB = 4 << 20


def get(port: int, path: str, headers: dict | None = None) -> tuple[float, int, dict, bytes]:
    """(seconds from sending the request to the last body byte, status, headers, body)"""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.connect()
        t0 = time.perf_counter()
        conn.request("GET", path, headers=headers or {})
        resp = conn.getresponse()
        body = resp.read()
        return time.perf_counter() - t0, resp.status, dict(resp.headers), body
    finally:
        conn.close()


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("throttle")
    # 4 MB (sent with sendfile when not throttled) and 100 kB (held in memory by the server)
    write_fake_scene(root / "s", [FOUR_MB, 100_000], seed=7)
    return root


def payload_paths(root: Path) -> dict[int, str]:
    return {p.stat().st_size: f"/scenes/s/data/{p.name}" for p in (root / "s" / "data").iterdir()}


def test_a_4mb_payload_over_20_mbit(root):
    srv = ServerThread(root, throttle=Link(20 * MBIT), shutdown_timeout=1)
    try:
        path = payload_paths(root)[FOUR_MB]
        seconds, status, headers, body = get(srv.port, path)
    finally:
        srv.stop()
    assert status == 200 and body == (root / "s" / path.removeprefix("/scenes/s/")).read_bytes()
    assert headers["Content-Length"] == str(FOUR_MB) and headers["ETag"] and headers["Cache-Control"].endswith(
        "immutable")
    mbps = FOUR_MB * 8 / seconds / 1e6
    assert 20 * 0.85 <= mbps <= 20 * 1.15, mbps


def test_the_rate_is_shared_by_all_connections(root):
    srv = ServerThread(root, throttle=Link(20 * MBIT), shutdown_timeout=1)
    path = payload_paths(root)[FOUR_MB]
    times = []
    try:
        threads = [threading.Thread(target=lambda: times.append(get(srv.port, path)[0])) for _ in range(2)]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        total = time.perf_counter() - t0
    finally:
        srv.stop()
    mbps = 2 * FOUR_MB * 8 / total / 1e6
    assert 20 * 0.85 <= mbps <= 20 * 1.15, mbps
    assert min(times) > 0.8 * total  # both progressed together (not one after the other)


def test_latency_is_added_to_every_request(root):
    srv = ServerThread(root, throttle=Link(None, 0.15), shutdown_timeout=1)
    try:
        small = payload_paths(root)[100_000]
        seconds, status, _, body = get(srv.port, small)
        assert status == 200 and len(body) == 100_000 and seconds >= 0.15
        seconds, status, _, _ = get(srv.port, "/healthz")
        assert status == 200 and seconds >= 0.15
        seconds, status, _, _ = get(srv.port, "/scenes/s/nothing.bin")  # errors too
        assert status == 404 and seconds >= 0.15
        etag = get(srv.port, "/scenes/s/manifest.msgpack")[2]["ETag"]
        seconds, status, _, body = get(srv.port, "/scenes/s/manifest.msgpack", {"If-None-Match": etag})
        assert status == 304 and body == b"" and seconds >= 0.15
    finally:
        srv.stop()


def test_range_and_head_pass_through(root):
    srv = ServerThread(root, throttle=Link(50 * MBIT, 0.0), shutdown_timeout=1)
    try:
        small = payload_paths(root)[100_000]
        data = (root / "s" / small.removeprefix("/scenes/s/")).read_bytes()
        _, status, headers, body = get(srv.port, small, {"Range": "bytes=10-19"})
        assert status == 206 and body == data[10:20] and headers["Content-Range"] == "bytes 10-19/100000"
        conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
        conn.request("HEAD", payload_paths(root)[FOUR_MB])
        resp = conn.getresponse()
        assert resp.status == 200 and resp.headers["Content-Length"] == str(FOUR_MB) and resp.read() == b""
        conn.close()
    finally:
        srv.stop()


@pytest.mark.parametrize("args, message", [
    (["--throttle-mbps", "0"], "--throttle-mbps 0.0: expected a positive number"),
    (["--throttle-mbps", "nan"], "--throttle-mbps nan: expected a positive number"),
    (["--latency-ms", "-1"], "--latency-ms -1.0: expected 0 or more"),
    (["--throttle-mbps", "20", "--workers", "2"], "need --workers 1"),
])
def test_cli_refuses_bad_link_options(root, args, message):
    r = run_cli("serve", root, "--port", "0", *args)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr
