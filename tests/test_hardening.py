"""Regression tests of issue 19 (a fuzz and fault campaign), findings 1-9: each input that once gave a traceback, a
hang, an unreadable scene, silent NaN or silently accepted garbage now gives what a careful tool gives.

Inputs are the real fixtures with one value rewritten, as the campaign found them (bench/fuzz.py runs the campaign
itself; tests/test_fuzz_campaign.py a short run of it).
"""
from __future__ import annotations

import gzip
import hashlib
import os
import pathlib
import shutil
import struct
import warnings
import zlib

import numpy as np
import pytest
import zstandard
from conftest import read_manifest_dict, real, run_cli, write_manifest_dict

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.errors import FormatError, InputError
from splatstream.format.limits import MAX_ABS_POSITION, MAX_ABS_SH, MAX_LOG_SCALE, MIN_LOG_SCALE
from splatstream.format.texformats import shuffle_bytes, unshuffle_bytes
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.ply import read_elements, read_gaussians_ply, read_header
from splatstream.scene_decode import decode_scene

FOREIGN = pathlib.Path(__file__).parent / "fixtures" / "foreign"
SUB64 = FOREIGN / "fruit_drops_sub64.ply"


def rewrite_ply_field(src: pathlib.Path, dst: pathlib.Path, field: str, values: dict[int, float]) -> None:
    """A copy of a binary PLY with `field` of the given rows replaced (the campaign's "one float rewritten")."""
    header = read_header(src)
    data = src.read_bytes()
    records = np.frombuffer(data[header.size:], header.element("vertex").dtype("<")).copy()
    for row, value in values.items():
        records[field][row] = value
    dst.write_bytes(data[:header.size] + records.tobytes())


def fails_cleanly(r, *needles: str) -> None:
    """Exit 2, one line naming what is wrong, no traceback."""
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = [line for line in r.stderr.strip().splitlines() if "warning" not in line]
    assert len(lines) == 1 and "Traceback" not in r.stderr and "internal error" not in r.stderr, r.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def no_temp_left(directory: pathlib.Path) -> None:
    assert [p.name for p in directory.iterdir() if p.name.startswith(".")] == []


# ----------------------------------------------------------------------------------------------- findings 1 to 3


@pytest.mark.parametrize("field,value,what", [
    ("scale_0", 1e30, "log scale"), ("scale_0", -7e4, "log scale"), ("f_dc_0", 7e4, "SH0"),
    ("f_rest_7", -7e4, "SH bands"), ("x", 2e38, "position"),
])
def test_values_beyond_the_format_are_refused_naming_field_and_count(tmp_path, field, value, what):
    """Findings 1 and 2: one splat with a value the format cannot hold (a log scale whose exp overflows, a value
    beyond float16 in an f16-ranged plane) once gave a LinAlgError or an unreadable scene; now exit 2 at read,
    naming the file, the field and the splat count, and --drop-invalid drops that splat."""
    src = tmp_path / "in.ply"
    rewrite_ply_field(real("fruit_drops_sh3.ply"), src, field, {17: value})
    # --max-leaf-splats 1024 builds LOD tiles (the eigh of finding 1) where the value got through.
    r = run_cli("encode", "-q", "--max-leaf-splats", "1024", src, tmp_path / "s")
    fails_cleanly(r, str(src), what, "1 of 4,721 splats has", "first at splat 17", "--drop-invalid")
    assert not (tmp_path / "s").exists()
    no_temp_left(tmp_path)
    r = run_cli("encode", "-q", "--max-leaf-splats", "1024", "--drop-invalid", src, tmp_path / "s")
    assert r.returncode == 0 and "dropped" in r.stderr, r.stderr
    g = decode_scene(tmp_path / "s")
    assert len(g) == 4720
    # convert writes only what its readers read back: the same screening applies.
    fails_cleanly(run_cli("convert", "-q", src, tmp_path / "o.splat"), what)


