"""The scene server, tested over real loopback HTTP (an in-process aiohttp runner in a thread, and the CLI as a
subprocess): statuses, headers, rejections, concurrency, scenes swapped while served, shutdown."""
from __future__ import annotations

import asyncio
import gzip
import hashlib
import http.client
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import aiohttp
import pytest
from conftest import real_path

from server.app import SCENE_ROOT
from server.scenes import SMALL_FILE_BYTES
from server.testing import ORIGIN, ServerThread, raw_request, request, write_fake_scene
from splatstream.format.manifest import pack_manifest, parse_manifest
from splatstream.format.names import MANIFEST_NAME

REPO = Path(__file__).resolve().parents[1]
REAL_PLY = real_path("fruit_drops_sh3.ply")
SIZES = [0, 1, 1000, SMALL_FILE_BYTES, SMALL_FILE_BYTES + 1, 3 << 20]  # both the in-memory and sendfile paths
sha = hashlib.sha256


def assert_error(status: int, headers, body: bytes, expected: int) -> None:
    assert status == expected, body
    assert headers["Content-Type"].startswith("application/json")
    err = json.loads(body)["error"]
    assert err["status"] == expected and isinstance(err["message"], str) and err["message"]
    assert "Traceback" not in err["message"]


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("root")
    write_fake_scene(root / "a", SIZES, seed=1)
    write_fake_scene(root / "nested" / "b", [10, 20], seed=2)
    write_fake_scene(root / ".a.tmp", [5], seed=3)  # a build in progress: never served
    (root / "a" / "other.txt").write_text("not a scene file")
    (root / "empty").mkdir()
    write_fake_scene(root / "nomanifest", [7], seed=4)
    (root / "nomanifest" / MANIFEST_NAME).unlink()
    (root / "broken").mkdir()
    (root / "broken" / MANIFEST_NAME).write_bytes(b"not msgpack \xc1")
    outside = tmp_path_factory.mktemp("outside")
    write_fake_scene(outside / "secret", [11], seed=5)
    (root / "evil").symlink_to(outside / "secret")  # scene directory leaving the root
    write_fake_scene(root / "c", [12], seed=6)
    secret_payload = next((outside / "secret" / "data").iterdir())
    (root / "c" / "data" / secret_payload.name).symlink_to(secret_payload)  # payload leaving the root
    (root / "alias").symlink_to(root / "a")  # a link inside the root is fine
    (root / "leak").mkdir()  # a scene directory inside the root whose manifest is a link leaving it
    (root / "leak" / MANIFEST_NAME).symlink_to(outside / "secret" / MANIFEST_NAME)
    (root / "fifo").mkdir()
    os.mkfifo(root / "fifo" / MANIFEST_NAME)
    return root


@pytest.fixture(scope="module")
def srv(root):
    s = ServerThread(root)
    yield s
    s.stop()


def payloads(root: Path, scene: str) -> dict[str, bytes]:
    d = root / scene / "data"
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


# -- basics --------------------------------------------------------------------------------------------------------
def test_healthz(srv):
    status, headers, body = request(srv.port, "/healthz")
    assert status == 200 and json.loads(body) == {"status": "ok"}
    assert headers["Cache-Control"] == "no-store"
    status, headers, body = request(srv.port, "/healthz", "HEAD")
    assert status == 200 and body == b"" and int(headers["Content-Length"]) > 0


def test_scene_list(srv):
    status, headers, body = request(srv.port, "/api/scenes")
    assert status == 200
    assert headers["Content-Type"] == "application/json; charset=utf-8"
    assert headers["Cache-Control"] == "no-cache"
    scenes = json.loads(body)["scenes"]
    ids = [s["id"] for s in scenes]
    assert ids == ["a", "alias", "c", "nested/b"]  # not hidden, not broken, not outside the root, not without manifest
    a = scenes[0]
    assert set(a) == {"id", "name", "splats", "sh_degree", "preset", "bounds", "bytes", "manifest"}
    assert a["manifest"] == "/scenes/a/manifest.msgpack"
    m = parse_manifest(request(srv.port, a["manifest"])[2])
    assert a["splats"] == m.splats > 1000 and a["sh_degree"] == 0 and a["preset"] == "very-high"
    assert a["bounds"] == {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}
    assert a["bytes"] == sum(SIZES) + len(request(srv.port, a["manifest"])[2])
    # revalidation
    status, h2, body2 = request(srv.port, "/api/scenes", headers={"If-None-Match": headers["ETag"]})
    assert status == 304 and body2 == b"" and h2["ETag"] == headers["ETag"]


