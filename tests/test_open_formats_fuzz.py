"""Hostile, truncated and corrupted SOG, streamed SOG, glTF/GLB and SPZ inputs: every one gives an InputError
naming the file (never another exception, a hang or an allocation the file cannot justify). Bounded: a fixed
seed and a few dozen mutations per fixture.
"""
from __future__ import annotations

import io
import json
import pathlib
import shutil
import struct
import warnings
import zipfile

import numpy as np
import pytest

from splatstream.errors import InputError
from splatstream.gaussians import Gaussians, normalize_quaternions
from splatstream.io import read_gaussians
from splatstream.writers.glb import glb_bytes
from splatstream.writers.spz import spz_bytes

FIXTURES = pathlib.Path(__file__).parent / "fixtures" / "foreign"
RNG = np.random.default_rng(23)


def small_scene(n: int = 30, degree: int = 1) -> Gaussians:
    k = (0, 3, 8, 15)[degree]
    return Gaussians(RNG.uniform(-1, 1, (n, 3)), normalize_quaternions(RNG.normal(size=(n, 4))),
                     RNG.normal(-4, 1, (n, 3)), RNG.normal(0, 2, n), RNG.normal(0, 1, (n, 3)),
                     RNG.normal(0, 0.2, (n, k, 3)))


def must_fail_cleanly(path: pathlib.Path, match: str | None = None) -> InputError:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(InputError, match=match) as info:
            read_gaussians(path)
    assert str(path) in str(info.value), str(info.value)
    return info.value


def decodes_or_fails_cleanly(path: pathlib.Path) -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            g = read_gaussians(path)
    except InputError:
        return
    assert np.isfinite(g.positions).all() and np.isfinite(g.opacity_logits).all()
    assert np.isfinite(g.log_scales).all() and np.isfinite(g.sh_rest).all()


MUTABLE = ["fruit_drops.sog", "fruit_drops_sub64_sh1.glb", "fruit_drops_sh0_v4.spz"]


