"""The encoder's output bytes, pinned: every engine (in memory, partitioned in this process, Dask) and input kind
(a binary PLY read by row ranges, an input read whole and spilled, a PLY whose header names its up axis) gives the
scene directory the encoder wrote at commit 615105a, before its two planners became one (issue 33). The digests
were computed with that commit's code on the same inputs; a change here is a change of the format's output and
needs its own reason."""
from __future__ import annotations

import hashlib
import os

import numpy as np
import pytest
from conftest import real

from splatstream import io, ply
from splatstream.encode import EncodeOptions, encode_file, plan
from splatstream.encode.local import encode_in_memory
from splatstream.errors import UsageError
from splatstream.format import presets
from splatstream.format.decode import decode_payload
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.ply import gaussians_to_records, write_gaussians_ply
from splatstream.readers.splat import write_splat
from splatstream.store import read_manifest

# Small leaves and a small memory per worker: a tree of several levels split into partitions. The grid merge named:
# these digests are the grid's on every engine (the default merge is auto, whose partitions are its merge domains:
# the same bytes as in memory only where the scene is one domain).
TREE = {"max_leaf_splats": 300, "lod_merge": "grid"}
SMALL_MEMORY = 1 << 20


def directory_digest(path: str) -> str:
    """One SHA-256 over every file's relative path and SHA-256, in path order."""
    lines = []
    for root, _, files in os.walk(path):
        for f in files:
            full = os.path.join(root, f)
            with open(full, "rb") as fh:
                lines.append(f"{os.path.relpath(full, path)} {hashlib.sha256(fh.read()).hexdigest()}\n")
    return hashlib.sha256("".join(sorted(lines)).encode()).hexdigest()


def write_inputs(base: str) -> dict[str, str]:
    """The inputs, written from a real scene: a binary PLY, a .splat (no row ranges: read whole and spilled) and
    a PLY whose header comment says z is up."""
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    g = Gaussians.concatenate([g, g.subset(slice(0, 600))])  # equal centres: kd median ties
    paths = {"ply": os.path.join(base, "scene.ply"), "splat": os.path.join(base, "scene.splat"),
             "zup": os.path.join(base, "zup.ply")}
    write_gaussians_ply(g, paths["ply"])
    write_splat(g, paths["splat"])
    records = gaussians_to_records(g)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment up_axis: z\nelement vertex {len(g)}\n"
              + "".join(f"property float {n}\n" for n in records.dtype.names) + "end_header\n")
    with open(paths["zup"], "wb") as f:
        f.write(header.encode() + records.tobytes())
    return paths