def test_compressed_ply_scale_bounds_beyond_float16(tmp_path):
    """Finding 1: a compressed.ply whose chunk scale bounds overflow float16 (default options)."""
    src = FOREIGN / "fruit_drops.compressed.ply"
    header, elements = read_elements(src)
    chunk = elements["chunk"].copy()
    chunk["max_scale_x"][0] = 7e4
    data = src.read_bytes()
    out = tmp_path / "big.compressed.ply"
    out.write_bytes(data[:header.size] + chunk.tobytes() + data[header.size + chunk.nbytes:])
    fails_cleanly(run_cli("encode", "-q", out, tmp_path / "s"), str(out), "log scale")


def test_the_encoder_checks_gaussians_handed_to_it(tmp_path):
    """Finding 2: the library encoder never writes what its reader refuses, whoever built the Gaussians."""
    g = read_gaussians_ply(SUB64)
    g.sh_dc[3, 1] = 7e4
    with pytest.raises(InputError, match="SH0 .* beyond \\+-65504: 1; first at splat 3"):
        encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="high"))
    assert not (tmp_path / "s").exists()
    no_temp_left(tmp_path)


def splats_at_the_limits() -> Gaussians:
    """fruit_drops with splats at the domain's edges: positions +-1e18, log scales -80 and 40, SH +-65504."""
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    g.positions[0] = [MAX_ABS_POSITION, -MAX_ABS_POSITION, MAX_ABS_POSITION]
    g.positions[1] = [-MAX_ABS_POSITION, MAX_ABS_POSITION, -MAX_ABS_POSITION]
    g.log_scales[2] = MAX_LOG_SCALE
    g.log_scales[3] = MIN_LOG_SCALE
    g.sh_dc[4] = [MAX_ABS_SH, -MAX_ABS_SH, MAX_ABS_SH]
    g.sh_rest[5] = MAX_ABS_SH
    g.sh_rest[6] = -MAX_ABS_SH
    return g


@pytest.mark.parametrize("preset", ["very-high", "high", "medium"])
def test_values_at_the_limits_encode_and_decode_exactly(tmp_path, preset):
    """The domain's edges are inside it: positions +-1e18, log scales -80 and 40, SH +-65504 encode (with LOD
    tiles, whose merged splats stay inside too) and decode to exactly those values, with no numpy warning. The grid
    merge (see the default's test below)."""
    g = splats_at_the_limits()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset=preset, max_leaf_splats=1024, lod_merge="grid"))
        every = decode_scene(tmp_path / "s", tiles=[t.id for t in m.tiles])
        leaves = decode_scene(tmp_path / "s")
    check_values_at_the_limits(m, every, leaves)


def test_values_at_the_limits_with_the_default_merge(tmp_path):
    """The same with the default merge in memory (auto), whose edge costs meet overlaps that overflow between
    splats 1e18 apart (lod_groups._cross2, _edge_costs: taken as 0 overlap and an unknown, largest cost): the
    values exact and inside the domain, and no numpy warning."""
    g = splats_at_the_limits()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium", max_leaf_splats=1024))
        every = decode_scene(tmp_path / "s", tiles=[t.id for t in m.tiles])
        leaves = decode_scene(tmp_path / "s")
    check_values_at_the_limits(m, every, leaves)


def check_values_at_the_limits(m, every: Gaussians, leaves: Gaussians) -> None:
    assert len(m.tiles) > 4
    assert np.isfinite(every.positions).all() and np.isfinite(every.log_scales).all()
    assert every.log_scales.max() <= MAX_LOG_SCALE and every.log_scales.min() >= MIN_LOG_SCALE
    assert np.abs(leaves.positions).max() == np.float32(MAX_ABS_POSITION)
    assert leaves.log_scales.max() == MAX_LOG_SCALE and leaves.log_scales.min() == MIN_LOG_SCALE
    assert np.abs(leaves.sh_dc).max() == MAX_ABS_SH and np.abs(leaves.sh_rest).max() == MAX_ABS_SH


