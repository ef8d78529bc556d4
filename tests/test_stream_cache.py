"""The streaming client's disk cache: verified reads, atomic writes, LRU size cap, manifests with ETags, the cache
directory's defaults, and two processes sharing one directory."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from client_gl.stream.cache import CACHE_DIR_ENV, DiskCache, default_cache_dir
from splatstream.errors import UsageError
from splatstream.format.manifest import PayloadEntry
from splatstream.format.names import payload_name

REPO = Path(__file__).resolve().parents[1]


def entry_for(data: bytes) -> PayloadEntry:
    sha = hashlib.sha256(data).hexdigest()
    return PayloadEntry(payload_name(sha), sha, len(data), len(data), len(data), ())


def payload(i: int, size: int = 100_000) -> tuple[PayloadEntry, bytes]:
    data = bytes([i % 251]) * 7 + os.urandom(size - 7)
    return entry_for(data), data


def test_put_get_round_trip_and_verification(tmp_path):
    cache = DiskCache(tmp_path)
    e, data = payload(1)
    assert cache.get(e) is None and not cache.contains(e.sha256)
    assert cache.put(e, data)
    assert cache.contains(e.sha256) and cache.get(e).data == data
    path = Path(cache.payload_path(e.sha256))
    assert path == tmp_path / "payloads" / e.sha256[:2] / f"{e.sha256}.bin"
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
    # Damaged on disk (same size, one bit): deleted, reported as a miss and counted.
    raw = bytearray(path.read_bytes())
    raw[5000] ^= 1
    path.write_bytes(bytes(raw))
    assert cache.get(e) is None and not path.exists() and not cache.contains(e.sha256)
    assert cache.stats.corrupt == 1
    # Truncated on disk.
    cache.put(e, data)
    path.write_bytes(data[:-1])
    assert cache.get(e) is None and not path.exists() and cache.stats.corrupt == 2
    # A new cache over the same directory finds what an earlier one wrote.
    cache.put(e, data)
    assert DiskCache(tmp_path).get(e).data == data


def test_lru_eviction_by_last_use(tmp_path):
    cache = DiskCache(tmp_path, max_bytes=450_000)  # holds four 100 kB payloads; evicts down to 405 kB
    items = [payload(i) for i in range(5)]
    for e, data in items[:4]:
        assert cache.put(e, data)
        time.sleep(0.01)  # distinct mtimes
    assert cache.get(items[0][0]).data == items[0][1]  # used again: now the most recent
    time.sleep(0.01)
    assert cache.put(*items[4])  # 500 kB > cap: the least recently used (item 1) goes
    present = [i for i, (e, _) in enumerate(items) if Path(cache.payload_path(e.sha256)).exists()]
    assert present == [0, 2, 3, 4]
    assert cache.stats.evicted == 1 and cache.stats.evicted_bytes == 100_000
    assert cache.size_bytes() == 400_000
    # A payload larger than the cap is not cached at all.
    big_e, big = payload(9, 500_000)
    assert not cache.put(big_e, big) and cache.get(big_e) is None


def test_eviction_counts_files_of_other_processes(tmp_path):
    a = DiskCache(tmp_path, max_bytes=450_000)
    b = DiskCache(tmp_path, max_bytes=450_000)
    items = [payload(i) for i in range(5)]
    for e, data in items[:2]:
        a.put(e, data)
        time.sleep(0.01)
    for e, data in items[2:5]:  # b did not know a's files, but rescans before evicting
        b.put(e, data)
        time.sleep(0.01)
    assert b.size_bytes() == 400_000
    assert not Path(b.payload_path(items[0][0].sha256)).exists()


def test_manifest_cache_with_etag(tmp_path):
    cache = DiskCache(tmp_path)
    url = "http://127.0.0.1:8000/scenes/garden/manifest.msgpack"
    assert cache.get_manifest(url) is None
    assert cache.put_manifest(url, b"\x81\xa4name\xa6garden", '"abc"')
    got = cache.get_manifest(url)
    assert got.data == b"\x81\xa4name\xa6garden" and got.etag == '"abc"'
    assert cache.get_manifest(url + "x") is None
    cache.put_manifest(url, b"new", None)  # replaced
    assert cache.get_manifest(url).data == b"new" and cache.get_manifest(url).etag is None
    path = Path(cache.manifest_path(url))
    path.write_bytes(path.read_bytes()[:-2])  # damaged record: deleted
    assert cache.get_manifest(url) is None and not path.exists() and cache.stats.corrupt == 1


def test_cache_directory_defaults(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_DIR_ENV, str(tmp_path / "env"))
    assert default_cache_dir() == str(tmp_path / "env")
    assert DiskCache().directory == str(tmp_path / "env") and (tmp_path / "env" / "payloads").is_dir()
    assert DiskCache(tmp_path / "arg").directory == str(tmp_path / "arg")  # the argument wins over the variable
    monkeypatch.delenv(CACHE_DIR_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert default_cache_dir() == str(tmp_path / "xdg" / "splatstream")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(UsageError, match=f"{blocker}/c: cannot create the cache directory"):
        DiskCache(blocker / "c")


WORKER = r"""
import hashlib, os, random, sys
from client_gl.stream.cache import DiskCache
from splatstream.format.manifest import PayloadEntry
from splatstream.format.names import payload_name

rng = random.Random(int(sys.argv[2]))
blobs = [bytes([i]) * 50_000 + bytes(range(256)) * 40 for i in range(12)]
entries = [PayloadEntry(payload_name(hashlib.sha256(b).hexdigest()), hashlib.sha256(b).hexdigest(), len(b), 0, 0, ())
           for b in blobs]
cache = DiskCache(sys.argv[1], max_bytes=300_000)  # room for about 5 of 12: constant eviction
hits = 0
for _ in range(300):
    i = rng.randrange(12)
    got = cache.get(entries[i])
    if got is None:
        cache.put(entries[i], blobs[i])
    else:
        assert got.data == blobs[i], "wrong bytes"
        hits += 1
print(hits, cache.stats.corrupt)
"""


def test_two_processes_share_one_cache(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(tmp_path), str(seed)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env) for seed in (1, 2)]
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err
        hits, corrupt = map(int, out.split())
        assert hits > 0 and corrupt == 0  # every hit had the right bytes; no torn file was ever seen
    leftovers = [p for p in (tmp_path / "payloads").rglob("*") if p.is_file() and p.name.startswith(".tmp-")]
    assert leftovers == []
    assert DiskCache(tmp_path, max_bytes=300_000).size_bytes() <= 300_000 + 2 * 61_000  # a put of each beyond the cap