# (input, preset, extra options) -> digest of the scene directory at 615105a, the same on every engine; medium's
# since its log scales went onto a 1023-level tile step (issue 32: format/presets.py PRESET_STEPS; every engine
# agrees on the new digests, printed by this file's __main__); the LOD cases since merged opacities and colours
# are matched at the 2-px viewing scale (format_spec/lod.md 6 step 5, branch lodq; "no-lod" unchanged by that); the
# LOD cases again since their manifests are 1.8 tile tables (format.md 6.2, branch manifest18: payloads unchanged,
# "no-lod" a one-tile scene, unchanged); every case again since a small payload's like byte planes share a zstd block
# (container._block_ends, issue 32: the same decompressed bytes, 0.5-2 % fewer stored); very-high's again since it
# takes zstd level 12 and joins more of its parts into a zstd block (presets.PRESET_ZSTD_LEVEL, PRESET_BLOCK_SLACK;
# issue 32: the same texels, faster to read); medium-low-sh8's again since it takes zstd level 12 with a shortest
# match of 6 and joins its parts within 2 % (PRESET_ZSTD_LEVEL, PRESET_ZSTD_MIN_MATCH, PRESET_BLOCK_SLACK; issue 32,
# lossydec: the same texels in fewer bytes, faster to read); the LOD cases again since the levels above the first
# merged one match opacity and base colour at 8 px (lod.OPACITY_MATCH_FAR_SSE_PX, format_spec/lod.md 6 step 5; issue
# 31: +0.74 dB median under a splat budget; "no-lod" unchanged); the LOD cases again since their manifests record how
# the tree was built (format.md 6, version 1.9: lod.merge, lod.viewing_scale_px; branch lodmeta31: every payload file
# identical, checked against the previous digests' encoder, "no-lod" a one-tile scene, unchanged); very-high's again
# since it joins its parts within 3.5 % and stores a small payload as one zstd block where that costs at most 1 %
# more (PRESET_BLOCK_SLACK, PRESET_ONE_BLOCK_SLACK; issue 32, vhdec2: the same texels, faster to read)
# (PRESET_BLOCK_SLACK ...) and after it (with very-high on both) the LOD cases again
# since the scale above the first merged one grows with the level, 8, 12, 16 px, recorded as the 1.10 key
# lod.viewing_scale_levels_px (lod.OPACITY_MATCH_FAR_GROWTH; issue 31, farpx31: +0.24 / +0.19 dB median at 2 / 6 %
# budgets; every engine agrees; "no-lod" unchanged; the two splat digests no case runs by this file's encode_case);
# the LOD cases again since a tree's manifest and pages hold the compact tile table (format.md 6.2, version 1.12:
# f32 bounds rounded outward, zstd; issue 31, branch manifest31: every payload file identical, only the manifest
# moves; memory, partitioned and Dask agree; "no-lod" a one-tile scene, unchanged; the two splat digests no case
# runs are left as they were)
# medium's and low's cases again since their rotations are stored in a canonical gauge (presets.
# PRESET_ROTATION_GAUGE, rotation_canon.py; issue 32, rot32: the same covariances, fewer bytes; memory, partitioned
# and Dask agree; medium-low-sh8 and very-high, which keep the input's rotations, unchanged); medium-low-sh8's again
# when every smallest-three preset took the half turns (evalrefresh32; its .splat digest, which no case runs, left)
# low's cases again (the .splat one too) since its rotations are cube565 (format 1.13, rotrange32: the cube gauge's
# range; memory, partitioned and Dask agree)
# medium-low-sh8's (the .splat one too) since it measures its rotations as medium-low does and takes cube8x4 on
# these inputs (format 1.14, presets.PRESET_ROTATION_CHOICES; issue 32, shvariants32; memory and partitioned agree)
# the LOD cases again since a tree's compact table names its files by 16 bytes of their SHA-256 and holds its spheres
# as radii (format 1.15, issue 31, digest31: every payload file's bytes identical to the previous digests' encoder's in
# the 12 cases run in this process, checked, the tile payloads renamed, the SH codebook's kept; memory, partitioned
# and Dask agree; "no-lod" a one-tile scene, unchanged; the two splat digests no case runs are left as they were)
# the LOD cases again since the compact table holds boxes as u8 steps of the parent's and radii as u8 steps of the
# half diagonal (format 1.16, issue 31, box16: only manifest.msgpack differs, every payload file's name and bytes
# identical to 1.15's, checked on ("ply", "medium") with relative_boxes off giving the 1.15 digest; "no-lod" unchanged;
# the two splat digests no case runs are left as they were)
DIGESTS: dict[tuple[str, str, str], str] = {
    ("ply", "medium", ""): "4b3434e232cae9f4b46e57bb43d857427b2fefa401643f34383d9495dae48021",
    ("ply", "low", ""): "99415427b20336eec3722b43c1d5428e65739a7bd7b5fb695143b82614a2f975",
    ("ply", "medium-low-sh8", ""): "8ad67272dc6de6fa8082918d3e4e091fb1aab062219f040171d1b132c8abd323",
    ("ply", "very-high", ""): "3f6c0d1470899de5d6e62e532cb456bc1d503ff6c0bc998a9566159fe4dcec74",
    ("splat", "medium", ""): "aaf141304e408c34c5af3d39b94afd9502934beaba5080ffdc113363b60e6852",
    ("splat", "low", ""): "a4585935a10907d3117720670840c1d4db9cf7a250b32767402a7fac83fb7f13",
    ("splat", "medium-low-sh8", ""): "1f09ba732bd04e89fb009bccd11338d3bb1e60e85da59b7695ffc0c92abdd595",
    ("splat", "very-high", ""): "7f7ffe0df874ff9b7b88e46e57a6a09e7a9b09b751668d8cd59cb381ec97b987",
    ("ply", "medium", "no-lod"): "f474285d9ddd827c6760a659704bb5f1cb650d2c650877b1a7fcd99e1fe3d77e",
    ("ply", "low", "sh1"): "a31fadc044c7f90406e169b6d0052e8f432fe709d72d4ae3d3943eb813dbb80e",
    ("zup", "medium", ""): "f41ed179136821253f487e96a2a0539dc0291a88faccb0503a3e1b98a1a25821",
}
# The cases run (a .splat's partitioned encode runs in memory unless on Dask: it is read whole anyway)
CASES = [("ply", "medium", "memory", ""), ("ply", "medium", "partitioned", ""), ("ply", "low", "memory", ""),
         ("ply", "low", "partitioned", ""), ("ply", "low", "dask", ""), ("ply", "medium-low-sh8", "partitioned", ""),
         ("ply", "very-high", "partitioned", ""), ("splat", "medium", "memory", ""), ("splat", "medium", "dask", ""),
         ("splat", "low", "memory", ""), ("ply", "medium", "memory", "no-lod"), ("ply", "low", "partitioned", "sh1"),
         ("zup", "medium", "memory", ""), ("zup", "medium", "partitioned", "")]