def test_scene_list_gzip(srv):
    status, headers, body = request(srv.port, "/api/scenes", headers={"Accept-Encoding": "gzip, br"})
    assert status == 200 and headers["Content-Encoding"] == "gzip"
    assert "Accept-Encoding" in headers["Vary"]
    assert json.loads(gzip.decompress(body))["scenes"][0]["id"] == "a"
    assert int(headers["Content-Length"]) == len(body)
    status, headers, body = request(srv.port, "/api/scenes", headers={"Accept-Encoding": "gzip;q=0, br"})
    assert status == 200 and "Content-Encoding" not in headers and json.loads(body)


def test_manifest(srv, root):
    raw = (root / "a" / MANIFEST_NAME).read_bytes()
    for method in ("GET", "HEAD"):
        status, headers, body = request(srv.port, "/scenes/a/manifest.msgpack", method)
        assert status == 200
        assert body == (raw if method == "GET" else b"")
        assert headers["Content-Type"] == "application/vnd.msgpack"
        assert headers["Content-Length"] == str(len(raw))
        assert headers["ETag"] == f'"{sha(raw).hexdigest()}"'
        assert headers["Cache-Control"] == "no-cache"
        assert headers["Accept-Ranges"] == "bytes"
    parse_manifest(body or raw)
    etag = headers["ETag"]
    for inm in (etag, f"W/{etag}", f'"nope", {etag}', "*"):
        status, h304, body = request(srv.port, "/scenes/a/manifest.msgpack", headers={"If-None-Match": inm})
        assert status == 304 and body == b"" and h304["ETag"] == etag and h304["Cache-Control"] == "no-cache"
    status, _, body = request(srv.port, "/scenes/a/manifest.msgpack", headers={"If-None-Match": '"other"'})
    assert status == 200 and body == raw


@pytest.mark.parametrize("size", SIZES)
def test_payload(srv, root, size):
    name, data = next((n, d) for n, d in payloads(root, "a").items() if len(d) == size)
    url = f"/scenes/a/data/{name}"
    status, headers, body = request(srv.port, url, headers={"Accept-Encoding": "gzip, deflate, br, zstd"})
    assert status == 200 and body == data and sha(body).hexdigest() == name[:64]
    assert headers["ETag"] == f'"{name[:64]}"'
    assert headers["Cache-Control"] == "public, max-age=31536000, immutable"
    assert headers["Content-Type"] == "application/octet-stream"
    assert headers["Content-Length"] == str(size)
    assert "Content-Encoding" not in headers  # payloads are zstd already: never compressed again
    status, headers, body = request(srv.port, url, "HEAD")
    assert status == 200 and body == b"" and headers["Content-Length"] == str(size)
    status, headers, body = request(srv.port, url, headers={"If-None-Match": f'"{name[:64]}"'})
    assert status == 304 and body == b"" and headers["Cache-Control"].endswith("immutable")
    status, headers, body = request(srv.port, url, headers={"If-Match": '"different"'})
    assert_error(status, headers, body, 412)
    assert headers["Cache-Control"] == "no-store"
    status, _, body = request(srv.port, url, headers={"If-Match": f'"{name[:64]}"'})
    assert status == 200 and body == data


def test_query_string_ignored(srv, root):
    status, _, body = request(srv.port, "/scenes/a/manifest.msgpack?v=3&x=%2F..")
    assert status == 200 and body == (root / "a" / MANIFEST_NAME).read_bytes()


def test_manifest_range(srv, root):
    raw = (root / "a" / MANIFEST_NAME).read_bytes()
    status, headers, body = request(srv.port, "/scenes/a/manifest.msgpack", headers={"Range": "bytes=-16"})
    n = len(raw)
    assert status == 206 and body == raw[-16:] and headers["Content-Range"] == f"bytes {n - 16}-{n - 1}/{n}"


def test_alias_inside_root(srv, root):
    status, _, body = request(srv.port, "/scenes/alias/manifest.msgpack")
    assert status == 200 and body == (root / "a" / MANIFEST_NAME).read_bytes()


# -- ranges --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("size", [1000, 3 << 20])
@pytest.mark.parametrize("spec, first, last", [
    ("bytes=0-9", 0, 9), ("bytes=10-", 10, None), ("bytes=-10", -10, None), ("bytes=5-99999999", 5, None),
    ("bytes=0-0", 0, 0),
])
def test_range(srv, root, size, spec, first, last):
    name, data = next((n, d) for n, d in payloads(root, "a").items() if len(d) == size)
    status, headers, body = request(srv.port, f"/scenes/a/data/{name}", headers={"Range": spec})
    want = data[first:] if last is None else data[first:last + 1]
    start = first % size
    assert status == 206 and body == want
    assert headers["Content-Range"] == f"bytes {start}-{start + len(want) - 1}/{size}"
    assert headers["Content-Length"] == str(len(want))
    assert headers["ETag"] == f'"{name[:64]}"'


