"""choose_modes' batched trials (splatstream/format/transport.py; issue 31's encode time): the same modes as the
one-candidate-at-a-time reference, and code_layer's reuse of the trials gives the same planes and parameters as
fitting and coding the chosen modes again. The scene-level check (every output byte the same) is
tests/test_encode_bytes.py's digests."""
from __future__ import annotations

import numpy as np
import pytest

from splatstream.format.transport import (
    BLOCK_TEXELS,
    FIELD_LAYOUTS,
    _block_costs,
    _choose,
    _cross_prediction,
    _field_dtype,
    _fit_cross,
    _plane_cost,
    _residual,
    _residual_rows,
    _sample_blocks,
    choose_modes,
    code_layer,
    field_bits,
    split_layer,
)


def reference_choose_modes(fields: list[np.ndarray], bits: tuple[int, ...]) -> list[tuple[bool, int | None]]:
    """choose_modes as first written: every candidate fitted, coded and measured on its own, the cheapest options
    taken by min() (the first of equal costs), the anchor sets in increasing mask order (the first of equal
    totals)."""
    nf = len(fields)
    blocks = len(fields[0]) // BLOCK_TEXELS
    pick = _sample_blocks(blocks)
    sample = fields if pick is None else [f.reshape(blocks, BLOCK_TEXELS)[pick].reshape(-1) for f in fields]
    alone = []
    for f, b in zip(sample, bits, strict=True):
        costs = {d: _plane_cost(_residual(f, b, d, None), b) for d in (False, True)}
        d = min(costs, key=costs.get)
        alone.append((costs[d], d))
    param_cost = 3.0 * len(sample[0]) // BLOCK_TEXELS
    cross = {}
    for i in range(nf):
        for r in range(nf):
            if i == r or bits[i] > 16 or bits[r] > 16:
                continue
            slope, intercept = _fit_cross(sample[i], sample[r], max(bits[i], bits[r]))
            pred = _cross_prediction(sample[r], slope, intercept)
            costs = {d: _plane_cost(_residual(sample[i], bits[i], d, pred), bits[i]) + param_cost
                     for d in (False, True)}
            d = min(costs, key=costs.get)
            cross[(i, r)] = (costs[d], d)
    best_total, best = float("inf"), None
    for mask in range(1, 1 << nf):
        anchors = [i for i in range(nf) if mask >> i & 1]
        total, modes = 0.0, []
        for i in range(nf):
            options = [(alone[i][0], alone[i][1], None)]
            if i not in anchors:
                options += [(cross[(i, r)][0], cross[(i, r)][1], r) for r in anchors if (i, r) in cross]
            cost, d, r = min(options, key=lambda o: o[0])
            total += cost
            modes.append((d, r))
        if total < best_total:
            best_total, best = total, modes
    return best