ENGINES = {"memory": {}, "partitioned": {"memory_per_worker": SMALL_MEMORY}, "dask": {"workers": 2,
                                                                                     "memory_per_worker": SMALL_MEMORY}}
EXTRA = {"": TREE, "no-lod": {"lod": False}, "sh1": {**TREE, "sh_degree": 1}}


def encode_case(inputs: dict[str, str], out: str, source: str, preset: str, engine: str, extra: str) -> str:
    encode_file(inputs[source], out, preset=preset, **ENGINES[engine], **EXTRA[extra])
    return directory_digest(out)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, str]:
    return write_inputs(str(tmp_path_factory.mktemp("inputs")))


@pytest.mark.parametrize("case", CASES, ids=["-".join(c for c in case if c) for case in CASES])
def test_output_bytes_are_615105a_s(inputs, tmp_path, case):
    if case[2] == "dask":
        pytest.importorskip("distributed")
    source, preset, _, extra = case
    assert encode_case(inputs, str(tmp_path / "out"), *case) == DIGESTS[source, preset, extra]


def test_the_default_merge_is_auto_in_memory_and_by_partitions(inputs, tmp_path):
    """Issue 31: an encode that names no merge takes auto (sharper at a splat budget), in memory and by partitions
    (inside partitions of at most 2^20 splats, its merge domains: branch partauto31, 6e9207e); a scene of one
    domain is the in-memory bytes on Dask. Where a domain does not fit the memory per worker the default takes the
    grid and a named auto is refused."""
    default = {"max_leaf_splats": 300}
    encode_file(inputs["ply"], str(tmp_path / "memory"), preset="low", **default)
    encode_file(inputs["ply"], str(tmp_path / "auto"), preset="low", lod_merge="auto", **default)
    encode_file(inputs["ply"], str(tmp_path / "parts"), preset="low", **ENGINES["partitioned"], **default)
    in_memory = directory_digest(str(tmp_path / "memory"))
    assert in_memory == directory_digest(str(tmp_path / "auto")) != DIGESTS["ply", "low", ""]
    assert directory_digest(str(tmp_path / "parts")) == DIGESTS["ply", "low", ""]  # 1 MiB: the grid
    for engine in ("partitioned", "dask"):
        if engine == "dask":
            pytest.importorskip("distributed")
        with pytest.raises(UsageError, match="--lod-merge auto: its merge domains"):
            encode_file(inputs["ply"], str(tmp_path / engine), preset="low", lod_merge="auto", **ENGINES[engine],
                        **default)
        assert not (tmp_path / engine).exists()
    encode_file(inputs["ply"], str(tmp_path / "dask"), preset="low", workers=2, **default)
    assert directory_digest(str(tmp_path / "dask")) == in_memory


