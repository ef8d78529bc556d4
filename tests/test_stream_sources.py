"""open_source: what a user types (a URL, a scene directory, a splat file) becomes a scene source, or a one-line
error naming it."""
from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import pytest
from conftest import real

from client_gl.stream.sources import HttpSource, StoreSource, open_source
from splatstream.encode import EncodeOptions
from splatstream.errors import InputError, UsageError
from splatstream.format.manifest import parse_manifest
from splatstream.format.names import sha256_hex
from splatstream.store import DirectoryStore, MemoryStore

REPO = Path(__file__).resolve().parents[1]
VECTOR = REPO / "format_spec" / "vectors" / "low"


@pytest.mark.parametrize("url", [
    "http://h:8000/scenes/city/block-7",
    "http://h:8000/scenes/city/block-7/",
    "http://h:8000/scenes/city/block-7/manifest.msgpack",
    "http://h:8000/scenes/city/block-7/manifest.msgpack?v=3",
])
def test_http_urls_resolve_payloads_against_the_manifest(url):
    src = open_source(url)
    assert isinstance(src, HttpSource)
    assert src.manifest_url == "http://h:8000/scenes/city/block-7/manifest.msgpack" == src.location == src.cache_key
    m = parse_manifest((VECTOR / "manifest.msgpack").read_bytes())
    entry = m.tiles[0].groups["base"]
    assert src.payload_url(entry) == f"http://h:8000/scenes/city/block-7/data/{entry.sha256}.bin"


@pytest.mark.parametrize("spec, error, message", [
    ("ftp://h/scenes/x", UsageError, "ftp://h/scenes/x: unsupported URL scheme 'ftp'"),
    ("http://h:8000/", UsageError, "expected the URL of a scene (http://HOST/scenes/ID), not of the server; the "
                                   "server lists its scenes at http://h:8000/api/scenes"),
    ("http:///scenes/x", UsageError, "expected an http:// or https:// URL of a scene"),
])
def test_bad_urls(spec, error, message):
    with pytest.raises(error) as exc:
        open_source(spec)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_local_paths(tmp_path):
    src = open_source(VECTOR)
    assert isinstance(src, StoreSource) and isinstance(src.store, DirectoryStore) and src.cache_key is None
    src = open_source(VECTOR / "manifest.msgpack")
    assert isinstance(src.store, DirectoryStore) and Path(src.store.path) == VECTOR
    assert asyncio.run(src.fetch_manifest()) == (VECTOR / "manifest.msgpack").read_bytes()

    with pytest.raises(InputError, match=f"^{tmp_path}/nope: no such file or directory \\(expected an http"):
        open_source(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=f"^{tmp_path}/empty: not a scene directory \\(no manifest.msgpack"):
        open_source(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match=f"^{tmp_path}/notes.txt: unrecognised file format"):
        open_source(tmp_path / "notes.txt")


def test_a_splat_file_is_encoded_in_memory_with_progress():
    ply = real("fruit_drops_sh3.ply")
    seen = []
    src = open_source(ply, encode_options=EncodeOptions(max_leaf_splats=1000),
                      progress=lambda stage, fraction: seen.append((stage, fraction)))
    assert isinstance(src, StoreSource) and isinstance(src.store, MemoryStore) and src.location == str(ply)
    m = parse_manifest(asyncio.run(src.fetch_manifest()))
    # 8 leaves of at most 1,000 splats, levels 2x apart up to a root of at most 128 (lod.TreeShape)
    assert m.splats == 4721 and m.lod.enabled and len(m.tiles) == 39
    assert seen[0] == ("read", 0.0) and ("read", 1.0) in seen and seen[-1] == ("encode", 1.0)
    entry = m.tiles[0].groups["base"]
    assert sha256_hex(asyncio.run(src.fetch_payload(entry)))[:32] == entry.sha256  # 1.15: 16 bytes of it


def test_a_local_store_reports_missing_payloads(tmp_path):
    scene = tmp_path / "s"
    shutil.copytree(VECTOR, scene)
    m = parse_manifest((scene / "manifest.msgpack").read_bytes())
    entry = m.tiles[0].groups["base"]
    (scene / entry.file).unlink()
    from client_gl.stream.sources import FetchError

    with pytest.raises(FetchError) as exc:
        asyncio.run(open_source(scene).fetch_payload(entry))
    assert exc.value.kind == "missing" and exc.value.transient
    assert str(exc.value) == f"{scene}/{entry.file}: payload file named in the manifest is missing"


def test_an_unbundled_sog_directory_is_a_splat_file():
    """A directory holding a SOG's meta.json and planes (no manifest.msgpack) is streamed as its meta.json is, as
    `convert`, `render` and `encode` read it (newuser57: `view` refused PlayCanvas's logo directory)."""
    unit = real("flowers_lod/3_0")
    src = open_source(unit, encode_options=EncodeOptions(max_leaf_splats=1000))
    assert isinstance(src, StoreSource) and isinstance(src.store, MemoryStore)
    by_meta = open_source(unit / "meta.json", encode_options=EncodeOptions(max_leaf_splats=1000))
    assert asyncio.run(src.fetch_manifest()) == asyncio.run(by_meta.fetch_manifest())
