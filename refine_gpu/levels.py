"""The merged LOD levels refined against gsplat renders of the full-detail scene (lod.md 6, the optional step;
`encode --lod-refine`; issue 31, phase 2 of bench/device/refine_lod_levels.py, whose rendering this is).

Each merged level is refined ALONE, drawn as its whole cut (lod_refine.level_cuts: its merged tiles and the
shallower leaves, the originals fixed), by Adam on the MSE of the clamped images against renders of the full
detail from lod_refine.refine_cameras' training cameras, once per variant (lod_refine.VARIANT_FIELDS: B opacity,
DC colour and log-scales; C also positions and rotations); each result, and the level as built, is then judged on
VALIDATION cameras (the same rule, another seed and count) and the best is kept, the level as built where no variant
beats it. Higher SH bands are never optimised.

Our renderer's conventions, matched in gsplat: the 0.3 px^2 low-pass (gsplat eps2d=0.3), the 0.99 opacity clamp
(gsplat clamps alpha at 0.999: the opacities are clamped to 0.99 before, the same within o (1 - exp(power)) for
o > 0.99), the 1/255 alpha cut (gsplat's), colour max(SH(dir) + 0.5, 0) with SH_C0 (gsplat's with sh_degree), black
background, pinhole K with the principal point at the image centre and pixel centres at +0.5 (camera.md), the
OpenCV world-to-camera matrix (Camera.world_to_camera_cv), splats with depth <= near culled (the view rule's near).
`dense_render` (a small dense torch rasteriser of the same conventions, on the CPU) is the numpy reference's
stand-in for tests; `gsplat_torch_rasterization` is gsplat's own autograd path on the CPU, to check our arguments.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from splatstream import lod_refine
from splatstream.camera import Camera, scene_orbit_views
from splatstream.format.manifest import LevelRefinement, LodRefinement
from splatstream.gaussians import Gaussians
from splatstream.lod import Tile
from splatstream.lod_refine import (
    GPU_ITERATIONS,
    GPU_SIZE_PX,
    TRAINING_CAMERAS,
    TRAINING_SEED,
    UNREFINED,
    VALIDATION_CAMERAS,
    VALIDATION_SEED,
    VARIANT_FIELDS,
    in_domain,
    kept_candidate,
    level_cuts,
    level_outcome,
    split_merged,
)
from splatstream.render_ref import ALPHA_MAX

OPACITY_MAX = ALPHA_MAX  # our renderers' alpha clamp (client_gl splat.frag), render_ref's
# Adam's learning rates per field (phase 1's); positions' is 2e-4 x the orbit distance (scale-free).
LR = {"opacity_logits": 0.05, "sh_dc": 0.005, "log_scales": 0.005, "rotations": 0.002}
POSITION_LR_PER_DISTANCE = 2e-4
EXTRA = "pip install 'splatstream[refine]'"


def missing(device: str = "cuda") -> str | None:
    """What this machine lacks for the refinement (None: nothing): torch, gsplat, a CUDA device, gsplat's CUDA
    extension (built on first use: about a minute and a half, then cached)."""
    try:
        import torch
    except ImportError:
        return "torch is not installed"
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return "gsplat is not installed"
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            return "no CUDA device (torch.cuda.is_available() is false)"
        from gsplat.cuda._backend import _C  # JIT-compiles gsplat's CUDA once (cached under ~/.cache/torch_extensions)

        if _C is None:
            return "gsplat's CUDA extension could not be built (nvcc / CUDA_HOME not found)"
    return None


# --- rendering ---------------------------------------------------------------------------------------------------

def camera_tensors(cams: list[Camera], torch, device):
    view = np.stack([c.world_to_camera_cv() for c in cams]).astype(np.float32)
    ks = np.stack([c.intrinsics() for c in cams]).astype(np.float32)
    return torch.from_numpy(view).to(device), torch.from_numpy(ks).to(device)


def eval_sh_torch(torch, sh, dirs, degree: int):
    """SH colour (N, 3) before the +0.5 offset: gsplat's pure-torch evaluation (the reference 3DGS basis, ours)."""
    from gsplat.cuda._torch_impl import _spherical_harmonics

    return _spherical_harmonics(degree, dirs, sh)


