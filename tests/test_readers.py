"""Foreign-format readers against the reference tool's own decoding (splat-transform 2.7.1, which embeds the
Niantic SPZ library), the .splat writer, content sniffing, and hostile / truncated / corrupted inputs.

The fixtures and how they were made: tests/fixtures/foreign/README.md.
"""
from __future__ import annotations

import gzip
import json
import pathlib
import shutil
import struct
import warnings
import zipfile

import numpy as np
import pytest
from conftest import real, with_shared

from splatstream.errors import InputError
from splatstream.gaussians import SH_C0, Gaussians, logit, sigmoid
from splatstream.io import read_gaussians, sniff_format, write_gaussians
from splatstream.ply import read_elements
from splatstream.readers.splat import read_splat, splat_records

FIXTURES = pathlib.Path(__file__).parent / "fixtures" / "foreign"
SOURCE_PLY = FIXTURES / "fruit_drops_sub16.ply"
SPZ_FIXTURES = ["fruit_drops_v2.spz", "fruit_drops_v3.spz", "fruit_drops_v4.spz", "fruit_drops_sh1_v4.spz"]
FOREIGN_FIXTURES = SPZ_FIXTURES + ["fruit_drops.compressed.ply"]
FIXTURE_COUNT = 296


def tool_output(path: pathlib.Path) -> dict[str, np.ndarray]:
    """The reference tool's PLY output as arrays in our conventions (its opacities may be +-inf, so the
    PLY is read raw rather than through the 3DGS reader)."""
    _, elements = read_elements(path)
    v = elements["vertex"]

    def cols(names: list[str]) -> np.ndarray:
        return np.stack([v[n].astype(np.float64) for n in names], axis=1)

    k = sum(1 for n in v.dtype.names if n.startswith("f_rest_")) // 3
    rest = cols([f"f_rest_{i}" for i in range(3 * k)]).reshape(len(v), 3, k).transpose(0, 2, 1) if k \
        else np.zeros((len(v), 0, 3))
    return {"positions": cols(["x", "y", "z"]), "log_scales": cols(["scale_0", "scale_1", "scale_2"]),
            "sh_dc": cols(["f_dc_0", "f_dc_1", "f_dc_2"]), "opacity_logits": v["opacity"].astype(np.float64),
            "rotations": cols(["rot_0", "rot_1", "rot_2", "rot_3"]), "sh_rest": rest}


