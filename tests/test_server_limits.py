"""Connection limits of the scene server (issue 19 findings 11-13), on real servers on loopback: header, idle and
send timeouts, the connection cap with its 503 reserve, eviction of idle connections, the file-descriptor budget,
log levels of client errors, and files the server's user may not read. The abuse scenario as a whole is in
test_server_abuse.py."""
from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from server.limits import FD_BASE, Limits, fit_to_fd_limit
from server.testing import ServerThread, request, write_fake_scene
from splatstream.format.names import MANIFEST_NAME

REPO = Path(__file__).resolve().parents[1]
FAST = Limits(max_connections=8, header_timeout=0.5, keepalive_timeout=1.5, send_timeout=1.0)
BIG = 32 << 20


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("root")
    write_fake_scene(root / "s", [1000, 64 << 10, BIG], seed=1)
    return root


def payload(root: Path, size: int) -> str:
    return next(p.name for p in (root / "s" / "data").iterdir() if p.stat().st_size == size)


def connect(port: int, rcvbuf: int | None = None) -> socket.socket:
    s = socket.socket()
    if rcvbuf:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # before connect: caps the TCP window
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    return s


def seconds_until_closed(s: socket.socket, limit: float = 10.0, drip: bytes | None = None) -> tuple[float, bytes]:
    """Seconds until the server closes `s` (EOF or reset), and what it sent; sends `drip` every 0.1 s meanwhile."""
    start = time.monotonic()
    got = b""
    while time.monotonic() - start < limit:
        ready, _, _ = select.select([s], [], [], 0.1)
        try:
            if ready:
                chunk = s.recv(65536)
                if not chunk:
                    return time.monotonic() - start, got
                got += chunk
            elif drip:
                s.sendall(drip)
        except (ConnectionResetError, BrokenPipeError):
            return time.monotonic() - start, got
    raise AssertionError(f"still open after {limit} s")


def still_open(s: socket.socket) -> bool:
    ready, _, _ = select.select([s], [], [], 0)
    if not ready:
        return True
    try:
        return s.recv(1, socket.MSG_PEEK) != b""
    except ConnectionResetError:
        return False


def read_response(s: socket.socket) -> tuple[int, dict[str, str], bytes]:
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = s.recv(65536)
        assert chunk, data
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    n = int(headers.get("content-length", 0))
    while len(body) < n:
        chunk = s.recv(65536)
        assert chunk
        body += chunk
    return int(lines[0].split()[1]), headers, body


def wait_for(condition, limit: float = 30.0) -> bool:
    """True as soon as condition() holds; the bound is generous (a loaded machine only makes it later)."""
    end = time.monotonic() + limit
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


@pytest.fixture
def fast(root):
    s = ServerThread(root, limits=FAST)
    yield s
    s.stop()


# -- timeouts (finding 13) -----------------------------------------------------------------------------------------
def test_silent_connection_closed_after_header_timeout(fast):
    with connect(fast.port) as s:
        took, got = seconds_until_closed(s)
    assert got == b"" and FAST.header_timeout - 0.1 <= took < FAST.header_timeout + 1.5


def test_slow_headers_closed_after_header_timeout(fast):
    """Slowloris: a header line every 0.1 s never completes the request; the connection goes at the header
    timeout, counted from the request's first byte."""
    with connect(fast.port) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        took, got = seconds_until_closed(s, drip=b"X-Slow: 1\r\n")
    assert got == b"" and FAST.header_timeout - 0.1 <= took < FAST.header_timeout + 1.5


def test_keepalive_connection_closed_after_idle_timeout(fast):
    with connect(fast.port) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        assert read_response(s)[0] == 200
        time.sleep(FAST.header_timeout + 0.3)  # idle longer than the header timeout: that does not apply here
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        assert read_response(s)[0] == 200
        took, got = seconds_until_closed(s)
    assert got == b"" and FAST.keepalive_timeout - 0.2 <= took < FAST.keepalive_timeout + 1.5