def rewrite_payload(scene: pathlib.Path, section: str, change) -> None:
    """Change one section of tile 0's base payload (unshuffled values, as a numpy array of the section's dtype),
    recompress it and make the manifest name it, so the checksums hold and only the value is wrong."""
    d = read_manifest_dict(scene)
    entry = d["tiles"][0]["groups"]["base"]
    raw = bytearray(zstandard.ZstdDecompressor().decompress((scene / entry["file"]).read_bytes()))
    s = next(x for x in entry["sections"] if x["name"] == section)
    element = int(s["filter"][7:]) if s["filter"] != "none" else 1
    dtype = np.dtype("<f4") if s.get("dtype") == "f32" or s.get("format") == "f32x4" else np.dtype("<f2")
    units = s.get("layers", 1) if s["kind"] == "texels" else 1
    unit = s["size"] // units
    for k in range(units):
        start = s["offset"] + k * unit
        stored = np.frombuffer(bytes(raw[start:start + unit]), np.uint8)
        values = unshuffle_bytes(stored, element).view(dtype).copy()
        change(values)
        raw[start:start + unit] = shuffle_bytes(values.view(np.uint8), element).tobytes()
    data = zstandard.ZstdCompressor().compress(bytes(raw))
    sha = hashlib.sha256(data).hexdigest()
    (scene / "data" / f"{sha}.bin").write_bytes(data)
    entry.update(file=f"data/{sha}.bin", sha256=sha, bytes=len(data))
    write_manifest_dict(scene, d, settle=True)


@pytest.fixture(scope="module")
def very_high_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("vh") / "s"
    # Byte-shuffled sections (no fields1), so rewrite_payload can edit values in place; the float-texel check runs
    # on the texels whatever the filter decoded them from (container.unpack_payload).
    encode_gaussians(read_gaussians_ply(SUB64), out, EncodeOptions(preset="very-high", transport="shuffle"))
    return out


@pytest.mark.parametrize("section,change,message", [
    ("position.range", lambda v: v.__setitem__(0, -2e38), "leaves the position domain"),
    ("position.range", lambda v: v.__setitem__(slice(0, 3), 5.0), "minimum exceeds its maximum"),
    ("scale.range", lambda v: v.__setitem__(3, 60000.0), "leaves the scale domain"),
    ("color.range", lambda v: v.__setitem__(0, np.inf), "non-finite range values"),
    ("position", lambda v: v.__setitem__(5, 1e38), "texel values outside [0, 1]"),
    ("rotation", lambda v: v.__setitem__(2, np.nan), "texel values outside [0, 1]"),
])
def test_scene_values_that_would_decode_to_nan_or_inf_are_refused(tmp_path, very_high_scene, section, change,
                                                                  message):
    """Finding 3: +-2e38 once decoded to NaN (f32 max - min overflowed). A reader now refuses every range or
    float texel from which min + t (max - min) could leave the finite domain, in numpy and (through the same
    unpack_payload) in the GL client; `render` refuses like `decode`."""
    scene = tmp_path / "s"
    shutil.copytree(very_high_scene, scene)
    rewrite_payload(scene, section, change)
    with pytest.raises(FormatError, match=message.replace("[", "\\[").replace("]", "\\]")):
        decode_scene(scene)
    fails_cleanly(run_cli("decode", scene, tmp_path / "o.ply"), f"section {section}", message)
    assert not (tmp_path / "o.ply").exists()


# ------------------------------------------------------------------------------------------------------ finding 4


def spz_v4_bytes(n: int, streams: list[bytes], sh_degree: int = 0) -> bytes:
    frames = [zstandard.ZstdCompressor(level=19).compress(s) for s in streams]
    header = struct.pack("<4sIIBBBBI12s", b"NGSP", 4, n, sh_degree, 12, 0, len(frames), 32, bytes(12))
    toc = b"".join(struct.pack("<QQ", len(f), len(s)) for f, s in zip(frames, streams, strict=True))
    return header + toc + b"".join(frames)


