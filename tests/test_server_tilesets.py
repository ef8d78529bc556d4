"""`splatstream serve` serving exported 3D Tiles tilesets (format_spec/http.md 14), as a real server process on
loopback: the three kinds of file (tileset.json, content, external tilesets), their caching headers, conditional
and range requests, CORS, and the path and containment rules shared with scenes."""
from __future__ import annotations

import hashlib
import http.client
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from server.tilesets import parse_tileset_path
from splatstream.gaussians import Gaussians
from splatstream.writers.glb import glb_bytes

ORIGIN = "http://127.0.0.1:9"


def write_tileset(directory: Path, tiles: int = 2) -> list[str]:
    """A small tileset directory (tileset.json, content-addressed .glb files and an external tileset holding the
    second tile, as export-3dtiles writes for a paged scene); the content names, then the external tileset's."""
    (directory / "tiles").mkdir(parents=True)
    rng = np.random.default_rng(0)
    names = []
    for i in range(tiles):
        n = 50 + 4000 * i  # the second is larger than the server's in-memory limit: sent with sendfile
        g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                      np.full((n, 3), -3, np.float32), np.zeros(n, np.float32), np.zeros((n, 3), np.float32),
                      np.zeros((n, 0, 3), np.float32))
        data = glb_bytes(g)
        name = f"tiles/{hashlib.sha256(data).hexdigest()}.glb"
        (directory / name).write_bytes(data)
        names.append(name)
    box = {"box": [0, 0, 0, 5, 0, 0, 0, 5, 0, 0, 0, 5]}
    external = json.dumps({"asset": {"version": "1.1"}, "geometricError": 1.0,
                           "root": {"boundingVolume": box, "geometricError": 1.0, "refine": "REPLACE",
                                    "children": [{"boundingVolume": box, "geometricError": 0.0,
                                                  "content": {"uri": names[1][len("tiles/"):]}}]}}).encode()
    external_name = f"tiles/{hashlib.sha256(external).hexdigest()}.json"
    (directory / external_name).write_bytes(external)
    tileset = {"asset": {"version": "1.1"}, "geometricError": 10.0,
               "root": {"boundingVolume": box, "geometricError": 1.0, "refine": "REPLACE",
                        "content": {"uri": names[0]},
                        "children": [{"boundingVolume": box, "geometricError": 1.0,
                                      "content": {"uri": external_name}}]}}
    (directory / "tileset.json").write_text(json.dumps(tileset))
    return [*names, external_name]


class Server:
    def __init__(self, root: Path, *extra: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "cli", "serve", str(root), "--port", "0",
                                      "--no-access-log", *extra], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                     stdin=subprocess.DEVNULL, text=True)
        self.started = line = self.proc.stderr.readline()
        m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        if not m:
            self.stop()
            raise AssertionError(f"server did not start: {line}{self.proc.stderr.read()}")
        self.port = int(m.group(1))

    def request(self, path: str, method: str = "GET", headers: dict | None = None):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        try:
            conn.putrequest(method, path, skip_accept_encoding=True)
            for k, v in (headers or {}).items():
                conn.putheader(k, v)
            conn.endheaders()
            r = conn.getresponse()
            return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
        finally:
            conn.close()

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return self.proc.stderr.read()


@pytest.fixture
def served(tmp_path):
    root = tmp_path / "root"
    names = write_tileset(root / "city" / "block-7")
    server = Server(root, "--cors-origin", ORIGIN)  # a root holding only a tileset is served
    try:
        yield server, root, names
    finally:
        server.stop()


def test_tileset_files_with_caching_headers_conditionals_ranges_and_cors(served):
    server, root, names = served
    # the start line counts the tilesets: it said '0 scenes from ROOT', which reads as nothing served
    assert server.started.startswith(f"splatstream serve: 0 scenes and 1 3D Tiles tileset from {root} at "), \
        server.started
    base = "/scenes/city/block-7"
    raw = (root / "city/block-7/tileset.json").read_bytes()
    status, h, body = server.request(f"{base}/tileset.json", headers={"Origin": ORIGIN})
    assert status == 200 and body == raw
    assert h["content-type"] == "application/json" and h["cache-control"] == "no-cache"
    assert h["etag"] == f'"{hashlib.sha256(raw).hexdigest()}"' and h["content-length"] == str(len(raw))
    assert h["access-control-allow-origin"] == ORIGIN and "ETag" in h["access-control-expose-headers"]
    status, h304, body = server.request(f"{base}/tileset.json", headers={"If-None-Match": h["etag"]})
    assert status == 304 and body == b"" and h304["etag"] == h["etag"]
    for name in names:
        data = (root / "city/block-7" / name).read_bytes()
        status, h, body = server.request(f"{base}/{name}", headers={"Origin": ORIGIN})
        assert status == 200 and body == data
        assert h["content-type"] == ("application/json" if name.endswith(".json") else "model/gltf-binary")
        assert h["cache-control"] == "public, max-age=31536000, immutable"
        assert h["etag"] == f'"{name[6:70]}"' and h["access-control-allow-origin"] == ORIGIN
        status, h, body = server.request(f"{base}/{name}", headers={"Range": "bytes=4-11"})
        assert status == 206 and body == data[4:12] and h["content-range"] == f"bytes 4-11/{len(data)}"
        status, h, body = server.request(f"{base}/{name}", method="HEAD")
        assert status == 200 and body == b"" and h["content-length"] == str(len(data))
    status, h, _ = server.request(f"{base}/tileset.json", method="OPTIONS",
                                  headers={"Origin": ORIGIN, "Access-Control-Request-Method": "GET"})
    assert status == 204 and h["access-control-allow-origin"] == ORIGIN
    status, _, _ = server.request(f"{base}/tileset.json", method="POST")
    assert status == 405


