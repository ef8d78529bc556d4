#!/usr/bin/env python3
"""Probe: why the statue scans lose to splat-transform at 2-25 % (issue 31; BENCHMARKS.md, "Why the statue scans
lose to splat-transform").

Builds our tree in memory (`lod.build_tiles`, the encoder's defaults: 16,384-splat leaves, reduction 2, `auto`) and
draws ONE WHOLE LEVEL of it (every tile of the level) from lod_vs_peers' 4 orbit views at 384 px (GL renderer,
float attributes), against the cached full-detail renders of bench/lod_vs_peers.py (--cache-dir). With
--peer-levels, splat-transform's adaptive levels of the same counts (chained 50 -> 25 -> 6 -> 2 %, as
lod_vs_peers builds them) are built into --work-dir and drawn the same way, with where their error lies.

Variants change one thing of the merge (applied to the module, one build each):

* `base`: the encoder as it is.
* `px=A/B`: opacity and base colour (lod.md 6 step 5) matched at A px on the first merged level (the children
  are leaves) and B px above it (0: no blur); the rule before 2026-11-29 is 2/2, 2/8 the one before 2026-11-30.
  `px=A/B/C`: above it opacity at B px and colour at C px.
* `rule:KEY=VALUE`: the cost grouping's GroupRule field (lod_groups.GroupRule) on every level;
  `above:KEY=VALUE`: the same above the first merged level only.
* `grow=A/G/CAP` (issue 31, branch `farpx31`): the level k above the first merged one (k = 1, 2, ...) matched at
  min(A x G^(k-1), CAP) px (opacity and colour; CAP `inf`: no cap), the first merged level at the encoder's
  OPACITY_MATCH_SSE_PX; `grow=8/1.5/16` is the encoder's rule since 2026-11-30 (lod.OPACITY_MATCH_FAR_GROWTH and
  _CAP_SSE_PX), `grow=8/1/inf` the 2 + 8 px rule before it; `far=C` is `grow=C/1/inf`.
* `opmax=C` (issue 31, branch `lodop31`): step 5's match without the 0.99 ceiling, capped at C (an opacity above 1
  draws as a flat-topped, wider splat: the renderer clamps alpha per pixel); `opmax=C@grow=A/G/CAP` with that
  viewing scale too. The probe carries an opacity o > 1 in a logit OVER_LOGIT + (o - 1) (the sigmoid of any logit
  there is 1.0 in float32) and, for every render of this process, reads the colour plane's opacity through
  over_opacity (the identity on every logit below OVER_LOGIT - 1).
* `optical`: the merged opacity from the members' summed optical depth, -log(1 - alpha_i) x dilated area,
  instead of their summed coverage (1 - exp(-depth / area) instead of min(0.99, coverage / area)).

    PYTHONPATH=. .venv/bin/python bench/probe_statue31.py statue-st-peter --cache-dir /tmp/lvp50/cache \
        --peer-levels --variants base px=2/4 px=2/8 px=2/0 rule:first_share=0.5 above:first_share=0.5 optical

Prints per variant each level of 1-60 % of the scene: PSNR dB (mean of the 4 views' MSE) and the share of the
merged splats at the opacity ceiling. Needs splat-transform for --peer-levels (bench/peers, `npm ci`).

    PYTHONPATH=. .venv/bin/python bench/probe_statue31.py --one-px 2 --variants base px=2/8 px=2/8/2

instead runs tests/test_lod.py's 1-px check (each level of the 2,000-splat-leaf `auto` tree of fruit_drops, lod_tile
and the donut, at this reduction, drawn from where its largest error is 1 px, 96x96, reference rasteriser) per
variant: PSNR dB against the full scene per level, root first.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import lod_vs_peers as lvp  # noqa: E402

from splatstream import lod  # noqa: E402
from splatstream.gaussians import Gaussians  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.orientation import detect_up  # noqa: E402


def error_split(imgs: list[np.ndarray], refs: list[np.ndarray]) -> list[float]:
    """Share of the squared error on the background (2 px outside the full render's coverage), the silhouette (a
    4-px band across its rim) and the interior; mean over the views."""
    out = []
    for a, b in zip(imgs, refs, strict=True):
        e = ((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2).sum(-1)
        cov = b.max(-1) > 1e-3
        grown, shrunk = cov.copy(), cov.copy()
        for axis in (0, 1):
            for s in (1, -1, 2, -2):
                grown |= np.roll(cov, s, axis)
                shrunk &= np.roll(cov, s, axis)
        total = e.sum()
        out.append([e[~grown].sum() / total, e[grown & ~shrunk].sum() / total, e[shrunk].sum() / total])
    return [round(float(x), 3) for x in np.mean(out, 0)]


def _blur(error: float, px: float) -> float:
    return 0.0 if px <= 0 else lod.LOW_PASS_PX2 * (error / px) ** 2


def _finish_tile_at(first_px: float, opacity_px: float, colour_px: float):
    """lod.finish_tile with the viewing scale `first_px` on the first merged level; above it opacity matched at
    `opacity_px` and base colour at `colour_px` (0: no blur)."""
    def finish_tile(merged, counts, far, near, child_error, appearance, above=1):
        errors, error = lod.tile_error_first(merged, counts, far, near, child_error)
        if child_error == 0.0 or opacity_px == colour_px:
            blur = _blur(error, first_px if child_error == 0.0 else opacity_px)
            lod.finish_appearance(merged, counts, appearance(blur), blur)
            return error
        logits, sh_dc = merged.opacity_logits, merged.sh_dc
        blur = _blur(error, colour_px)
        lod.finish_appearance(merged, counts, appearance(blur), blur)
        colour = merged.sh_dc
        merged.opacity_logits, merged.sh_dc = logits, sh_dc
        blur = _blur(error, opacity_px)
        lod.finish_appearance(merged, counts, appearance(blur), blur)
        merged.sh_dc = colour
        return error
    return finish_tile


def _optical_terms(opacity_logits, log_scales, sh_dc, blur):
    alpha = 1.0 / (1.0 + np.exp(-np.clip(opacity_logits.astype(np.float64), -700, 700)))
    area = lod._coverage_area(log_scales, blur)
    weight = alpha * area + 1e-300
    depth = np.logaddexp(0.0, opacity_logits.astype(np.float64)) * area  # -log(1 - alpha) x area
    return np.stack([depth, weight, weight * sh_dc[:, 0], weight * sh_dc[:, 1], weight * sh_dc[:, 2]])


def _optical_finish(merged, counts, sums, blur):
    single = counts == 1
    alpha = np.clip(-np.expm1(-sums[0] / lod._coverage_area(merged.log_scales, blur)), 1e-7,
                    lod.MAX_MERGED_OPACITY)
    logits = np.log(alpha / (1.0 - alpha)).astype(np.float32)
    merged.opacity_logits = np.where(single, merged.opacity_logits, logits)
    merged.sh_dc = np.where(single[:, None], merged.sh_dc, (sums[2:5].T / sums[1][:, None]).astype(np.float32))


def _rule_groups(spec: str, above_only: bool):
    key, value = spec.split("=")
    rule = dataclasses.replace(lod.AUTO_RULE, **{key: type(getattr(lod.AUTO_RULE, key))(value)})
    plain = lod.level_auto_groups

    def level_auto_groups(members, masses, targets, cap, blurs, rule_=lod.AUTO_RULE, pool=None,
                          sample=lod.AUTO_CHOICE_SAMPLE, judge_every_level=False):
        first = all(b == 0.0 for b in blurs)
        use = rule_ if (above_only and first) else rule
        return plain(members, masses, targets, cap, blurs, use, pool, sample, judge_every_level)
    return level_auto_groups


def grow_px(above: int, start: float, growth: float, cap: float) -> float:
    """px of `grow=START/GROWTH/CAP` on the level `above` levels above the first merged one (>= 1)."""
    return min(start * growth ** (above - 1), cap)


def _grow_patches(start: float, growth: float, cap: float) -> dict:
    """The library's growing rule (lod.viewing_scale_px): the level k above the first merged one at
    min(start x growth^(k - 1), cap) px."""
    return {"OPACITY_MATCH_FAR_SSE_PX": start, "OPACITY_MATCH_FAR_GROWTH": growth,
            "OPACITY_MATCH_FAR_CAP_SSE_PX": cap}


OVER_DRAW_MAX = 8.0  # the largest opacity the patched shaders draw (the largest cap probed)
OVER_LOGIT = 40.0  # float32 sigmoid(40) == 1.0; no input reaches it (ply clamps opacity logits at about 13.8)


def over_logits(alpha: np.ndarray) -> np.ndarray:
    """Logits of opacities that may exceed 1: o > 1 as OVER_LOGIT + (o - 1) (probe-only carrier)."""
    a = np.asarray(alpha, np.float64)
    below = np.log(np.minimum(a, 0.999) / (1.0 - np.minimum(a, 0.999)))
    return np.where(a >= 0.999, OVER_LOGIT + (a - 1.0), below).astype(np.float32)


def over_opacity(logits: np.ndarray) -> np.ndarray:
    """The inverse of over_logits: the sigmoid below OVER_LOGIT - 1, o = 1 + (logit - OVER_LOGIT) above."""
    from splatstream.gaussians import sigmoid

    lg = np.asarray(logits)
    return np.where(lg >= OVER_LOGIT - 1.0, 1.0 + (lg.astype(np.float64) - OVER_LOGIT),
                    sigmoid(lg)).astype(np.float32)


def install_over_opacity() -> None:
    """Every later encode of this process (the renders' in-memory encode) stores over_opacity in the colour plane,
    and every shader compiled after this draws the decoded opacity up to OVER_DRAW_MAX instead of clamping it at 1
    (splat.vert, cull.comp). Call it before the first render: compiled programs are kept. The CPU-sort path's host
    mirror still clips at 1 (its off-screen cull only: extents up to 17 % short for an opacity of 8)."""
    from client_gl.gpu import shadergen
    from splatstream.format import codec

    if codec.sigmoid is over_opacity:
        return
    codec.sigmoid = over_opacity
    plain = shadergen.read_shader
    shadergen.read_shader = lambda name: plain(name).replace("clamp(col.a, 0.0, 1.0)",
                                                             f"clamp(col.a, 0.0, {OVER_DRAW_MAX!r})")


def _finish_uncapped(cap: float):
    """lod.finish_appearance with the match's ceiling at `cap` instead of MAX_MERGED_OPACITY."""
    def finish_appearance(merged, counts, sums, blur):
        covered, total = sums[0], sums[1]
        single = counts == 1
        alpha = np.clip(covered / lod._coverage_area(merged.log_scales, blur), 1e-7, cap)
        merged.opacity_logits = np.where(single, merged.opacity_logits, over_logits(alpha))
        merged.sh_dc = np.where(single[:, None], merged.sh_dc, (sums[2:5].T / total[:, None]).astype(np.float32))
    return finish_appearance


def variant_patches(variant: str) -> dict:
    if variant == "base":
        return {}
    if variant.startswith("opmax="):
        cap, _, scale = variant[6:].partition("@")
        return {"finish_appearance": _finish_uncapped(float(cap)), **(variant_patches(scale) if scale else {})}
    if variant.startswith("px="):
        px = [float(x) for x in variant[3:].split("/")]
        return {"finish_tile": _finish_tile_at(px[0], px[1], px[-1])}
    if variant.startswith(("rule:", "above:")):
        kind, spec = variant.split(":", 1)
        return {"level_auto_groups": _rule_groups(spec, kind == "above")}
    if variant.startswith("grow="):
        start, growth, cap = (float(x) for x in variant[5:].split("/"))
        return _grow_patches(start, growth, cap)
    if variant.startswith("far="):
        return _grow_patches(float(variant[4:]), 1.0, math.inf)
    if variant == "optical":
        return {"appearance_terms": _optical_terms, "finish_appearance": _optical_finish}
    raise SystemExit(f"unknown variant {variant}")


def build_variant(g: Gaussians, variant: str, max_leaf_splats: int = 16384, reduction: float = 2.0
                  ) -> list[lod.Tile]:
    """lod.build_tiles(g, ..., merge="auto") with `variant`'s patches of the lod module, restored afterwards."""
    patches = variant_patches(variant)
    saved = {k: getattr(lod, k) for k in patches}
    try:
        for k, v in patches.items():
            setattr(lod, k, v)
        return lod.build_tiles(g, max_leaf_splats, reduction, merge="auto")
    finally:
        for k, v in saved.items():
            setattr(lod, k, v)


def encode_variant(full: str, out: str, variant: str) -> int:
    """`splatstream encode FULL OUT` in this process with `variant`'s patches of the lod module (the default encode
    of a scene this size builds its tree here, lod.build_tiles, `auto`)."""
    from cli.main import main as cli_main

    patches = variant_patches(variant)
    saved = {k: getattr(lod, k) for k in patches}
    try:
        for k, v in patches.items():
            setattr(lod, k, v)
        return cli_main(["encode", full, out])
    finally:
        for k, v in saved.items():
            setattr(lod, k, v)


def one_px(variants: list[str], reduction: float) -> None:
    """tests/test_lod.py's 1-px check (level_views) of its scenes, the trees built with each variant."""
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
    import test_lod  # the test's own scenes, cameras and renderer

    if any(v.startswith("opmax=") for v in variants):
        # the reference rasteriser reads Gaussians.opacities: the probe's opacities above 1 drawn as they are
        Gaussians.opacities = property(lambda self: over_opacity(self.opacity_logits))
    for name in test_lod.REAL_PLYS:
        for variant in variants:
            tiles = build_variant(test_lod.scene(name), variant, test_lod.MAX_LEAF, reduction)
            saved = test_lod.tree
            test_lod.tree = lambda _name, reduction=4.0, _tiles=tiles: _tiles
            try:
                levels = [f"L{level} {test_lod.psnr(full, coarse):.2f}"
                          for level, _n, (full, _), (coarse, _) in test_lod.level_views(name)]
            finally:
                test_lod.tree = saved
            print(f"{name} reduction {reduction:g} {variant}: " + ", ".join(levels), flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?")
    ap.add_argument("--one-px", type=float, default=None, metavar="REDUCTION",
                    help="instead: tests/test_lod.py's 1-px check of its scenes, trees at this reduction")
    ap.add_argument("--cache-dir", help="lod_vs_peers' --cache-dir (full.ply, ref_KEY.npy)")
    ap.add_argument("--work-dir", default="/tmp/probe_statue31")
    ap.add_argument("--peer-levels", action="store_true")
    ap.add_argument("--splat-transform", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "peers",
                                                              "node_modules", ".bin", "splat-transform"))
    ap.add_argument("--variants", nargs="+", default=["base"])
    ap.add_argument("--encode", metavar="OUT",
                    help="instead: `splatstream encode CACHE/SCENE/full.ply OUT` (the default preset) with the one "
                         "--variants' patches, for bench/lod_vs_peers.py --our-scene-dir (which reuses OUT)")
    ap.add_argument("--json", help="also write {variant: [{level, count, share, psnr}]} here")
    args = ap.parse_args(argv)
    if args.one_px:
        one_px(args.variants, args.one_px)
        return 0
    if not (args.scene and args.cache_dir):
        ap.error("SCENE and --cache-dir, or --one-px")

    sdir = os.path.join(args.cache_dir, args.scene)
    if args.encode:
        if len(args.variants) != 1:
            ap.error("--encode takes one variant")
        if args.variants[0].startswith("opmax="):
            ap.error("--encode cannot write opmax: the view client clamps opacity at 1 (whole levels only)")
        return encode_variant(os.path.join(sdir, "full.ply"), args.encode, args.variants[0])
    g = read_gaussians(os.path.join(sdir, "full.ply"))
    n = len(g)
    cams = lvp.view_cameras(g.positions, detect_up(g).up, 4, 384)
    refs = list(np.load(os.path.join(sdir, f"ref_{lvp.camera_key(cams)}.npy")))

    def psnr(imgs: list[np.ndarray]) -> float:
        return round(lvp.mean_psnr([lvp.quality(a, b)[0] for a, b in zip(imgs, refs, strict=True)]), 2)

    if args.peer_levels:
        os.makedirs(args.work_dir, exist_ok=True)
        prev = os.path.join(sdir, "full.ply")
        for c in lvp.budget_counts(n, [0.5, 0.25, 0.06, 0.02]):
            out = os.path.join(args.work_dir, f"{args.scene}_st_{c}.ply")
            if not os.path.exists(out):
                subprocess.run([args.splat_transform, "-w", "-g", "cpu", "--no-tty", prev, "--decimate-adaptive",
                                str(c), out], check=True, capture_output=True)
            prev = out
            imgs = lvp.render_views(read_gaussians(out), cams)
            print(f"{args.scene} splat-transform {c} ({c / n:.3f}): {psnr(imgs)} dB, error background / "
                  f"silhouette / interior {error_split(imgs, refs)}", flush=True)
    if any(v.startswith("opmax=") for v in args.variants):
        install_over_opacity()  # before the first render: shaders compiled later draw opacities above 1
    results: dict[str, list[dict]] = {}
    for variant in args.variants:
        tiles = build_variant(g, variant)
        row = []
        results[variant] = []
        for level in sorted({t.level for t in tiles}):
            parts = [t.gaussians for t in tiles if t.level == level]
            count = sum(len(p) for p in parts)
            if not 0.01 * n <= count <= 0.6 * n:
                continue
            merged = Gaussians.concatenate(parts)
            imgs = lvp.render_views(merged, cams)
            results[variant].append({"level": level, "count": count, "share": count / n, "psnr": psnr(imgs)})
            row.append(f"L{level} {count} ({count / n:.3f}): {psnr(imgs)} dB, ceiling "
                       f"{float(np.mean(merged.opacities >= 0.98)):.2f}, over 1 "
                       f"{float(np.mean(merged.opacity_logits >= OVER_LOGIT - 1.0)):.2f}, "
                       f"split {error_split(imgs, refs)}")
        print(f"{args.scene} {variant}:\n  " + "\n  ".join(row), flush=True)
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"scene": args.scene, "splats": n, "variants": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