def test_range_if_range(srv, root):
    name, data = next((n, d) for n, d in payloads(root, "a").items() if len(d) == 1000)
    url = f"/scenes/a/data/{name}"
    status, _, body = request(srv.port, url, headers={"Range": "bytes=0-9", "If-Range": f'"{name[:64]}"'})
    assert status == 206 and body == data[:10]
    for stale in ('"other"', f'W/"{name[:64]}"', "Sat, 21 Nov 2026 04:00:00 GMT"):
        status, headers, body = request(srv.port, url, headers={"Range": "bytes=0-9", "If-Range": stale})
        assert status == 200 and body == data and "Content-Range" not in headers


@pytest.mark.parametrize("spec", ["bytes=9-5", "bytes=0-1,5-6", "items=0-5", "bytes=x-y", "bytes=-"])
def test_range_ignored(srv, root, spec):
    name, data = next((n, d) for n, d in payloads(root, "a").items() if len(d) == 1000)
    status, headers, body = request(srv.port, f"/scenes/a/data/{name}", headers={"Range": spec})
    assert status == 200 and body == data and "Content-Range" not in headers


@pytest.mark.parametrize("fields", [
    [("Range", "bytes=0-9"), ("Range", "bytes=10-19")],
    [("Range", "bytes=0-9"), ("Range", "bytes=0-9")],
    [("Range", "bytes=5000-"), ("Range", "bytes=0-9")],  # the first alone: 416
    [("Range", "bytes=0-9"), ("If-Range", "ETAG"), ("If-Range", '"other"')],
    [("Range", "bytes=0-9"), ("If-Range", "ETAG"), ("If-Range", "ETAG")],
])
def test_two_range_or_if_range_fields_are_ignored(srv, root, fields):
    """Two Range fields (or two If-Range validators) in one request: neither is picked (the first was: newuser64);
    the whole file, 200, as for several ranges in one field (http.md section 5, item 3)."""
    name, data = next((n, d) for n, d in payloads(root, "a").items() if len(d) == 1000)
    etag = f'"{name[:64]}"'
    head = "".join(f"{k}: {etag if v == 'ETAG' else v}\r\n" for k, v in fields)
    out = raw_request(srv.port, f"GET /scenes/a/data/{name} HTTP/1.1\r\nHost: x\r\n{head}Connection: close\r\n\r\n"
                      .encode())
    status_line, rest = out.split(b"\r\n", 1)
    head_bytes, body = rest.split(b"\r\n\r\n", 1)
    assert status_line.startswith(b"HTTP/1.1 200 "), out[:300]
    assert b"content-range" not in head_bytes.lower() and body == data
    # one of each still ranges
    status, _, body = request(srv.port, f"/scenes/a/data/{name}", headers={"Range": "bytes=0-9", "If-Range": etag})
    assert status == 206 and body == data[:10]


@pytest.mark.parametrize("spec", ["bytes=1000-", "bytes=5000-6000", "bytes=-0", "bytes=18446744073709551616-",
                                  "bytes=18446744073709551615-18446744073709551616", "bytes=" + "9" * 5000 + "-"])
def test_range_not_satisfiable(srv, root, spec):
    name, _ = next((n, d) for n, d in payloads(root, "a").items() if len(d) == 1000)
    status, headers, body = request(srv.port, f"/scenes/a/data/{name}", headers={"Range": spec})
    assert_error(status, headers, body, 416)
    assert headers["Content-Range"] == "bytes */1000"
    assert headers["Cache-Control"] == "no-store"  # an error is never cached like the immutable payload


def test_range_empty_file_and_head(srv, root):
    name = next(n for n, d in payloads(root, "a").items() if len(d) == 0)
    status, headers, body = request(srv.port, f"/scenes/a/data/{name}", headers={"Range": "bytes=0-"})
    assert_error(status, headers, body, 416)
    assert headers["Content-Range"] == "bytes */0"
    name = next(n for n, d in payloads(root, "a").items() if len(d) == 1000)
    status, headers, body = request(srv.port, f"/scenes/a/data/{name}", "HEAD", headers={"Range": "bytes=0-9"})
    assert status == 200 and body == b"" and headers["Content-Length"] == "1000"  # Range applies to GET only


# -- rejections ----------------------------------------------------------------------------------------------------
def _secret_name(root: Path) -> str:
    return next(p.name for p in (root / "c" / "data").iterdir() if p.is_symlink())


