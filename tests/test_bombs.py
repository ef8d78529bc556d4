"""Issue 37, bombs: inputs small on disk that once unpacked or decompressed into gigabytes are refused before
anything large is built, naming the file and the field. (bench/fuzz.py --network measures the time and peak
memory of each under the CLI; here only the outcome is checked, never a time.)"""
from __future__ import annotations

import json
import shutil
import struct
import zipfile
from pathlib import Path

import msgpack
import pytest
from conftest import read_manifest_dict, write_manifest_dict

from splatstream.errors import FormatError, InputError
from splatstream.format.manifest import MAX_MANIFEST_BYTES, max_blocks, parse_manifest
from splatstream.io import read_gaussians
from splatstream.store import load_manifest

REPO = Path(__file__).resolve().parents[1]
FOREIGN = REPO / "tests" / "fixtures" / "foreign"
VECTOR = REPO / "format_spec" / "vectors" / "low"


@pytest.mark.parametrize("value, problem", [
    ([{}] * (1 << 20), "expected a map at the top"),
    ({"format": "splatstream", "tiles": [{}] * (12 << 20)}, "would unpack into about"),
    ({"format": "splatstream", "tiles": [[[[]]]] * (4 << 20)}, "would unpack into about"),
    ({"format": "splatstream", "x": ["ab"] * (12 << 20)}, "would unpack into about"),
])
def test_msgpack_bombs_are_refused_before_they_are_unpacked(value, problem):
    """A 64 MiB manifest holding one array of empty maps reached 4.9 GB before 'checksum: missing'."""
    raw = msgpack.packb(value)
    assert len(raw) <= MAX_MANIFEST_BYTES
    with pytest.raises(FormatError, match=f"^https://h/scenes/x/manifest.msgpack: .*{problem}"):
        parse_manifest(raw, "https://h/scenes/x/manifest.msgpack")


def test_a_texture_larger_than_its_chunks_need_is_refused(tmp_path):
    """1-splat leaves declaring 8192x8192 textures (sharing one small zstd payload that decompresses to 1 GiB)
    were decoded and drawn: a texture may have at most max_blocks(chunks) blocks (format.md 4.1)."""
    scene = tmp_path / "s"
    shutil.copytree(VECTOR, scene, ignore=shutil.ignore_patterns("expected.json"))
    load_manifest(scene)  # the vector itself is fine
    m = read_manifest_dict(scene)
    tile = min(m["tiles"], key=lambda t: t["splats"])
    chunks = -(-tile["splats"] // 256)
    section = next(s for s in tile["groups"]["base"]["sections"] if s["kind"] == "texels")
    section["width"] = section["height"] = 8192
    write_manifest_dict(scene, m)
    with pytest.raises(FormatError, match=rf"texture 8192x8192 has 262144 blocks of 16x16 texels for {chunks} "
                                          rf"chunks \(at most {max_blocks(chunks)}"):
        load_manifest(scene)
    assert max_blocks(1) == 130 and max_blocks(1000) == 2128


def _sog_with_meta(path: Path, write_meta) -> None:
    src = zipfile.ZipFile(FOREIGN / "fruit_drops.sog")
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name in src.namelist():
            if name == "meta.json":
                write_meta(z)
            else:
                z.writestr(name, src.read(name))


def test_a_bundled_sog_whose_meta_json_inflates_to_gigabytes_is_refused(tmp_path):
    """meta.json inflating to 3.5 GiB was read whole: a JSON member is at most MAX_JSON_BYTES, checked on the
    declared size and again as it is inflated (in pieces)."""
    def big(z):
        with z.open("meta.json", "w", force_zip64=True) as f:
            f.write(b"{")
            for _ in range(5):
                f.write(b" " * (1 << 24))
            f.write(b"}")

    path = tmp_path / "bomb.sog"
    _sog_with_meta(path, big)
    with pytest.raises(InputError, match=r"bomb.sog: SOG meta.json: member 'meta.json' declares 83886082 bytes"):
        read_gaussians(path)



def test_gltf_spz_and_ply_bombs_are_refused(tmp_path):
    """Declared sizes far beyond the file: refused from the header, before any allocation."""
    # GLB: a buffer claiming 4 GiB in a small file
    data = (FOREIGN / "fruit_drops_sub64_sh1.glb").read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    doc["buffers"][0]["byteLength"] = 4 << 30
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + json_len:]
    glb = tmp_path / "b.glb"
    glb.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    with pytest.raises(InputError, match=r"b.glb: buffers\[0\]: holds \d+ bytes, byteLength says 4294967296"):
        read_gaussians(glb)
    # PLY: a billion vertices declared in a small file
    ply = tmp_path / "b.ply"
    src = (FOREIGN / "fruit_drops_sub64.ply").read_bytes()
    assert b"element vertex 74\n" in src
    ply.write_bytes(src.replace(b"element vertex 74\n", b"element vertex 1000000000\n", 1))
    with pytest.raises(InputError, match="b.ply"):
        read_gaussians(ply)