@pytest.mark.parametrize("engine", ["memory", "partitioned"])
def test_the_input_is_sniffed_and_its_header_read_once(inputs, tmp_path, monkeypatch, engine):
    """Issue 33: one encode opens its input once (io.open_input) and screens the splats' domain once."""
    calls: dict[str, int] = {}

    def counted(module, name):
        original = getattr(module, name)

        def wrapper(*args, **kwargs):
            calls[name] = calls.get(name, 0) + 1
            return original(*args, **kwargs)
        monkeypatch.setattr(module, name, wrapper)

    for module, name in ((io, "_sniff"), (io, "read_header"), (ply, "read_header"), (io, "domain_violations"),
                         (plan, "domain_violations")):
        counted(module, name)
    encode_file(inputs["zup"], str(tmp_path / "out"), preset="medium", **ENGINES[engine], **TREE)
    assert calls == {"_sniff": 1, "read_header": 1, **({"domain_violations": 1} if engine == "memory" else {})}



def test_very_high_at_its_zstd_level_decodes_to_level_1s_texels_from_fewer_bytes():
    """very-high takes zstd level 12 (presets.PRESET_ZSTD_LEVEL; issue 32: zstd reads its frames 8-15 % faster than
    level 1's, BENCHMARKS.md "Decode speed", vhdec): every payload decodes to exactly the texels and ranges it held
    at level 1 (the lossless preset stays lossless; readers need not know the level: format.md 5.1), and the scene is
    stored in fewer bytes. (The fields1-or-shuffle trials run at the level too, up to transport.TRIAL_LEVEL_MAX, so
    a section's filter may differ: its texels may not.)"""
    assert EncodeOptions(preset="very-high").resolved_zstd_level == 12
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    texels: dict[int | None, list[bytes]] = {}
    stored: dict[int | None, int] = {}
    for level in (None, 1):
        store = encode_in_memory(g, EncodeOptions(preset="very-high", zstd_level=level, **TREE))
        m = read_manifest(store)
        texels[level], stored[level] = [], 0
        for t in m.tiles:
            for group, entry in sorted(t.groups.items()):
                data = store.read_payload(entry)
                stored[level] += len(data)
                for name, plane in sorted(decode_payload(data, entry, group, "test", m.uses_codebook).items()):
                    texels[level] += [name.encode()] + [np.ascontiguousarray(x).tobytes() for x in plane.layers]
                    texels[level].append(b"" if plane.ranges is None else np.ascontiguousarray(plane.ranges).tobytes())
    assert len(texels[None]) > 100 and texels[None] == texels[1]
    assert stored[None] < 0.995 * stored[1]


def scene_texels(store) -> tuple[list[bytes], int]:
    """(every plane's texels and ranges, decoded, in a fixed order; the bytes of every payload stored)."""
    m = read_manifest(store)
    texels, stored = [], 0
    for t in m.tiles:
        for group, entry in sorted(t.groups.items()):
            data = store.read_payload(entry)
            stored += len(data)
            for name, plane in sorted(decode_payload(data, entry, group, "test", m.uses_codebook).items()):
                texels += [name.encode()] + [np.ascontiguousarray(x).tobytes() for x in plane.layers]
                texels.append(b"" if plane.ranges is None else np.ascontiguousarray(plane.ranges).tobytes())
    return texels, stored