@pytest.mark.parametrize("path, status", [
    ("/scenes/../etc/passwd", 400),
    ("/scenes/a/../a/manifest.msgpack", 400),
    ("/scenes/a/./manifest.msgpack", 400),
    ("/scenes/%2e%2e/%2e%2e/%2e%2e/etc/passwd", 400),
    ("/scenes/a/%2E%2E/a/manifest.msgpack", 400),
    ("/scenes/a%2Fmanifest.msgpack", 400),
    ("/scenes/nested%2fb/manifest.msgpack", 400),
    ("/scenes/%2Fetc%2Fpasswd", 400),
    ("/scenes/%252e%252e/a/manifest.msgpack", 400),
    ("/scenes/nested%252Fb/manifest.msgpack", 400),
    ("/scenes/a%5Cmanifest.msgpack", 400),
    ("/scenes/a%00/manifest.msgpack", 400),
    ("/scenes/a%00.msgpack", 400),
    # issue 37: an encoded CR LF is a control character wherever it is (the router's patterns do not match it)
    ("/scenes/a%0d%0a/manifest.msgpack", 400),
    ("/scenes/a/manifest.msgpack%0D%0A", 400),
    (f"/scenes/a/data/{'0' * 64}.bin%0d%0aX-Injected:%201", 400),
    ("/%0d%0a", 400),
    ("/healthz%0a", 400),
    ("/api/%2e%2e/scenes", 400),
    ("/scenes//etc/passwd", 404),
    ("//etc/passwd", 404),
    ("/etc/passwd", 404),
    ("/", 404),
    ("/scenes/", 404),
    ("/scenes/a", 404),
    ("/scenes/a/", 404),
    ("/scenes/a/data/", 404),
    ("/scenes/a/other.txt", 404),
    ("/scenes/.a.tmp/manifest.msgpack", 404),
    ("/scenes/%2ea.tmp/manifest.msgpack", 404),
    ("/scenes/nope/manifest.msgpack", 404),
    ("/scenes/empty/manifest.msgpack", 404),
    (f"/scenes/a/data/{'0' * 64}.bin", 404),
    (f"/scenes/nope/data/{'0' * 64}.bin", 404),
    ("/scenes/evil/manifest.msgpack", 404),  # symlinked scene leaving the root
    ("/scenes/fifo/manifest.msgpack", 404),  # not a regular file (and must not hang)
    ("/scenes/a/manifest.msgpack/", 404),
])
def test_rejected_paths(srv, path, status):
    for method in ("GET", "HEAD"):
        st, headers, body = request(srv.port, path, method)
        if method == "GET":
            assert_error(st, headers, body, status)
        else:
            assert st == status and body == b""
        assert headers["Cache-Control"] == "no-store"


def test_rejected_symlinks(srv, root):
    name = _secret_name(root)
    assert (root / "c" / "data" / name).read_bytes()  # the link works on disk ...
    st, headers, body = request(srv.port, f"/scenes/c/data/{name}")
    assert_error(st, headers, body, 404)  # ... but leaves the root, so it is not served
    st, headers, body = request(srv.port, f"/scenes/evil/data/{name}")
    assert_error(st, headers, body, 404)


def test_manifest_link_leaving_the_root_is_not_listed(srv, root):
    """Issue 19 finding 10: the scene list applies the containment rule of serving, so it never shows the name,
    splat count, bounds or size of a manifest outside the root."""
    assert (root / "leak" / MANIFEST_NAME).read_bytes()  # readable on disk through the link
    assert_error(*request(srv.port, "/scenes/leak/manifest.msgpack"), 404)
    status, _, body = request(srv.port, "/api/scenes")
    assert status == 200
    scenes = json.loads(body)["scenes"]
    assert "leak" not in [x["id"] for x in scenes]
    assert "secret" not in [x["name"] for x in scenes]
    assert b"secret" not in body


def test_payload_of_directory_without_manifest(srv, root):
    name = next((root / "nomanifest" / "data").iterdir()).name
    assert_error(*request(srv.port, f"/scenes/nomanifest/data/{name}"), 404)