def test_spz_decompression_bombs_fail_early_naming_the_file(tmp_path):
    """Finding 4: a 97 KB SPZ once yielded 5M splats (40 s, 914 MB); a 972 KB one died at 6.5 GB RSS. The count a
    file declares is now bounded by what its size can plausibly hold and by the memory budget."""
    n = 5_000_000
    sizes = [9, 1, 3, 3, 4]
    path = tmp_path / "bomb.spz"
    path.write_bytes(spz_v4_bytes(n, [bytes(n * s) for s in sizes]))
    assert path.stat().st_size < 100_000
    with pytest.raises(InputError, match="compresses its attributes more than 64:1") as err:
        read_gaussians(path)
    assert str(path) in str(err.value)
    # gzip (v2/v3): the same bound before a byte is inflated
    legacy = tmp_path / "bomb_v3.spz"
    legacy.write_bytes(gzip.compress(struct.pack("<4sIIBBBB", b"NGSP", 3, n, 0, 12, 0, 0) + bytes(n * 20), 9))
    fails_cleanly(run_cli("convert", "-q", legacy, tmp_path / "o.ply"), str(legacy), "numPoints")


def test_declared_counts_beyond_the_memory_budget_are_refused(tmp_path):
    """Every reader with a count checks it against the memory budget (SPLATSTREAM_MEMORY_BUDGET) first."""
    import subprocess
    import sys

    env = dict(os.environ, SPLATSTREAM_MEMORY_BUDGET="100000")
    for src in (FOREIGN / "fruit_drops_v4.spz", real("fruit_drops_sh3.ply"), FOREIGN / "fruit_drops.compressed.ply",
                real("winter_fountain_first3000.splat")):
        r = subprocess.run([sys.executable, "-m", "cli", "convert", "-q", str(src),
                            str(tmp_path / "o.ply")], capture_output=True, text=True, env=env, timeout=120)
        fails_cleanly(r, str(src), "memory budget of 0.1 MiB")


def test_hostile_counts_in_ply_sog_and_ascii(tmp_path):
    # ASCII PLY: a count its bytes cannot hold is refused before the data is tokenised.
    path = tmp_path / "lie.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 4000000000\nproperty float x\nend_header\n1 2 3\n")
    with pytest.raises(InputError, match="declare 4000000000 ASCII values, but 6 bytes"):
        read_elements(path)
    # binary PLY: the count against the file length, before the memory budget or an allocation
    data = SUB64.read_bytes().replace(b"element vertex 74", b"element vertex 7400000000")
    path.write_bytes(data)
    with pytest.raises(InputError, match="truncated: header declares 7400000000 rows"):
        read_gaussians(path)
    # SOG: a count far beyond what its position textures can encode
    import json

    shutil.copytree(FOREIGN / "fruit_drops_sh1_sog", tmp_path / "sog")
    meta = json.loads((tmp_path / "sog" / "meta.json").read_text())
    meta["count"] = 2_000_000
    (tmp_path / "sog" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="count: 2000000 splats, but the two position textures"):
        read_gaussians(tmp_path / "sog")


# ------------------------------------------------------------------------------------------------------ finding 5


def test_non_regular_files_inside_a_sog_directory_are_refused(tmp_path):
    """Finding 5: besides the input itself (checked on main), every file a reader opens on its own: a FIFO in
    place of a WebP plane of an unbundled SOG once hung `convert`."""
    shutil.copytree(FOREIGN / "fruit_drops_sh1_sog", tmp_path / "sog")
    (tmp_path / "sog" / "means_l.webp").unlink()
    os.mkfifo(tmp_path / "sog" / "means_l.webp")
    for command in (["convert", "-q", tmp_path / "sog", tmp_path / "o.ply"], ["encode", "-q", tmp_path / "sog",
                                                                              tmp_path / "s"]):
        fails_cleanly(run_cli(*command), "means_l.webp is not a regular file")
    fifo = tmp_path / "in.ply"
    os.mkfifo(fifo)
    fails_cleanly(run_cli("encode", "-q", fifo, tmp_path / "s2"), "not a regular file")
    fails_cleanly(run_cli("convert", "-q", fifo, tmp_path / "o.spz"), "not a regular file")
    assert not (tmp_path / "o.ply").exists() and not (tmp_path / "s").exists()


