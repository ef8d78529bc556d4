"""The canonical rotation gauge (splatstream/rotation_canon.py): the same covariance for every splat, rotations
within pi/8 of the identity per axis, and the encoder's use of it (presets.PRESET_ROTATION_GAUGE)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import real

from splatstream.encode import EncodeOptions
from splatstream.encode.local import encode_in_memory
from splatstream.format import presets as P
from splatstream.gaussians import Gaussians, covariances, normalize_quaternions, rotation_matrices
from splatstream.io import read_gaussians
from splatstream.rotation_canon import CUBE_GROUP, HALF_TURNS, SCALE_PERMUTATION, canonical_gauge
from splatstream.scene_decode import decode_scene

# The gauge's covariance change is float32 rounding of the returned quaternion: about 1e-7 of the largest scale
# squared (measured 1.0e-7 over 200,000 random splats); the bound leaves room for the worst case.
COVARIANCE_BOUND = 1e-6


def _random_splats(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    ls = (rng.normal(size=(n, 3)) - 4.0).astype(np.float32)
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), q, ls, np.zeros(n, np.float32),
                     np.zeros((n, 3), np.float32), np.zeros((n, 0, 3), np.float32))


def _covariance_change(a: Gaussians, b: Gaussians) -> np.ndarray:
    """Per splat: the largest entry of the covariance difference over the largest scale squared."""
    ca = covariances(replace(a, rotations=normalize_quaternions(a.rotations)))
    cb = covariances(b)
    return np.abs(ca - cb).max(axis=(1, 2)) / np.exp(2.0 * a.log_scales.astype(np.float64).max(axis=1))


def test_cube_group_is_the_24_rotations_of_a_cube():
    assert CUBE_GROUP.shape == (24, 4)
    np.testing.assert_allclose(np.linalg.norm(CUBE_GROUP, axis=1), 1.0)
    r = rotation_matrices(CUBE_GROUP)
    # Signed permutation matrices of determinant 1, each rotation once (q and -q are one rotation).
    assert np.allclose(np.abs(r).sum(axis=1), 1.0) and np.allclose(np.linalg.det(r), 1.0)
    assert len({tuple(np.rint(m).astype(int).ravel()) for m in r}) == 24
    assert all(sorted(p) == [0, 1, 2] for p in SCALE_PERMUTATION.tolist())


def test_every_splat_keeps_its_covariance_and_gets_the_rotation_closest_to_identity():
    g = _random_splats(50_000)
    q, ls = canonical_gauge(g.rotations, g.log_scales)
    assert q.dtype == np.float32 and ls.dtype == g.log_scales.dtype
    out = replace(g, rotations=q, log_scales=ls)
    assert _covariance_change(g, out).max() <= COVARIANCE_BOUND
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    # w the largest component and every other within tan(pi/8) w: the closest of the 24 to the identity.
    assert (np.abs(q[:, 1:]) <= np.tan(np.pi / 8) * q[:, :1] + 1e-6).all()
    assert q[:, 0].min() >= 0.85
    # The scales are the input's, permuted.
    np.testing.assert_array_equal(np.sort(ls, axis=1), np.sort(g.log_scales, axis=1))


def test_half_turns_keep_the_scales_and_permute_the_components():
    g = _random_splats(20_000, seed=1)
    q, ls = canonical_gauge(g.rotations, g.log_scales, "half-turns")
    assert len(HALF_TURNS) == 4 and (SCALE_PERMUTATION[HALF_TURNS] == [0, 1, 2]).all()
    assert _covariance_change(g, replace(g, rotations=q, log_scales=ls)).max() <= COVARIANCE_BOUND
    np.testing.assert_array_equal(ls, g.log_scales)
    # w the largest component, and the components the input's (normalised) up to order and sign: a quaternion on
    # a smallest-three grid stays on it.
    assert (q[:, :1] >= np.abs(q[:, 1:]) - 1e-7).all()
    unit = normalize_quaternions(g.rotations)
    np.testing.assert_allclose(np.sort(np.abs(q), axis=1), np.sort(np.abs(unit), axis=1), atol=1e-7)
    with pytest.raises(ValueError, match="gauge"):
        canonical_gauge(g.rotations, g.log_scales, "octahedron")


def test_a_rotation_near_the_identity_and_an_empty_set_are_left_alone():
    q = np.array([[1.0, 0.01, -0.02, 0.03]], np.float32)
    ls = np.array([[-3.0, -4.0, -5.0]], np.float32)
    out_q, out_ls = canonical_gauge(q, ls)
    np.testing.assert_allclose(out_q, normalize_quaternions(q), atol=1e-7)
    np.testing.assert_array_equal(out_ls, ls)
    eq, els = canonical_gauge(np.zeros((0, 4), np.float32), np.zeros((0, 3), np.float32))
    assert eq.shape == (0, 4) and els.shape == (0, 3)


def test_a_quarter_turn_swaps_the_two_scales_it_exchanges():
    # A quarter turn about z: x -> y. Its gauge is the identity with the x and y scales swapped.
    c = np.float32(np.sqrt(0.5))
    q, ls = canonical_gauge(np.array([[c, 0, 0, c]], np.float32), np.array([[-1.0, -2.0, -3.0]], np.float32))
    np.testing.assert_allclose(q, [[1.0, 0.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_array_equal(ls, [[-2.0, -1.0, -3.0]])


# low with its rotations as before format 1.13 (norm565 over [-1, 1]): cube565 stores the cube gauge always, which
# its range needs (presets.rotation_gauge; tests/test_format_1_13.py), so the gauge's own effect is measured on norm565;
# medium-low's on norm8x4, the half turns it keeps where they measure closer (1.14: guitar's rotations take cube8x4)
@pytest.mark.parametrize("preset,gauge,overrides", [("medium", "half-turns", {}),
                                                    ("medium-low", "half-turns", {"rotation": "norm8x4"}),
                                                    ("low", "cube", {"rotation": "norm565"})])
def test_the_encoder_stores_the_gauge_with_the_same_picture_and_fewer_bytes(preset, gauge, overrides, monkeypatch):
    g = read_gaussians(real("guitar.compressed.ply")).subset(np.arange(20_000))
    sizes, decoded = {}, {}
    for on in (False, True):
        monkeypatch.setattr(P, "PRESET_ROTATION_GAUGE", {preset: gauge} if on else {})
        store = encode_in_memory(g, EncodeOptions(preset=preset, lod=False, overrides=overrides))
        sizes[on] = sum(len(b) for b in store.payloads.values())
        decoded[on] = decode_scene(store)
    q = decoded[True].rotations
    if gauge == "cube":  # the decoded rotations near the identity
        assert (np.abs(q[:, 1:]) <= np.tan(np.pi / 8) * q[:, :1] + 0.02).all()
    else:
        assert (q[:, :1] >= np.abs(q[:, 1:]) - 0.01).all()
    # Both decodes the same covariances within the formats' own error (each against the input).
    change = {k: _covariance_change(g, d) for k, d in decoded.items()}
    assert np.percentile(change[True], 99) <= 1.1 * np.percentile(change[False], 99)
    assert sizes[True] < sizes[False]
