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


class LoggedSource(HttpSource):
    """The real HTTP source, with the files it was asked for logged (payloads and pages)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.files: list[str] = []

    async def fetch_payload(self, entry, on_bytes=None):
        data = await super().fetch_payload(entry, on_bytes)
        self.files.append(entry.file)
        return data


def _stream(server, scene: str, cam, options: StreamOptions):
    """Converge a view over loopback: (the last update, the engine's tree, the base payloads fetched (tile ids, in
    order), the page files fetched)."""
    src = LoggedSource(f"http://127.0.0.1:{server.port}/scenes/{scene}/")
    f = Fetcher(src, request_timeout_s=5.0, retry=RetryPolicy(base_s=0.02, cap_s=0.2), seed=0).start()
    try:
        engine = StreamEngine(f, CountingPool(10_000), options)
        u = converge(engine, cam)
        m = engine.manifest
        engine.close()
    finally:
        f.close()
    files = {g.file: (t.id, name) for t in m.tiles for name, g in t.groups.items()}
    bases = [files[x][0] for x in src.files if x in files and files[x][1] == "base"]
    return u, m, bases, [x for x in src.files if x not in files]


@pytest.mark.parametrize("budget", [600, 2000])
def test_a_small_cut_is_fetched_directly_without_the_root(root, server, budget):
    """Issue 31: a cut whose payloads are under fill_min_bytes is fetched itself, without its coarse-to-fine
    ancestors or the root (the first frame draws the cut); with fill_min_bytes 0 the root and ancestors come first
    as before. The same cut either way."""
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    sel = SelectionOptions(max_sse=1.0, max_splats=budget)
    u, m, bases, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False))
    assert sum(m.tile(t).groups["base"].bytes for t in u.draw) <= StreamOptions.fill_min_bytes
    assert m.root not in u.draw and len(u.draw) > 4
    assert sorted(bases) == sorted(u.draw)  # every base fetched is drawn, each once; no root
    u0, _, bases0, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False, fill_min_bytes=0))
    assert sorted(u0.draw) == sorted(u.draw)
    assert bases0[0] == m.root and set(bases0) > set(u.draw)  # coarse to fine: the root first, then ancestors
    # a session that asked for the root with the manifest (no splat budget bounds the cut): the root, drawn first,
    # and the cut, no other ancestor
    u1, _, bases1, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False, root_first=True))
    assert sorted(u1.draw) == sorted(u.draw) and bases1[0] == m.root and sorted(bases1[1:]) == sorted(u.draw)


def test_a_large_cut_still_loads_coarse_to_fine(root, server):
    """Above fill_root_bytes (here no band: fill_root_bytes 0) the root comes first and the ancestors are filled in
    (what a user sees while a large cut loads does not change)."""
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    sel = SelectionOptions(max_sse=1.0)
    u, m, bases, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False, fill_min_bytes=16 << 10,
                                                                 fill_root_bytes=0))
    assert sum(m.tile(t).groups["base"].bytes for t in u.draw) > 16 << 10
    assert bases[0] == m.root and set(bases) - set(u.draw) - {m.root}  # ancestors other than the root


def test_a_page_head_whose_page_loads_is_not_fetched_for_a_small_cut(root, server):
    """In a paged scene a cut tile whose page is loading stands for the children the cut wants: with a small cut
    its payload is not fetched (it would be drawn, then replaced); the root is, for the first frame only (the cut
    waits for its pages, a round trip more). The cut is the unpaged scene's. With fill_min_bytes 0 the root and the
    ancestors come first, the heads still not."""
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    sel = SelectionOptions(max_sse=1.0, max_splats=2000)
    u, m, bases, pages = _stream(server, "paged", cam, StreamOptions(sel, prefetch=False))
    head_of = {t.page.file: t.id for t in m.tiles if t.page is not None}
    heads = {head_of[p] for p in pages}  # the tiles whose pages were read
    assert len(heads) == len(pages) >= 2
    assert not (set(bases) - set(u.draw)) & heads  # no head fetched while its page loaded (unless drawn)
    # the root only for the first frame (the cut waits for pages: a round trip more), each base once
    assert bases[0] == m.root and m.root not in bases[1:] and len(bases) == len(set(bases))
    # (a base fetched and not drawn is a tile of an earlier cut that the budget gave up when pages grew the tree)
    assert len(set(bases) - set(u.draw) - {m.root}) <= 2
    uw, _, _, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False))
    assert sorted(u.draw) == sorted(uw.draw)
    # always coarse to fine: the root and ancestors first, but still no head whose page loads (the fill rule does
    # not name the level just above the cut)
    u0, _, bases0, pages0 = _stream(server, "paged", cam, StreamOptions(sel, prefetch=False, fill_min_bytes=0))
    assert sorted(u0.draw) == sorted(u.draw)
    assert bases0[0] == m.root
    parent = {c: t.id for t in m.tiles for c in t.children}
    gap, step = StreamOptions.fill_gap, StreamOptions.fill_step
    named = {m.root}  # the fill rule's ancestors of the drawn tiles: fill_gap levels up, then every fill_step-th
    for t in u0.draw:
        d, a = 0, t
        while a in parent:
            a, d = parent[a], d + 1
            if d >= gap and (d - gap) % step == 0:
                named.add(a)
    extra = set(bases0) - set(u0.draw) - named
    assert len(extra) <= 2  # (tiles of an earlier cut that the budget gave up when pages grew the tree)


def test_a_mid_size_cut_fetches_the_root_then_the_cut_paged_or_not(root, server):
    """Between fill_min_bytes and fill_root_bytes (client.md 1.4): the root, then the cut, no ancestor between; in a
    paged scene the same, its pages after the root's base and no head whose page loads fetched (a loading head
    counts `lod.reduction` times its bytes in the rule). Thresholds around the cut's bytes B: the test holds
    whatever the encoder's sizes. With fill_root_bytes 0 the same cut loads coarse to fine (main's rule before)."""
    whole = load_manifest(root / "whole")
    cam = orbit(whole, 2.5, 0.3)
    sel = SelectionOptions(max_sse=1.0, max_splats=2000)
    u, m, _, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False))
    B = sum(m.tile(t).groups["base"].bytes for t in u.draw)
    band = StreamOptions(sel, prefetch=False, fill_min_bytes=B // 2, fill_root_bytes=8 * B)
    ub, _, bases, _ = _stream(server, "whole", cam, band)
    assert sorted(ub.draw) == sorted(u.draw) and m.root not in ub.draw
    assert bases[0] == m.root and sorted(bases[1:]) == sorted(u.draw)  # the root, then the cut, each once
    up, mp, bases_p, pages = _stream(server, "paged", cam, band)
    assert sorted(up.draw) == sorted(u.draw)
    head_of = {t.page.file: t.id for t in mp.tiles if t.page is not None}
    heads = {head_of[p] for p in pages}
    assert len(heads) >= 2
    assert bases_p[0] == mp.root and len(bases_p) == len(set(bases_p))
    assert not (set(bases_p) - set(up.draw)) & heads  # no head fetched while its page loaded
    # (a base fetched and not drawn is a tile of an earlier cut that the budget gave up when pages grew the tree)
    assert len(set(bases_p) - set(up.draw) - {mp.root}) <= 2
    u0, _, bases0, _ = _stream(server, "whole", cam, StreamOptions(sel, prefetch=False, fill_min_bytes=B // 2,
                                                                     fill_root_bytes=0))
    assert sorted(u0.draw) == sorted(u.draw)
    assert bases0[0] == m.root and len(set(bases0) - set(u.draw) - {m.root}) > 0  # the ancestors between


def test_the_root_is_asked_for_early_only_where_the_cut_may_be_large(root):
    """PreparedSource.open asks for the root's base with the manifest unless the splat budget bounds the cut's bases
    (at the root's bytes a splat) to fill_min_bytes or less; --fill-min-kb sets the threshold (0: always)."""
    from cli.commands import view as view_cmd
    from cli.main import build_parser
    from client_gl.streaming import ViewOptions, root_wanted

    m = load_manifest(root / "whole")
    r = m.tile(m.root)
    per_splat = r.groups["base"].bytes / r.splats
    small = int(StreamOptions.fill_min_bytes / per_splat) - 1
    assert small > r.splats
    assert not root_wanted(m, ViewOptions(max_splats=small))
    assert root_wanted(m, ViewOptions(max_splats=2 * small + 100))
    assert root_wanted(m, ViewOptions())  # no splat budget: the cut may be large
    assert root_wanted(m, ViewOptions(max_splats=small, fill_min_bytes=0))
    assert root_wanted(m, ViewOptions(max_splats=small, fill_levels=False))  # --skip-levels: the root first
    args = build_parser().parse_args(["view", str(root / "whole"), "--headless", "--fill-min-kb", "0"])
    assert view_cmd._options(args).fill_min_bytes == 0
    args = build_parser().parse_args(["view", str(root / "whole"), "--headless"])
    assert view_cmd._options(args).fill_min_bytes == StreamOptions.fill_min_bytes
    assert view_cmd._options(args).fill_root_bytes == StreamOptions.fill_root_bytes
    args = build_parser().parse_args(["view", str(root / "whole"), "--headless", "--fill-root-kb", "256"])
    assert view_cmd._options(args).fill_root_bytes == 256 << 10
    # the root and the cut: the root is wanted early wherever the estimated cut exceeds fill_min_bytes, whatever
    # fill_root_bytes (above it coarse to fine wants the root as well)
    assert root_wanted(m, ViewOptions(max_splats=2 * small + 100, fill_root_bytes=0))
    assert not root_wanted(m, ViewOptions(max_splats=small, fill_root_bytes=1 << 30))
