"""refine_gpu (the torch side of `encode --lod-refine`, lod.md 6): its renderers against the numpy reference
(splatstream.render_ref), and the refiner end to end. Skipped without torch and gsplat (CI has neither); the CUDA
tests need a GPU: bench/device/run_refine_encode.sh runs this file there, with pytest or, where the machine's image
has none, as a script (`python3 tests/test_lod_refine_torch.py`)."""
from __future__ import annotations

import math
import sys

import numpy as np

if __name__ == "__main__":  # a script (the GPU machine's image has no pytest): the __main__ block below runs it
    pytest = None
else:
    import pytest


class Skipped(Exception):
    pass


def skip(reason: str):
    if pytest is not None:
        pytest.skip(reason)
    raise Skipped(reason)


def need(module: str):
    if pytest is not None:
        return pytest.importorskip(module)
    return __import__(module)


need("torch")
need("gsplat")

import torch  # noqa: E402

from refine_gpu.levels import LevelRefiner, RefineSettings, Renderer, to_params  # noqa: E402
from splatstream.camera import Camera  # noqa: E402
from splatstream.encode import EncodeOptions, encode_in_memory  # noqa: E402
from splatstream.format.manifest import parse_manifest  # noqa: E402
from splatstream.format.manifest.versions import VERSION_1_11  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402
from splatstream.lod import build_tiles  # noqa: E402
from splatstream.lod_refine import level_cuts, psnr_of  # noqa: E402
from splatstream.render_ref import render  # noqa: E402


def scene(n: int = 1500, seed: int = 3, degree: int = 1) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    k = (degree + 1) ** 2 - 1
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), q.astype(np.float32),
                     rng.normal(-2.8, 0.4, size=(n, 3)).astype(np.float32),
                     rng.normal(0, 1.5, size=n).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32),
                     rng.normal(0, 0.2, (n, k, 3)).astype(np.float32))


CAM = Camera((3.0, -2.0, 1.5), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 50.0, 40, 32, 0.01, 100.0)


def test_cpu_renderers_match_the_numpy_reference():
    g = scene(400)
    ref = np.clip(render(g, CAM), 0, 1)
    for backend in ("dense", "gsplat-torch"):
        img = Renderer(torch, "cpu", 1, backend)(to_params(torch, g, "cpu"), [CAM])[0].numpy()
        assert psnr_of(float(np.mean((np.clip(img, 0, 1) - ref) ** 2))) > 50.0, backend


def test_the_cpu_gsplat_path_leaves_gsplat_as_it_was():
    """gsplat-torch swaps gsplat's CUDA helpers only during its call: a CUDA render after it in the same process
    (the device's script runs every test in one process) must find gsplat's own."""
    import gsplat.rendering as gr
    from gsplat.cuda import _torch_impl as ti

    before = (gr.isect_tiles, gr.isect_offset_encode, gr.spherical_harmonics, ti._rasterize_to_pixels)
    Renderer(torch, "cpu", 1, "gsplat-torch")(to_params(torch, scene(50), "cpu"), [CAM])
    assert (gr.isect_tiles, gr.isect_offset_encode, gr.spherical_harmonics, ti._rasterize_to_pixels) == before


def test_gsplat_on_cuda_matches_the_dense_reference():
    if not torch.cuda.is_available():
        skip("no CUDA device")
    g = scene(2000)
    cam = Camera((3.0, -2.0, 1.5), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 50.0, 96, 80, 0.01, 100.0)
    ref = np.clip(render(g, cam), 0, 1)
    img = Renderer(torch, "cuda", 1, "gsplat")(to_params(torch, g, "cuda"), [cam])[0].clamp(0, 1).cpu().numpy()
    p = psnr_of(float(np.mean((img - ref) ** 2)))
    print(f"gsplat (CUDA) against render_ref: {p:.2f} dB")
    assert p > 35.0, p  # gsplat culls at 3 sigma, the reference at alpha 1/255: small differences only


def refine(device: str, backend: str, iterations: int, size: int):
    g = scene()
    tiles = build_tiles(g, 256, 2.0, merge="auto")
    refiner = LevelRefiner(RefineSettings(iterations=iterations, size=size, training_cameras=12,
                                          validation_cameras=6, batch=4, device=device, backend=backend))
    refined, record = refiner(g, tiles, (0.0, 0.0, 1.0), lambda stage, f: None)
    return g, tiles, refined, record, refiner.report


def check_refinement(tiles, refined, record, report) -> None:
    cuts = level_cuts(tiles)
    assert [lv.level for lv in record.levels] == [c.level for c in cuts]
    for cut, lv, rep in zip(cuts, record.levels, report, strict=True):
        psnr = dict(lv.validation_psnr)
        assert set(psnr) == {"none", "B", "C"} and lv.kept in psnr
        assert psnr[lv.kept] == max(psnr.values())  # kept by validation, the level as built on a tie
        assert rep["kept"] == lv.kept and rep["iterations"] == {"B": record.iterations, "C": record.iterations}
        if lv.kept == "none":
            assert not set(cut.merged) & set(refined)
            continue
        assert set(cut.merged) <= set(refined)
        for tid in cut.merged:
            a, b = tiles[tid].gaussians, refined[tid]
            assert len(a) == len(b) and np.array_equal(a.sh_rest, b.sh_rest)  # higher bands never optimised
            assert not np.array_equal(a.opacity_logits, b.opacity_logits)
            if lv.kept == "B":
                assert np.array_equal(a.positions, b.positions) and np.array_equal(a.rotations, b.rotations)
    assert all(tiles[t].children for t in refined)  # leaves never


def test_the_refiner_on_the_cpu_keeps_per_level_what_validates_best():
    g, tiles, refined, record, report = refine("cpu", "dense", 8, 24)
    check_refinement(tiles, refined, record, report)
    assert any(lv.kept != "none" for lv in record.levels)
    m = parse_manifest(encode_in_memory(g, EncodeOptions(max_leaf_splats=256, lod_refiner=LevelRefiner(
        RefineSettings(iterations=2, size=16, training_cameras=4, validation_cameras=2, batch=2, device="cpu",
                       backend="dense")))).read_manifest())
    assert m.version >= VERSION_1_11 and m.lod.refinement.size_px == 16  # 1.12 with the compact table


def test_the_refiner_on_cuda_improves_the_levels():
    if not torch.cuda.is_available():
        skip("no CUDA device")
    g, tiles, refined, record, report = refine("cuda", "gsplat", 100, 128)
    check_refinement(tiles, refined, record, report)
    gains = [dict(lv.validation_psnr)[lv.kept] - dict(lv.validation_psnr)["none"] for lv in record.levels]
    print("validation gains per level (dB):", " ".join(f"{x:.2f}" for x in gains))
    assert sum(1 for lv in record.levels if lv.kept != "none") >= len(record.levels) // 2
    assert math.isfinite(sum(gains)) and max(gains) > 0.5


if __name__ == "__main__":
    failed = 0
    for name, fn in list(globals().items()):
        if name.startswith("test_") and callable(fn):
            try:
                fn()
                print(f"PASSED {name}")
            except Skipped as e:
                print(f"SKIPPED {name}: {e}")
            except Exception as e:  # noqa: BLE001 (a script's report of every test)
                failed += 1
                print(f"FAILED {name}: {e!r}")
    sys.exit(1 if failed else 0)
