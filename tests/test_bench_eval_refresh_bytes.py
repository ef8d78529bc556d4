"""bench/eval_refresh_bytes.py (issue 32, eval32): a report's preset rows get the bytes of a fresh encode made as
`evaluate` makes it; quality fields and peer rows stay as measured; a row whose texels' shape moved is refused."""
from __future__ import annotations

import copy
import shutil

import pytest
from conftest import load_bench, real

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians

R = load_bench("eval_refresh_bytes")
UP = (0.0, -1.0, 0.0)


def stale_report(path, tmp_path) -> tuple[dict, object]:
    """A report of fruit_drops (SH3, 4,721 splats) with one low-plus row of made-up bytes and one peer row, and the
    manifest of low-plus encoded as evaluate encodes it."""
    g = read_gaussians(path)
    m = encode_gaussians(g, tmp_path / "enc", EncodeOptions(preset="low-plus", lod=False, up=UP))
    preset = {"label": "low-plus", "kind": "preset", "preset": "low-plus", "overrides": {}, "formats": dict(m.formats),
              "gpu_bytes": m.gpu_bytes, "sh_codebook_entries": m.sh_codebook.entries, "disk_bytes": 1000,
              "disk_bytes_per_splat": 0.2, "compression": 99.0, "bytes_on_disk_total": 1000, "leaf_bytes_on_disk": 900,
              "attributes": {}, "psnr_mean": 43.58, "psnr_per_view": [43.0, 44.0], "encode_seconds": 0.26}
    peer = {"label": "st-spz", "kind": "compare", "disk_bytes": 97875, "psnr_mean": 36.69}
    report = {"input": {"path": "/elsewhere/" + path.name, "bytes": path.stat().st_size, "splats": len(g)},
              "encode_options": {"lod": False, "zstd_level": None}, "camera_rule": {"up": list(UP)},
              "rows": [preset, peer]}
    return report, m


def test_preset_bytes_from_a_fresh_encode_quality_and_peers_kept(tmp_path):
    path = real("fruit_drops_sh3.ply")
    report, m = stale_report(path, tmp_path)
    before = copy.deepcopy(report)
    changed = R.refresh(report, [str(path.parent)])
    row, peer = report["rows"]
    # the payloads to the byte; the manifest within a few bytes (it records the encode's seconds)
    assert row["leaf_bytes_on_disk"] == m.leaf_bytes_on_disk
    assert abs(row["disk_bytes"] - m.bytes_on_disk) <= 16
    assert row["disk_bytes"] == row["bytes_on_disk_total"]
    assert row["disk_bytes_per_splat"] == pytest.approx(row["disk_bytes"] / 4721, abs=1e-6)
    assert row["compression"] == pytest.approx(path.stat().st_size / row["disk_bytes"], abs=1e-6)
    assert row["attributes"]["sh"]["disk_bytes"] == m.attributes["sh"].disk_bytes
    assert sum(a["disk_bytes"] for a in row["attributes"].values()) <= row["leaf_bytes_on_disk"]
    assert changed == [("low-plus", 1000, row["disk_bytes"])]
    assert row["bytes_refreshed"]["disk_bytes_before"] == 1000
    for key in ("psnr_mean", "psnr_per_view", "encode_seconds", "formats", "gpu_bytes"):
        assert row[key] == before["rows"][0][key]
    assert peer == before["rows"][1]


def test_only_filters_rows(tmp_path):
    path = real("fruit_drops_sh3.ply")
    report, _ = stale_report(path, tmp_path)
    assert R.refresh(report, [str(path.parent)], only={"medium"}) == []
    assert report["rows"][0]["disk_bytes"] == 1000


def test_refuses_a_row_whose_texels_moved_and_another_input(tmp_path):
    path = real("fruit_drops_sh3.ply")
    report, _ = stale_report(path, tmp_path)
    moved = copy.deepcopy(report)
    moved["rows"][0]["gpu_bytes"] += 4  # the formats' texels are not the report's: not a bytes-only change
    with pytest.raises(ValueError, match="gpu_bytes"):
        R.refresh(moved, [str(path.parent)])
    other = tmp_path / "in"
    other.mkdir()
    shutil.copy(path, other / path.name)
    with open(other / path.name, "ab") as f:
        f.write(b"\0")
    with pytest.raises(ValueError, match="bytes, the report's input has"):
        R.refresh(report, [str(other)])
    with pytest.raises(ValueError, match="not found"):
        R.refresh(report, [str(tmp_path / "nowhere")])
