"""The standard 3DGS PLY reader: every variant the reference writers produce, and every kind of bad input."""
import numpy as np
import pytest
from conftest import real, run_cli

from splatstream.errors import InputError
from splatstream.gaussians import SH_REST_COEFFS
from splatstream.ply import gaussians_to_records, read_gaussians_ply, write_gaussians_ply

RNG = np.random.default_rng(7)


def make_records(n=300, degree=3, normals=True):
    from splatstream.gaussians import Gaussians, normalize_quaternions

    g = Gaussians(RNG.normal(size=(n, 3)), normalize_quaternions(RNG.normal(size=(n, 4))), RNG.normal(-4, 1, (n, 3)),
                  RNG.normal(size=n), RNG.normal(size=(n, 3)), RNG.normal(0, 0.1, (n, SH_REST_COEFFS[degree], 3)))
    return g, gaussians_to_records(g, normals)


def write_ply(path, records, fmt="binary_little_endian", dtype="float", order=None, extra=None, count=None):
    names = list(records.dtype.names)
    if extra:
        names.append(extra)
    if order is not None:
        names = [names[i] for i in order]
    cols = {n: records[n] if n in records.dtype.names else np.ones(len(records), np.float32) for n in names}
    n = len(records) if count is None else count
    header = ["ply", f"format {fmt} 1.0", "comment test", f"element vertex {n}"]
    header += [f"property {dtype} {name}" for name in names] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        if fmt == "ascii":
            mat = np.stack([cols[name] for name in names], 1)
            f.write("\n".join(" ".join(repr(float(v)) for v in row) for row in mat).encode() + b"\n")
        else:
            bo = "<" if fmt == "binary_little_endian" else ">"
            t = "f4" if dtype == "float" else "f8"
            arr = np.empty(len(records), [(name, bo + t) for name in names])
            for name in names:
                arr[name] = cols[name]
            f.write(arr.tobytes())


def assert_same(a, b, atol=1e-6):
    for field in ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert np.allclose(getattr(a, field), getattr(b, field), atol=atol), field


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("dtype", ["float", "double"])
def test_formats_and_property_types(tmp_path, fmt, dtype):
    g, rec = make_records(50)
    write_ply(tmp_path / "a.ply", rec, fmt=fmt, dtype=dtype)
    assert_same(read_gaussians_ply(tmp_path / "a.ply"), g, atol=1e-5 if fmt == "ascii" else 1e-6)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_degree_inferred_and_normals_optional(tmp_path, degree):
    g, rec = make_records(40, degree=degree, normals=degree % 2 == 0)
    write_ply(tmp_path / "a.ply", rec)
    back = read_gaussians_ply(tmp_path / "a.ply")
    assert back.sh_degree == degree
    assert_same(back, g)


def test_any_property_order_and_unknown_properties(tmp_path):
    g, rec = make_records(60)
    order = list(RNG.permutation(len(rec.dtype.names) + 1))
    write_ply(tmp_path / "a.ply", rec, order=order, extra="transform")
    assert_same(read_gaussians_ply(tmp_path / "a.ply"), g)


def test_quaternions_are_normalised(tmp_path):
    g, rec = make_records(20)
    for i in range(4):
        rec[f"rot_{i}"] *= 3.0
    write_ply(tmp_path / "a.ply", rec)
    back = read_gaussians_ply(tmp_path / "a.ply")
    assert np.allclose(np.linalg.norm(back.rotations, axis=1), 1.0, atol=1e-6)
    assert np.all(back.rotations[:, 0] >= 0)


def test_real_scenes_read_and_write_back(tmp_path):
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))  # carries an extra 'transform' property
    assert len(g) == 4721 and g.sh_degree == 3
    assert np.abs(g.sh_rest).max() > 0
    write_gaussians_ply(g, tmp_path / "b.ply")
    assert_same(read_gaussians_ply(tmp_path / "b.ply"), g, atol=0)
    d = read_gaussians_ply(real("donut_sh0_no_normals.ply"))
    assert len(d) == 45624 and d.sh_degree == 0


# ----------------------------------------------------------------------------------------------------------------
# Bad input: a clear message naming the file and what is wrong, exit code 2, no traceback, no output left behind.


