#!/usr/bin/env python3
"""Would the geometric error as u8 steps of the parent's move cuts? (issue 31, gerr17; a probe, no format change.)

Streams a scene as bench/small_budget_bytes.py does (the directory, --no-prefetch, a lod_vs_peers JSON's cameras)
three times a view: the manifest as parsed (`f32`), and with every parsed tile's `geometric_error` replaced, in
this process right after the client parses the manifest, by what a u8 coding would decode to:

  `lin255`  box16's estimate (bench/results/box16/error8_estimate.py): q = ceil(e / pe * 255), 0..255, decoded
            e' = pe' * q / 255;
  `log16`   q in 0..254 the largest step with pe' * 2^(-q/16) >= e, decoded e' = pe' * 2^(-q/16); 255 codes 0.

pe' is the parent's decoded error (what a reader has; the encoder quantises against it, so e' >= e always: the
screen-space error stays conservative); a leaf's 0 stays 0; a tile without a parent in the table (the root) keeps
its f32 error. Per view: the drawn cut (tile ids), drawn splats, bytes, and whether the cut equals the `f32` run's.

    PYTHONPATH=. python bench/probe_error_steps.py SCENE_DIR LOD_VS_PEERS.json --budgets 0.02,0.06,0.25,0.5 \
        --out OUT.json
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

VARIANTS = ("f32", "lin255", "log16")


def stepped_errors(ids: list[int], parent_of: dict[int, int], error: dict[int, float], variant: str,
                   codes: dict | None = None) -> dict:
    """Tile id -> the error a u8 coding `variant` decodes to (module doc); top-down so a parent's decoded value is
    known first. codes: filled with tile id -> its u8 code (the tiles with a parent)."""
    out: dict[int, float] = {}
    codes = {} if codes is None else codes

    def decoded(t: int) -> float:
        if t in out:
            return out[t]
        e = float(error[t])
        p = parent_of.get(t)
        if p is None or variant == "f32":
            out[t] = e
            return e
        pe = decoded(p)
        if e == 0.0 or pe <= 0.0:
            out[t] = 0.0 if e == 0.0 else e
            codes[t] = 0 if variant == "lin255" else 255
            return out[t]
        if variant == "lin255":
            q = min(255, int(np.ceil(e / pe * 255)))
            while q < 255 and pe * q / 255 < e:
                q += 1
            v = pe * q / 255
            codes[t] = q
        else:  # log16 (log1: whole octaves, a coarse coding to check that the probe reaches the client's cut)
            k = 16 if variant == "log16" else 1
            q = min(254, max(0, int(np.floor(-k * np.log2(e / pe)))))
            while q > 0 and pe * 2.0 ** (-q / k) < e:
                q -= 1
            v = pe * 2.0 ** (-q / k)
            codes[t] = q
        out[t] = max(v, e)  # q = 0 (lin255: 255) is pe' itself, >= e (a child's error is at most its parent's)
        return out[t]

    for t in ids:
        decoded(t)
    return out


def _patch(variant: str):
    """Wrap the client's parse_manifest (client_gl.stream.fetch) so that its tiles carry `variant`'s errors.
    Returns the undo."""
    from client_gl.stream import fetch

    orig = fetch.parse_manifest

    def parse(*a, **k):
        m = orig(*a, **k)
        parent_of = {c: t.id for t in m.tiles for c in t.children}
        e = stepped_errors([t.id for t in m.tiles], parent_of, {t.id: t.geometric_error for t in m.tiles}, variant)
        tiles = tuple(dataclasses.replace(t, geometric_error=e[t.id]) for t in m.tiles)
        return dataclasses.replace(m, tiles=tiles)

    if variant != "f32":
        fetch.parse_manifest = parse
    return lambda: setattr(fetch, "parse_manifest", orig)


def picture(scene_dir: str, n: int, cam, size: int, ctx, variant: str, ref_gaussians) -> dict:
    """A view streamed again as measure_view streams it (the same `view` options) with `variant`'s errors: its image,
    the drawn cut, and the full-detail picture of the same camera (render_image of the source, as lod_vs_peers)."""
    from lod_vs_peers import stream_until_converged, view_argv

    from cli.commands import view as view_cmd
    from cli.commands.args import parse_size
    from cli.main import build_parser
    from client_gl.offscreen import render_image
    from client_gl.streaming import StreamingSession

    argv = view_argv(scene_dir, n, size, cam.eye, cam.target, cam.up, cam.fov_y_deg) + ["--quiet", "--no-prefetch"]
    args = build_parser().parse_args(argv)
    camera = view_cmd._fixed_camera(args, parse_size(args.size))
    undo = _patch(variant)
    try:
        session = StreamingSession.open(scene_dir, ctx, view_cmd._options(args))
        try:
            stream_until_converged(session, camera, 300, f"{scene_dir} view")
            image = np.asarray(session.read_image(), dtype=np.float32)[..., :3]
            draw = sorted(int(t) for t in session.last.draw)
        finally:
            session.close()
    finally:
        undo()
    ref = np.asarray(render_image(ref_gaussians, camera), dtype=np.float32)
    return {"image": image, "draw": draw, "ref": ref}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir")
    ap.add_argument("bench_json")
    ap.add_argument("--budgets", default="0.02,0.06,0.25,0.5")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--sizes", default=None, help="window sizes, comma-separated (default: --size); a smaller window "
                    "is a farther camera for the screen-space error (sse = error * focal / distance)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--ref", default=None, metavar="PLY",
                    help="the full-detail source (lod_vs_peers' cache full.ply): where a cut moved, the PSNR of each "
                         "variant's picture against its render, and against the f32 picture")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from small_budget_bytes import _whole_tree, measure_view

    from client_gl.offscreen import create_context
    from splatstream.camera import Camera

    d = json.load(open(args.bench_json))
    cams = [Camera.from_dict(c) for c in d["cameras"]]
    tree = _whole_tree(args.scene_dir)
    whole = tree[2]
    parent_of = {c: t.id for t in whole.tiles for c in t.children}
    err = {t.id: t.geometric_error for t in whole.tiles}
    variants = args.variants.split(",")
    stats = {}
    for v in variants:
        e = stepped_errors(list(err), parent_of, err, v)
        rel = [e[t] / err[t] - 1 for t in err if err[t] > 0]
        stats[v] = {"max_rel_increase": max(rel), "mean_rel_increase": float(np.mean(rel)),
                    "below_true": sum(e[t] < err[t] for t in err)}
    ctx = create_context()
    rows, ref_g = [], None
    try:
        sizes = [args.size] if args.sizes is None else [int(x) for x in args.sizes.split(",")]
        for b, size in ((float(x), sz) for x in args.budgets.split(",") for sz in sizes):
            n = max(1, int(round(b * d["splats"])))
            for i, c in enumerate(cams):
                cell = {"fraction": b, "budget": n, "view": i, "size": size}
                for v in variants:
                    undo = _patch(v)
                    try:
                        r = measure_view(args.scene_dir, n, c, size, False, ctx, tree)
                    finally:
                        undo()
                    cell[v] = {k: r[k] for k in ("draw", "drawn_splats", "drawn_tile_bytes", "downloaded",
                                                 "manifest", "drawn_tiles")}
                for v in variants[1:]:
                    cell[v]["same_cut"] = cell[v]["draw"] == cell[variants[0]]["draw"]
                rows.append(cell)
                moved = [v for v in variants[1:] if not cell[v]["same_cut"]]
                if moved and args.ref:
                    from lod_vs_peers import quality

                    if ref_g is None:
                        from splatstream.io import read_gaussians
                        ref_g = read_gaussians(args.ref)
                    pics = {v: picture(args.scene_dir, n, c, size, ctx, v, ref_g) for v in [variants[0], *moved]}
                    for v, pic in pics.items():
                        cell[v]["picture_same_cut"] = pic["draw"] == cell[v]["draw"]
                        cell[v]["psnr"], cell[v]["ssim"] = quality(pic["image"], pic["ref"])
                        if v != variants[0]:
                            cell[v]["psnr_vs_f32_picture"] = quality(pic["image"], pics[variants[0]]["image"])[0]
                    print("   PSNR " + ", ".join(f"{v} {cell[v]['psnr']:.3f} dB" for v in pics), flush=True)
                print(f"{d['scene']} {b:g} {size} px view {i}: {n:,} splats, f32 "
                      f"{cell[variants[0]]['drawn_splats']:,} drawn; "
                      + ", ".join(f"{v} {cell[v]['drawn_splats']:,}{' MOVED' if v in moved else ''}"
                                  for v in variants[1:]), flush=True)
    finally:
        ctx.release()
    if args.out:
        json.dump({"scene": d["scene"], "scene_dir": args.scene_dir, "variants": variants, "error_stats": stats,
                   "rows": rows}, open(args.out, "w"), indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