def test_stalled_download_is_aborted(fast, root):
    """A client that stops reading a large (sendfile) response is cut off after the send timeout."""
    name = payload(root, BIG)
    with connect(fast.port, rcvbuf=65536) as s:
        s.sendall(f"GET /scenes/s/data/{name} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        assert wait_for(lambda: any(c.busy for c in fast.guard.normal))
        start = time.monotonic()
        assert wait_for(lambda: fast.guard.open_connections == 0, FAST.send_timeout + 30)
        assert time.monotonic() - start >= FAST.send_timeout - 0.2
        got = 0
        try:
            while chunk := s.recv(1 << 20):
                got += len(chunk)
        except ConnectionResetError:
            pass
    assert 0 < got < BIG // 2  # what the socket buffers held, not the file


def test_stalled_pipelined_responses_are_aborted(fast, root):
    """A client that pipelines requests for in-memory responses and reads none: the server's write buffer
    fills, writing pauses, and the connection is aborted after the send timeout."""
    name = payload(root, 64 << 10)
    n = 400
    with connect(fast.port, rcvbuf=16384) as s:
        s.setblocking(False)
        data = f"GET /scenes/s/data/{name} HTTP/1.1\r\nHost: x\r\n\r\n".encode() * n
        sent = 0
        end = time.monotonic() + 5
        while sent < len(data) and time.monotonic() < end:
            try:
                sent += s.send(data[sent:])
            except BlockingIOError:
                time.sleep(0.01)
        assert wait_for(lambda: any(c.paused_since for c in fast.guard.normal))
        start = time.monotonic()
        assert wait_for(lambda: fast.guard.open_connections == 0, FAST.send_timeout + 30)
        assert time.monotonic() - start >= FAST.send_timeout - 0.5
        s.setblocking(True)
        got = 0
        try:
            while chunk := s.recv(1 << 20):
                got += len(chunk)
        except ConnectionResetError:
            pass
    assert got < n * (64 << 10) // 2


# -- the cap (finding 13) ------------------------------------------------------------------------------------------
def test_over_the_cap_503_with_retry_after_and_healthz_answers(root):
    limits = Limits(max_connections=4, header_timeout=5, keepalive_timeout=5, send_timeout=5)
    s = ServerThread(root, limits=limits)
    try:
        assert s.guard.limits.reserve == 2
        slow = [connect(s.port) for _ in range(4)]
        for c in slow:
            c.sendall(b"GET /healthz HTTP/1.1\r\n")  # requests begun: not idle, so not evicted
        assert wait_for(lambda: len(s.guard.normal) == 4 and all(c.got_bytes for c in s.guard.normal))
        status, headers, body = request(s.port, "/api/scenes")
        assert status == 503 and headers["Retry-After"] == "2" and headers["Connection"] == "close"
        assert headers["Cache-Control"] == "no-store"
        assert json.loads(body)["error"]["status"] == 503
        status, headers, body = request(s.port, "/healthz")  # the reserve answers health checks
        assert status == 200 and json.loads(body) == {"status": "ok"} and headers["Connection"] == "close"
        assert all(still_open(c) for c in slow)
        for c in slow:
            c.close()
        assert wait_for(lambda: request(s.port, "/api/scenes")[0] == 200)
    finally:
        s.stop()


def test_idle_connections_are_evicted_at_the_cap(root):
    limits = Limits(max_connections=4, header_timeout=5, keepalive_timeout=5, send_timeout=5)
    s = ServerThread(root, limits=limits)
    try:
        idle = []
        for n in range(1, 5):
            idle.append(connect(s.port))
            assert wait_for(lambda n=n: len(s.guard.normal) == n)
        status, _, _ = request(s.port, "/api/scenes")
        assert status == 200  # not 503: the connection idle longest made room
        assert seconds_until_closed(idle[0], limit=2)[1] == b""
        assert all(still_open(c) for c in idle[1:])
        assert s.guard.evicted == 1
        for c in idle:
            c.close()
    finally:
        s.stop()


def _limit_fds(n: int):
    return lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (n, n))


def test_fd_limit_lowers_the_cap():
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256)); "
            "from server.limits import Limits, fit_to_fd_limit; "
            "lim, fds, lowered = fit_to_fd_limit(Limits(max_connections=1024)); "
            "print(lim.max_connections, lim.reserve, lim.accept_batch, lim.fds_needed(), fds, lowered)")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True).stdout
    cap, reserve, batch, need, fds, lowered = out.split()
    assert lowered == "True" and int(fds) == 256 and int(need) <= 256
    assert int(cap) + int(reserve) <= (256 - FD_BASE) // 3 + 1 and int(cap) >= 40
    # here (limit 20000 or whatever the machine has) the default fits, possibly after raising the soft limit
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard >= Limits().with_reserve().fds_needed():
        code = ("from server.limits import Limits, fit_to_fd_limit; import resource; "
                "lim, fds, lowered = fit_to_fd_limit(Limits()); "
                "print(lim.max_connections, lowered, resource.getrlimit(resource.RLIMIT_NOFILE)[0] >= fds)")
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
        assert out.stdout.split() == ["1024", "False", "True"]
    assert fit_to_fd_limit  # (imported for the reader: the function under test)


