"""Format 1.4: the chunk order `input` (format.md 3). A one-tile encode of an input already cut into quantised
chunks of 256 (compressed.ply) keeps the input's order, so its chunks and their grids are the input's."""
from __future__ import annotations

import pathlib

import numpy as np
import pytest
from conftest import read_manifest_dict, real, write_manifest_dict

from splatstream.decoder import decode_scene
from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.encode.plan import input_is_chunk_quantised
from splatstream.errors import FormatError
from splatstream.format.manifest import writer_version
from splatstream.io import read_gaussians

FIXTURES = pathlib.Path(__file__).parent / "fixtures" / "foreign"
CHUNKED = FIXTURES / "fruit_drops.compressed.ply"  # 296 splats: one tile, a full chunk and a partial one


def test_a_compressed_ply_is_chunk_quantised_and_continuous_or_reordered_inputs_are_not():
    g = read_gaussians(CHUNKED)
    assert input_is_chunk_quantised(g)
    assert input_is_chunk_quantised(read_gaussians(real("guitar.compressed.ply")))  # a real one, 90,854 splats
    assert not input_is_chunk_quantised(read_gaussians(real("fruit_drops_sh3.ply")))
    shuffled = g.subset(np.random.default_rng(0).permutation(len(g)))
    assert not input_is_chunk_quantised(shuffled)  # the same values, chunks of other splats


def test_writer_version_is_1_4_only_in_the_input_order():
    medium = {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"}
    assert writer_version(medium, chunk_order="input") == (1, 4)
    assert writer_version(medium, chunk_order="morton") == writer_version(medium) == (1, 2)
    assert writer_version({**medium, "position": "norm16x4"}, chunk_order="luminance") == (1, 3)


def _colour_error_in_steps(g, dec) -> float:
    """Largest SH0 error of the decoded scene against its input, in steps of the input's own per-chunk grids
    (dec in input order)."""
    n = len(g) // 256 * 256
    v = g.sh_dc[:n].reshape(-1, 256, 3).astype(np.float64)
    step = (v.max(axis=1, keepdims=True) - v.min(axis=1, keepdims=True)) / 255
    err = np.abs(dec.sh_dc[:n].reshape(-1, 256, 3) - v)
    return float(np.max(np.divide(err, step, out=np.zeros_like(err), where=step > 0)))


def test_one_tile_encode_of_a_chunked_input_keeps_its_order_and_grids(tmp_path):
    g = read_gaussians(CHUNKED)
    m = encode_gaussians(g, tmp_path / "kept", EncodeOptions(preset="medium"))
    assert m.version == (1, 4) and m.chunk_order == "input" and len(m.tiles) == 1
    d = read_manifest_dict(tmp_path / "kept")
    assert d["version"] == [1, 4] and d["chunk_order"] == "input"
    dec = decode_scene(tmp_path / "kept")
    # input order: each decoded splat is its input splat (positions within a step of medium's 11-bit grid)
    extent = g.positions.max(axis=0) - g.positions.min(axis=0)
    assert np.all(np.abs(dec.positions - g.positions) <= extent / 1023)
    kept = _colour_error_in_steps(g, dec)
    assert kept < 0.35  # the input's codes, off by the f16 rounding of the ranges only
    opacity = 1 / (1 + np.exp(-dec.opacity_logits.astype(np.float64)))
    assert np.abs(opacity * 255 - np.rint(opacity * 255)).max() < 2e-3  # on the input's 8-bit grid
    morton = encode_gaussians(g, tmp_path / "morton", EncodeOptions(preset="medium", chunk_order="morton"))
    assert morton.version == (1, 2) and morton.chunk_order == "morton"


def test_a_manifest_below_1_4_may_not_name_the_input_order(tmp_path):
    g = read_gaussians(CHUNKED)
    encode_gaussians(g, tmp_path / "s", EncodeOptions(preset="medium"))
    d = read_manifest_dict(tmp_path / "s")
    d["version"] = [1, 3]
    write_manifest_dict(tmp_path / "s", d)
    with pytest.raises(FormatError, match="chunk_order.*version 1.4 chunk order; the manifest is version 1.3"):
        decode_scene(tmp_path / "s")
