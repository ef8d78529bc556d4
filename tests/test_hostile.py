"""Issue 37, the short network campaign: every mode of the hostile server (tests/hostile_server.py) against the
library's fetcher, and the findings against `view --headless` (bench/fuzz.py --network runs the long one and
measures it). Each ends with the right bytes (or the clean picture), or with one line naming the URL and the
problem; the disk cache holds only verified payloads afterwards. No assertion depends on timing: the bounds are
generous deadlines of the run itself."""
from __future__ import annotations

import hashlib
import re
import sys
import time
from pathlib import Path

import pytest
from conftest import real, run_cli
from hostile_server import HostileServer, Mode, texture_bomb_scene, undecodable_scene

from client_gl.stream.cache import DiskCache
from client_gl.stream.fetch import Fetcher, RetryPolicy
from client_gl.stream.sources import FetchError, HttpSource
from splatstream.format.names import digest_matches, payload_name
from splatstream.store import load_manifest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    from splatstream.encode import encode_file

    work = tmp_path_factory.mktemp("hostile")
    src = real("fruit_drops_sh3.ply")  # bundled
    encode_file(src, work / "root" / "s", max_leaf_splats=1000)
    encode_file(src, work / "s2", max_leaf_splats=300)  # other tiles, other payloads
    undecodable_scene(work / "root" / "s", work / "root" / "s_bad")
    texture_bomb_scene(work / "root" / "s", work / "root" / "s_tex")
    return work


@pytest.fixture
def server(root):
    with HostileServer(root / "root") as srv:
        yield srv


def cache_verified(cache: Path) -> bool:
    """Every cached payload's bytes hash to its name: the whole SHA-256, or its 16-byte prefix (format 1.15)."""
    return all(digest_matches(hashlib.sha256(f.read_bytes()).hexdigest(), f.stem) for f in cache.rglob("*.bin"))


def fetch_all(url: str, cache: Path, budget_s: float = 30.0, until_failing: bool = False,
              manifest_timeout_s: float = 3.0):
    """(payloads delivered by key, the payloads wanted, failing() at the end): once every payload arrived, or
    (until_failing) once one has failed, or at the budget (a generous bound, not a measurement); FetchError from
    the manifest."""
    f = Fetcher(HttpSource(url), cache=DiskCache(cache), request_timeout_s=2.0, stall_timeout_s=0.5,
                request_deadline_s=2.0, manifest_timeout_s=manifest_timeout_s,
                retry=RetryPolicy(base_s=0.02, cap_s=0.2), seed=0).start()
    try:
        m = f.manifest()
        wanted = {(t.id if t is not None else None, g): p for t, g, p in m.payloads()}
        f.want([(0.0, k, e) for k, e in wanted.items()])
        got = {}
        deadline = time.monotonic() + budget_s
        while len(got) < len(wanted) and time.monotonic() < deadline:
            for key, _, body in f.done():
                got[key] = body
            if until_failing and f.failing():
                break
            time.sleep(0.01)
        return got, wanted, f.failing()
    finally:
        f.close()


TRANSIENT = [Mode("reset", "manifest", 1), Mode("truncate", "manifest", 1), Mode("503", "manifest", 2),
             Mode("gzip", "manifest"), Mode("stall", "root", 1), Mode("reset", "payload", 1),
             Mode("truncate", "payload", 1), Mode("wrong", "payload", 1), Mode("gzip", "payload"),
             Mode("500", "payload", 1), Mode("503", "payload", 2), Mode("404", "payload", 1)]


@pytest.mark.parametrize("mode", TRANSIENT, ids=lambda m: f"{m.fault}-{m.target}-{m.times}")
def test_transient_faults_deliver_exact_bytes(root, server, mode, tmp_path):
    server.set_mode(mode)
    got, wanted, _ = fetch_all(server.url("s"), tmp_path / "c")
    assert set(got) == set(wanted)
    for key, entry in wanted.items():
        assert got[key].data == (root / "root" / "s" / entry.file).read_bytes(), key
    assert cache_verified(tmp_path / "c")


PERMANENT = [("drip", "not complete within 2 s"), ("stall", "no data for 0.5 s"), ("reset", "cut short"),
             ("truncate", "cut short"), ("wrong", "checksum"), ("500", "server error 500"),
             ("404", "is not on the server (404"), ("redirect_loop", "too many redirects")]


@pytest.mark.parametrize("fault, problem", PERMANENT)
def test_a_payload_that_fails_for_good_is_named(root, server, fault, problem, tmp_path):
    server.set_mode(Mode(fault, "root", drip_s=0.2))
    got, wanted, failing = fetch_all(server.url("s"), tmp_path / "c", until_failing=True)
    assert len(got) < len(wanted) and failing
    key, message, attempts = failing[0]
    assert message.startswith(server.url("s") + "/data/") and problem in message and "\n" not in message, message
    assert attempts >= 1 and key not in got
    assert cache_verified(tmp_path / "c")


MANIFEST_ERRORS = [("drip", "no complete manifest within 3 s"), ("stall", "no complete manifest within 3 s"),
                   ("500", "server error 500"), ("404", "no such scene"), ("redirect_loop", "too many redirects"),
                   ("huge_manifest", "expected at most"), ("manifest_bomb", "would unpack into about"),
                   ("nested_manifest", "not a splatstream manifest")]