@pytest.mark.parametrize("name", MUTABLE)
def test_truncations(tmp_path, name):
    data = (FIXTURES / name).read_bytes()
    for keep in (0, 1, 4, 11, 12, 19, 20, 100, len(data) // 3, len(data) // 2, len(data) - 4, len(data) - 1):
        path = tmp_path / f"cut{keep}_{name}"
        path.write_bytes(data[:keep])
        must_fail_cleanly(path)


@pytest.mark.parametrize("name", MUTABLE)
def test_bit_flips(tmp_path, name):
    data = np.frombuffer((FIXTURES / name).read_bytes(), np.uint8)
    path = tmp_path / name
    for _ in range(40):
        corrupt = data.copy()
        at = RNG.integers(0, len(data), size=int(RNG.integers(1, 4)))
        corrupt[at] ^= (1 << RNG.integers(0, 8, size=len(at))).astype(np.uint8)
        path.write_bytes(corrupt.tobytes())
        decodes_or_fails_cleanly(path)


@pytest.mark.parametrize("fixture, rounds", [("fruit_drops_sh1_sog", 6), ("logo_v1_sub300_sh2", 4)])
def test_bit_flips_in_unbundled_sog(tmp_path, fixture, rounds):
    """Each file of an unbundled SOG (version 2, and version 1) corrupted in turn (meta.json and the WebP planes)."""
    base = FIXTURES / fixture
    for member in sorted(p.name for p in base.iterdir()):
        data = np.frombuffer((base / member).read_bytes(), np.uint8)
        for _ in range(rounds):
            scene = tmp_path / "scene"
            shutil.rmtree(scene, ignore_errors=True)
            shutil.copytree(base, scene)
            corrupt = data.copy()
            at = RNG.integers(0, len(data), size=2)
            corrupt[at] ^= RNG.integers(1, 256, size=2, dtype=np.uint8)
            (scene / member).write_bytes(corrupt.tobytes())
            decodes_or_fails_cleanly(scene)


# ---- SOG header lies ------------------------------------------------------------------------------------------------

def unbundled(tmp_path: pathlib.Path, edit) -> pathlib.Path:
    scene = tmp_path / "scene"
    shutil.rmtree(scene, ignore_errors=True)
    shutil.copytree(FIXTURES / "fruit_drops_sh1_sog", scene)
    meta = json.loads((scene / "meta.json").read_text())
    edit(meta, scene)
    (scene / "meta.json").write_text(json.dumps(meta))
    return scene


def set_path(meta: dict, keys: tuple, value) -> None:
    for key in keys[:-1]:
        meta = meta[key]
    meta[keys[-1]] = value


@pytest.mark.parametrize("keys,value,match", [
    (("count",), 10 ** 15, "count"),
    (("count",), 5000, "expected at least 5000"),
    (("count",), -1, "count"),
    (("count",), "296", "count"),
    (("version",), 3, "expected 2"),
    (("means", "mins"), [0, 0], "means.mins"),
    (("means", "maxs"), [0, "x", 1], "means.maxs"),
    (("scales", "codebook"), [1.0] * 10, "past the 10-entry codebook"),
    (("sh0", "codebook"), [], "sh0.codebook"),
    (("means", "files"), ["means_l.webp", "../means_u.webp"], "not a relative name inside the scene"),
    (("quats", "files"), ["/etc/passwd"], "not a relative name"),
    (("scales", "files"), ["missing.webp"], "does not exist"),
    (("shN", "count"), 2, "past the palette"),
    (("shN", "bands"), 7, "shN.bands"),
    (("shN", "files"), ["shN_labels.webp", "shN_labels.webp"], "width 192"),
])
def test_sog_meta_lies(tmp_path, keys, value, match):
    scene = unbundled(tmp_path, lambda meta, _: set_path(meta, keys, value))
    must_fail_cleanly(scene, match)


def unbundled_v1(tmp_path: pathlib.Path, edit) -> pathlib.Path:
    """The SOG version 1 fixture (300 splats of PlayCanvas's logo with a band-2 SH palette), meta.json edited."""
    scene = tmp_path / "scene_v1"
    shutil.rmtree(scene, ignore_errors=True)
    shutil.copytree(FIXTURES / "logo_v1_sub300_sh2", scene)
    meta = json.loads((scene / "meta.json").read_text())
    edit(meta, scene)
    (scene / "meta.json").write_text(json.dumps(meta))
    return scene


def _relabel(scene: pathlib.Path, label: int) -> None:
    from PIL import Image
    rgba = np.asarray(Image.open(scene / "shN_labels.webp").convert("RGBA")).copy()
    rgba[0, 0, :2] = label & 255, label >> 8
    Image.fromarray(rgba).save(scene / "shN_labels.webp", format="WEBP", lossless=True, exact=True)


def _recentroid(scene: pathlib.Path, width: int) -> None:
    from PIL import Image
    Image.fromarray(np.full((2, width, 4), 255, np.uint8)).save(scene / "shN_centroids.webp", format="WEBP",
                                                               lossless=True)


@pytest.mark.parametrize("edit,match", [
    (lambda m, s: m.update(version=1), "expected 2, or none"),
    (lambda m, s: m["means"].pop("shape"), "means.shape: missing"),
    (lambda m, s: m["means"].update(shape=[]), "means.shape"),
    (lambda m, s: m["means"].update(shape=["300", 3]), r"means.shape\[0\]"),
    (lambda m, s: m["means"].update(shape=[10 ** 15, 3]), r"means.shape\[0\]"),
    (lambda m, s: [m[k]["shape"].__setitem__(0, 5000) for k in ("means", "scales", "quats", "sh0")],
     "expected at least 5000"),
    (lambda m, s: m["means"].update(shape=[5000, 3]), "means.shape says 5000"),
    (lambda m, s: m["sh0"].update(shape=[299, 1, 4]), "sh0.shape"),
    (lambda m, s: m["scales"].update(shape=7), "scales.shape"),
    (lambda m, s: m["scales"].pop("mins"), "scales.mins"),
    (lambda m, s: m["scales"].update(maxs=[1, 2]), "scales.maxs"),
    (lambda m, s: m["sh0"].update(mins=[0, 0, 0]), "sh0.mins"),
    (lambda m, s: m["sh0"].update(maxs=[0, 0, 0, float("nan")]), "sh0.maxs"),
    (lambda m, s: m["quats"].update(encoding="quaternion_xyz"), "quats.encoding"),
    (lambda m, s: m.pop("sh0"), "sh0"),
    (lambda m, s: m["shN"].update(mins=[-1]), "shN.mins"),
    (lambda m, s: m["shN"].pop("maxs"), "shN.maxs"),
    (lambda m, s: m["shN"].update(files=["shN_centroids.webp"]), "shN.files"),
    (lambda m, s: _recentroid(s, 100), "100 texels wide"),
    (lambda m, s: _relabel(s, 128), "past the palette"),
])
def test_sog_version_1_lies(tmp_path, edit, match):
    """A broken SOG version 1 meta.json or plane is a one-line error naming the file and the field."""
    error = must_fail_cleanly(unbundled_v1(tmp_path, edit), match)
    assert "\n" not in str(error)


def test_sog_lossy_and_oversized_textures(tmp_path):
    from PIL import Image

    def lossy(meta, scene):
        rgba = np.asarray(Image.open(scene / "quats.webp").convert("RGBA"))
        Image.fromarray(rgba).save(scene / "quats.webp", format="WEBP", lossless=False, quality=90)

    must_fail_cleanly(unbundled(tmp_path, lossy), "not a lossless WebP")

    def huge(meta, scene):
        # A tiny lossless WebP claiming 16384 x 16384 texels: refused from its header, before decoding.
        data = bytearray((scene / "sh0.webp").read_bytes())
        struct.pack_into("<I", data, 21, (16383 & 0x3FFF) | ((16383 & 0x3FFF) << 14) | (struct.unpack_from(
            "<I", data, 21)[0] & 0xF0000000))
        (scene / "sh0.webp").write_bytes(bytes(data))

    must_fail_cleanly(unbundled(tmp_path, huge), "16384x16384 texels")

    def bad_tag(meta, scene):
        rgba = np.asarray(Image.open(scene / "quats.webp").convert("RGBA")).copy()
        rgba[0, 0, 3] = 17
        Image.fromarray(rgba).save(scene / "quats.webp", format="WEBP", lossless=True)

    must_fail_cleanly(unbundled(tmp_path, bad_tag), "alpha outside 252..255")
    must_fail_cleanly(unbundled(tmp_path, lambda meta, scene: (scene / "sh0.webp").write_bytes(b"RIFF")),
                      "not a lossless WebP")


def test_sog_zip_bomb_and_budget(tmp_path, monkeypatch):
    """A zip member that inflates past the memory budget is refused from its header, before inflating."""
    bomb = tmp_path / "bomb.sog"
    with zipfile.ZipFile(FIXTURES / "fruit_drops.sog") as src, zipfile.ZipFile(bomb, "w") as out:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "sh0.webp":
                data = bytes(32 << 20)
            out.writestr(info.filename, data, compress_type=zipfile.ZIP_DEFLATED)
    assert bomb.stat().st_size < 1 << 20
    monkeypatch.setenv("SPLATSTREAM_MEMORY_BUDGET", str(16 << 20))
    must_fail_cleanly(bomb, "memory budget")
    # The same budget refuses a count whose decoded size would not fit, before any texture is decoded.
    monkeypatch.setenv("SPLATSTREAM_MEMORY_BUDGET", str(20_000))
    must_fail_cleanly(FIXTURES / "fruit_drops.sog", "count")


def test_sog_zip_member_missing_or_corrupt(tmp_path):
    path = tmp_path / "missing.sog"
    with zipfile.ZipFile(FIXTURES / "fruit_drops.sog") as src, zipfile.ZipFile(path, "w") as out:
        for info in src.infolist():
            if info.filename != "quats.webp":
                out.writestr(info, src.read(info))
    must_fail_cleanly(path, "no member 'quats.webp'")
    data = bytearray((FIXTURES / "fruit_drops.sog").read_bytes())
    offset = data.index(b"RIFF") + 40  # inside the first stored WebP: the zip CRC no longer matches
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
    must_fail_cleanly(path, "corrupt")


# ---- streamed SOG lies ----------------------------------------------------------------------------------------

def streamed(tmp_path: pathlib.Path, edit) -> pathlib.Path:
    scene = tmp_path / "lod"
    shutil.rmtree(scene, ignore_errors=True)
    shutil.copytree(FIXTURES / "fruit_drops_lod", scene)
    meta = json.loads((scene / "lod-meta.json").read_text())
    edit(meta)
    (scene / "lod-meta.json").write_text(json.dumps(meta))
    return scene


@pytest.mark.parametrize("edit,match", [
    (lambda m: (m.pop("counts"), m["tree"]["lods"]["0"].update(count=75)), "holds 74 splats"),
    (lambda m: m["tree"]["lods"]["0"].update(offset=10), "holds 74 splats"),
    (lambda m: m["tree"]["lods"]["0"].update(file=7), "tree lods.file"),
    (lambda m: m.update(counts=[70, 37]), "counts"),
    (lambda m: m.update(lodLevels=0), "lodLevels"),
    (lambda m: m.update(version=2), "version"),
    (lambda m: m.update(filenames=["../../0_0/meta.json", "1_0/meta.json"]), "not a relative name"),
    (lambda m: m.update(tree=[]), "tree"),
    (lambda m: m["tree"].update(lods={"9": {"file": 0, "offset": 0, "count": 1}}), "level"),
    (lambda m: m["tree"].update(children={"a": 1}), "children"),
    (lambda m: m.update(environment=5), "environment"),
])
def test_streamed_sog_lies(tmp_path, edit, match):
    must_fail_cleanly(streamed(tmp_path, edit), match)


def test_streamed_sog_deep_nesting(tmp_path):
    scene = tmp_path / "deep"
    scene.mkdir()
    deep = "[" * 100000 + "]" * 100000
    (scene / "lod-meta.json").write_text('{"lodLevels": 1, "filenames": [], "tree": ' + deep + "}")
    must_fail_cleanly(scene, "not valid JSON")


# ---- glTF / GLB lies -------------------------------------------------------------------------------------------------

def split_glb(data: bytes) -> tuple[dict, bytes]:
    json_length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + json_length]), data[28 + json_length:]