# (preset, its zstd level before issue 32's lossydec round, which had no shortest match or block slack of its own;
# medium-low-9bit and low-plus-10bit-cb8 before the round after, eval32; medium-high before tidy32; high-sh255, new in
# hole32, against the encoder's default level)
LOSSY_BEFORE = [("high", 1), ("medium-low-sh8", 1), ("low-plus-9bit-sh5", 16), ("medium-low-12bit", 16),
                ("medium-low-9bit", 16), ("low-plus-10bit-cb8", 16), ("medium-high", 1), ("high-sh255", 1)]


@pytest.mark.parametrize("preset,level", LOSSY_BEFORE, ids=[p for p, _ in LOSSY_BEFORE])
def test_lossy_presets_zstd_choices_decode_to_the_same_texels_from_fewer_bytes(monkeypatch, preset, level):
    """The lossy presets' zstd choices for their decode (presets.PRESET_ZSTD_LEVEL, PRESET_ZSTD_MIN_MATCH,
    PRESET_BLOCK_SLACK; issue 32, BENCHMARKS.md "Decode speed", lossydec): a shortest match of 6 and parts joined
    within 1-2 % give every payload exactly the texels and ranges of the preset's level alone (readers need not
    know the level: format.md 5.1), and the scene fewer bytes, not more (the README's preset table is met on
    bytes)."""
    assert presets.PRESET_ZSTD_MIN_MATCH[preset] == 6 and 0 < presets.PRESET_BLOCK_SLACK[preset] <= 0.02
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    texels, stored = scene_texels(encode_in_memory(g, EncodeOptions(preset=preset, **TREE)))
    monkeypatch.setitem(presets.PRESET_ZSTD_LEVEL, preset, level)
    monkeypatch.delitem(presets.PRESET_ZSTD_MIN_MATCH, preset)
    monkeypatch.delitem(presets.PRESET_BLOCK_SLACK, preset)
    texels_before, stored_before = scene_texels(encode_in_memory(g, EncodeOptions(preset=preset, **TREE)))
    assert len(texels) > 50 and texels == texels_before
    assert stored < stored_before

if __name__ == "__main__":  # prints every case's digest with whichever splatstream is imported
    import sys
    import tempfile

    sys.path.insert(0, os.path.dirname(__file__))
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_inputs(tmp)
        for i, case in enumerate(CASES):
            print(f"    {case!r}: \"{encode_case(paths, os.path.join(tmp, f'o{i}'), *case)}\",", flush=True)


@pytest.mark.parametrize("variant", ["medium-low-sh16", "medium-low-sh8"])
def test_a_per_splat_sh_preset_without_sh_bands_writes_its_bases_bytes(variant):
    """newuser63: on an SH0 scene medium-low-sh16 and -sh8 wrote medium-low's planes at zstd level 12 (shortest match
    6), 0.4 % more bytes than medium-low's level 9, where the README's table says "= medium-low (no SH bands)". Without
    SH bands (as read, or kept by --sh-degree 0) a per-splat SH preset takes its base's zstd settings: every payload
    the same bytes. With SH bands it keeps its own (its scenes' bytes unchanged)."""
    sample = os.path.join(os.path.dirname(__file__), "..", "samples", "donut.ply")
    donut = read_gaussians(sample).subset(np.arange(6000))
    fruit = read_gaussians(real("fruit_drops_sh3.ply"))
    for g, sh_degree in ((donut, None), (fruit, 0)):
        assert g.sh_degree == 0 or sh_degree == 0
        payloads = {}
        for preset in ("medium-low", variant):
            m = read_manifest(encode_in_memory(g, EncodeOptions(preset=preset, sh_degree=sh_degree, **TREE)))
            payloads[preset] = sorted(e.sha256 for _, _, e in m.payloads())
        assert payloads[variant] == payloads["medium-low"]
    assert presets.compression_preset(variant, 3) == variant and presets.compression_preset(variant, 0) == "medium-low"
    opts = EncodeOptions(preset=variant)
    assert opts.zstd_level_for(1) == 12 and opts.zstd_level_for(0) == 9
