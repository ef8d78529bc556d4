"""GPU radix sort (compute shaders) against numpy's stable argsort; CPU sort path ordering."""
from __future__ import annotations

import numpy as np
import pytest

moderngl = pytest.importorskip("moderngl")


@pytest.fixture(scope="module")
def sorter(gl_compute_context):
    from client_gl.gpu.sort import GpuRadixSort

    s = GpuRadixSort(gl_compute_context, 40000)
    yield s
    s.release()


def _check(sorter, keys: np.ndarray) -> None:
    keys = keys.astype(np.uint32)
    values = np.random.default_rng(1).permutation(len(keys)).astype(np.uint32)
    out_k, out_v = sorter.sort_arrays(keys, values)
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(out_k, keys[order])
    np.testing.assert_array_equal(out_v, values[order])


@pytest.mark.parametrize("n", [0, 1, 2, 255, 256, 257, 2047, 2048, 2049, 4097, 12345, 40000])
def test_random_keys(sorter, n):
    rng = np.random.default_rng(n)
    _check(sorter, rng.integers(0, 2**32, n, dtype=np.uint64))


@pytest.mark.parametrize("kind", ["all_equal", "sorted", "reversed", "few_values", "high_bits", "max_min"])
def test_adversarial_keys(sorter, kind):
    n = 9001  # not a multiple of the work-group tile
    rng = np.random.default_rng(7)
    keys = {
        "all_equal": np.full(n, 0xDEADBEEF, np.uint64),
        "sorted": np.sort(rng.integers(0, 2**32, n, dtype=np.uint64)),
        "reversed": np.sort(rng.integers(0, 2**32, n, dtype=np.uint64))[::-1],
        "few_values": rng.integers(0, 3, n).astype(np.uint64),
        "high_bits": rng.integers(0, 16, n).astype(np.uint64) << np.uint64(28),
        "max_min": np.where(rng.random(n) < 0.5, 0, 2**32 - 1).astype(np.uint64),
    }[kind]
    _check(sorter, keys)


def test_depth_keys_give_back_to_front(sorter):
    depths = np.random.default_rng(3).uniform(0.2, 50.0, 5000).astype(np.float32)
    depths[100:200] = depths[50]  # ties keep index order
    keys = np.uint32(0xFFFFFFFF) - depths.view(np.uint32)
    _, ids = sorter.sort_arrays(keys)
    from client_gl.gpu.sort import depth_order

    np.testing.assert_array_equal(ids, depth_order(depths))


def test_auto_sort_choice(gl_compute_context):
    from client_gl.gpu.renderer import choose_sort, is_software

    ctx = gl_compute_context
    expected = "cpu" if is_software(ctx) or ctx.version_code < 430 else "gpu"
    assert choose_sort(ctx, "auto") == expected
    assert choose_sort(ctx, "cpu") == "cpu"
    assert choose_sort(ctx, "gpu") == "gpu"


@pytest.mark.parametrize("per_pass", [False, True])
@pytest.mark.parametrize("radix_bits,fused", [(4, False), (5, True), (6, True), (7, True), (8, True), (8, False)])
def test_variants_sort_like_numpy(gl_compute_context, radix_bits, fused, per_pass):
    """The measurement variants (8-bit digits, the five-dispatch pass, each pass its own programs) sort as the
    default does, and the fused pass leaves its block sums at zero for the next sort (several sorts of different
    sizes in a row)."""
    from client_gl.gpu.sort import GpuRadixSort

    s = GpuRadixSort(gl_compute_context, 30000, radix_bits=radix_bits, fused=fused, per_pass=per_pass)
    assert s.passes() == {4: 8, 5: 8, 6: 6, 7: 6, 8: 4}[radix_bits]
    assert s.passes(24) == {4: 6, 5: 6, 6: 4, 7: 4, 8: 4}[radix_bits]
    rng = np.random.default_rng(radix_bits)
    for n in (0, 1, 2049, 30000, 777):
        _check(s, rng.integers(0, 2**32, n, dtype=np.uint64))
    for kind in ("few_values", "high_bits"):
        keys = rng.integers(0, 3, 9001) if kind == "few_values" else rng.integers(0, 16, 9001) << 28
        _check(s, keys.astype(np.uint64))
    if fused:
        assert not np.frombuffer(s.reduced.read(), np.uint32).any()
    s.release()


def _check_low_bits(ctx, s, seed: int) -> None:
    """Sorting 20,000 keys by their low 13 bits (the tile sort at 1080p) is a stable sort by those bits."""
    import struct

    n = 20000
    rng = np.random.default_rng(seed)
    keys = rng.integers(0, 8160, n).astype(np.uint32)
    values = rng.permutation(n).astype(np.uint32)
    kb, vb = ctx.buffer(keys.tobytes()), ctx.buffer(values.tobytes())
    params = ctx.buffer(struct.pack("4I", n, 0, 0, 0))
    s.setup(params)
    s.sort(params, kb, vb, bits=13)
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(np.frombuffer(kb.read(), np.uint32), keys[order])
    np.testing.assert_array_equal(np.frombuffer(vb.read(), np.uint32), values[order])
    for b in (kb, vb, params):
        b.release()


@pytest.mark.parametrize("per_pass", [False, True])
@pytest.mark.parametrize("radix_bits", [4, 6, 7, 8])
def test_low_bits_sort_is_stable(gl_compute_context, radix_bits, per_pass):
    """A sort by the low bits only (the tile sort: 13 bits at 1080p) is a stable sort by those bits."""
    from client_gl.gpu.sort import GpuRadixSort

    s = GpuRadixSort(gl_compute_context, 20000, radix_bits=radix_bits, per_pass=per_pass)
    _check_low_bits(gl_compute_context, s, 5)
    s.release()


def test_one_program_set_serves_every_pass_and_sorter(gl_compute_context):
    """Without per_pass a sort compiles three programs whatever its passes (a first frame's compiles: the depth and
    tile sorts 6 programs, not 18), sorters of one digit width share them (each pass sets its uniforms right before
    its dispatches), and the storage bindings after a sort are those the per-pass programs leave."""
    from client_gl.gpu.sort import GpuRadixSort

    ctx = gl_compute_context
    shared = [GpuRadixSort(ctx, 20000, radix_bits=6) for _ in range(2)]
    for k, s in enumerate(shared):
        _check(s, np.random.default_rng(k).integers(0, 2**32, 12345, dtype=np.uint64))
        _check_low_bits(ctx, s, 9 + k)
    assert shared[0]._programs(0) == shared[1]._programs(3)  # the same three programs, whatever the pass
    assert len({id(p) for s in shared for p in s._programs(0)}) == 3
    per_pass = GpuRadixSort(ctx, 20000, radix_bits=6, per_pass=True)
    _check(per_pass, np.random.default_rng(5).integers(0, 2**32, 12345, dtype=np.uint64))
    assert len({id(p) for k in range(per_pass.passes()) for p in per_pass._programs(k)}) == 3 * per_pass.passes()
    for s in (*shared, per_pass):
        s.release()
