"""The committed test vectors in format_spec/vectors decode to their expected values."""
import json
import pathlib

import numpy as np
import pytest

from splatstream.decoder import decode_scene
from splatstream.manifest import load_manifest

VECTORS = pathlib.Path(__file__).resolve().parents[1] / "format_spec" / "vectors"


@pytest.mark.parametrize("preset", ["high", "medium", "low", "very-low"])
def test_vector_decodes_to_expected_values(preset):
    if preset in ("low", "very-low"):
        pytest.importorskip("texture2ddecoder")
    scene = VECTORS / preset
    expected = json.loads((scene / "expected.json").read_text())
    m = load_manifest(scene)
    codebook = preset in ("low", "very-low")  # format 1.1: SH codebook
    assert m["version"] == ([1, 1] if codebook else [1, 0]) and ("sh_codebook" in m) == codebook
    assert m["preset"] == preset and m["splats"] == expected["splats"] == 260
    g = decode_scene(scene)
    for field in ("positions", "rotations", "log_scales", "opacities", "sh_dc", "sh_rest"):
        got = getattr(g, field)
        want = np.array(expected[field], np.float32)
        assert got.shape == want.shape, field
        assert np.array_equal(got, want), (preset, field, float(np.abs(got - want).max()))


def test_vectors_verify_their_checksums(tmp_path):
    import shutil

    from splatstream.errors import FormatError

    shutil.copytree(VECTORS / "medium", tmp_path / "s")
    payload = next((tmp_path / "s" / "data").iterdir())
    data = bytearray(payload.read_bytes())
    data[len(data) // 2] ^= 0xFF
    payload.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="checksum mismatch"):
        decode_scene(tmp_path / "s")


def test_newer_major_version_is_rejected(tmp_path):
    import shutil

    from splatstream.errors import FormatError
    from splatstream.manifest import MANIFEST_NAME, pack_manifest

    shutil.copytree(VECTORS / "high", tmp_path / "s")
    m = load_manifest(tmp_path / "s")
    m["version"] = [2, 0]
    (tmp_path / "s" / MANIFEST_NAME).write_bytes(pack_manifest(m))
    with pytest.raises(FormatError, match="major version 2"):
        load_manifest(tmp_path / "s")
    m["version"] = [1, 7]
    m["a_future_key"] = {"x": 1}
    (tmp_path / "s" / MANIFEST_NAME).write_bytes(pack_manifest(m))
    assert len(decode_scene(tmp_path / "s")) == 260