# ------------------------------------------------------------------------------------------------------ finding 6


def test_zero_filled_splat_file_is_not_a_splat_file(tmp_path):
    path = tmp_path / "zeros.splat"
    path.write_bytes(bytes(320_000))
    fails_cleanly(run_cli("encode", "-q", path, tmp_path / "s"), str(path), "10,000 of 10,000 records are implausible",
                  "all-zero scale", "does not look like a .splat file")


def test_splat_records_with_all_scales_zero_are_invalid_and_one_zero_axis_is_flat(tmp_path):
    from splatstream.readers.splat import SPLAT_RECORD, splat_records

    records = splat_records(read_gaussians_ply(SUB64))
    records["scale"][5] = 0.0
    records["scale"][6, 2] = 0.0
    path = tmp_path / "z.splat"
    path.write_bytes(records.tobytes())
    with pytest.raises(InputError, match="1 of 74 splats is invalid"):
        read_gaussians(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = read_gaussians(path, drop_invalid=True)
    assert len(g) == 73 and SPLAT_RECORD.itemsize == 32
    assert g.log_scales[5, 2] == np.float32(np.log(np.float32(1e-30)))  # record 6 is row 5 after the drop


def test_legacy_spz_with_trailing_bytes_or_a_second_member(tmp_path):
    data = (FOREIGN / "fruit_drops_v3.spz").read_bytes()
    assert len(read_gaussians(FOREIGN / "fruit_drops_v3.spz")) == 296
    for suffix, what in ((b"garbage!", "trailing bytes"), (gzip.compress(b"more"), "a second gzip member")):
        path = tmp_path / "t.spz"
        path.write_bytes(data + suffix)
        with pytest.raises(InputError, match=f"{len(suffix)} bytes follow the end of the SPZ gzip stream \\({what}"):
            read_gaussians(path)
    assert zlib.decompress(data, 31)[:4] == b"NGSP"


def ascii_ply(path: pathlib.Path, rows: np.ndarray, properties: str = "float") -> None:
    names = rows.dtype.names
    lines = ["ply", "format ascii 1.0", f"element vertex {len(rows)}"]
    lines += [f"property {properties if n == 'x' else 'float'} {n}" for n in names] + ["end_header"]
    lines += [" ".join(repr(float(v)) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")


def test_ascii_ply_tokens_must_be_plain_numbers(tmp_path):
    from splatstream.ply import gaussians_to_records

    g = read_gaussians_ply(SUB64)
    rows = gaussians_to_records(g)
    path = tmp_path / "a.ply"
    ascii_ply(path, rows)
    back = read_gaussians(path)
    assert np.array_equal(back.positions, g.positions) and np.array_equal(back.sh_rest, g.sh_rest)
    text = path.read_text()
    first = repr(float(rows[3]["y"]))
    for bad in ("1_000", "0x10", "1e5e5", "--1", "1.5.2"):
        path.write_text(text.replace(" " + first + " ", f" {bad} ", 1))
        with pytest.raises(InputError, match=f"element vertex, row 3, property y: '{bad}' is not a number"):
            read_gaussians(path)
    # An integer property holding a fraction, or a value its type cannot hold, is refused (not truncated/wrapped).
    ascii_ply(path, rows, properties="uchar")
    with pytest.raises(InputError, match="row 0, property x: .* is not an integer in 0..255"):
        read_gaussians(path)


def test_ply_with_two_vertex_elements_is_refused(tmp_path):
    data = SUB64.read_bytes()
    at = data.index(b"end_header")
    path = tmp_path / "two.ply"
    path.write_bytes(data[:at] + b"element vertex 0\nproperty float x\n" + data[at:])
    with pytest.raises(InputError, match="element 'vertex' declared twice"):
        read_gaussians(path)


# ------------------------------------------------------------------------------------------------------ finding 9


def start_slow_encode(src: pathlib.Path, out: pathlib.Path):
    """An encode with a write phase of seconds (zstd 19 on f32 planes, many tiles), and its temporary directory
    once payloads are being written into it."""
    import signal
    import subprocess
    import sys
    import time

    # SIGINT as a terminal sends it: a suite started in the background (`cmd &` in a script) inherits SIGINT ignored,
    # and a Python started with SIGINT ignored keeps ignoring it.
    proc = subprocess.Popen([sys.executable, "-m", "cli", "encode", "-q", "--preset", "very-high",
                             "--zstd-level", "19", "--max-leaf-splats", "2048", str(src), str(out)],
                            stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        temps = [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.{proc.pid}.")]
        if temps and any(temps[0].glob("data/*.bin")):
            return proc, temps[0]
        time.sleep(0.01)
    proc.kill()
    pytest.fail(f"the encode never reached its write phase: {proc.communicate()[1]}")


def test_sigterm_during_the_write_phase_cleans_up_like_ctrl_c(tmp_path):
    """Finding 9: SIGTERM once left a 54 MB .scene.*.tmp behind with no message (8 of 8 runs)."""
    import signal

    src = real("donut_sh0_no_normals.ply")
    for sig, code, word in ((signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")):
        out = tmp_path / f"scene_{word}"
        proc, temp = start_slow_encode(src, out)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == code, (proc.returncode, err)
        assert err.strip() == f"splatstream encode: {word}" + (" (SIGTERM); partial output removed"
                                                              if sig == signal.SIGTERM else ""), err
        assert not temp.exists() and not out.exists()
        no_temp_left(tmp_path)


def test_after_sigkill_the_next_write_removes_stale_temporaries(tmp_path):
    import signal

    out = tmp_path / "scene"
    proc, temp = start_slow_encode(real("donut_sh0_no_normals.ply"), out)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert temp.is_dir() and any(temp.glob("data/*.bin"))  # nothing can clean up after SIGKILL itself
    # A temporary of a live writer (here: a name with this test's own pid, and one with pid 1) is kept.
    live = tmp_path / f".scene.{os.getpid()}.abcdefgh.tmp"
    init = tmp_path / ".scene.1.abcdefgh.tmp"
    live.mkdir()
    init.mkdir()
    r = run_cli("encode", "-q", SUB64, out)
    assert r.returncode == 0, r.stderr
    assert not temp.exists() and live.is_dir() and init.is_dir()
    assert len(decode_scene(out)) == 74
    # The same for files: a convert killed mid-write leaves .o.ply.<pid>.<random>.tmp; the next one removes it.
    stale = tmp_path / f".o.ply.{proc.pid}.x1y2z3.tmp"
    stale.write_bytes(b"half a PLY")
    r = run_cli("convert", "-q", SUB64, tmp_path / "o.ply")
    assert r.returncode == 0 and not stale.exists() and (tmp_path / "o.ply").is_file()


# ------------------------------------------------------------------------- found by the campaign (bench/fuzz.py)


def test_splat_writer_refuses_what_splat_readers_take_for_garbage(tmp_path):
    """A position of 1e18 is inside the scene format's domain but beyond what a .splat reader accepts (the format
    has no header, so plausibility is all a reader has): convert refuses instead of writing an unreadable file."""
    g = read_gaussians_ply(SUB64)
    g.positions[3, 0] = 5e7
    src = tmp_path / "far.ply"
    from splatstream.ply import write_gaussians_ply

    write_gaussians_ply(g, src)
    out = tmp_path / "far.splat"
    fails_cleanly(run_cli("convert", "-q", src, out), str(out), "1 of 74 splats has a position beyond +-1e7")
    assert not out.exists()
    no_temp_left(tmp_path)
    fails_cleanly(run_cli("convert", "-q", src, tmp_path / "far.spz"), str(tmp_path / "far.spz"), "SPZ cannot hold")
    assert run_cli("convert", "-q", src, tmp_path / "far.glb").returncode == 0


def test_nothing_left_after_dropping_is_an_error_naming_the_input(tmp_path):
    """--drop-invalid dropping every splat once wrote an empty .splat that nothing can read back."""
    src = tmp_path / "bad.ply"
    rewrite_ply_field(SUB64, src, "f_rest_35", dict.fromkeys(range(74), 65520.0))
    for command in (["convert", "-q", "--drop-invalid", src, tmp_path / "o.splat"],
                    ["encode", "-q", "--drop-invalid", src, tmp_path / "s"]):
        fails_cleanly(run_cli(*command), str(src), "holds no splats")
    assert not (tmp_path / "o.splat").exists() and not (tmp_path / "s").exists()


def test_huge_finite_quaternions_and_transforms_give_no_numpy_warnings():
    from splatstream.gaussians import normalize_quaternions

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q = normalize_quaternions(np.array([[1e30, 1e30, 0, 0], [0.5, 0.5, 0.5, 0.5], [np.inf, 0, 0, 0]],
                                           np.float32))
    assert np.allclose(q[0], [2**-0.5, 2**-0.5, 0, 0]) and np.allclose(q[1], [0.5] * 4)
    assert not np.isfinite(q[2]).all()  # left for the readers' value screen to report


def test_gltf_node_transforms_must_be_finite(tmp_path):
    import json

    from splatstream.readers.gltf import read_gltf

    data = (FOREIGN / "fruit_drops_sub64_sh1.glb").read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    doc["nodes"][0]["translation"] = [float("inf"), 0, 0]
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + json_len:]
    path = tmp_path / "t.glb"
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="nodes\\[0\\]: .* or not finite"):
            read_gltf(path)


def test_gltf_primitive_extensions_of_the_wrong_type(tmp_path):
    """A primitive whose `extensions` is a number once gave a TypeError traceback."""
    import json

    data = (FOREIGN / "fruit_drops_sub64_sh1.glb").read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    for value in (-1e18, ["KHR_gaussian_splatting"], "KHR_gaussian_splatting"):
        doc["meshes"][0]["primitives"][0]["extensions"] = value
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + json_len:]
        path = tmp_path / "t.glb"
        path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
        with pytest.raises(InputError, match="no primitive with KHR_gaussian_splatting"):
            read_gaussians(path)


def test_extreme_but_finite_opacity_logits_encode_without_numpy_warnings(tmp_path):
    """An opacity logit of -7e4 is finite (alpha 0) and inside the domain; every sigmoid on the way (orientation,
    LOD masses, the colour plane, SPZ) once printed 'overflow encountered in exp'."""
    src = tmp_path / "o.ply"
    rewrite_ply_field(SUB64, src, "opacity", {0: -7e4, 1: 7e4})
    for args in (["encode", "-q", "--max-leaf-splats", "256", src, tmp_path / "s"],
                 ["convert", "-q", src, tmp_path / "o.spz"]):
        r = run_cli(*args)
        assert r.returncode == 0 and r.stderr == "", r.stderr
    g = decode_scene(tmp_path / "s")
    assert sorted(g.opacity_logits)[0] == pytest.approx(-13.8155, abs=1e-3)  # alpha clamped to 1e-6 on decode


@pytest.mark.parametrize("preset", ["low", "high"])
def test_values_at_the_f16_edge_survive_codebook_and_lod_means(tmp_path, preset):
    """An SH coefficient of 65504 (float16's largest) in every splat: the SH codebook's entries and merged LOD
    splats are means of it, which float rounding put an ulp above 65504, and the encoder once wrote that range as
    +inf (a scene its own decoder refused). Ranges are now clamped to the plane's domain."""
    src = tmp_path / "edge.ply"
    rewrite_ply_field(real("fruit_drops_sh3.ply"), src, "f_rest_14", dict.fromkeys(range(4721), 65504.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = read_gaussians(src)
        m = encode_gaussians(g, tmp_path / "s", EncodeOptions(preset=preset, max_leaf_splats=1024))
        every = decode_scene(tmp_path / "s", tiles=[t.id for t in m.tiles])
    assert len(m.tiles) > 4 and np.isfinite(every.sh_rest).all()
    assert every.sh_rest[:, 14, 0].max() == 65504.0  # f_rest_14: coefficient 14 of the red channel (channel-major)


def test_gltf_json_values_of_the_wrong_type(tmp_path):
    """Unhashable JSON values where names or indices belong once gave TypeError tracebacks."""
    import json

    data = (FOREIGN / "fruit_drops_sub64_sh1.glb").read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    original = json.loads(data[20:20 + json_len])
    for edit, message in ((lambda d: d.__setitem__("extensionsRequired", [[0, 0, 0]]), "extensionsRequired"),
                          (lambda d: d["bufferViews"][0].__setitem__("buffer", {"a": 1}), "buffers: index"),
                          # issue 37: accessor fields of the wrong JSON type gave "internal error: TypeError"
                          (lambda d: d["accessors"][0].__setitem__("componentType", []),
                           r"accessor 0 \(POSITION\) componentType: \[\] \(expected an integer"),
                          (lambda d: d["accessors"][0].__setitem__("componentType", {}), "componentType: {}"),
                          (lambda d: d["accessors"][0].__setitem__("count", True), "count True"),
                          (lambda d: d["accessors"][3].__setitem__("normalized", "yes"),
                           "normalized: 'yes' \\(expected true or false\\)"),
                          (lambda d: d["bufferViews"][0].__setitem__("byteLength", True), "bufferViews\\[0\\]")):
        doc = json.loads(json.dumps(original))
        edit(doc)
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + json_len:]
        path = tmp_path / "t.glb"
        path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
        with pytest.raises(InputError, match=message):
            read_gaussians(path)


def test_pack_manifest_dict_takes_any_damaged_map():
    """The test and campaign helper writes damaged maps; a version of the wrong type is written without a
    checksum (and then refused by the reader naming `version`), not a TypeError."""
    import msgpack

    from splatstream.format.manifest import pack_manifest_dict, parse_manifest

    data = pack_manifest_dict({"format": "splatstream", "version": ["x", 2], "checksum": "0" * 64})
    assert msgpack.unpackb(data) == {"format": "splatstream", "version": ["x", 2]}
    with pytest.raises(FormatError, match="version: expected \\[major, minor\\]"):
        parse_manifest(data, "m")


def test_gltf_node_cycle_is_refused_at_once(tmp_path):
    """A node that is its own child was walked 65,536 times (9 s of CPU) before being refused."""
    import json

    data = (FOREIGN / "fruit_drops_sub64_sh1.glb").read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    doc["nodes"][0]["children"] = [0]
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + json_len:]
    path = tmp_path / "t.glb"
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    with pytest.raises(InputError, match="nodes\\[0\\]: reached twice"):  # at the second visit, not the 65,536th
        read_gaussians(path)


@pytest.mark.parametrize("fmt,dtype", [("f16x4", "<f2"), ("f32x4", "<f4")])
def test_float_texel_check_by_bits_accepts_exactly_zero_to_one(fmt, dtype):
    """The decoder's fast check of float texels (their bits as unsigned integers) accepts what t >= 0 and t <= 1
    accept, -0.0 and subnormals included, and refuses the rest with the count and the first bad value."""
    from splatstream.errors import FormatError
    from splatstream.format.container import _check_float_texels
    from splatstream.format.manifest import Section

    info = np.finfo(np.dtype(dtype))
    section = Section("position", "texels", 0, 0, "none", format=fmt)
    good = np.array([0.0, -0.0, 1.0, 0.5, info.smallest_subnormal, np.nextafter(np.float32(1), 0)], dtype)
    _check_float_texels([good.tobytes()], section, "t")
    above_one = np.nextafter(np.array(1.0, dtype), np.array(2.0, dtype))
    for bad in (above_one, -info.smallest_subnormal, np.nan, np.inf, -np.inf, -1.0):
        layer = np.concatenate([good, np.array([bad], dtype)])
        with pytest.raises(FormatError, match="1 " + fmt + " texel values outside"):
            _check_float_texels([layer.tobytes()], section, "t")
