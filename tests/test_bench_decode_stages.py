"""bench/decode_stages.py (issue 32, vhdec32b): its wrappers of the group path's calls decode the same texels,
reach every stage, and are put back by close(). No timing is asserted (only that each wrapped call ran)."""
from __future__ import annotations

import pytest
from conftest import load_bench, real

from splatstream.encode import EncodeOptions
from splatstream.encode.local import encode_in_memory
from splatstream.format import container, transport
from splatstream.io import read_gaussians

decode_jit = pytest.importorskip("client_gl.stream.decode_jit", reason="numba (the `fast` extra) is not installed")


@pytest.fixture
def installed():
    """The compiled kernels during the test, numpy's path after it."""
    decode_jit.install()
    yield
    decode_jit.uninstall()


def test_stages_wrap_the_group_path_without_changing_its_texels_and_close_puts_it_back(installed):
    stages_module = load_bench("decode_stages")
    quiet = stages_module.decode_quiet
    store = encode_in_memory(read_gaussians(real("lod_tile_sh3_zero_rest.ply")), EncodeOptions(preset="very-high"))
    case = quiet.Case(store)
    reference = case.texels()
    originals = (container.run_whole_at, container._unpack_group, container._decompress_group,
                 container._decompress_into, transport.whole_kernel())
    stages = stages_module.Stages(transport.whole_kernel())
    try:
        assert case.texels() == reference
        stages.reset()
        took = case.run("verified")
        spent = stages.spent
        assert set(spent) == set(stages_module.STAGES)
        for stage in ("zstd", "plan", "call", "kernel", "views"):  # each wrapped call ran
            assert spent[stage] > 0, stage
        assert sum(spent.values()) <= took + 1e-6  # the stages are parts of the pass
    finally:
        stages.close()
    assert (container.run_whole_at, container._unpack_group, container._decompress_group, container._decompress_into,
            transport.whole_kernel()) == originals