def make_glb(gltf: dict, binary: bytes) -> bytes:
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    binary += bytes(-len(binary) % 4)
    return b"".join([struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(binary)),
                     struct.pack("<II", len(text), 0x4E4F534A), text, struct.pack("<II", len(binary), 0x004E4942),
                     binary])


def edited_glb(tmp_path: pathlib.Path, edit, compression: str = "none") -> pathlib.Path:
    gltf, binary = split_glb(glb_bytes(small_scene(), compression))
    edited = edit(gltf, binary)
    binary = edited if isinstance(edited, bytes) else binary
    path = tmp_path / "edited.glb"
    path.write_bytes(make_glb(gltf, binary))
    return path


def attribute_accessor(gltf: dict, name: str) -> dict:
    return gltf["accessors"][gltf["meshes"][0]["primitives"][0]["attributes"][name]]


def primitive(gltf: dict) -> dict:
    return gltf["meshes"][0]["primitives"][0]


@pytest.mark.parametrize("edit,match", [
    (lambda g, b: attribute_accessor(g, "POSITION").update(count=10 ** 9), "do not fit"),
    (lambda g, b: attribute_accessor(g, "KHR_gaussian_splatting:SCALE").update(count=29), "POSITION count"),
    (lambda g, b: g["bufferViews"][0].update(byteLength=10 ** 9), "do not fit its"),
    (lambda g, b: g["bufferViews"][0].update(byteStride=2), "do not fit its"),
    (lambda g, b: attribute_accessor(g, "POSITION").update(byteOffset=3), "do not fit"),
    (lambda g, b: attribute_accessor(g, "KHR_gaussian_splatting:OPACITY").update(componentType=5125),
     "componentType"),
    (lambda g, b: attribute_accessor(g, "KHR_gaussian_splatting:ROTATION").update(type="VEC3"), "expected VEC4"),
    (lambda g, b: attribute_accessor(g, "POSITION").update(sparse={"count": 1}), "sparse"),
    (lambda g, b: primitive(g)["attributes"].pop("KHR_gaussian_splatting:SCALE"), "missing KHR_gaussian_splatting"),
    (lambda g, b: primitive(g)["attributes"].pop("KHR_gaussian_splatting:SH_DEGREE_1_COEF_1"), "partially"),
    (lambda g, b: primitive(g).update(mode=4), "POINTS"),
    (lambda g, b: primitive(g)["extensions"]["KHR_gaussian_splatting"].update(kernel="box"), "kernel"),
    (lambda g, b: g.update(extensionsRequired=["KHR_draco_mesh_compression"]), "not supported"),
    (lambda g, b: primitive(g).update(extensions={}), "no primitive with KHR_gaussian_splatting"),
    (lambda g, b: g["nodes"][0].update(mesh=3), "does not name"),
    (lambda g, b: g["nodes"][0].update(children=[0]), "cycle"),
    (lambda g, b: g["nodes"][0].update(matrix=[1, 2]), "wrong shape"),
    (lambda g, b: g["buffers"][0].update(uri="http://example.com/x.bin"), "only files beside"),
    (lambda g, b: g["asset"].update(version="1.0"), "expected 2.x"),
])
def test_glb_lies(tmp_path, edit, match):
    must_fail_cleanly(edited_glb(tmp_path, edit), match)


