"""Bytes verified once where they enter (issue 33, point 4): the fetcher and the disk cache hand on a VerifiedPayload,
which decoding takes without hashing again; raw bytes from any other caller are still verified, with the same
messages; the streaming client parses the manifest once per session."""
from __future__ import annotations

import pathlib
import pickle
import shutil
import time

import pytest

from client_gl.stream.cache import DiskCache
from client_gl.stream.fetch import Fetcher
from client_gl.stream.sources import StoreSource
from splatstream.errors import FormatError
from splatstream.format import container
from splatstream.format.container import VerifiedPayload, verify_payload
from splatstream.format.decode import decode_payload
from splatstream.format.manifest import parse_manifest
from splatstream.store import MemoryStore

VECTOR = pathlib.Path(__file__).resolve().parents[1] / "format_spec" / "vectors" / "medium"


@pytest.fixture()
def hashes(monkeypatch):
    """Counts the payload hashes computed (container.sha256_hex is where verify_payload hashes)."""
    calls = []
    real = container.sha256_hex

    def counting(data):
        calls.append(len(data))
        return real(data)

    monkeypatch.setattr(container, "sha256_hex", counting)
    return calls


@pytest.fixture(scope="module")
def scene():
    manifest = parse_manifest((VECTOR / "manifest.msgpack").read_bytes())
    base = manifest.tile(manifest.root).groups["base"]
    return manifest, base, (VECTOR / base.file).read_bytes()


def test_only_verify_payload_makes_one(scene):
    _, base, data = scene
    with pytest.raises(TypeError, match="made by verify_payload"):
        VerifiedPayload(data, base.sha256)
    payload = verify_payload(data, base, "p")
    assert payload.data is data and payload.matches(base) and len(payload) == base.bytes
    copied = pickle.loads(pickle.dumps(payload))  # to a decode process and back
    assert type(copied) is VerifiedPayload and copied.data == data and copied.matches(base)


def test_decode_hashes_raw_bytes_once_and_verified_bytes_never(scene, hashes):
    _, base, data = scene
    planes = decode_payload(data, base, "base", "p")
    assert hashes == [base.bytes]
    payload = verify_payload(data, base, "p")
    hashes.clear()
    again = decode_payload(payload, base, "base", "p")
    assert hashes == [] and planes.keys() == again.keys()
    assert all((a.layers[0] == b.layers[0]).all() for a, b in zip(planes.values(), again.values(), strict=True))


def test_corrupt_bytes_are_caught_with_the_same_messages(scene):
    manifest, base, data = scene
    corrupt = bytearray(data)
    corrupt[len(corrupt) // 2] ^= 1
    with pytest.raises(FormatError, match=r"^p: sha256: checksum mismatch: the payload is corrupt or was replaced$"):
        decode_payload(bytes(corrupt), base, "base", "p")
    with pytest.raises(FormatError, match=rf"^p: bytes: payload is {len(data) - 1} bytes, the manifest says"):
        decode_payload(data[:-1], base, "base", "p")
    # A VerifiedPayload of another entry is not taken on trust: its bytes are checked against this one.
    other = next(p for t, g, p in manifest.payloads() if p.sha256 != base.sha256)
    wrong = verify_payload((VECTOR / other.file).read_bytes(), other, "q")
    with pytest.raises(FormatError, match=r"^p: (bytes|sha256): "):
        decode_payload(wrong, base, "base", "p")


def test_cache_hands_out_verified_payloads(scene, tmp_path, hashes):
    _, base, data = scene
    cache = DiskCache(tmp_path)
    cache.put(base, data)
    hashes.clear()
    got = cache.get(base)
    assert type(got) is VerifiedPayload and got.data == data and hashes == [base.bytes]
    decode_payload(got, base, "base", "p")
    assert hashes == [base.bytes]  # the cache's check was the only one


def test_the_fetcher_verifies_once_and_parses_the_manifest_once(tmp_path, hashes, monkeypatch):
    shutil.copytree(VECTOR, tmp_path / "s")
    payloads = {p.relative_to(tmp_path / "s").as_posix(): p.read_bytes() for p in (tmp_path / "s" / "data").iterdir()}
    store = MemoryStore((tmp_path / "s" / "manifest.msgpack").read_bytes(), payloads)
    parses = []
    real_parse = parse_manifest

    def counting_parse(*args, **kwargs):
        parses.append(args[1] if len(args) > 1 else "")
        return real_parse(*args, **kwargs)

    monkeypatch.setattr("client_gl.stream.fetch.parse_manifest", counting_parse)
    with Fetcher(StoreSource(store)) as f:
        m = f.manifest()
        assert len(parses) == 1 and f.manifest_bytes == store.manifest_bytes
        wanted = {(t.id if t is not None else None, g): p for t, g, p in m.payloads()}
        f.want([(0.0, k, e) for k, e in wanted.items()])
        got = {}
        deadline = time.monotonic() + 30.0  # a generous bound, not a measurement
        while len(got) < len(wanted) and time.monotonic() < deadline:
            got.update({k: (e, d) for k, e, d in f.done()})
            time.sleep(0.005)
    assert got.keys() == wanted.keys()
    distinct = {e.sha256 for e in wanted.values()}
    assert len(hashes) == len(distinct)  # each distinct payload hashed once, on arrival
    for (tile, group), (entry, payload) in got.items():
        assert type(payload) is VerifiedPayload and payload.matches(entry)
        decode_payload(payload, entry, group, "p", codebook=m.uses_codebook and tile is not None)
    assert len(hashes) == len(distinct) and len(parses) == 1  # decoding hashed nothing, nobody parsed again
