"""Fast SH-only rate-distortion screening (issue 32): the image is linear in the splats' colours.

With positions, rotations, scales and opacity exact, the reference rasterizer's blend weights do not depend on the
colours, so every view is image = sum_i w_pi colour_i(view) over the (pixel, splat, weight) triplets of one render.
This script records those triplets once per view (one reference render's work), then measures any SH coding in
about a second: encode with every other attribute lossless (f32x4), decode, match the splats back to the input by
position, evaluate colour per view, blend with the recorded weights, PSNR against the original's blend. The SH-only
MSE adds to the rest of a preset's error (measured once per base preset with sh=f32x4 by sh_coding_probe.py):
predicted PSNR = -10 log10(MSE_base + MSE_sh). Screening only; the named presets are confirmed with full renders.

    python bench/sh_linear_probe.py SCENE.ply --out DIR [--views 4 --size 384] CONFIG ...

CONFIG as in sh_coding_probe.py ("LABEL:PRESET[,sh=FORMAT][,sh_codebook=...][,sh_steps=G1/G2/G3]"); only its SH
coding counts (the other attributes are encoded lossless).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from sh_coding_probe import parse_config, register  # noqa: E402

from splatstream.camera import scene_orbit_views  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.metrics import psnr_from_mse  # noqa: E402
from splatstream.orientation import detect_up  # noqa: E402
from splatstream.render_ref import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, preprocess, tile_lists  # noqa: E402
from splatstream.sh import eval_sh, view_directions  # noqa: E402

LOSSLESS = {"position": "f32x4", "rotation": "f32x4", "scale": "f32x4", "color": "f32x4"}


def weights(g, camera, max_batch: int = 512, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pixel index, splat index into g, blend weight) of every contribution above `floor` (render_ref.rasterize)."""
    p = preprocess(g, camera)
    width, height = camera.width, camera.height
    grid_x, grid_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    ids, offsets = tile_lists(p, grid_x, grid_y)
    ly, lx = np.divmod(np.arange(TILE * TILE), TILE)
    ca, cb, cc = p.conic[:, 0], p.conic[:, 1], p.conic[:, 2]
    out_p, out_s, out_w = [], [], []
    for tyi in range(grid_y):
        for txi in range(grid_x):
            k = tyi * grid_x + txi
            lst = ids[offsets[k]:offsets[k + 1]]
            if len(lst) == 0:
                continue
            gx, gy = txi * TILE + lx, tyi * TILE + ly
            pix = np.where((gx < width) & (gy < height), gy * width + gx, -1)
            pxs, pys = gx.astype(np.float64), gy.astype(np.float64)
            t_cur = np.ones(TILE * TILE)
            done = np.zeros(TILE * TILE, bool)
            pos, batch = 0, 16
            while pos < len(lst):
                s = lst[pos:pos + batch]
                pos += batch
                batch = min(batch * 2, max_batch)
                dx = p.xy[s, 0][None, :] - pxs[:, None]
                dy = p.xy[s, 1][None, :] - pys[:, None]
                power = -0.5 * (ca[None, s] * dx * dx + cc[None, s] * dy * dy) - cb[None, s] * dx * dy
                alpha = np.minimum(ALPHA_MAX, p.opacity[None, s] * np.exp(np.minimum(power, 0.0)))
                alpha[(power > 0) | (alpha < ALPHA_MIN)] = 0.0
                alpha[done] = 0.0
                tcum = np.empty((TILE * TILE, len(s) + 1))
                tcum[:, 0] = t_cur
                np.subtract(1.0, alpha, out=tcum[:, 1:])
                np.cumprod(tcum, axis=1, out=tcum)
                valid = tcum[:, 1:] >= T_MIN
                n_valid = valid.sum(axis=1)
                w = np.where(valid, alpha * tcum[:, :-1], 0.0)
                r, c = np.nonzero((w > floor) & (pix >= 0)[:, None])
                out_p.append(pix[r].astype(np.int32))
                out_s.append(p.index[s][c].astype(np.int32))
                out_w.append(w[r, c].astype(np.float32))
                t_cur = tcum[np.arange(TILE * TILE), n_valid]
                done |= n_valid < len(s)
                if done.all():
                    break
    return np.concatenate(out_p), np.concatenate(out_s), np.concatenate(out_w)


def blend(pix, idx, w, colour, npix) -> np.ndarray:
    return np.stack([np.bincount(pix, weights=w * colour[idx, c], minlength=npix) for c in range(3)], axis=1)