def test_glb_invalid_values(tmp_path):
    def poison(gltf, binary):
        data = bytearray(binary)
        view = gltf["bufferViews"][attribute_accessor(gltf, "KHR_gaussian_splatting:OPACITY")["bufferView"]]
        struct.pack_into("<f", data, view["byteOffset"] + 4, 1.5)
        view = gltf["bufferViews"][attribute_accessor(gltf, "POSITION")["bufferView"]]
        struct.pack_into("<f", data, view["byteOffset"] + 24, float("nan"))
        return bytes(data)

    path = edited_glb(tmp_path, poison)
    must_fail_cleanly(path, "2 of 30 splats are invalid .1 non-finite POSITION, 1 OPACITY outside")
    with pytest.warns(UserWarning, match="dropped"):
        assert len(read_gaussians(path, drop_invalid=True)) == 28


@pytest.mark.parametrize("edit,match", [
    (lambda g, b: attribute_accessor(g, "POSITION").update(count=31), "SPZ data holds 30"),
    (lambda g, b: b[:40] + bytes(len(b) - 40), "gzip"),
    (lambda g, b: primitive(g)["extensions"]["KHR_gaussian_splatting"]["extensions"][
        "KHR_gaussian_splatting_compression_spz_2"].pop("bufferView"), "needs a bufferView"),
])
def test_glb_spz_lies(tmp_path, edit, match):
    must_fail_cleanly(edited_glb(tmp_path, edit, "spz"), match)


