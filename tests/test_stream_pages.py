"""A paged scene (format.md 6.1) served by `splatstream serve`'s app on loopback and streamed by the real fetcher
and engine over real sockets: pages are served and cached like payloads, the first frame needs the root manifest
only, and the stream converges to the cut of the same scene unpaged."""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from conftest import real
from test_stream_engine import CountingPool, orbit

from client_gl.stream.engine import StreamEngine, StreamOptions
from client_gl.stream.fetch import Fetcher, RetryPolicy
from client_gl.stream.selection import SelectionOptions
from client_gl.stream.sources import HttpSource
from server.testing import ServerThread, request
from splatstream.encode import encode_file
from splatstream.format.manifest import parse_manifest
from splatstream.store import load_manifest


def converge(engine, cam, timeout_s: float = 300.0):
    """Frames until the stream converges: a generous bound on the wall clock (a loaded machine is only later), the
    frames paced so that the fetcher's thread runs between them."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        u = engine.update(cam)
        if u.converged:
            return u
        engine.wait(0.01)
        time.sleep(0.005)
    raise AssertionError(f"did not converge in {timeout_s} s")


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("paged-root")
    ply = real("fruit_drops_sh3.ply")
    encode_file(ply, root / "paged", max_leaf_splats=300, page_tiles=4, page_levels=2)
    encode_file(ply, root / "whole", max_leaf_splats=300)
    return root


@pytest.fixture(scope="module")
def server(root):
    s = ServerThread(root)
    yield s
    s.stop()


def test_pages_are_served_like_payloads(root, server):
    m = parse_manifest((root / "paged" / "manifest.msgpack").read_bytes())
    ref = next(t.page for t in m.tiles if t.page is not None)
    status, headers, body = request(server.port, f"/scenes/paged/{ref.file}")
    assert status == 200 and len(body) == ref.bytes
    assert headers["Cache-Control"] == "public, max-age=31536000, immutable"
    assert headers["ETag"] == f'"{ref.sha256}"'
    status, _, body = request(server.port, "/api/scenes")
    body = json.loads(body)
    scenes = {s["id"]: s for s in (body["scenes"] if isinstance(body, dict) else body)}
    assert scenes["paged"]["bytes"] == m.bytes_on_disk  # listed like any scene, its pages counted


def test_a_paged_scene_streams_over_http_to_the_unpaged_cut(root, server):
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    opts = StreamOptions(SelectionOptions(max_sse=1.0), prefetch=False)
    draws, fetched = {}, {}
    for scene in ("whole", "paged"):
        f = Fetcher(HttpSource(f"http://127.0.0.1:{server.port}/scenes/{scene}/"), request_timeout_s=5.0,
                    retry=RetryPolicy(base_s=0.02, cap_s=0.2), seed=0).start()
        try:
            engine = StreamEngine(f, CountingPool(10_000), opts)
            if scene == "paged":
                # the first frame's tree: the root manifest's tiles only
                assert engine.pages is not None and len(engine.manifest.tiles) < len(whole.tiles)
                manifest_bytes = len(f.manifest_bytes)
            u = converge(engine, cam)
            draws[scene] = sorted(u.draw)
            fetched[scene] = engine
            engine.close()
        finally:
            f.close()
    assert draws["paged"] == draws["whole"]
    paged = fetched["paged"].pages
    root_m = paged.root
    assert 0 < paged.pages_read < root_m.paged.pages  # only the pages the cut reached
    assert manifest_bytes < len((root / "whole" / "manifest.msgpack").read_bytes())