def dense_render(torch, means, quats, scales, opac, sh, degree: int, cam: Camera):
    """(H, W, 3) float32: our conventions (render_ref's preprocess; every pixel against every splat, no 3-sigma
    cut, as the GL renderer's alpha >= 1/255 box), for small tests on the CPU."""
    dev, dt = means.device, means.dtype
    m = torch.tensor(cam.world_to_camera_cv(), dtype=dt, device=dev)
    t = means @ m[:3, :3].T + m[:3, 3]
    keep = t[:, 2] > cam.near
    t, means, quats, scales, opac, sh = t[keep], means[keep], quats[keep], scales[keep], opac[keep], sh[keep]
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    tz = t[:, 2]
    limx, limy = 1.3 * cam.tan_half_fov_x, 1.3 * cam.tan_half_fov_y
    tx = torch.clamp(t[:, 0] / tz, -limx, limx) * tz
    ty = torch.clamp(t[:, 1] / tz, -limy, limy) * tz
    zero = torch.zeros_like(tz)
    j = torch.stack([torch.stack([fx / tz, zero, -fx * tx / (tz * tz)], -1),
                     torch.stack([zero, fy / tz, -fy * ty / (tz * tz)], -1)], 1)
    q = quats / quats.norm(dim=1, keepdim=True)
    w, x, y, z = q.unbind(1)
    r = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)
    rs = r * scales[:, None, :]
    cov3 = rs @ rs.transpose(1, 2)
    tm = j @ m[:3, :3]
    c2 = tm @ cov3 @ tm.transpose(1, 2)
    a, b, c = c2[:, 0, 0] + 0.3, c2[:, 0, 1], c2[:, 1, 1] + 0.3
    det = a * c - b * b
    ca, cb, cc = c / det, -b / det, a / det
    px = fx * t[:, 0] / tz + cx
    py = fy * t[:, 1] / tz + cy
    dirs = means - torch.tensor(cam.eye, dtype=dt, device=dev)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    colour = torch.clamp_min(eval_sh_torch(torch, sh, dirs, degree) + 0.5, 0.0)
    order = torch.argsort(tz)
    gy, gx = torch.meshgrid(torch.arange(cam.height, device=dev, dtype=dt) + 0.5,
                            torch.arange(cam.width, device=dev, dtype=dt) + 0.5, indexing="ij")
    dx = px[order][None, :] - gx.reshape(-1, 1)
    dy = py[order][None, :] - gy.reshape(-1, 1)
    power = -0.5 * (ca[order] * dx * dx + cc[order] * dy * dy) - cb[order] * dx * dy
    alpha = torch.clamp(opac[order] * torch.exp(torch.clamp(power, max=0.0)), max=OPACITY_MAX)
    alpha = torch.where((power > 0) | (alpha < 1.0 / 255.0), torch.zeros_like(alpha), alpha)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    img = (alpha * trans) @ colour[order]
    return img.reshape(cam.height, cam.width, 3)


class Renderer:
    """Batched renders of a splat set (torch tensors) from cameras: gsplat on CUDA, dense_render on the CPU."""

    def __init__(self, torch, device: str, degree: int, backend: str = "gsplat"):
        self.torch, self.device, self.degree = torch, device, degree
        self.backend = "dense" if device == "cpu" and backend == "gsplat" else backend
        if self.backend == "gsplat":
            from gsplat import rasterization
            self.rasterization = rasterization
        elif self.backend == "gsplat-torch":
            self.rasterization = gsplat_torch_rasterization()

    def __call__(self, p: dict, cams: list[Camera]):
        torch = self.torch
        opac = torch.sigmoid(p["opacity_logits"]).clamp(max=OPACITY_MAX)
        scales = torch.exp(p["log_scales"])
        sh = torch.cat([p["sh_dc"][:, None, :], p["sh_rest"]], 1)
        if self.backend == "dense":
            return torch.stack([dense_render(torch, p["positions"], p["rotations"], scales, opac, sh, self.degree, c)
                                for c in cams])
        view, ks = camera_tensors(cams, torch, self.device)
        img, _, _ = self.rasterization(p["positions"], p["rotations"], scales, opac, sh, view, ks,
                                       cams[0].width, cams[0].height, near_plane=min(c.near for c in cams),
                                       far_plane=1e10, eps2d=0.3, sh_degree=self.degree)
        return img


