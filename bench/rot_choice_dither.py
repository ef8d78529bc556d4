"""How much of a paired rotation-format difference is the luck of where a few splats fall on the grids (issue 32,
cube9bit32): the scene re-drawn with every splat's log scales and rotation moved by a small random amount (a new,
equally valid input; its own reference renders), then each preset encoded with the half turns (`rotation=norm8x4`)
and with `cube8x4`, paired, same cameras (the stored report's) and renderer (GL).

    python bench/rot_choice_dither.py SCENE STORED_REPORT.json --presets P1,P2 --seeds 10 [--json OUT.json]

Seed 0 is the input as it is (no dither). The dither is far below what the picture resolves but moves each value to
another place between its grid points, so each seed draws the rounding anew: the spread of (cube8x4 - half turns)
over seeds is that rounding's noise on this scene, and its mean the expected difference.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from rot_choice_probe import covariances  # noqa: E402  (bench/ is not a package: run from it or with it on sys.path)

from cli.commands.renderers import gl_renderer  # noqa: E402
from splatstream.encode.local import encode_gaussians  # noqa: E402
from splatstream.encode.options import EncodeOptions  # noqa: E402
from splatstream.evaluate import cameras_from_report  # noqa: E402
from splatstream.format.layout import morton_order  # noqa: E402
from splatstream.format.presets import resolve_formats, rotation_gauge  # noqa: E402
from splatstream.gaussians import Gaussians, normalize_quaternions  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.metrics import psnr_from_mse  # noqa: E402
from splatstream.rotation_canon import canonical_gauge  # noqa: E402
from splatstream.scene_decode import decode_scene  # noqa: E402

ARMS = {"half": {"rotation": "norm8x4"}, "cube": {"rotation": "cube8x4"}}


def dithered(g: Gaussians, seed: int, log_scale: float, angle_deg: float) -> Gaussians:
    """`g` with each log scale moved by U(-log_scale, log_scale) and each rotation turned by a random axis and an
    angle U(0, angle_deg): seed 0 leaves it as it is."""
    if seed == 0:
        return g
    rng = np.random.default_rng(seed)
    n = len(g)
    ls = g.log_scales + rng.uniform(-log_scale, log_scale, (n, 3)).astype(np.float32)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    half = np.radians(rng.uniform(0, angle_deg, n)) / 2
    d = np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * axis], axis=1)
    q = g.rotations.astype(np.float64)
    w1, x1, y1, z1 = q.T
    w2, x2, y2, z2 = d.T
    turned = np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                       w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)
    return replace(g, log_scales=ls, rotations=normalize_quaternions(turned))


def measures(g: Gaussians, decoded: Gaussians) -> dict[str, float]:
    """Candidate per-scene measures of how far the decoded covariances are from the input's."""
    return _measures(g, decoded, input_index(g, decoded))


def input_index(g: Gaussians, decoded: Gaussians) -> np.ndarray:
    """For each decoded splat the input splat it stores: the decode is in the input's order, in Morton order of its
    positions (one tile, no LOD) or matched splat by splat; checked by position."""
    tolerance = 0.01 * float(np.ptp(g.positions))
    if len(decoded) == len(g) and float(np.abs(decoded.positions - g.positions).max()) <= tolerance:
        return np.arange(len(g))  # the input's order kept (a chunk-quantised input, e.g. a compressed PLY)
    order = morton_order(g.positions)
    if not len(decoded) == len(g) or float(np.abs(decoded.positions - g.positions[order]).max()) > tolerance:
        # the keyed transport stores the splats in another order: each decoded splat matched to the input's
        # nearest by position, its colour breaking ties (several may share a quantised position); brute force
        feats_in = np.concatenate([g.positions, 1e-4 * g.sh_dc], axis=1).astype(np.float64)
        feats_de = np.concatenate([decoded.positions, 1e-4 * decoded.sh_dc], axis=1).astype(np.float64)
        order = np.empty(len(decoded), np.int64)
        for s in range(0, len(decoded), 256):
            d = ((feats_de[s:s + 256, None, :] - feats_in[None, :, :]) ** 2).sum(axis=2)
            order[s:s + 256] = np.argmin(d, axis=1)
    if float(np.abs(decoded.positions - g.positions[order]).max()) > tolerance:
        raise SystemExit("the decode's splats do not match the input's")
    return order


def _measures(g: Gaussians, decoded: Gaussians, order: np.ndarray) -> dict[str, float]:
    src = g.rotations[order], g.log_scales[order]
    cin = covariances(*src)
    err = np.linalg.norm(covariances(decoded.rotations, decoded.log_scales) - cin, axis=(1, 2))
    rel = err / np.linalg.norm(cin, axis=(1, 2))
    s = np.sort(np.exp(src[1].astype(np.float64)), axis=1)
    opacity = 1 / (1 + np.exp(-g.opacity_logits[order].astype(np.float64)))
    area = s[:, 2] * s[:, 1]
    w = opacity * area
    return {"cov_rel": float(np.mean(rel)), "cov_rel_opacity_area": float(np.sum(w * rel) / np.sum(w)),
            "cov_rel_opacity_area_sq": float(np.sum(w * rel ** 2) / np.sum(w)),
            "cov_rel_opacity_area_max": float(np.max(w * rel) / np.mean(w))}


