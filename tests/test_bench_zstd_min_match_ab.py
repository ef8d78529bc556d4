"""bench/zstd_min_match_ab.py (issue 32, zmatch): its "joined" variant takes the preset's shortest match on the
payloads whose blocks may be joined only, and the library's compressor is back after it encodes."""
import zstandard
from conftest import load_bench

from splatstream.format import container

Z = load_bench("zstd_min_match_ab")


def test_joined_only_keeps_the_shortest_match_up_to_merge_max_raw(monkeypatch):
    calls = []
    monkeypatch.setattr(Z, "_COMPRESSOR", lambda *args: calls.append(args))
    Z._joined_only(16, -1, container.MERGE_MAX_RAW, 6)
    Z._joined_only(16, 0, container.MERGE_MAX_RAW + 1, 6)
    assert calls == [(16, -1, container.MERGE_MAX_RAW, 6), (16, 0, container.MERGE_MAX_RAW + 1, 0)]


def test_the_compressors_frames_decode_the_same():
    data = bytes(range(256)) * 256
    for raw in (container.MERGE_MAX_RAW, container.MERGE_MAX_RAW + 1):
        cctx = Z._joined_only(16, 0, raw, 6)
        assert zstandard.ZstdDecompressor().decompress(cctx.compress(data)) == data


def test_encode_both_restores_the_compressor(monkeypatch):
    seen = []

    def fake_case(store):
        seen.append(container._compressor)
        return store

    monkeypatch.setattr(Z.dq, "Case", fake_case)
    monkeypatch.setattr(Z, "encode_in_memory", lambda g, opts: opts)
    cases = Z.encode_both(None, "medium-low-9bit", lod=False)
    assert list(cases) == ["every", "joined"]
    assert seen == [Z._COMPRESSOR, Z._joined_only]
    assert container._compressor is Z._COMPRESSOR
    assert not cases["joined"].lod and cases["joined"].preset == "medium-low-9bit"