@pytest.mark.parametrize("fault, problem", MANIFEST_ERRORS)
def test_manifest_faults_end_with_one_named_line(server, fault, problem, tmp_path):
    server.set_mode(Mode(fault, "manifest", drip_s=0.2))
    # The manifest's 3 s timeout is what the drip and stall cases test, and what ends the retried 500s; the bomb and
    # the nesting must be named for what they are however slowly a loaded machine moves and parses their 64 MiB (at
    # load 4 the bomb once took over 3 s and was reported as a timeout), so they get a bound no load reaches.
    timeout_s = 120.0 if fault in ("manifest_bomb", "nested_manifest") else 3.0
    t0 = time.monotonic()
    with pytest.raises(FetchError) as exc:
        fetch_all(server.url("s"), tmp_path / "c", manifest_timeout_s=timeout_s)
    assert time.monotonic() - t0 < 2 * timeout_s + 60  # bounded by the manifest timeout; never a hang
    msg = str(exc.value)
    assert msg.startswith(server.url("s") + "/manifest.msgpack: ") and problem in msg and "\n" not in msg, msg


# -- the findings under `view --headless` -------------------------------------------------------------------------


def view(url: str, tmp_path: Path, *args: str):
    env_cache = tmp_path / "cache"
    import os
    import subprocess

    env = dict(os.environ, SPLATSTREAM_CACHE_DIR=str(env_cache))
    return subprocess.run([sys.executable, "-m", "cli", "view", url, "--headless", "--size", "160x120",
                           "--gpu-mem-mb", "16", *args], capture_output=True, text=True, env=env,
                          stdin=subprocess.DEVNULL, timeout=300)


def _headless_available():
    pytest.importorskip("moderngl")
    from client_gl.offscreen import GLUnavailableError, shared_context

    try:
        shared_context()
    except GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")


def test_view_names_a_payload_that_does_not_decode_and_keeps_it_out_of_the_cache(root, server, tmp_path):
    _headless_available()
    r = view(server.url("s_bad"), tmp_path, "--timeout", "60")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1, r.stderr
    assert lines[-2].startswith(f"view: {server.url('s_bad')}/data/") and "does not decode" in lines[-2], r.stderr
    assert "Traceback" not in r.stderr
    src = root / "root" / "s"  # its files named by 16 bytes of their SHA-256 (format 1.15), s_bad's by all 32
    bad = next(e.file for _, _, e in load_manifest(root / "root" / "s_bad").payloads()
               if not (src / e.file).exists() and not (src / payload_name(e.sha256[:32])).exists())
    cached = {f.name for f in (tmp_path / "cache").rglob("*.bin")}
    assert cached and bad.split("/")[-1] not in cached and cache_verified(tmp_path / "cache")
    # fetched once: not read again and again
    assert len([p for p, _ in server.requests(bad)]) == 1


def test_view_continues_with_a_scene_re_encoded_mid_stream(root, server, tmp_path):
    _headless_available()
    server.set_mode(Mode("reencode", times=1, alt=str(root / "s2")))  # swapped after the first payload
    r = view(server.url("s"), tmp_path, "--timeout", "60", "--screenshot", str(tmp_path / "a.png"), "--size",
             "640x480", "--max-sse", "0.5")
    assert r.returncode == 0, r.stderr
    log = server.requests("/data/")
    assert any(status == 404 for _, status in log), log  # old payloads were asked for after the swap
    # and the switch is said (the view rebuilt its pool and fetched again without a word: newuser60)
    said = [ln for ln in r.stderr.splitlines() if "the scene was re-encoded on the server" in ln]
    assert len(said) == 1 and said[0].startswith(f"view: {server.url('s')}/manifest.msgpack: "), r.stderr
    assert said[0].endswith(" splats, preset medium)"), said[0]
    clean = HostileServer(root / "root")
    (root / "root" / "s2").exists() or (root / "root" / "s2").symlink_to(root / "s2")
    with clean:
        r2 = view(clean.url("s2"), tmp_path / "clean", "--timeout", "60", "--screenshot", str(tmp_path / "b.png"),
                  "--size", "640x480", "--max-sse", "0.5")
    assert r2.returncode == 0, r2.stderr
    from fuzz import _image_psnr

    assert _image_psnr(tmp_path / "a.png", tmp_path / "b.png") >= 40


def test_view_names_a_permanent_payload_failure_at_the_timeout(server, tmp_path):
    _headless_available()
    server.set_mode(Mode("404", "root"))
    r = view(server.url("s"), tmp_path, "--timeout", "4")
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    last = lines[-2]
    assert last.startswith(f"view: not converged after 4 s: {server.url('s')}/data/") and "404" in last, r.stderr
    # and said once as it happened, not only at the timeout (a missing payload: 120 s of 'streaming' lines before)
    said = [ln for ln in lines if ln.endswith("; retrying until --timeout 4 s")]
    assert len(said) == 1 and said[0].startswith(f"view: {server.url('s')}/data/") and "404" in said[0], r.stderr
    assert lines.index(said[0]) < len(lines) - 2


def test_view_refuses_a_tile_declaring_a_huge_texture(server, tmp_path):
    _headless_available()
    r = view(server.url("s_tex"), tmp_path, "--timeout", "60")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(
        f"splatstream view: error: {server.url('s_tex')}/manifest.msgpack: tiles[")
    assert "texture 8192x8192" in r.stderr


def test_view_refuses_a_gpu_budget_below_the_root_tile(server, tmp_path):
    _headless_available()
    r = run_cli("view", server.url("s"), "--headless", "--gpu-mem-mb", "0.01", "--timeout", "60")
    assert r.returncode == 2, r.stderr
    assert "--gpu-mem-mb 0.01: too small for this scene" in r.stderr and "give --gpu-mem-mb" in r.stderr
    # the bytes with thousands separators, as the CLI writes counts elsewhere ('33800 bytes' before: newuser64)
    need = re.search(r"its root tile alone takes ([\d,]+) bytes", r.stderr)
    assert need is not None, r.stderr
    assert need.group(1) == f"{int(need.group(1).replace(',', '')):,}" and "," in need.group(1), r.stderr