def test_glb_container_lies(tmp_path):
    data = bytearray(glb_bytes(small_scene()))
    path = tmp_path / "x.glb"
    for offset, value, match in [(4, 1, "version 1"), (8, len(data) + 4, "length"),
                                 (12, 10 ** 8, "declares"), (16, 0x004E4942, "first chunk must be JSON")]:
        edited = bytearray(data)
        struct.pack_into("<I", edited, offset, value)
        path.write_bytes(bytes(edited))
        must_fail_cleanly(path, match)
    must_fail_cleanly(edited_glb(tmp_path, lambda g, b: g["buffers"][0].update(byteLength=10 ** 12)),
                      "byteLength says")
    json_path = tmp_path / "x.gltf"
    json_path.write_text("{" * 50000)
    must_fail_cleanly(json_path)


def test_spz_v4_stream_count_lie(tmp_path):
    data = bytearray(spz_bytes(small_scene(degree=3), 4))
    data[15] = 5
    path = tmp_path / "x.spz"
    path.write_bytes(bytes(data))
    must_fail_cleanly(path, "SH degree 3 have 6 non-empty arrays")


def test_pillow_bomb_limit_is_not_relied_upon():
    """Our own texel bound refuses oversized planes before Pillow is asked (its bomb check only warns)."""
    from splatstream.readers.sog import webp_size

    buffer = io.BytesIO()
    from PIL import Image

    Image.new("RGBA", (8, 4)).save(buffer, format="WEBP", lossless=True)
    assert webp_size(buffer.getvalue()) == (8, 4)
    buffer = io.BytesIO()
    Image.new("RGBA", (8, 4)).save(buffer, format="WEBP", lossless=False)
    assert webp_size(buffer.getvalue()) is None
