"""Where SH coding loses on a real scene (issue 32): lean rate-distortion runs of SH codings, with cached renders.

    python bench/sh_coding_probe.py SCENE.ply --out DIR [--views 4 --size 384] [--stats] CONFIG ...

CONFIG is "LABEL:PRESET[,ATTR=FORMAT...][,sh_codebook=off|auto|fine|N][,sh_steps=G1/G2/G3][,zstd=L]" (sh_steps:
tile-step levels of SH bands 1, 2, 3, format.md 4.3.1; one value applies to every band), and with sh_steps
`sh_importance=E` (the importance exponent), `sh_zero=1` (0 on each chunk's grid), `sh_pool=1` (one step per band
plane), `sh_round=R` (rounding offset towards 0); `pos_k=K` (and `pos_gmin=`) a size-relative position step
(TileStep.per_size: the tile's median splat size / K, between pos_gmin and pos_g, else 4095, levels; `pos_axis=1`
the middle axis as the size, TileStep.size_axis);
`pos_g=`, `scale_g=`, `rgb_g=`, `opa_g=` replace (or add)
the preset's tile-step levels of positions, log scales, SH0 R, G, B and opacity (a colour step added by `rgb_g` or
`opa_g` alone has the other's levels from low-plus-9bit's: 255 and 55). Every config is encoded
without the LOD tree (as `splatstream eval` does by default), decoded, and rendered with the numpy reference
renderer from the same orbit views `eval` uses; the reference renders and every result are cached under DIR (a
config is not run again while its result file exists). `--compare LABEL=DECODED@ENCODED` adds peers.
`--stats` prints SH statistics of the input: distinct SH rows, energy (RMS) per band, and for codebooks of several
sizes the opacity x footprint-weighted RMS error per band.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.camera import scene_orbit_views  # noqa: E402
from splatstream.format import presets as P  # noqa: E402
from splatstream.format.steps import TileStep  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.metrics import psnr_from_mse  # noqa: E402
from splatstream.orientation import detect_up  # noqa: E402
from splatstream.render_ref import render  # noqa: E402

BANDS = {1: slice(0, 3), 2: slice(3, 8), 3: slice(8, 15)}


def parse_config(spec: str) -> tuple[str, str, dict]:
    label, rest = spec.split(":", 1)
    parts = rest.split(",")
    preset, extra = parts[0], {"overrides": {}}
    for p in parts[1:]:
        k, v = p.split("=", 1)
        if k == "sh_codebook":
            extra["sh_codebook"] = v
        elif k == "sh_steps":
            extra["sh_steps"] = [float(x) for x in v.split("/")]
        elif k == "sh_importance":
            extra["sh_importance"] = float(v)
        elif k == "sh_zero":
            extra["sh_zero"] = bool(int(v))
        elif k == "sh_round":
            extra["sh_round"] = float(v)
        elif k == "sh_pool":
            extra["sh_pool"] = bool(int(v))
        elif k in ("pos_g", "scale_g", "rgb_g", "opa_g", "pos_k", "pos_gmin", "pos_axis"):
            extra[k] = float(v)
        elif k == "zstd":
            extra["zstd"] = int(v)
        elif k == "transport":
            extra["transport"] = v
        elif k == "gauge":  # the canonical rotation gauge (presets.PRESET_ROTATION_GAUGE): cube, half-turns, off
            extra["gauge"] = v
        else:
            extra["overrides"][k] = v
    return label, preset, extra


def register(label: str, preset: str, extra: dict) -> str:
    """A temporary preset for this config (formats, steps, codebook and zstd level of `preset`, then the config's)."""
    name = f"probe-{label}"
    P.PRESETS[name] = {**P.PRESETS[preset], **extra["overrides"]}
    steps = dict(P.PRESET_STEPS.get(preset, {}))
    for a in extra["overrides"]:
        steps.pop(a, None)
    if "sh_steps" in extra:
        g = extra["sh_steps"]
        for b in (1, 2, 3):
            lv = g[min(b - 1, len(g) - 1)]
            steps[f"sh{b}"] = TileStep((lv,) * 3, shared=1, importance=extra.get("sh_importance", 0.0),
                                        zero=extra.get("sh_zero", False), rounding=extra.get("sh_round", 0.5),
                                        pooled=extra.get("sh_pool", False))
    if "pos_g" in extra:
        steps["position"] = TileStep((extra["pos_g"],) * 3, shared=3)
    if "pos_k" in extra:  # a size-relative position step (TileStep.per_size), at most pos_g (else 4095) levels
        steps["position"] = TileStep((extra.get("pos_g", 4095.0),) * 3, shared=3, per_size=extra["pos_k"],
                                     size_levels_min=extra.get("pos_gmin", 1.0),
                                     size_axis=int(extra.get("pos_axis", 2)))
    if "scale_g" in extra:
        steps["scale"] = TileStep((extra["scale_g"],) * 3, shared=3)
    if "rgb_g" in extra or "opa_g" in extra:
        old = steps.get("color", TileStep((255.0, 255.0, 255.0, 55.0), shared=3)).levels
        steps["color"] = TileStep((extra.get("rgb_g", old[0]),) * 3 + (extra.get("opa_g", old[3]),), shared=3)
    P.PRESET_STEPS[name] = steps
    cb = extra.get("sh_codebook", P.PRESET_SH_CODEBOOK.get(preset, "off"))
    P.PRESET_SH_CODEBOOK[name] = cb
    P.PRESET_ZSTD_LEVEL[name] = extra.get("zstd", P.PRESET_ZSTD_LEVEL.get(preset, 1))
    P.PRESET_TRANSPORT[name] = extra.get("transport", P.PRESET_TRANSPORT.get(preset, "fields"))
    gauge = extra.get("gauge", P.PRESET_ROTATION_GAUGE.get(preset, "off"))
    if gauge == "off":
        P.PRESET_ROTATION_GAUGE.pop(name, None)
    else:
        P.PRESET_ROTATION_GAUGE[name] = gauge
    return name


def stats(g) -> dict:
    from splatstream.encode.codebook import codebook_rows, codebook_weights
    from splatstream.vq import _unique_rows, build_codebook

    rows = codebook_rows(g)
    first, _ = _unique_rows(rows)
    w = codebook_weights(g)
    w = w / w.sum()
    out = {"splats": len(g), "sh_degree": g.sh_degree, "distinct_rows": int(len(first)),
           "sh0_rms": float(np.sqrt((g.sh0 ** 2).mean())) if hasattr(g, "sh0") else None, "bands": {}}
    sh = g.sh_rest
    for b in range(1, g.sh_degree + 1):
        x = sh[:, BANDS[b]]
        out["bands"][b] = {"rms": float(np.sqrt((x ** 2).mean())),
                           "weighted_rms": float(np.sqrt((w[:, None, None] * x ** 2).sum() / x[0].size))}
    rng = np.random.default_rng(0)
    fit = rows if len(rows) <= 1 << 18 else rows[np.sort(rng.choice(len(rows), 1 << 18, replace=False))]
    fw = codebook_weights(g) if fit is rows else None
    out["codebooks"] = {}
    for k in (256, 1024, 4096, 16384, 65536):
        if k > len(first) * 2:
            continue
        t = time.perf_counter()
        cb = build_codebook(fit, k, weights=fw)
        lab = cb.assign(rows)
        err = (rows - cb.entries[lab]).reshape(sh.shape)
        per = {b: float(np.sqrt((w[:, None, None] * err[:, BANDS[b]] ** 2).sum() / err[0, BANDS[b]].size))
               for b in range(1, g.sh_degree + 1)}
        out["codebooks"][k] = {"weighted_rms_error": per, "used": int(len(np.unique(lab))),
                               "fit_s": round(time.perf_counter() - t, 1)}
        print(f"  codebook {k}: {per} ({out['codebooks'][k]['fit_s']} s)", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("configs", nargs="*")
    ap.add_argument("--out", required=True)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--stats", action="store_true")
    ap.add_argument("--lod", action="store_true")
    ap.add_argument("--compare", nargs="*", default=[])
    ap.add_argument("--keep", action="store_true", help="keep the encoded scenes under OUT/enc")
    args = ap.parse_intermixed_args()
    from splatstream.encode import EncodeOptions, encode_gaussians
    from splatstream.scene_decode import decode_scene

    os.makedirs(args.out, exist_ok=True)
    g = read_gaussians(args.scene)
    if args.stats:
        s = stats(g)
        print(json.dumps(s, indent=1))
        json.dump(s, open(os.path.join(args.out, "stats.json"), "w"), indent=1)
    up = detect_up(g).up
    cams = scene_orbit_views(g.positions, args.views, args.size, args.size, up=up)
    ref_path = os.path.join(args.out, f"ref_{args.views}_{args.size}.npz")
    if os.path.exists(ref_path):
        refs = list(np.load(ref_path)["refs"])
    else:
        t = time.perf_counter()
        refs = [render(g, c) for c in cams]
        np.savez(ref_path, refs=np.stack(refs))
        print(f"references: {time.perf_counter() - t:.1f} s", flush=True)

    def quality(src) -> list[float]:
        ps = []
        for c, r in zip(cams, refs, strict=True):
            a = np.clip(render(src, c).astype(np.float64), 0, 1)
            ps.append(psnr_from_mse(float(np.mean((a - np.clip(r, 0, 1)) ** 2))))
        return ps

    def mean_psnr(ps: list[float]) -> float:
        return psnr_from_mse(float(np.mean([10 ** (-p / 10) for p in ps])))

    results = []
    for spec in args.configs:
        label, preset, extra = parse_config(spec)
        key = hashlib.sha1(spec.encode()).hexdigest()[:8]
        res_path = os.path.join(args.out, f"res_{label}_{key}{'_lod' if args.lod else ''}.json")
        if os.path.exists(res_path):
            r = json.load(open(res_path))
        else:
            name = register(label, preset, extra)
            out_dir = os.path.join(args.out, "enc", label)
            t = time.perf_counter()
            m = encode_gaussians(g, out_dir, EncodeOptions(preset=name, lod=args.lod, up=tuple(up)),
                                 source_name=args.scene)
            enc_s = time.perf_counter() - t
            ps = quality(decode_scene(out_dir))
            attrs = {a: round(s.disk_bytes / len(g), 3) for a, s in m.attributes.items()}
            r = {"label": label, "spec": spec, "bytes_per_splat": m.bytes_on_disk / len(g), "psnr": mean_psnr(ps),
                 "psnr_views": ps, "encode_s": enc_s, "attr_bytes": attrs,
                 "sh_codebook_entries": m.sh_codebook.entries if m.sh_codebook else None}
            json.dump(r, open(res_path, "w"), indent=1)
            if not args.keep:
                import shutil

                shutil.rmtree(out_dir, ignore_errors=True)
        results.append(r)
        print(f"{r['label']:>28}: {r['bytes_per_splat']:6.2f} B/splat {r['psnr']:6.2f} dB  enc {r['encode_s']:5.1f} s  "
              f"{r['attr_bytes']}", flush=True)
    for c in args.compare:
        label, rest = c.split("=", 1)
        dec, enc = rest.split("@")
        res_path = os.path.join(args.out, f"peer_{label}.json")
        if os.path.exists(res_path):
            r = json.load(open(res_path))
        else:
            from splatstream.evaluate import read_compare

            ps = quality(read_compare(dec)[0])
            r = {"label": label, "bytes_per_splat": os.path.getsize(enc) / len(g), "psnr": mean_psnr(ps),
                 "psnr_views": ps}
            json.dump(r, open(res_path, "w"), indent=1)
        print(f"{r['label']:>28}: {r['bytes_per_splat']:6.2f} B/splat {r['psnr']:6.2f} dB (peer)", flush=True)


if __name__ == "__main__":
    main()
