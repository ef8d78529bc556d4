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
