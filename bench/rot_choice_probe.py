"""Why a preset's measured rotation choice loses PSNR on a scene (issue 32, cube9bit32): one preset encoded twice
(half turns, `rotation=norm8x4`, and `cube8x4`), decoded, and the two decodes mixed attribute by attribute, drawn
with eval's cameras and renderer.

    python bench/rot_choice_probe.py SCENE.ply STORED_REPORT.json --preset medium-low-9bit \
        [--json OUT.json] [--markdown OUT.md]

Reports (every PSNR the mean over the stored report's views, against the input drawn by the same renderer):
* each arm drawn from its scene directory (what eval measures) and from its decode (the check that the decode is
  what is drawn);
* hybrids: the half-turn decode with one attribute group of the cube decode (rotation and scales, which together
  make the covariance; positions; opacity; SH0; SH1..), and the other way round: where the loss lives;
* per splat, in the input's order, the rotation error of both formats (plan.rotation_error_deg, the encoder's
  measure), its mean and tail, and how the splats whose error grows differ (size, anisotropy, opacity);
* the gauge's effect on the stored scales: the cube gauge permutes each splat's scales, so a per-chunk grid or a
  tile step sees other values per axis; the scale error of both decodes against the input's covariance;
* split hybrids: the half-turn decode with the cube decode's covariance on a subset of splats (those whose angle
  error falls, those whose grows), to see whether a per-splat measure weighted by what the picture sees would
  predict the sign.
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

from cli.commands.renderers import gl_renderer  # noqa: E402
from splatstream.encode.local import encode_gaussians  # noqa: E402
from splatstream.encode.options import EncodeOptions  # noqa: E402
from splatstream.encode.plan import rotation_error_deg  # noqa: E402
from splatstream.evaluate import cameras_from_report  # noqa: E402
from splatstream.format.presets import resolve_formats, rotation_gauge  # noqa: E402
from splatstream.gaussians import Gaussians, rotation_matrices  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.metrics import psnr_from_mse  # noqa: E402
from splatstream.rotation_canon import canonical_gauge  # noqa: E402
from splatstream.scene_decode import decode_scene  # noqa: E402

# rotation and scales travel together: the two arms store them in different gauges (the cube permutes the scales),
# so one without the other is another covariance (the decomposition below separates them within one arm instead)
GROUPS = {"covariance (rotation + scales)": ("rotations", "log_scales"), "positions": ("positions",),
          "opacity": ("opacity_logits",), "SH0": ("sh_dc",), "SH1..": ("sh_rest",)}


def quality(render, source, cameras, references) -> tuple[float, list[float]]:
    """(PSNR of the mean MSE over the views, per-view PSNR), as evaluate.Row.psnr_mean."""
    mses = []
    for cam, ref in zip(cameras, references, strict=True):
        img = np.clip(np.asarray(render(source, cam), np.float64), 0, 1)
        mses.append(float(np.mean((img - np.clip(ref, 0, 1)) ** 2)))
    return psnr_from_mse(float(np.mean(mses))), [psnr_from_mse(m) for m in mses]


def mixed(base: Gaussians, other: Gaussians, fields: tuple[str, ...], mask: np.ndarray | None = None) -> Gaussians:
    """`base` with `fields` taken from `other` (on the splats of `mask` only, if given); same splat order."""
    out = {}
    for f in fields:
        a, b = getattr(base, f), getattr(other, f)
        out[f] = b.copy() if mask is None else np.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)
    return replace(base, **out)


def covariances(rotations: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """(N, 3, 3) covariances R S S^T R^T, float64, of rotations not necessarily unit (an input PLY's)."""
    q = rotations.astype(np.float64)
    m = rotation_matrices(q / np.linalg.norm(q, axis=1, keepdims=True)) * np.exp(log_scales.astype(np.float64))[:, None]
    return m @ np.transpose(m, (0, 2, 1))


def input_order(decoded: Gaussians, g: Gaussians) -> np.ndarray:
    """For each decoded splat the index of the input splat it came from: the nearest input position, with the
    input's colour breaking near ties (the decode's positions are quantised; brute force, small scenes only)."""
    feats_in = np.concatenate([g.positions, 1e-3 * g.sh_dc], axis=1).astype(np.float64)
    feats_de = np.concatenate([decoded.positions, 1e-3 * decoded.sh_dc], axis=1).astype(np.float64)
    out = np.empty(len(decoded), np.int64)
    for s in range(0, len(decoded), 512):
        d = ((feats_de[s:s + 512, None, :] - feats_in[None, :, :]) ** 2).sum(axis=2)
        out[s:s + 512] = np.argmin(d, axis=1)
    return out


def stats(v: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(v)), "p50": float(np.percentile(v, 50)), "p90": float(np.percentile(v, 90)),
            "p99": float(np.percentile(v, 99)), "max": float(np.max(v))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("stored", help="the stored eval report whose cameras are used")
    ap.add_argument("--preset", default="medium-low-9bit")
    ap.add_argument("--json")
    ap.add_argument("--markdown")
    ap.add_argument("--keep", help="keep the two encoded scenes here")
    ap.add_argument("--largest", type=int, default=20, help="the largest splats probed one at a time")
    args = ap.parse_args(argv)

    report = json.load(open(args.stored))
    cameras = cameras_from_report(report)
    up = tuple(report["camera_rule"]["up"])
    evr = gl_renderer()
    if evr is None:
        raise SystemExit("the GL renderer does not open here")
    render = evr.render
    g = read_gaussians(args.scene)
    refs = [np.asarray(render(g, c), np.float64) for c in cameras]
    scratch = None if args.keep else tempfile.TemporaryDirectory(prefix="rot_choice_probe_")  # removed at exit
    root = args.keep or scratch.name
    out: dict = {"scene": args.scene, "preset": args.preset, "splats": len(g), "views": len(cameras)}
    arms = {"half": {"rotation": "norm8x4"}, "cube": {"rotation": "cube8x4"}}
    dec: dict[str, Gaussians] = {}
    for arm, overrides in arms.items():
        d = os.path.join(root, arm)
        m = encode_gaussians(g, d, EncodeOptions(preset=args.preset, overrides=overrides, lod=False, up=up),
                             source_name=args.scene)
        dec[arm] = decode_scene(d)
        scene_psnr, per_view = quality(render, d, cameras, refs)
        decode_psnr, _ = quality(render, dec[arm], cameras, refs)
        out[arm] = {"bytes_per_splat": m.bytes_on_disk / len(g), "psnr_scene": scene_psnr, "psnr_per_view": per_view,
                    "psnr_decoded": decode_psnr, "formats": dict(m.formats)}
    half, cube = dec["half"], dec["cube"]
    if not np.array_equal(half.positions, cube.positions):
        raise SystemExit("the two decodes' splats are not in the same order (their positions differ)")

    # attribute groups swapped both ways
    swaps = {}
    for name, fields in GROUPS.items():
        swaps[name] = {"half + cube's": quality(render, mixed(half, cube, fields), cameras, refs)[0],
                       "cube + half's": quality(render, mixed(cube, half, fields), cameras, refs)[0]}
    out["swaps"] = swaps

    # per splat, input order
    formats = resolve_formats(args.preset)
    err = {arm: rotation_error_deg(g.rotations, g.log_scales, args.preset, {**formats, **ov})
           for arm, ov in arms.items()}
    out["angle_error_deg"] = {arm: stats(e) for arm, e in err.items()}
    grows = err["cube"] > err["half"]
    ls = g.log_scales.astype(np.float64)
    size = np.exp(ls.max(axis=1))
    aniso = np.exp(ls.max(axis=1) - ls.min(axis=1))
    opacity = 1 / (1 + np.exp(-g.opacity_logits.astype(np.float64)))
    out["grows"] = {"splats": int(grows.sum()),
                    "share": float(grows.mean()),
                    "median size grows / falls": [float(np.median(size[grows])), float(np.median(size[~grows]))],
                    "median anisotropy grows / falls": [float(np.median(aniso[grows])),
                                                        float(np.median(aniso[~grows]))],
                    "median opacity grows / falls": [float(np.median(opacity[grows])),
                                                     float(np.median(opacity[~grows]))]}
    # the decodes mapped to the input (nearest position), per-splat covariance error in the input's units
    idx = input_order(half, g)
    cov_in = covariances(g.rotations[idx], g.log_scales[idx])
    norm_in = np.linalg.norm(cov_in, axis=(1, 2))
    cov_err = {arm: np.linalg.norm(covariances(d.rotations, d.log_scales) - cov_in, axis=(1, 2)) / norm_in
               for arm, d in dec.items()}
    out["covariance_rel_error"] = {arm: stats(e) for arm, e in cov_err.items()}
    out["mapped_unique"] = int(len(np.unique(idx)))
    # sorted log-scale errors of each decode (the gauge permutes the axes: sort to compare like with like)
    sls_in = np.sort(g.log_scales[idx].astype(np.float64), axis=1)
    out["sorted_log_scale_abs_error"] = {
        arm: stats(np.abs(np.sort(d.log_scales.astype(np.float64), axis=1) - sls_in).ravel())
        for arm, d in dec.items()}
    out["position_abs_error"] = {arm: stats(np.abs(d.positions.astype(np.float64) - g.positions[idx]).ravel())
                                 for arm, d in dec.items()}
    # split hybrids: half's decode with cube's covariance where the angle error falls / grows
    falls_dec = err["cube"][idx] <= err["half"][idx]
    fields = GROUPS["covariance (rotation + scales)"]
    out["split"] = {"cube's covariance where its angle error falls":
                    quality(render, mixed(half, cube, fields, falls_dec), cameras, refs)[0],
                    "cube's covariance where its angle error grows":
                    quality(render, mixed(half, cube, fields, ~falls_dec), cameras, refs)[0]}
    # per-splat screen-weighted sensitivity: cube's covariance on one group of splats by size decile
    order = np.argsort(size[idx])
    deciles = np.array_split(order, 10)
    out["covariance_by_size_decile"] = []
    for k, members in enumerate(deciles):
        mask = np.zeros(len(half), bool)
        mask[members] = True
        out["covariance_by_size_decile"].append({"decile": k, "max size": float(size[idx][members].max()),
                                                 "psnr": quality(render, mixed(half, cube, fields, mask), cameras,
                                                                 refs)[0]})
    # rotation error against scale error: each arm with its decoded rotations or the input's (in that arm's gauge),
    # and its decoded scales or the input's (permuted by that gauge)
    out["decomposition"] = {}
    for arm, ov in arms.items():
        gauge = rotation_gauge(args.preset, {**formats, **ov})
        q_exact, ls_exact = canonical_gauge(g.rotations[idx], g.log_scales[idx], gauge)
        d = dec[arm]
        for rot_name, rot in (("decoded", d.rotations), ("exact", q_exact)):
            for sc_name, sc in (("decoded", d.log_scales), ("exact", ls_exact)):
                label = f"{arm}: rotations {rot_name}, scales {sc_name}"
                out["decomposition"][label] = quality(render, replace(d, rotations=rot, log_scales=sc), cameras,
                                                      refs)[0]
    # the largest splats one at a time: the half decode with the cube decode's covariance on that splat alone
    base = quality(render, half, cameras, refs)[0]
    largest = np.argsort(-size[idx])[:args.largest]
    rows = []
    sls = {arm: np.sort(d.log_scales.astype(np.float64), axis=1) for arm, d in dec.items()}
    for i in largest:
        mask = np.zeros(len(half), bool)
        mask[i] = True
        j = idx[i]
        rows.append({"decoded": int(i), "input": int(j), "size": float(size[j]), "anisotropy": float(aniso[j]),
                     "scales": [float(v) for v in np.exp(np.sort(ls[j]))], "opacity": float(opacity[j]),
                     "angle half": float(err["half"][j]), "angle cube": float(err["cube"][j]),
                     "log-scale error half": float(np.abs(sls["half"][i] - sls_in[i]).max()),
                     "log-scale error cube": float(np.abs(sls["cube"][i] - sls_in[i]).max()),
                     "cov error half": float(cov_err["half"][i]), "cov error cube": float(cov_err["cube"][i]),
                     "dB": quality(render, mixed(half, cube, fields, mask), cameras, refs)[0] - base})
    out["largest"] = rows
    text = json.dumps(out, indent=1)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