def correlated_layer(fmt: str, blocks: int, seed: int) -> np.ndarray:
    """A layer of `blocks` 16x16 blocks whose fields follow one smooth signal plus noise (so that deltas and
    cross predictions both pay somewhere), as texel bytes in texture order."""
    rng = np.random.default_rng(seed)
    width = 16 * min(blocks, 4)
    height = 16 * (blocks // min(blocks, 4))
    n = width * height
    dtype, words, layout = FIELD_LAYOUTS[fmt]
    word = np.dtype(dtype)
    signal = np.cumsum(rng.normal(0, 1, n))
    out = np.zeros((n, words), word)
    for w in range(words):
        for k, (shift, bits) in enumerate(layout):
            top = (1 << bits) - 1
            noise = rng.integers(0, 1 + (w + k) % 5, n)
            f = (np.abs(signal * (1 + w + k) + noise) * 3).astype(np.int64) % (top + 1)
            if (w + k) % 3 == 2:
                f = rng.integers(0, top + 1, n)  # a noise field: no mode pays
            if bits == word.itemsize * 8:
                out[:, w] = f.astype(word)
            else:
                out[:, w] |= (f.astype(np.uint64) << np.uint64(shift)).astype(word)
    return out.reshape(-1).view(np.uint8), width, height


FORMATS = sorted(FIELD_LAYOUTS)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("blocks", [1, 6, 80])  # 80: over the sample's 64 blocks, so no trials are kept
def test_choose_equals_the_reference_and_its_trials_are_the_chosen_codes(fmt, blocks):
    layer, width, height = correlated_layer(fmt, blocks, seed=blocks + len(fmt))
    bits = field_bits(fmt)
    fields = split_layer(layer, fmt, width, height)
    modes, trials = _choose(fields, bits)
    assert modes == reference_choose_modes(fields, bits) == choose_modes(fields, bits)
    assert (trials is None) == (_sample_blocks(len(fields[0]) // BLOCK_TEXELS) is not None)
    if trials is None:
        return
    nf = len(fields)
    for i in range(nf):
        refs = [None] + [r for r in range(nf) if (i, r) in trials.cross]
        assert len(refs) == (nf if bits[i] <= 16 and sum(b <= 16 for b in bits) == nf else 1)
        for ref in refs:
            for delta in (False, True):
                z, params = trials.code(i, delta, ref)
                pred = None
                if ref is not None:
                    slope, intercept = _fit_cross(fields[i], fields[ref], max(bits[i], bits[ref]))
                    assert [p.dtype for p in params] == [slope.dtype, intercept.dtype]
                    assert np.array_equal(params[0], slope) and np.array_equal(params[1], intercept)
                    pred = _cross_prediction(fields[ref], slope, intercept)
                want = _residual(fields[i], bits[i], delta, pred)
                assert z.dtype == want.dtype and np.array_equal(z, want)


@pytest.mark.parametrize("fmt", FORMATS)
def test_code_layer_with_its_trials_equals_coding_the_chosen_modes_again(fmt):
    layer, width, height = correlated_layer(fmt, 6, seed=7)
    chosen = code_layer(layer, fmt, width, height)  # the trials' codes
    again = code_layer(layer, fmt, width, height, chosen.modes)  # fitted and coded again
    assert chosen.modes == again.modes
    assert [p.tobytes() for p in chosen.params] == [p.tobytes() for p in again.params]
    assert [p.dtype for p in chosen.planes] == [p.dtype for p in again.planes]
    assert [p.tobytes() for p in chosen.planes] == [p.tobytes() for p in again.planes]
    assert any(r is not None for _, r in chosen.modes) or fmt in ("f32x4", "index16")


@pytest.mark.parametrize("bits", [(5, 6, 5), (10, 10, 10, 2), (11, 10, 11), (9, 9, 9), (16, 16), (8, 8), (32, 32)])
def test_residual_rows_equal_residual_row_by_row(bits):
    rng = np.random.default_rng(sum(bits))
    n = 3 * BLOCK_TEXELS
    for t in {_field_dtype(b) for b in bits}:
        rows = [b for b in bits if _field_dtype(b) is t]
        values = np.stack([rng.integers(0, 1 << b, n, dtype=np.uint64).astype(t) for b in rows])
        pred = rng.integers(-40000, 70000, (len(rows), n)).astype(np.int32)
        for p in (None, pred):
            x, d = _residual_rows(values, tuple(rows), p)
            for k, b in enumerate(rows):
                plain, delta = (_residual(values[k], b, d, None if p is None else p[k]) for d in (False, True))
                assert x[k].dtype == plain.dtype and np.array_equal(x[k], plain) and np.array_equal(d[k], delta)


def test_block_costs_equal_plane_cost_row_by_row():
    """Blocks of 8, 16 and 32-bit codes (planes with one value, all 256 values, skewed counts) measured in one
    batch give _plane_cost's floats exactly."""
    rng = np.random.default_rng(31)
    n = 6 * BLOCK_TEXELS
    blocks = [(np.stack([rng.integers(0, 256, n), np.zeros(n), rng.geometric(0.4, n)]).astype(np.uint8), 8),
              (np.stack([rng.geometric(0.3, n), rng.integers(0, 1 << 10, n)]).astype(np.uint16), 11),
              (np.stack([rng.integers(0, 1 << 20, n) * 3]).astype(np.uint32), 32),
              (np.stack([rng.integers(0, 32, n)]).astype(np.uint8), 5)]
    costs = _block_costs(blocks)
    assert costs == [[_plane_cost(z, b) for z in codes] for codes, b in blocks]
    assert costs[0][1] == 0.0 and abs(costs[0][0] - n) < 0.05 * n


def test_block_costs_with_more_planes_than_a_uint16_bin_index_holds():
    rng = np.random.default_rng(5)
    n = BLOCK_TEXELS
    codes = rng.geometric(0.2, (300, n)).astype(np.uint16)  # 600 byte planes: bins past 2^16
    assert _block_costs([(codes, 12)]) == [[_plane_cost(z, 12) for z in codes]]


def test_choose_modes_takes_fields_in_wider_arrays_as_before():
    """Fields handed in a wider integer type than their code type (a caller's arrays, not split_layer's) give the
    reference's modes: each residual is cut to its code type as _residual cuts it."""
    layer, width, height = correlated_layer("norm8x4", 6, seed=11)
    fields = [f.astype(np.uint16) for f in split_layer(layer, "norm8x4", width, height)]
    bits = field_bits("norm8x4")
    assert choose_modes(fields, bits) == reference_choose_modes(fields, bits)