def test_raw_backslash_and_literal_nul(srv):
    for target in (b"/scenes/a\\..\\a/manifest.msgpack", b"/scenes/..\\..\\etc\\passwd"):
        out = raw_request(srv.port, b"GET " + target + b" HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert out.startswith(b"HTTP/1.1 400 "), out[:200]
    # a literal NUL never reaches a handler: the HTTP parser refuses the request line
    out = raw_request(srv.port, b"GET /scenes/a\x00/manifest.msgpack HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
    assert re.match(rb"HTTP/1.[01] 400 ", out), out[:200]


def test_absolute_form_target(srv):
    out = raw_request(srv.port, b"GET http://127.0.0.1/scenes/../../etc/passwd HTTP/1.1\r\nHost: x\r\n"
                                b"Connection: close\r\n\r\n")
    assert re.match(rb"HTTP/1.1 40[04] ", out), out[:200]
    assert b"root:" not in out


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH"])
@pytest.mark.parametrize("path", ["/scenes/a/manifest.msgpack", "/api/scenes", "/healthz"])
def test_method_not_allowed(srv, method, path):
    st, headers, body = request(srv.port, path, method, body=b"x")
    assert_error(st, headers, body, 405)
    assert headers["Allow"] == "GET, HEAD, OPTIONS"


def test_request_limits(srv):
    st, _, _ = request(srv.port, "/healthz", headers={"X-Big": "x" * 20000})
    assert st in (400, 431)
    st, _, _ = request(srv.port, "/healthz", headers={f"X-H{i}": "1" for i in range(200)})
    assert st in (400, 431)
    st, _, _ = request(srv.port, "/" + "a" * 20000)
    assert st in (400, 414)
    st, headers, body = request(srv.port, "/healthz", "POST", body=b"x" * 100_000)
    assert st == 405


def test_unexpected_exception_is_a_json_500(root, caplog):
    caplog.set_level(logging.INFO, logger="splatstream.server")
    s = ServerThread(root)
    try:
        def boom(sp):
            raise RuntimeError("secret internal detail")

        s.app[SCENE_ROOT].open = boom
        st, headers, body = request(s.port, "/scenes/a/manifest.msgpack")
        assert_error(st, headers, body, 500)
        assert b"secret" not in body and b"RuntimeError" not in body
        assert request(s.port, "/healthz")[0] == 200  # still serving
        # a server fault is logged at ERROR, with its traceback (client errors are not: test_server_limits.py)
        faults = [r for r in caplog.records if r.levelno == logging.ERROR]
        assert len(faults) == 1 and "GET /scenes/a/manifest.msgpack" in faults[0].getMessage()
        assert "secret internal detail" in caplog.text
    finally:
        s.stop()


# -- CORS ----------------------------------------------------------------------------------------------------------
def test_cors(srv, root):
    name = next(n for n, d in payloads(root, "a").items() if len(d) == 1000)
    for path in ("/scenes/a/manifest.msgpack", f"/scenes/a/data/{name}", "/api/scenes", "/scenes/nope/x"):
        st, headers, _ = request(srv.port, path, headers={"Origin": ORIGIN})
        assert headers["Access-Control-Allow-Origin"] == ORIGIN, path
        expose = {v.strip() for v in headers["Access-Control-Expose-Headers"].split(",")}
        assert {"ETag", "Content-Range", "Content-Length"} <= expose
        assert "Origin" in headers["Vary"]
        st, headers, _ = request(srv.port, path, headers={"Origin": "https://evil.example"})
        assert "Access-Control-Allow-Origin" not in headers
    st, headers, _ = request(srv.port, f"/scenes/a/data/{name}", headers={"Origin": ORIGIN, "Range": "bytes=0-1"})
    assert st == 206 and headers["Access-Control-Allow-Origin"] == ORIGIN


def test_cors_preflight(srv):
    pre = {"Origin": ORIGIN, "Access-Control-Request-Method": "GET",
           "Access-Control-Request-Headers": "range, if-none-match"}
    st, headers, body = request(srv.port, "/scenes/a/manifest.msgpack", "OPTIONS", headers=pre)
    assert st == 204 and body == b""
    assert headers["Access-Control-Allow-Origin"] == ORIGIN
    assert "GET" in headers["Access-Control-Allow-Methods"]
    allowed = {v.strip().lower() for v in headers["Access-Control-Allow-Headers"].split(",")}
    assert {"range", "if-none-match"} <= allowed
    assert int(headers["Access-Control-Max-Age"]) > 0
    st, headers, _ = request(srv.port, "/scenes/a/manifest.msgpack", "OPTIONS",
                             headers={**pre, "Origin": "https://evil.example"})
    assert st == 204 and "Access-Control-Allow-Origin" not in headers
    assert "Access-Control-Allow-Methods" not in headers
    st, headers, _ = request(srv.port, "/api/scenes", "OPTIONS")
    assert st == 204 and headers["Allow"] == "GET, HEAD, OPTIONS"


def test_cors_any_origin(root):
    s = ServerThread(root, cors=("*",))
    try:
        st, headers, _ = request(s.port, "/scenes/a/manifest.msgpack", headers={"Origin": "https://x.example"})
        assert st == 200 and headers["Access-Control-Allow-Origin"] == "*"
    finally:
        s.stop()


# -- load and change -----------------------------------------------------------------------------------------------
def test_200_concurrent_downloads(srv, root):
    files = [f"/scenes/a/data/{n}" for n in payloads(root, "a")] + \
            [f"/scenes/nested/b/data/{n}" for n in payloads(root, "nested/b")]

    async def main():
        conn = aiohttp.TCPConnector(limit=200, force_close=False)
        async with aiohttp.ClientSession(connector=conn, auto_decompress=False) as session:
            async def one(i):
                url = files[i % len(files)]
                async with session.get(f"http://127.0.0.1:{srv.port}{url}") as r:
                    assert r.status == 200
                    body = await r.read()
                    return url, sha(body).hexdigest()

            return await asyncio.gather(*(one(i) for i in range(200)))

    results = asyncio.run(main())
    assert len(results) == 200
    for url, digest in results:
        assert url.endswith(f"/{digest}.bin")


def _fetch_scene(port: int, scene: str) -> tuple[bytes, dict[str, bytes | None]]:
    """The manifest and every payload it references (None where 404)."""
    st, _, raw = request(port, f"/scenes/{scene}/manifest.msgpack")
    assert st == 200
    m = parse_manifest(raw)
    got = {}
    for _, _, g in m.payloads():
        st, _, body = request(port, f"/scenes/{scene}/{g.file}")
        assert st in (200, 404)
        got[g.sha256] = body if st == 200 else None
    return raw, got


def test_scene_swapped_while_served(tmp_path):
    root = tmp_path / "root"
    versions = {}
    versions[0] = write_fake_scene(root / "s", [4 << 20, 100, 2000], seed=100)
    s = ServerThread(root)
    try:
        manifests = {request(s.port, "/scenes/s/manifest.msgpack")[2]}
        # A large download in flight (read slowly) across the swap still delivers the old, complete bytes.
        big = versions[0][0]
        conn = http.client.HTTPConnection("127.0.0.1", s.port, timeout=10)
        conn.request("GET", f"/scenes/s/data/{big}.bin")
        resp = conn.getresponse()
        head = resp.read(1024)
        stop = threading.Event()
        errors: list[str] = []
        seen: list[bytes] = []

        def reader():
            while not stop.is_set():
                try:
                    raw, got = _fetch_scene(s.port, "s")
                except Exception as exc:  # noqa: BLE001 - reported below
                    errors.append(repr(exc))
                    return
                seen.append(raw)
                for digest, body in got.items():
                    if body is not None and sha(body).hexdigest() != digest:
                        errors.append(f"payload {digest} served with wrong bytes")

        threads = [threading.Thread(target=reader) for _ in range(3)]
        for t in threads:
            t.start()
        for v in range(1, 9):
            versions[v] = write_fake_scene(root / "s", [4 << 20, 100 + v, 2000 + v], seed=100 + v)
            manifests.add((root / "s" / MANIFEST_NAME).read_bytes())
            time.sleep(0.03)
        stop.set()
        for t in threads:
            t.join(30)
        rest = resp.read()
        conn.close()
        assert sha(head + rest).hexdigest() == big
        assert not errors, errors[:5]
        assert seen and set(seen) <= manifests  # every manifest served was one whole version, never a mix
        raw, got = _fetch_scene(s.port, "s")
        assert raw == (root / "s" / MANIFEST_NAME).read_bytes()
        assert all(body is not None and sha(body).hexdigest() == d for d, body in got.items())
        assert set(got) == set(versions[8])
        assert_error(*request(s.port, f"/scenes/s/data/{versions[0][1]}.bin"), 404)  # old payloads are gone
        # a scene added while the server runs shows up at once
        write_fake_scene(root / "t", [10], seed=7)
        assert [x["id"] for x in json.loads(request(s.port, "/api/scenes")[2])["scenes"]] == ["s", "t"]
    finally:
        s.stop()


def test_root_symlink_switched(tmp_path):
    """Deploying by switching a 'current' link to a new release directory takes effect at the next request."""
    write_fake_scene(tmp_path / "r1" / "s", [10], seed=1)
    write_fake_scene(tmp_path / "r2" / "s", [20], seed=2)
    (tmp_path / "current").symlink_to(tmp_path / "r1")
    s = ServerThread(tmp_path / "current")
    try:
        assert request(s.port, "/scenes/s/manifest.msgpack")[2] == (tmp_path / "r1" / "s" / MANIFEST_NAME).read_bytes()
        (tmp_path / "next").symlink_to(tmp_path / "r2")
        os.replace(tmp_path / "next", tmp_path / "current")
        assert request(s.port, "/scenes/s/manifest.msgpack")[2] == (tmp_path / "r2" / "s" / MANIFEST_NAME).read_bytes()
        name = next((tmp_path / "r2" / "s" / "data").iterdir()).name
        assert request(s.port, f"/scenes/s/data/{name}")[0] == 200
    finally:
        s.stop()


def test_real_encoded_scene(tmp_path):
    from splatstream.encode import encode_file

    m = encode_file(REAL_PLY, tmp_path / "root" / "fruit")
    s = ServerThread(tmp_path / "root")
    try:
        scenes = json.loads(request(s.port, "/api/scenes")[2])["scenes"]
        assert [(x["id"], x["splats"], x["sh_degree"]) for x in scenes] == [("fruit", m.splats, m.sh_degree)]
        raw, got = _fetch_scene(s.port, "fruit")
        assert raw == pack_manifest(m)
        assert got and all(body is not None and sha(body).hexdigest() == d for d, body in got.items())
    finally:
        s.stop()


# -- the command ---------------------------------------------------------------------------------------------------
def _cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli", "serve", *args], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _started(proc: subprocess.Popen) -> int:
    line = proc.stderr.readline()
    m = re.search(r"at http://127\.0\.0\.1:(\d+)/", line)
    assert m, line + proc.stderr.read() if proc.poll() is not None else line
    return int(m.group(1))


@pytest.mark.parametrize("setup, message", [
    (lambda p: p / "missing", "no such directory"),
    (lambda p: ((p / "e").mkdir(), p / "e")[1], "holds no scene"),
    (lambda p: ((p / "f").write_text("x"), p / "f")[1], "not a directory"),
    (lambda p: (write_fake_scene(p / "sc", [1]), p / "sc")[1], "is itself a scene directory"),
])
def test_cli_bad_root(tmp_path, setup, message):
    proc = _cli(str(setup(tmp_path)), "--port", "0")
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and message in err and "Traceback" not in err


def test_cli_counts_only_the_scenes_it_lists(tmp_path):
    """A scene whose manifest does not parse is skipped by /api/scenes: the start line counted it ('2 scenes from
    ...' beside a list of 1) and its warning came only with the first request. Now both at start."""
    root = tmp_path / "root"
    write_fake_scene(root / "good", [100])
    write_fake_scene(root / "broken", [100])
    data = (root / "broken" / MANIFEST_NAME).read_bytes()
    (root / "broken" / MANIFEST_NAME).write_bytes(data[:len(data) // 2])  # truncated
    proc = _cli(str(root), "--port", "0", "--no-access-log")
    try:
        warning = proc.stderr.readline()
        # 'skipped' read as not served, where its files still are (newuser64)
        assert ("scene broken: left out of /api/scenes (its files are still served), its manifest is not valid: "
                "broken/manifest.msgpack") in warning, warning
        started = proc.stderr.readline()
        assert started.startswith(f"splatstream serve: 1 scene from {root} at http://127.0.0.1:"), started
        port = int(re.search(r"at http://127\.0\.0\.1:(\d+)/", started).group(1))
        status, _, body = request(port, "/api/scenes")
        assert status == 200 and [s["id"] for s in json.loads(body)["scenes"]] == ["good"]
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)


def test_cli_warns_of_scene_directories_it_cannot_serve(tmp_path):
    """A scene under a name that is not URL-safe ('my scene', 'été', or inside 'dir x/') was left out of /api/scenes
    without a word; hidden directories (build temporaries) stay skipped quietly."""
    root = tmp_path / "root"
    for name in ("ok", "my scene", "été", "dir x/inner", ".hidden/s"):
        write_fake_scene(root / name, [100])
    proc = _cli(str(root), "--port", "0", "--no-access-log")
    try:
        warning = proc.stderr.readline()
        assert warning.strip() == ("splatstream serve: warning: 3 scene directories not served: a name in the path is "
                                   "not URL-safe (letters, digits, '.', '_', '-'; not starting with '.'): "
                                   "'dir x/inner', 'my scene', 'été'; rename them"), warning
        started = proc.stderr.readline()
        assert started.startswith(f"splatstream serve: 1 scene from {root} at "), started
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)


def test_cli_names_the_exports_it_does_not_serve(tmp_path):
    """`serve` of a root holding `export-sog-lod`'s and `export-rad`'s outputs beside a scene answered their URLs
    404 without a word at start; a root holding only a streamed SOG said 'holds no scene ... and no tileset'."""
    root = tmp_path / "root"
    write_fake_scene(root / "scene", [100])
    (root / "sog" / "garden").mkdir(parents=True)
    (root / "sog" / "garden" / "lod-meta.json").write_text("{}")
    (root / "garden.rad").write_bytes(b"RAD0")
    (root / ".build.rad").write_bytes(b"RAD0")  # hidden: skipped quietly, as hidden scenes are
    (root / "scene" / "x.rad").write_bytes(b"RAD0")  # inside a scene: not looked at
    proc = _cli(str(root), "--port", "0", "--no-access-log")
    try:
        note = proc.stderr.readline()
        assert note.strip() == ("splatstream serve: note: 2 exports not served (this server serves scene directories "
                                "and 3D Tiles tilesets): garden.rad (a Spark .rad), sog/garden/ (a PlayCanvas streamed "
                                "SOG); serve them with a static web server that answers Range requests (nginx, an "
                                "object store)"), note
        started = proc.stderr.readline()
        assert started.startswith(f"splatstream serve: 1 scene from {root} at "), started
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    proc = _cli(str(root / "sog"), "--port", "0")
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "a streamed SOG (lod-meta.json) or a Spark .rad is not served" in err, err


def test_cli_names_a_scene_directory_that_also_holds_a_tileset(tmp_path):
    """A scene directory with a tileset.json copied in serves its scene alone (http.md 14): its tileset.json answered
    404 with nothing said at start ('1 scene from ...')."""
    root = tmp_path / "root"
    write_fake_scene(root / "garden", [100])
    (root / "garden" / "tileset.json").write_text('{"asset": {"version": "1.1"}}')
    proc = _cli(str(root), "--port", "0", "--no-access-log")
    try:
        note = proc.stderr.readline()
        assert note.strip() == ("splatstream serve: note: 1 scene directory also holds tileset.json, not served (a "
                                "scene directory serves its scene alone): garden/; export the tileset into a "
                                "directory of its own (splatstream export-3dtiles SCENE_DIR OUT_DIR)"), note
        started = proc.stderr.readline()
        assert started.startswith(f"splatstream serve: 1 scene from {root} at "), started
        port = int(re.search(r":(\d+)/ ", started).group(1))
        status, _, body = request(port, "/scenes/garden/manifest.msgpack")
        assert status == 200 and body == (root / "garden" / MANIFEST_NAME).read_bytes()
        assert request(port, "/scenes/garden/tileset.json")[0] == 404
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)


def test_cli_port_in_use(root):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        proc = _cli(str(root), "--port", str(port))
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "already in use" in err and "Traceback" not in err


def test_cli_host_not_of_this_machine(root):
    # 192.0.2.1 (TEST-NET-1, RFC 5737) is never a local address: a usage error (2), not a failure (1)
    proc = _cli(str(root), "--host", "192.0.2.1", "--port", "0")
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "192.0.2.1 is not an address of this machine" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("workers", [1, 2])
def test_cli_graceful_sigterm(tmp_path, workers):
    root = tmp_path / "root"
    (big,) = write_fake_scene(root / "big", [32 << 20], seed=9)
    proc = _cli(str(root), "--port", "0", "--workers", str(workers))
    try:
        port = _started(proc)
        assert request(port, "/healthz")[0] == 200
        with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 65536)
            s.sendall(f"GET /scenes/big/data/{big}.bin HTTP/1.1\r\nHost: x\r\n\r\n".encode())
            data = bytearray(s.recv(65536))
            assert data.startswith(b"HTTP/1.1 200 ")
            time.sleep(0.2)  # the server is blocked on a full socket: the response is in flight
            proc.send_signal(signal.SIGTERM)
            time.sleep(0.3)
            assert proc.poll() is None  # still sending
            end = data.index(b"\r\n\r\n") + 4 + (32 << 20)
            while len(data) < end and (chunk := s.recv(1 << 20)):
                data += chunk
        head, _, body = bytes(data).partition(b"\r\n\r\n")
        assert sha(body).hexdigest() == big  # the in-flight response finished
        assert proc.wait(timeout=30) == 0
        err = proc.stderr.read()
        assert "stopped" in err and "Traceback" not in err
        assert f"GET /scenes/big/data/{big}.bin HTTP/1.1\" 200 {32 << 20}" in err  # the access log
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=2).close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_scene_list_writes_no_negative_zero(tmp_path):
    """newuser63: a scene whose splats lie at x = -0.0 listed '"min": [-0.0, ...]' in /api/scenes; the list says 0.0
    (the manifest keeps its bounds as stored)."""
    import numpy as np

    from splatstream.ply import read_gaussians_ply, write_gaussians_ply

    one = read_gaussians_ply(REPO / "samples" / "donut.ply").subset(np.arange(1))
    one.positions[0] = (-0.0, 0.5, 1.0)
    write_gaussians_ply(one, tmp_path / "one.ply")
    root = tmp_path / "root"
    r = subprocess.run([sys.executable, "-m", "cli.main", "encode", "-q", str(tmp_path / "one.ply"), str(root / "one")],
                       cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert parse_manifest((root / "one" / MANIFEST_NAME).read_bytes()).bounds.min[0] == 0.0  # -0.0 as stored
    s = ServerThread(root)
    try:
        status, _, body = request(s.port, "/api/scenes")
    finally:
        s.stop()
    assert status == 200 and b"-0.0" not in body, body
    assert json.loads(body)["scenes"][0]["bounds"] == {"min": [0.0, 0.5, 1.0], "max": [0.0, 0.5, 1.0]}