def _cli(*args: str, fds: int | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli", "serve", *args], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_limit_fds(fds) if fds else None)


def _port(proc: subprocess.Popen) -> tuple[int, str]:
    lines = ""
    while True:
        line = proc.stderr.readline()
        assert line, lines + proc.stderr.read()
        lines += line
        m = re.search(r"at http://127\.0\.0\.1:(\d+)/", line)
        if m:
            return int(m.group(1)), lines


def test_cli_fd_limit(root):
    proc = _cli(str(root), "--port", "0", fds=256)
    try:
        port, head = _port(proc)
        assert "--max-connections lowered from 1024 to" in head and "limit 256" in head
        assert request(port, "/healthz")[0] == 200
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    proc = _cli(str(root), "--port", "0", fds=40)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 1 and "file descriptor limit (40, ulimit -n) is too low" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("args, message", [
    (["--max-connections", "2"], "--max-connections 2: expected at least 4"),
    (["--header-timeout", "0"], "--header-timeout 0.0: expected seconds"),
    (["--keepalive-timeout", "nan"], "--keepalive-timeout nan: expected seconds"),
    (["--send-timeout", "-1"], "--send-timeout -1.0: expected seconds"),
])
def test_cli_bad_limits(root, args, message):
    proc = _cli(str(root), "--port", "0", *args)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and message in err and "Traceback" not in err


# -- log levels (finding 12) ---------------------------------------------------------------------------------------
def test_client_errors_are_not_logged_as_errors(tmp_path):
    """Requests refused by the HTTP parser (400/431), by path validation (400/404) or by method (405), and links
    leaving the root (404) are the client's doing: no ERROR (nor WARNING) line, no traceback."""
    root = tmp_path / "root"
    write_fake_scene(root / "s", [10], seed=2)
    write_fake_scene(tmp_path / "outside", [11], seed=3)
    secret = next((tmp_path / "outside" / "data").iterdir())
    (root / "s" / "data" / secret.name).symlink_to(secret)
    proc = _cli(str(root), "--port", "0", "--no-access-log")
    try:
        port, _ = _port(proc)
        raw = [b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"x" * 20000 + b"\r\n\r\n",
               b"GET /scenes/a\x00/manifest.msgpack HTTP/1.1\r\nHost: x\r\n\r\n",
               b"GARBAGE\r\n\r\n", b"GET / HTTP/9.9\r\n\r\n", b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03"]
        for data in raw:
            with connect(port) as s:
                s.sendall(data)
                took, got = seconds_until_closed(s)
                assert got == b"" or re.match(rb"HTTP/1.[01] 4\d\d ", got), got[:100]
        for path, expected in (("/scenes/../etc/passwd", 400), ("/nope", 404), (f"/scenes/s/data/{secret.name}", 404),
                               ("/scenes/s/data/" + "0" * 64 + ".bin", 404)):
            assert request(port, path)[0] == expected
        assert request(port, "/healthz", "DELETE")[0] == 405
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert "ERROR" not in err and "WARNING" not in err and "Traceback" not in err, err


# -- files the server may not read (finding 11, server side) ------------------------------------------------------
NOBODY = 65534


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs root to run a server as another uid")
def test_world_readable_scene_served_to_another_user():
    """A scene written with the usual modes (files 0644, directories 0755) by one user is served by a server
    running as another; payloads left 0600 (as the encoder wrote them before) answer 403, not a misleading 404,
    and are reported at start."""
    base = tempfile.mkdtemp(prefix="splatstream-uid-", dir="/tmp")
    try:
        os.chmod(base, 0o755)
        root = Path(base) / "root"
        pub = write_fake_scene(root / "pub", [100, 200_000], seed=4, atomic=False)
        priv = write_fake_scene(root / "priv", [300, 400], seed=5, atomic=False)
        for d, _, files in os.walk(root):
            os.chmod(d, 0o755)
            for f in files:
                os.chmod(os.path.join(d, f), 0o644)
        for sha in priv:
            os.chmod(root / "priv" / "data" / f"{sha}.bin", 0o600)
        # The interpreter lives where only root may look, so import everything first, then drop to `nobody`.
        code = ("import os, sys; import server.run, server.app, server.limits, server.scenes, server.http; "
                "import aiohttp.web, encodings.idna; "
                f"os.setgroups([]); os.setgid({NOBODY}); os.setuid({NOBODY}); "
                f"sys.exit(server.run.serve({str(root)!r}, port=0, access_log=False))")
        proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            port, head = _port(proc)
            assert re.search(rf"1 scene with files this server \(uid {NOBODY}\) may not read; they answer 403: "
                             r"priv/data/[0-9a-f]{64}\.bin \(mode 0600, owner uid 0\)\n", head), head
            status, _, raw = request(port, "/scenes/pub/manifest.msgpack")
            assert status == 200 and raw == (root / "pub" / MANIFEST_NAME).read_bytes()
            for sha in pub:
                status, _, body = request(port, f"/scenes/pub/data/{sha}.bin")
                assert status == 200 and hashlib.sha256(body).hexdigest() == sha
            for sha in priv * 3:
                status, headers, body = request(port, f"/scenes/priv/data/{sha}.bin")
                assert status == 403 and "file permissions" in json.loads(body)["error"]["message"]
            ids = [x["id"] for x in json.loads(request(port, "/api/scenes")[2])["scenes"]]
            assert ids == ["priv", "pub"]
        finally:
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=30)
        warnings = [line for line in err.splitlines() if "permission denied" in line]
        assert len(warnings) == 1 and "mode 0600, owner uid 0; this server runs as uid 65534" in warnings[0]
        assert "Traceback" not in err and proc.returncode == 0
    finally:
        subprocess.run(["rm", "-rf", base], check=False)