def gsplat_torch_rasterization():
    """gsplat's `_rasterization` (its autograd version) with the CUDA helpers it still calls swapped for gsplat's own
    pure-torch ones: the same call as `rasterization`, on the CPU, to check our arguments' conventions here."""
    import gsplat.rendering as gr
    import torch
    from gsplat.cuda import _torch_impl as ti

    seen = {}

    def isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, **kw):
        seen.update(radii=radii, depths=depths)  # the compositing below needs them (CUDA's has the tile lists)
        return ti._isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height)

    def composite(means2d, conics, colors, opacities, width, height, *a, backgrounds=None, **kw):
        """gsplat's per-pixel blend (rasterize_to_pixels_fwd.cu: alpha = min(0.999, o exp(power)), skipped when
        power > 0 or alpha < 1/255, pixel centres at +0.5), every pixel against every splat in depth order."""
        out_c, out_a = [], []
        gy, gx = torch.meshgrid(torch.arange(height, dtype=means2d.dtype) + 0.5,
                                torch.arange(width, dtype=means2d.dtype) + 0.5, indexing="ij")
        for c in range(means2d.shape[0]):
            ok = (seen["radii"][c] > 0).all(-1)
            order = torch.argsort(torch.where(ok, seen["depths"][c], torch.inf))[:int(ok.sum())]
            m, q, o, col = means2d[c][order], conics[c][order], opacities[c][order], colors[c][order]
            dx = m[None, :, 0] - gx.reshape(-1, 1)
            dy = m[None, :, 1] - gy.reshape(-1, 1)
            power = -0.5 * (q[:, 0] * dx * dx + q[:, 2] * dy * dy) - q[:, 1] * dx * dy
            alpha = torch.clamp(o * torch.exp(torch.clamp(power, max=0.0)), max=0.999)
            alpha = torch.where((power > 0) | (alpha < 1.0 / 255.0), torch.zeros_like(alpha), alpha)
            trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
            out_c.append(((alpha * trans) @ col).reshape(height, width, -1))
            out_a.append((1 - trans[:, -1] * (1 - alpha[:, -1])).reshape(height, width, 1))
        return torch.stack(out_c), torch.stack(out_a)

    swaps = {(gr, "isect_tiles"): isect_tiles,
             (gr, "isect_offset_encode"): lambda ids, n, tw, th: torch.zeros((n, th, tw), dtype=torch.int32),
             (gr, "spherical_harmonics"): lambda deg, dirs, coeffs, masks=None: ti._spherical_harmonics(deg, dirs,
                                                                                                         coeffs),
             (ti, "_rasterize_to_pixels"): composite}  # _rasterization imports it when called

    def rasterization(*args, **kwargs):
        # Swapped only for the call: gsplat's CUDA `rasterization` reads the same module globals, and a later CUDA
        # render in this process must find them as gsplat made them.
        kept = {key: getattr(*key) for key in swaps}
        for (module, name), f in swaps.items():
            setattr(module, name, f)
        try:
            return gr._rasterization(*args, **kwargs)
        finally:
            for (module, name), f in kept.items():
                setattr(module, name, f)

    return rasterization


def to_params(torch, g: Gaussians, device: str) -> dict:
    f = {"positions": g.positions, "rotations": g.rotations, "log_scales": g.log_scales,
         "opacity_logits": g.opacity_logits, "sh_dc": g.sh_dc, "sh_rest": g.sh_rest}
    return {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)).to(device) for k, v in f.items()}


# --- the refiner -------------------------------------------------------------------------------------------------

@dataclass
class RefineSettings(lod_refine.SharedRefineSettings):
    """Phase 1's settings (BENCHMARKS.md, "Refining the merged levels against the originals"): 384 px (at 40 px,
    positions and rotations overfit the pixels), 300 Adam steps of 8 views per level and variant."""
    iterations: int = GPU_ITERATIONS
    size: int = GPU_SIZE_PX
    training_cameras: int = TRAINING_CAMERAS
    validation_cameras: int = VALIDATION_CAMERAS
    training_seed: int = TRAINING_SEED
    validation_seed: int = VALIDATION_SEED
    batch: int = 8
    variants: tuple[str, ...] = ("B", "C")
    # Wall-clock cap per level and variant (None: the iterations only); at least `min_iterations` are run.
    seconds_per_variant: float | None = None
    min_iterations: int = 30
    device: str = "cuda"
    backend: str = "gsplat"  # "dense" / "gsplat-torch": the CPU stand-ins (tests)
    seed: int = 0