def bad_inputs(tmp_path):
    g, rec = make_records(100)
    cases = {}
    write_ply(tmp_path / "good.ply", rec)
    data = (tmp_path / "good.ply").read_bytes()
    (tmp_path / "truncated.ply").write_bytes(data[:-1000])
    cases["truncated.ply"] = "truncated"
    write_ply(tmp_path / "lying_more.ply", rec, count=150)
    cases["lying_more.ply"] = "declares 150 rows"
    write_ply(tmp_path / "lying_less.ply", rec, count=80)
    cases["lying_less.ply"] = "do not match"
    nan = rec.copy()
    nan["x"][3] = np.nan
    nan["opacity"][5] = np.nan  # an infinite opacity logit is alpha 0 or 1 and is read (test_infinite_opacity)
    write_ply(tmp_path / "nan.ply", nan)
    cases["nan.ply"] = "2 of 100 splats have non-finite values"
    zero = rec.copy()
    for i in range(4):
        zero[f"rot_{i}"][7] = 0
    write_ply(tmp_path / "zero_quat.ply", zero)
    cases["zero_quat.ply"] = "zero-length quaternion"
    names = [n for n in rec.dtype.names if n != "scale_1"]
    write_ply(tmp_path / "missing.ply", rec[names])
    cases["missing.ply"] = "missing required properties scale_1"
    (tmp_path / "empty.ply").write_bytes(b"")
    cases["empty.ply"] = "empty"
    (tmp_path / "notply.ply").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    cases["notply.ply"] = "unrecognised file format"
    (tmp_path / "noend.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    cases["noend.ply"] = "end_header"
    return cases


def test_bad_inputs_raise_clear_errors(tmp_path):
    for name, needle in bad_inputs(tmp_path).items():
        if name == "notply.ply":
            continue  # sniffed by the CLI's reader dispatch, see the CLI test
        with pytest.raises(InputError) as exc:
            read_gaussians_ply(tmp_path / name)
        assert name in str(exc.value) and needle in str(exc.value), (name, str(exc.value))


def test_bad_inputs_through_the_cli(tmp_path):
    for name, needle in bad_inputs(tmp_path).items():
        out = tmp_path / f"out_{name}"
        r = run_cli("encode", tmp_path / name, out, "-q")
        assert r.returncode == 2, (name, r.returncode, r.stderr)
        assert "Traceback" not in r.stderr and needle in r.stderr and name in r.stderr, (name, r.stderr)
        assert not out.exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == [], leftovers


def test_drop_invalid_drops_with_a_warning(tmp_path):
    bad_inputs(tmp_path)
    r = run_cli("encode", tmp_path / "nan.ply", tmp_path / "scene", "--drop-invalid", "-q")
    assert r.returncode == 0, r.stderr
    assert "warning" in r.stderr and "dropped" in r.stderr
    r = run_cli("info", tmp_path / "scene", "--json")
    import json

    assert json.loads(r.stdout)["splats"] == 98


def test_infinite_opacity_is_alpha_one_or_zero(tmp_path):
    """splat-transform writes an opacity logit of +inf for fully opaque splats: +-inf are alpha 1 / 0, read as the
    finite logit of the 8-bit-alpha readers (+-13.8) with a count in the warning; NaN stays an error."""
    _, rec = make_records(100, 0)
    rec["opacity"][3] = np.inf
    rec["opacity"][4] = np.inf
    rec["opacity"][7] = -np.inf
    write_ply(tmp_path / "inf.ply", rec)
    with pytest.warns(UserWarning, match=r"3 of 100 splats have an infinite opacity logit \(2 \+inf = alpha 1, 1 "
                      r"-inf = alpha 0\)"):
        g = read_gaussians_ply(tmp_path / "inf.ply")
    assert len(g) == 100
    limit = np.log((1 - 1e-6) / 1e-6)
    assert g.opacity_logits[3] == g.opacity_logits[4] == pytest.approx(limit, rel=1e-6)
    assert g.opacity_logits[7] == pytest.approx(-limit, rel=1e-6)
    assert g.opacities[3] == pytest.approx(1.0, abs=1e-6) and g.opacities[7] == pytest.approx(0.0, abs=1e-6)
    others = np.setdiff1d(np.arange(100), [3, 4, 7])
    assert np.array_equal(g.opacity_logits[others], rec["opacity"][others])
    rec["opacity"][9] = np.nan
    write_ply(tmp_path / "nan.ply", rec)
    with pytest.raises(InputError, match="1 of 100 splats has non-finite values.*opacity: 1"), \
            pytest.warns(UserWarning, match="infinite opacity"):
        read_gaussians_ply(tmp_path / "nan.ply")


def _with_face_element(path, faces, fmt="binary_little_endian", before_vertex=False, in_vertex=False):
    """`path` rewritten with a mesh's `face` element (list property) after the splats (or before them, or a list
    property in the vertex element itself), holding `faces` triangles."""
    data = path.read_bytes()
    end = data.index(b"end_header\n")
    header, body = data[:end].decode(), data[end + len(b"end_header\n"):]
    face = f"element face {faces}\nproperty list uchar int vertex_indices\n"
    if in_vertex:
        header = header.replace("property float x\n", "property list uchar int ids\nproperty float x\n")
    elif before_vertex:
        header = header.replace("element vertex", face + "element vertex")
    else:
        header += face
    if fmt == "ascii":
        rows = "".join("3 0 1 2\n" for _ in range(faces)).encode()
    else:
        rows = (np.array([3], np.uint8).tobytes() + np.array([0, 1, 2], "<i4").tobytes()) * faces
    path.write_bytes(header.encode() + b"end_header\n" + (rows + body if before_vertex else body + rows))


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
@pytest.mark.parametrize("faces", [0, 2])
def test_a_face_element_after_the_splats_is_skipped(tmp_path, fmt, faces):
    """newuser63: a PLY with a mesh's `face` element (a list property) after its vertex element, as mesh tools
    write one, was refused ('list property ... is not supported'); the splats are read, the faces skipped, and
    the partitioned reader's row layout finds the same rows. A list before the splats or inside them is refused."""
    from splatstream.ply import vertex_layout

    g, rec = make_records(30)
    write_ply(tmp_path / "a.ply", rec, fmt=fmt)
    _with_face_element(tmp_path / "a.ply", faces, fmt)
    assert_same(read_gaussians_ply(tmp_path / "a.ply"), g, atol=1e-5)
    layout = vertex_layout(tmp_path / "a.ply")
    assert layout is None if fmt == "ascii" else (layout.rows == 30 and layout.offset == (tmp_path / "a.ply")
                                                  .read_bytes().index(b"end_header\n") + len(b"end_header\n"))
    if faces == 0:  # no rows to skip: the counts must still match the data (a row fewer declared is refused)
        data = (tmp_path / "a.ply").read_bytes().replace(b"element vertex 30", b"element vertex 29", 1)
        (tmp_path / "lying.ply").write_bytes(data)
        with pytest.raises(InputError, match="do not match"):
            read_gaussians_ply(tmp_path / "lying.ply")
    for kind, needle in (("before_vertex", "element face: an element with a list property before element vertex"),
                         ("in_vertex", "element vertex: list property 'uchar int ids' is not supported")):
        write_ply(tmp_path / f"{kind}.ply", rec, fmt=fmt)
        _with_face_element(tmp_path / f"{kind}.ply", faces, fmt, **{kind: True})
        r = run_cli("encode", tmp_path / f"{kind}.ply", tmp_path / f"out_{kind}", "-q")
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr
        assert not (tmp_path / f"out_{kind}").exists()


def test_a_compressed_ply_with_a_list_property_is_refused_naming_it(tmp_path):
    """A compressed PLY's elements are fixed (chunk, vertex, sh): one with a list property, skipped in a standard
    PLY after the splats, is refused there rather than read without it (an `sh` element would read as SH0)."""
    from conftest import ROOT

    data = (ROOT / "tests" / "fixtures" / "foreign" / "fruit_drops.compressed.ply").read_bytes()
    end = data.index(b"end_header\n")
    header, body = data[:end].decode(), data[end + len(b"end_header\n"):]
    cases = {"face": header + "element face 0\nproperty list uchar int vertex_indices\n",
             "sh": header.replace("property uchar f_rest_0\n",
                                  "property list uchar int ids\nproperty uchar f_rest_0\n")}
    for name, text in cases.items():
        (tmp_path / f"{name}.ply").write_bytes(text.encode() + b"end_header\n" + body)
        r = run_cli("encode", tmp_path / f"{name}.ply", tmp_path / f"out_{name}", "-q")
        assert r.returncode == 2 and f"({name} from the first with a list property)" in r.stderr, r.stderr
        assert len(r.stderr.splitlines()) == 1 and not (tmp_path / f"out_{name}").exists()