def same_sign(q: np.ndarray) -> np.ndarray:
    """Unit quaternions with w >= 0 (q and -q are the same rotation)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def assert_matches(g: Gaussians, ref: dict[str, np.ndarray], rotation_atol: float = 1e-6) -> dict[str, float]:
    """Per-attribute max |ours - reference|; the reference decodes the same quantized values, so the bounds
    are float rounding, not quantization steps."""
    errors = {
        "positions": np.abs(g.positions - ref["positions"]).max(),
        "log_scales": np.abs(g.log_scales - ref["log_scales"]).max(),
        "sh_dc": np.abs(g.sh_dc - ref["sh_dc"]).max(),
        # Compared after the sigmoid: the tool keeps +-inf logits for alpha bytes 0 and 255, we clamp.
        "opacity": np.abs(g.opacities - 1.0 / (1.0 + np.exp(-ref["opacity_logits"]))).max(),
        "rotations": np.abs(g.rotations - same_sign(ref["rotations"])).max(),
        "sh_rest": np.abs(g.sh_rest - ref["sh_rest"]).max() if g.sh_rest.size else 0.0,
    }
    bounds = {"positions": 1e-6, "log_scales": 1e-6, "sh_dc": 1e-5, "opacity": 2e-6, "rotations": rotation_atol,
              "sh_rest": 1e-6}
    for name, err in errors.items():
        assert err <= bounds[name], f"{name}: max error {err} > {bounds[name]}"
    return errors


@pytest.mark.parametrize("name", FOREIGN_FIXTURES)
def test_fixture_matches_tool_ply_output(name):
    g = read_gaussians(FIXTURES / name)
    ref = tool_output(FIXTURES / f"{name}.tool.ply")
    assert len(g) == len(ref["positions"]) == FIXTURE_COUNT
    assert g.sh_rest.shape[1] == ref["sh_rest"].shape[1] == (3 if "sh1" in name else 15)
    assert_matches(g, ref)


@pytest.mark.parametrize("name,bands", [("logo_v1_sub300", 0), ("logo_v1_sub300_sh2", 2)])
def test_sog_version_1_matches_tool_ply_output(tmp_path, name, bands):
    """SOG version 1 (no `version`, per-channel mins/maxs): 300 splats cut from PlayCanvas's logo, the second with
    a made-up band-2 SH palette (tests/fixtures/foreign/make_sog_v1.py), against splat-transform's readSogV1.
    Unbundled (the meta.json or its directory) and bundled as a .sog zip, as a v2 scene can be."""
    ref = tool_output(FIXTURES / f"{name}.tool.ply")
    assert ref["sh_rest"].shape[1] == (0, 3, 8, 15)[bands] and (not bands or np.abs(ref["sh_rest"]).max() > 0.3)
    bundled = tmp_path / f"{name}.sog"
    with zipfile.ZipFile(bundled, "w") as archive:
        for member in sorted((FIXTURES / name).iterdir()):
            archive.write(member, member.name)
    for path in (FIXTURES / name / "meta.json", FIXTURES / name, bundled):
        g = read_gaussians(path)
        assert len(g) == len(ref["positions"]) == 300 and g.sh_rest.shape == ref["sh_rest"].shape
        errors = assert_matches(g, ref)
        # The same float64 lerps as the tool's: bit-identical but for our normalised rotations.
        assert errors["positions"] == errors["log_scales"] == errors["sh_dc"] == errors["sh_rest"] == 0
        assert np.abs(g.opacity_logits - ref["opacity_logits"]).max() == 0


def test_sog_version_1_unit_of_a_streamed_sog(tmp_path):
    """A streamed SOG whose units are version 1 (lod-meta.json names a unit's meta.json): its rows as the unit's."""
    shutil.copytree(FIXTURES / "logo_v1_sub300", tmp_path / "0_0")
    tree = {"bound": {"min": [-2, -3, -1], "max": [2, 1, 1]},
            "children": [{"lods": {"0": {"file": 0, "offset": 0, "count": 120}}},
                         {"lods": {"0": {"file": 0, "offset": 120, "count": 180}}}]}
    (tmp_path / "lod-meta.json").write_text(json.dumps({"lodLevels": 1, "filenames": ["0_0/meta.json"],
                                                        "counts": [300], "tree": tree}))
    g = read_gaussians(tmp_path / "lod-meta.json")
    assert len(g) == 300
    assert_matches(g, tool_output(FIXTURES / "logo_v1_sub300.tool.ply"))


@pytest.mark.parametrize("name", ["fruit_drops_v2.spz", "fruit_drops_v3.spz", "fruit_drops_v4.spz"])
def test_spz_is_original_within_quantization(name):
    """SPZ was written from SOURCE_PLY: decoding (including RUB -> RDF) gives it back within each step."""
    g = read_gaussians(FIXTURES / name)
    src = read_gaussians(SOURCE_PLY)
    assert np.abs(g.positions - src.positions).max() <= 0.5 / 4096 + 1e-6  # 12 fractional bits
    in_range = (src.log_scales > -10) & (src.log_scales < 255 / 16 - 10)  # 8-bit log scale covers [-10, 5.94]
    assert np.abs(g.log_scales - src.log_scales)[in_range].max() <= 0.5 / 16 + 1e-6
    assert np.abs(g.sh_dc - src.sh_dc).max() <= 0.5 / (0.15 * 255) + 1e-4
    assert np.abs(g.opacities - src.opacities).max() <= 0.5 / 255 + 1e-6
    # Rotation error as the angle between the quaternions: 8-bit xyz (v2) vs 9-bit smallest three (v3+).
    angle = 2 * np.arccos(np.clip(np.abs((g.rotations * src.rotations).sum(axis=1)), 0, 1))
    assert angle.max() <= (0.05 if "v2" in name else 0.006)
    # SH bands: x * 128 rounded, then snapped to buckets of 8 (band 1, 5 bits) or 16 (bands 2-3, 4 bits) steps
    # of 1/128: error at most (bucket / 2 + 0.5) / 128 inside the clamped range [-1, 1].
    clipped = np.clip(src.sh_rest, -1, 127 / 128)
    assert np.abs(g.sh_rest[:, :3] - clipped[:, :3]).max() <= 4.5 / 128 + 1e-6
    assert np.abs(g.sh_rest[:, 3:] - clipped[:, 3:]).max() <= 8.5 / 128 + 1e-6


def test_compressed_ply_is_original_within_quantization():
    """The tool reorders splats (Morton order) before chunking: match them back by position, then compare."""
    g = read_gaussians(FIXTURES / "fruit_drops.compressed.ply")
    src = read_gaussians(SOURCE_PLY)
    distance = np.linalg.norm(g.positions[:, None] - src.positions[None], axis=2)
    match = distance.argmin(axis=1)
    assert len(set(match.tolist())) == len(g) == len(src)  # a permutation
    src = src.subset(match)
    assert distance.min(axis=1).max() < 1e-3  # 11/10/11-bit positions inside chunks a few cm wide
    angle = 2 * np.arccos(np.clip(np.abs((g.rotations * src.rotations).sum(axis=1)), 0, 1))
    assert angle.max() < 0.005  # 10-bit smallest three
    assert np.abs(g.opacities - src.opacities).max() <= 0.5 / 255 + 1e-6
    assert np.abs(g.sh_rest - np.clip(src.sh_rest, -4, 4)).max() <= 4 / 256 + 1e-6  # 8 bits over [-4, 4]


def real_samples(name: str) -> tuple[int, np.ndarray, dict[str, np.ndarray]]:
    data = np.load(FIXTURES / "real_tool_samples.npz")
    v = data[f"{name}_values"].astype(np.float64)
    ref = {"positions": v[:, 0:3], "log_scales": v[:, 3:6], "sh_dc": v[:, 6:9], "opacity_logits": v[:, 9],
           "rotations": v[:, 10:14], "sh_rest": np.zeros((len(v), 0, 3))}
    return int(data[f"{name}_count"]), data[f"{name}_rows"], ref


@pytest.mark.parametrize("file,name,count", with_shared([("guitar.compressed.ply", "guitar", 90854),
                                                         ("biker.compressed.ply", "biker", 152746)]))
def test_real_compressed_ply_matches_tool(file, name, count):
    path = real(file)
    assert sniff_format(path) == "compressed_ply"
    g = read_gaussians(path)
    tool_count, rows, ref = real_samples(name)
    assert len(g) == tool_count == count
    assert g.sh_degree == 0
    assert_matches(g.subset(rows), ref)


def test_real_splat_matches_tool():
    path = real("winter_fountain.splat")
    assert sniff_format(path) == "splat"
    g = read_gaussians(path)
    tool_count, rows, ref = real_samples("winter_fountain")
    assert len(g) == tool_count == 93713
    # Rotation bytes are q * 128 + 128 (antimatter15's writer): we invert exactly, (b - 128) / 128; the tool
    # decodes b / 255 * 2 - 1, which differs by less than one byte step.
    assert_matches(g.subset(rows), ref, rotation_atol=1 / 128)


def test_splat_writer_round_trip(tmp_path):
    path = real("winter_fountain_first3000.splat")  # the real file's first records, as its writer made them
    original = np.fromfile(path, splat_records(Gaussians.empty()).dtype)
    g = read_splat(path)
    out = tmp_path / "again.splat"
    write_gaussians(g, out)
    again = np.fromfile(out, original.dtype)
    np.testing.assert_array_equal(again["position"], original["position"])
    np.testing.assert_allclose(again["scale"], original["scale"], rtol=1e-6)
    np.testing.assert_array_equal(again["rgba"], original["rgba"])
    # Rotations were renormalised and given w >= 0 on reading: same rotation within one byte step per component.
    q0 = same_sign((original["rotation"].astype(np.float64) - 128) / 128)
    q1 = same_sign((again["rotation"].astype(np.float64) - 128) / 128)
    assert np.abs(q0 - q1).max() <= 1.5 / 128


def test_splat_writer_quantization(tmp_path):
    src = read_gaussians(SOURCE_PLY)
    out = tmp_path / "x.splat"
    write_gaussians(src, out)
    g = read_gaussians(out)
    assert len(g) == len(src) and g.sh_degree == 0
    np.testing.assert_array_equal(g.positions, src.positions)
    np.testing.assert_allclose(g.log_scales, src.log_scales, atol=1e-5)
    visible = (src.base_colors >= 0) & (src.base_colors <= 1)  # .splat clamps colour to [0, 1]
    assert np.abs(g.base_colors - src.base_colors)[visible].max() <= 0.5 / 255 + 1e-6
    assert np.abs(g.opacities - src.opacities).max() <= 0.5 / 255 + 1e-6
    assert np.abs(g.rotations - src.rotations).max() <= 0.02


def test_sniffing_is_by_content(tmp_path):
    for name, fmt in [("fruit_drops_v3.spz", "spz"), ("fruit_drops_v4.spz", "spz"),
                      ("fruit_drops.compressed.ply", "compressed_ply"), ("fruit_drops_sub16.ply", "ply")]:
        renamed = tmp_path / (name.replace(".", "_") + ".splat")  # a misleading extension
        shutil.copy(FIXTURES / name, renamed)
        assert sniff_format(renamed) == fmt
        assert len(read_gaussians(renamed)) == FIXTURE_COUNT
    unknown = tmp_path / "scene.bin"
    unknown.write_bytes(bytes(64))
    with pytest.raises(InputError, match="unrecognised file format"):
        read_gaussians(unknown)


def test_splat_starting_with_gzip_magic_is_still_splat(tmp_path):
    records = splat_records(read_gaussians(SOURCE_PLY))
    raw = bytearray(records.tobytes())
    raw[0:2] = b"\x1f\x8b"  # low bytes of the first x coordinate: a tiny change of a valid position
    path = tmp_path / "lucky.splat"
    path.write_bytes(bytes(raw))
    assert sniff_format(path) == "splat"
    assert len(read_gaussians(path)) == FIXTURE_COUNT
    spz_named_splat = tmp_path / "really_spz.splat"
    shutil.copy(FIXTURES / "fruit_drops_v3.spz", spz_named_splat)
    assert sniff_format(spz_named_splat) == "spz"


def test_splat_plausibility(tmp_path):
    noise = tmp_path / "noise.splat"
    noise.write_bytes(np.random.default_rng(1).integers(0, 256, 32 * 200, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="does not look like a .splat file"):
        read_gaussians(noise)
    odd = tmp_path / "odd.splat"
    odd.write_bytes(bytes(33))
    with pytest.raises(InputError, match="not a multiple of 32"):
        read_gaussians(odd)


def test_splat_invalid_rows(tmp_path):
    records = splat_records(read_gaussians(SOURCE_PLY))
    records["position"][5] = np.nan
    records["scale"][7, 1] = -1.0
    path = tmp_path / "bad.splat"
    records.tofile(path)
    with pytest.raises(InputError, match="2 of 296 splats are invalid.*--drop-invalid"):
        read_gaussians(path)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        assert len(read_gaussians(path, drop_invalid=True)) == 294


# ---- hostile, truncated and corrupted inputs -----------------------------------------------------------------

def must_fail_cleanly(path: pathlib.Path, match: str | None = None) -> InputError:
    with pytest.raises(InputError, match=match) as info:
        read_gaussians(path)
    assert str(path) in str(info.value)
    return info.value


@pytest.mark.parametrize("name", FOREIGN_FIXTURES)
def test_truncated(tmp_path, name):
    data = (FIXTURES / name).read_bytes()
    for keep in (1, 3, 20, 40, 200, len(data) // 2, len(data) - 1):
        path = tmp_path / f"cut{keep}_{name}"
        path.write_bytes(data[:keep])
        must_fail_cleanly(path)


def test_truncated_splat(tmp_path):
    data = real("winter_fountain_first3000.splat").read_bytes()[:32 * 100]
    path = tmp_path / "cut.splat"
    path.write_bytes(data[:-5])
    must_fail_cleanly(path, "not a multiple of 32")


@pytest.mark.parametrize("name", FOREIGN_FIXTURES)
def test_random_corruption_never_crashes(tmp_path, name):
    """Flipped bytes anywhere either still decode (quantized payload bytes have no redundancy) or give an
    InputError: never another exception."""
    data = np.frombuffer((FIXTURES / name).read_bytes(), np.uint8)
    rng = np.random.default_rng(7)
    path = tmp_path / name
    for _ in range(40):
        corrupt = data.copy()
        at = rng.integers(0, min(len(data), 600) if rng.random() < 0.7 else len(data), size=3)
        corrupt[at] ^= rng.integers(1, 256, size=3, dtype=np.uint8)
        path.write_bytes(corrupt.tobytes())
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                g = read_gaussians(path)
        except InputError:
            continue
        assert np.isfinite(g.positions).all() and np.isfinite(g.opacity_logits).all()


def v4_with(tmp_path, **fields) -> pathlib.Path:
    data = bytearray((FIXTURES / "fruit_drops_v4.spz").read_bytes())
    offsets = {"version": (4, "<I"), "num_points": (8, "<I"), "sh_degree": (12, "<B"), "fractional_bits": (13, "<B"),
               "flags": (14, "<B"), "num_streams": (15, "<B"), "toc_offset": (16, "<I"), "reserved": (20, "<B")}
    for name, value in fields.items():
        offset, fmt = offsets[name]
        struct.pack_into(fmt, data, offset, value)
    path = tmp_path / "edited.spz"
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("fields,match", [
    ({"num_points": 0xFFFFFFFF}, "numPoints"),
    ({"num_points": 297}, "uncompressedSize"),
    ({"version": 5}, "version 5 is not supported"),
    ({"version": 3}, "plaintext 'NGSP' header with version 3"),
    ({"sh_degree": 9}, "shDegree"),
    ({"fractional_bits": 30}, "fractionalBits"),
    ({"flags": 0x80}, "flags"),
    ({"num_streams": 7}, "numStreams"),
    ({"toc_offset": 10_000_000}, "tocByteOffset"),
    ({"reserved": 1}, "reserved"),
])
def test_spz_v4_bad_header_fields(tmp_path, fields, match):
    must_fail_cleanly(v4_with(tmp_path, **fields), match)


def legacy_with(tmp_path, payload: bytes) -> pathlib.Path:
    path = tmp_path / "edited.spz"
    path.write_bytes(gzip.compress(payload))
    return path


def test_spz_legacy_bad_fields(tmp_path):
    body = bytearray(gzip.decompress((FIXTURES / "fruit_drops_v3.spz").read_bytes()))
    for offset, fmt, value, match in [(4, "<I", 1, "version 1"), (4, "<I", 4, "version 4 inside a gzip"),
                                      (8, "<I", 0xFFFFFFFF, "numPoints"), (8, "<I", 100, "decompresses to more"),
                                      (8, "<I", 300, "need exactly 19516"), (15, "<B", 7, "reserved"),
                                      (14, "<B", 2, "extension")]:
        edited = bytearray(body)
        struct.pack_into(fmt, edited, offset, value)
        must_fail_cleanly(legacy_with(tmp_path, bytes(edited)), match)
    must_fail_cleanly(legacy_with(tmp_path, b"PK\x03\x04" + bytes(40)), "not SPZ")
    must_fail_cleanly(legacy_with(tmp_path, b"NGSP"), "16-byte SPZ header")


def test_spz_decompression_bomb_is_cut_off(tmp_path):
    """A header declaring 10 points followed by 64 MiB of zeros: rejected after decompressing only what 10
    points need (+1 byte), not the whole stream."""
    header = struct.pack("<4sIIBBBB", b"NGSP", 3, 10, 0, 12, 0, 0)
    path = legacy_with(tmp_path, header + bytes(64 << 20))
    assert path.stat().st_size < 200_000
    must_fail_cleanly(path, "decompresses to more than the 216 bytes")


def test_compressed_ply_hostile_header(tmp_path):
    data = (FIXTURES / "fruit_drops.compressed.ply").read_bytes()
    for old, new, match in [(b"element vertex 296", b"element vertex 9999999999", "chunks for"),
                            (b"element chunk 2", b"element chunk 3", "chunks for 296 splats"),
                            (b"element sh 296", b"element sh 295", "rows for 296 splats"),
                            (b"property uint packed_scale", b"property float packed_scale", "uint properties"),
                            (b"property float min_r", b"property float min_q", "properties")]:
        path = tmp_path / "edited.compressed.ply"
        path.write_bytes(data.replace(old, new, 1))
        must_fail_cleanly(path, match)
    # A consistent header declaring far more splats than the file holds: refused before allocating.
    huge = data
    for old, new in [(b"element chunk 2", b"element chunk 39062500"),
                     (b"element vertex 296", b"element vertex 10000000000"),
                     (b"element sh 296", b"element sh 10000000000")]:
        huge = huge.replace(old, new, 1)
    path = tmp_path / "huge.compressed.ply"
    path.write_bytes(huge)
    must_fail_cleanly(path, "truncated")


def test_compressed_ply_non_finite_chunk_bounds(tmp_path):
    data = bytearray((FIXTURES / "fruit_drops.compressed.ply").read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    struct.pack_into("<f", data, start + 4, float("nan"))  # chunk 0, min_y
    path = tmp_path / "nan.compressed.ply"
    path.write_bytes(bytes(data))
    must_fail_cleanly(path, "min_y")


def test_sh_and_opacity_conventions():
    """colour = 0.5 + SH_C0 * f_dc and logit opacity hold for every reader (checked on a decoded fixture)."""
    g = read_gaussians(FIXTURES / "fruit_drops.compressed.ply")
    np.testing.assert_allclose(g.base_colors, 0.5 + SH_C0 * g.sh_dc, rtol=1e-6)
    np.testing.assert_allclose(logit(sigmoid(g.opacity_logits)), g.opacity_logits, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(g.rotations, axis=1), 1.0, atol=1e-6)
    assert (g.rotations[:, 0] >= 0).all()


def test_render_of_decode_matches_render_of_tool_ply():
    """Our SPZ decode and the tool's PLY of the same file render the same image (reference rasterizer)."""
    render_ref = pytest.importorskip("splatstream.render_ref")
    from splatstream.camera import suggested_camera

    g = read_gaussians(FIXTURES / "fruit_drops_v3.spz")
    ref = tool_output(FIXTURES / "fruit_drops_v3.spz.tool.ply")
    tool_g = Gaussians(ref["positions"], same_sign(ref["rotations"]), ref["log_scales"],
                       logit(1.0 / (1.0 + np.exp(-ref["opacity_logits"]))), ref["sh_dc"], ref["sh_rest"])
    camera = suggested_camera(g.positions, width=64, height=48)
    ours, theirs = render_ref.render(g, camera), render_ref.render(tool_g, camera)
    assert ours.max() > 0.05  # the scene is in view
    assert np.abs(ours - theirs).max() < 1e-3


def test_a_truncated_sog_says_so(tmp_path):
    """A .sog cut short keeps its zip members' start and loses the central directory at the end: it said 'not a
    readable zip file (File is not a zip file)' of what is one, truncated; a file that is no zip still says that."""
    data = (pathlib.Path(__file__).parent / "fixtures" / "foreign" / "fruit_drops.sog").read_bytes()
    (tmp_path / "cut.sog").write_bytes(data[:len(data) // 2])
    with pytest.raises(InputError, match=r"zip archive: starts as a zip file but its central directory \(at the "
                                         r"end\) is missing: truncated\?"):
        read_gaussians(tmp_path / "cut.sog")