class LevelRefiner:
    """lod_refine.LodRefiner on torch: (splats, tree, up, progress) -> ({tile id: refined splats}, record)."""

    name = "--lod-refine gpu"  # in messages (encode/driver.py); it does not run by partitions (no runs_by_partitions)

    def __init__(self, settings: RefineSettings | None = None):
        self.settings = settings or RefineSettings()
        self.report: list[dict] = []  # per level: splats, validation PSNR per candidate, kept, seconds

    def __call__(self, g: Gaussians, tiles: list[Tile], up, progress) -> tuple[dict[int, Gaussians], LodRefinement]:
        import torch

        s = self.settings
        dev = s.device
        train, valid = s.cameras(g.positions, up)
        orbit = scene_orbit_views(g.positions, 1, s.size, s.size, up=up, elevation_deg=25.0)[0]
        dist = math.dist(orbit.eye, orbit.target)
        render = Renderer(torch, dev, g.sh_degree, s.backend)

        def renders(p: dict, cams: list[Camera]):
            with torch.no_grad():
                return torch.cat([render(p, cams[i:i + s.batch]) for i in range(0, len(cams), s.batch)]).clamp(0, 1)

        full = to_params(torch, g, dev)
        gt, gt_valid = renders(full, train), renders(full, valid)
        del full

        def mse_over(p: dict, cams: list[Camera], target) -> float:
            return mean_mse(torch, render, p, cams, target, s.batch)

        cuts = level_cuts(tiles)
        refined: dict[int, Gaussians] = {}
        levels: list[LevelRefinement] = []
        self.report = []
        progress("refine", 0.0)
        for k, cut in enumerate(cuts):
            t0 = time.perf_counter()
            merged = Gaussians.concatenate([tiles[i].gaussians for i in cut.merged])
            pm = to_params(torch, merged, dev)
            pf = to_params(torch, Gaussians.concatenate([tiles[i].gaussians for i in cut.fixed]), dev) \
                if cut.fixed else None

            def whole(p: dict, pf=pf) -> dict:
                return p if pf is None else {f: torch.cat([pf[f], p[f]]) for f in p}

            scores = {UNREFINED: mse_over(whole(pm), valid, gt_valid)}
            results = {}
            iters = {}
            for v in s.variants:
                p, iters[v] = fit_fields(torch, render, whole, pm, VARIANT_FIELDS[v], train, gt, dist,
                                         iterations=s.iterations, batch=s.batch, seed=s.seed + cut.level,
                                         seconds=s.seconds_per_variant, min_iterations=s.min_iterations)
                scores[v] = mse_over(whole(p), valid, gt_valid)
                results[v] = p
            kept = kept_candidate(scores)
            if kept != UNREFINED:
                p = results[kept]
                refined.update(split_merged(tiles, cut, {f: in_domain(f, p[f].detach().cpu().numpy())
                                                         for f in VARIANT_FIELDS[kept]}))
            secs = time.perf_counter() - t0
            level, psnr = level_outcome(cut, scores, kept, len(merged), secs, s.log)
            levels.append(level)
            self.report.append({"level": cut.level, "merged_splats": len(merged), "validation_psnr": psnr,
                                "kept": kept, "iterations": iters, "seconds": round(secs, 2)})
            progress("refine", (k + 1) / len(cuts))
            del pm, pf, results
        return refined, s.record(s.variants, levels)


def fit_fields(torch, render, whole, pm: dict, fields: tuple[str, ...], cams: list[Camera], gt, dist: float, *,
               iterations: int, batch: int, seed: int, seconds: float | None = None,
               min_iterations: int = 0) -> tuple[dict, int]:
    """Adam on the MSE of `cams`' renders against `gt` (batches of `batch` views), `fields` of the merged splats `pm`
    free, the rest fixed (`whole` adds the level's fixed splats): at most `iterations` steps, and where `seconds` is
    given, no step begun after it once `min_iterations` are done. Returns the fitted values and the steps taken."""
    p = {f: (x.clone().requires_grad_(True) if f in fields else x) for f, x in pm.items()}
    groups = [{"params": [p[f]], "lr": LR.get(f, POSITION_LR_PER_DISTANCE * dist)} for f in fields]
    opt = torch.optim.Adam(groups, eps=1e-15)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    it = 0
    while it < iterations and (seconds is None or it < min_iterations or time.perf_counter() - t0 < seconds):
        views = rng.choice(len(cams), size=min(batch, len(cams)), replace=False)
        img = render(whole(p), [cams[i] for i in views]).clamp(0, 1)
        loss = ((img - gt[torch.as_tensor(views, device=gt.device)]) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        it += 1
    return {f: x.detach() for f, x in p.items()}, it


def mean_mse(torch, render, p: dict, cams: list[Camera], target, batch: int) -> float:
    """The mean over `cams` of each render's MSE against `target` (clamped images), inf where not finite."""
    with torch.no_grad():
        err = sum(float(((render(p, cams[i:i + batch]).clamp(0, 1) - target[i:i + batch]) ** 2)
                        .mean(dim=(1, 2, 3)).sum()) for i in range(0, len(cams), batch))
    err /= len(cams)
    return err if math.isfinite(err) else math.inf