def test_tileset_path_and_containment_rules(served, tmp_path):
    server, root, names = served
    base = "/scenes/city/block-7"
    sha = names[0][6:70]
    # A scene directory never serves tileset files, even if it holds some; content needs its tileset.json.
    scene = root / "scene-with-tileset"
    (scene / "tiles").mkdir(parents=True)
    (scene / "manifest.msgpack").write_bytes(b"\x80")
    (scene / "tileset.json").write_text("{}")
    shutil.copy(root / "city/block-7" / names[0], scene / names[0])
    stray = root / "stray"
    (stray / "tiles").mkdir(parents=True)
    shutil.copy(root / "city/block-7" / names[0], stray / names[0])
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "tileset.json").write_text("{}")
    os.symlink(outside, root / "link-out")
    (root / ".hidden").mkdir()
    (root / ".hidden" / "tileset.json").write_text("{}")
    cases = {
        f"{base}/tileset.json": 200,
        f"{base}/tiles/{sha}.glb": 200,
        f"{base}/tiles/{sha.upper()}.glb": 404,  # names are lowercase hex
        f"{base}/tiles/{sha[:-1]}.glb": 404,
        f"{base}/{names[2]}": 200,  # an external tileset
        f"{base}/tiles/{sha}.json": 404,  # no such external tileset
        f"{base}/tiles/{sha[:-1]}.json": 404,
        f"{base}/tiles/tileset.json": 404,
        f"{base}/tiles/": 404,
        f"{base}/other.json": 404,
        f"{base}/tiles/../tileset.json": 400,
        f"{base}/tiles/%2e%2e/tileset.json": 400,
        "/scenes/city%2Fblock-7/tileset.json": 400,
        "/scenes/tileset.json": 404,
        "/scenes/.hidden/tileset.json": 404,
        "/scenes/link-out/tileset.json": 404,  # a link leaving the root
        "/scenes/scene-with-tileset/tileset.json": 404,
        f"/scenes/scene-with-tileset/tiles/{sha}.glb": 404,
        f"/scenes/stray/tiles/{sha}.glb": 404,
        f"/scenes/scene-with-tileset/{names[2]}": 404,
        "/scenes/nope/tileset.json": 404,
        "/scenes/a/b/c/d/e/f/g/h/i/tileset.json": 404,
    }
    got = {path: server.request(path)[0] for path in cases}
    assert got == cases
    status, h, body = server.request("/scenes/nope/tileset.json")
    assert h["cache-control"] == "no-store" and json.loads(body)["error"]["status"] == 404


def test_parse_tileset_path_leaves_scene_paths_alone():
    sha = "ab" * 32
    assert parse_tileset_path(f"/scenes/a/b/tiles/{sha}.glb").tileset_id == "a/b"
    assert parse_tileset_path("/scenes/a/tileset.json").kind == "tileset"
    assert parse_tileset_path(f"/scenes/a/tiles/{sha}.json").kind == "external"
    for other in (f"/scenes/a/data/{sha}.bin", "/scenes/a/manifest.msgpack", "/api/scenes", f"/scenes/a/{sha}.glb"):
        assert parse_tileset_path(other) is None


def test_serve_refuses_a_root_with_neither_scene_nor_tileset(tmp_path):
    (tmp_path / "empty").mkdir()
    r = subprocess.run([sys.executable, "-m", "cli", "serve", str(tmp_path / "empty"), "--port", "0"],
                       capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and "no tileset" in r.stderr
    write_tileset(tmp_path / "ts")
    r = subprocess.run([sys.executable, "-m", "cli", "serve", str(tmp_path / "ts"), "--port", "0"],
                       capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and "is itself a tileset directory" in r.stderr
    server = Server(tmp_path)  # the parent: serves the tileset `ts`
    try:
        assert server.request("/scenes/ts/tileset.json")[0] == 200
    finally:
        server.stop()


def test_serve_help_names_the_tilesets_it_serves(capsys):
    # `serve --help` said ROOT holds scene directories and named only /scenes/<id>/... of a scene, where serve
    # serves export-3dtiles tilesets too (README, Serve), and not what it leaves out (newuser64)
    from cli.main import main

    with pytest.raises(SystemExit):
        main(["serve", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "every 3D Tiles tileset export-3dtiles wrote (a directory holding tileset.json) at " \
           "/scenes/<id>/tileset.json" in text, text
    assert "Streamed SOGs and .rad files are not served" in text
    assert "directory holding scene directories and 3D Tiles tilesets" in text
