"""The PlayCanvas SOG writer (splatstream/writers/sog.py): our reader and splat-transform read back what it writes,
within SOG's quantisation of the input."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from conftest import ROOT
from test_open_formats import rotation_angle, sog_bounds
from test_tool_roundtrip import attribute_errors, run_tool, tool_gaussians

from splatstream.format.layout import morton_order
from splatstream.gaussians import Gaussians, normalize_quaternions
from splatstream.io import read_gaussians
from splatstream.readers.sog import read_sog
from splatstream.writers.sog import palette_size, quantise_1d, sog_unit, texture_size, write_sog

SOURCE = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"


def check_within_quantisation(g: Gaussians, src: Gaussians, meta: dict) -> dict[str, float]:
    """`g` read back from a SOG we wrote of `src` (same order): every attribute within what SOG keeps."""
    errors = {"position": float(np.abs(g.positions - src.positions).max())}
    assert (np.abs(g.positions - src.positions) <= sog_bounds(meta, g) / 2 + 1e-6).all()  # rounded: half a step
    # Rotations: the smallest three to 8 bits, rounded: each within half a step (0.0028), the largest rebuilt from
    # them; measured 0.015 rad on the fixture (splat-transform's truncated bytes: 0.023).
    errors["rotation_angle"] = float(rotation_angle(g.rotations, src.rotations).max())
    assert errors["rotation_angle"] < 0.02
    errors["opacity"] = float(np.abs(g.opacities - src.opacities).max())
    assert errors["opacity"] <= 0.5 / 255 + 1e-6
    # Scales and colours: the nearest entry of the 256-entry codebook, also under a zero alpha (WebP `exact`).
    for field, key in (("log_scales", "scales"), ("sh_dc", "sh0")):
        book = np.asarray(meta[key]["codebook"])
        nearest = np.abs(getattr(src, field)[..., None] - book).min(axis=-1)
        assert (np.abs(getattr(g, field) - getattr(src, field)) <= nearest + 1e-5).all(), field
        errors[field] = float(np.abs(getattr(g, field) - getattr(src, field)).max())
    if src.sh_degree:
        errors["sh_rest_rms"] = float(np.sqrt(((g.sh_rest - src.sh_rest) ** 2).mean()))
        assert errors["sh_rest_rms"] < 0.03
    return errors


def test_layout_sizes_follow_splat_transform():
    assert texture_size(4721) == (72, 68)  # ceil(sqrt(4721) / 4) * 4 = 72; ceil(4721 / 72 / 4) * 4 = 68
    assert texture_size(1) == (4, 4)
    assert palette_size(4721) == 4096 and palette_size(1_000_000) == 65536 and palette_size(100) == 64


def test_quantise_1d_exact_for_few_values_and_nearest_otherwise():
    book, labels = quantise_1d(np.array([[3.0, -1.0], [3.0, 0.5]]))
    assert len(book) == 256 and book[0] == -1.0 and book[1] == 0.5 and book[2] == 3.0
    assert book[labels].tolist() == [[3.0, -1.0], [3.0, 0.5]]
    values = np.random.default_rng(1).normal(size=20000)
    book, labels = quantise_1d(values)
    assert np.all(np.diff(book) >= 0)
    nearest = np.abs(values[:, None] - book[None]).min(axis=1)
    assert np.allclose(np.abs(values - book[labels]), nearest, atol=1e-6)
    assert np.sqrt((nearest ** 2).mean()) < 0.01  # 256 entries over a normal sample's +-4 range


def test_sog_round_trip_through_our_reader(tmp_path):
    src = read_gaussians(SOURCE)
    path = tmp_path / "x.sog"
    write_sog(src, path)
    with zipfile.ZipFile(path) as archive:
        names = set(archive.namelist())
        meta = json.loads(archive.read("meta.json"))
    assert names == {"meta.json", "means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp",
                     "shN_centroids.webp", "shN_labels.webp"}
    assert meta["version"] == 2 and meta["count"] == len(src) == 4721
    assert meta["shN"]["bands"] == 3 and meta["shN"]["count"] == 4096 and len(meta["shN"]["codebook"]) == 256
    g = read_sog(path)
    errors = check_within_quantisation(g, src.subset(morton_order(src.positions)), meta)
    assert errors["position"] < 1e-5


def test_unit_keeps_order_when_asked():
    src = read_gaussians(SOURCE).with_sh_degree(0).subset(np.arange(500))
    unit = sog_unit(src, reorder=False)
    assert set(unit.files) == {"means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"}
    assert "shN" not in unit.meta


def test_convert_writes_sog(tmp_path):
    out = tmp_path / "x.sog"
    r = subprocess.run([sys.executable, "-m", "cli", "convert", str(SOURCE), str(out), "-q"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert len(read_gaussians(out)) == 4721
    assert [p.name for p in tmp_path.iterdir()] == ["x.sog"]  # no temporary left behind


def test_splat_transform_reads_our_sog(tmp_path):
    """The peer tool decodes our .sog to the same splats our reader does (it is the format's reference reader)."""
    src = read_gaussians(SOURCE)
    path = tmp_path / "ours.sog"
    write_sog(src, path)
    run_tool(path, tmp_path / "tool.ply")
    reference = tool_gaussians(tmp_path / "tool.ply")
    errors = attribute_errors(read_sog(path), reference)
    for name, bound in {"positions": 1e-6, "log_scales": 1e-6, "sh_dc": 1e-6, "sh_rest": 1e-6, "opacity": 1e-6,
                        "rotation_angle": 1e-5}.items():
        assert errors[name] <= bound, (name, errors)


@pytest.mark.parametrize("count", [0, 1])
def test_tiny_scenes(tmp_path, count):
    src = read_gaussians(SOURCE).subset(np.arange(count))
    write_sog(src, tmp_path / "x.sog")
    g = read_sog(tmp_path / "x.sog")
    assert len(g) == count
    if count:
        assert np.abs(g.positions - src.positions).max() < 1e-6


def test_a_unit_reports_its_progress_inside_its_sh_palette():
    """A SOG unit's SH palette (build_codebook's tree fit) is most of its time: 30-35 s for a 524,288-splat unit of a
    2M-splat scene on a busy 2-core machine, where export-sog-lod's bar stood still. `progress` hears the planes,
    then the palette cell by cell, never backwards, ending at 1; the files are the same bytes as without it."""
    rng = np.random.default_rng(5)
    n = 20_000  # a palette of 16,384 over 20,000 rows: the tree fit (a smaller one is one flat k-means)
    rotations = normalize_quaternions(rng.normal(size=(n, 4)).astype(np.float32))
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rotations,
                  rng.normal(-3, 0.5, (n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                  rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 3, 3)).astype(np.float32))
    heard: list[float] = []
    unit = sog_unit(g, reorder=False, progress=heard.append)
    assert heard == sorted(heard) and heard[-1] == pytest.approx(1.0) and len(heard) > 10, heard
    assert heard[0] == pytest.approx(0.15)  # the planes, before the palette
    assert unit.files == sog_unit(g, reorder=False).files and unit.meta == sog_unit(g, reorder=False).meta