def decoded_sh_in_input_order(g, label: str, preset: str, extra: dict, up) -> tuple[np.ndarray, float, dict]:
    """SH rest of the decoded scene, matched back to the input's splat order by exact position; SH bytes/splat."""
    from splatstream.encode import EncodeOptions, encode_gaussians
    from splatstream.scene_decode import decode_scene

    extra = {**extra, "overrides": {**extra["overrides"], **LOSSLESS}}
    name = register(label, preset, extra)
    # Carry each splat's index through the encode in SH0 (lossless f32x4, which no SH coding reads): i // 1024 and
    # i % 1024 in R and G (SH0 must stay within f16's range, format.md 4.8).
    from dataclasses import replace

    i = np.arange(len(g))
    dc = g.sh_dc.copy()
    dc[:, 0], dc[:, 1] = i // 1024, i % 1024
    with tempfile.TemporaryDirectory() as tmp:
        m = encode_gaussians(replace(g, sh_dc=dc), tmp + "/s", EncodeOptions(preset=name, lod=False, up=tuple(up)))
        d = decode_scene(tmp + "/s")
    back = np.rint(d.sh_dc[:, 0]).astype(np.int64) * 1024 + np.rint(d.sh_dc[:, 1]).astype(np.int64)
    if not np.array_equal(np.sort(back), i):
        raise RuntimeError("the splat indices did not survive the encode")
    sh = np.empty_like(g.sh_rest)
    sh[back] = d.sh_rest
    sh_bytes = m.attributes["sh"].disk_bytes / len(g)
    info = {"sh_bytes": sh_bytes, "entries": m.sh_codebook.entries if m.sh_codebook else None}
    return sh, sh_bytes, info


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("configs", nargs="*")
    ap.add_argument("--out", required=True)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=384)
    args = ap.parse_intermixed_args()
    os.makedirs(args.out, exist_ok=True)
    g = read_gaussians(args.scene)
    up = detect_up(g).up
    cams = scene_orbit_views(g.positions, args.views, args.size, args.size, up=up)
    wpath = os.path.join(args.out, f"weights_{args.views}_{args.size}.npz")
    if os.path.exists(wpath):
        z = np.load(wpath)
        trip = [(z[f"p{i}"], z[f"s{i}"], z[f"w{i}"]) for i in range(len(cams))]
    else:
        t = time.perf_counter()
        trip = [weights(g, c) for c in cams]
        np.savez(wpath, **{f"{k}{i}": v for i, tr in enumerate(trip) for k, v in zip("psw", tr, strict=True)})
        print(f"weights: {time.perf_counter() - t:.1f} s, {sum(len(t[0]) for t in trip):,} triplets", flush=True)
    npix = args.size * args.size
    dirs = [view_directions(g.positions, np.asarray(c.eye)) for c in cams]
    refs = [np.clip(blend(*tr, eval_sh(g.sh_dc, g.sh_rest, dv), npix), 0, 1) for tr, dv in zip(trip, dirs, strict=True)]
    res_path = os.path.join(args.out, "linear.json")
    results = json.load(open(res_path)) if os.path.exists(res_path) else {}
    for spec in args.configs:
        label, preset, extra = parse_config(spec)
        if spec in results:
            r = results[spec]
        else:
            sh, sh_bytes, info = decoded_sh_in_input_order(g, label, preset, extra, up)
            mses = []
            for tr, dv, ref in zip(trip, dirs, refs, strict=True):
                img = np.clip(blend(*tr, eval_sh(g.sh_dc, sh, dv), npix), 0, 1)
                mses.append(float(np.mean((img - ref) ** 2)))
            band_err = {}
            for b, sl in ((1, slice(0, 3)), (2, slice(3, 8)), (3, slice(8, 15))):
                if sl.start < g.sh_rest.shape[1]:
                    band_err[b] = float(np.sqrt(np.mean((sh[:, sl] - g.sh_rest[:, sl]) ** 2)))
            r = {"label": label, "mse_sh": float(np.mean(mses)), "psnr_sh_only": psnr_from_mse(float(np.mean(mses))),
                 "band_rms_error": band_err, **info}
            results[spec] = r
            json.dump(results, open(res_path, "w"), indent=1)
        print(f"{r['label']:>24}: SH {r['sh_bytes']:6.2f} B/splat  SH-only PSNR {r['psnr_sh_only']:6.2f} dB  "
              f"band RMS err {r['band_rms_error']}", flush=True)


if __name__ == "__main__":
    main()