def psnr(render, source, cameras, references) -> float:
    mses = [float(np.mean((np.clip(np.asarray(render(source, c), np.float64), 0, 1) - np.clip(r, 0, 1)) ** 2))
            for c, r in zip(cameras, references, strict=True)]
    return psnr_from_mse(float(np.mean(mses)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("stored", help="the stored eval report whose cameras are used")
    ap.add_argument("--presets", default="medium-low-9bit")
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0 (the input) .. N-1")
    ap.add_argument("--log-scale", type=float, default=0.02, help="the log-scale dither's half width")
    ap.add_argument("--angle", type=float, default=0.5, help="the rotation dither's largest angle, degrees")
    ap.add_argument("--measures", action="store_true", help="also candidate covariance measures per arm")
    ap.add_argument("--decompose", action="store_true",
                    help="also each arm with the input's scales, and with the input's rotations (renders)")
    ap.add_argument("--psnr-from", help="an earlier output of this script (same scene, dither and seeds): its PSNR "
                    "taken as they are, only the encodes and --measures run (no renders)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    report = json.load(open(args.stored))
    cameras = cameras_from_report(report)
    up = tuple(report["camera_rule"]["up"])
    evr = gl_renderer()
    if evr is None:
        raise SystemExit("the GL renderer does not open here")
    g0 = read_gaussians(args.scene)
    earlier = {}
    if args.psnr_from:
        old = json.load(open(args.psnr_from))
        if (old["log_scale"], old["angle_deg"]) != (args.log_scale, args.angle):
            raise SystemExit(f"{args.psnr_from}: another dither")
        earlier = {(r["seed"], r["preset"]): r for r in old["rows"]}
    scratch = tempfile.TemporaryDirectory(prefix="rot_choice_dither_")  # the encodes, removed at exit
    root = scratch.name
    presets = args.presets.split(",")
    rows = []
    for seed in range(args.seeds):
        g = dithered(g0, seed, args.log_scale, args.angle)
        refs = None if earlier and not args.decompose else [np.asarray(evr.render(g, c), np.float64) for c in cameras]
        for p in presets:
            row = {"seed": seed, "preset": p}
            old = earlier.get((seed, p))
            if earlier and old is None:
                raise SystemExit(f"{args.psnr_from}: no row for seed {seed}, {p}")
            for arm, ov in ARMS.items():
                d = os.path.join(root, f"{p}_{arm}")
                m = encode_gaussians(g, d, EncodeOptions(preset=p, overrides=ov, lod=False, up=up),
                                     source_name=args.scene)
                row[arm] = old[arm] if old else psnr(evr.render, d, cameras, refs)
                row[f"{arm}_bytes"] = m.bytes_on_disk / len(g)
                if old and row[f"{arm}_bytes"] != old[f"{arm}_bytes"]:
                    raise SystemExit(f"{args.psnr_from}: seed {seed}, {p}, {arm}: other bytes, another encoder")
                if args.measures or args.decompose:
                    decoded = decode_scene(d)
                    order = input_index(g, decoded)
                if args.measures:
                    for k, v in _measures(g, decoded, order).items():
                        row[f"{arm}_{k}"] = v
                if args.decompose:
                    # the arm's rotations with the input's scales, and its scales with the input's rotations (both
                    # in the arm's gauge: the cube permutes the scales): what each attribute's rounding costs
                    gauge = rotation_gauge(p, {**resolve_formats(p), **ov})
                    q_in, ls_in = canonical_gauge(g.rotations[order], g.log_scales[order], gauge)
                    row[f"{arm}_exact_scales"] = psnr(evr.render, replace(decoded, log_scales=ls_in), cameras, refs)
                    row[f"{arm}_exact_rotations"] = psnr(evr.render, replace(decoded, rotations=q_in), cameras, refs)
            row["delta"] = row["cube"] - row["half"]
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = {}
    for p in presets:
        d = np.array([r["delta"] for r in rows if r["preset"] == p])
        dith = d[1:] if len(d) > 1 else d
        summary[p] = {"input": float(d[0]), "dithered mean": float(np.mean(dith)),
                      "dithered sd": float(np.std(dith, ddof=1)) if len(dith) > 1 else None,
                      "dithered min": float(np.min(dith)), "dithered max": float(np.max(dith)),
                      "cube better": int(np.sum(dith > 0)), "of": int(len(dith))}
    print(json.dumps(summary, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scene": args.scene, "log_scale": args.log_scale, "angle_deg": args.angle, "rows": rows,
                       "summary": summary}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
