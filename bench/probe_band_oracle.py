"""How many SH-band bytes any per-tile band rule could save, and at what PSNR: an oracle against practical rules.

Issue 13 asks bands by need to save 30 % of the bytes of every band of every selected tile at under 0.5 dB of PSNR.
The area rule (format_spec/client.md 1.3) does not get there. This probe asks whether any rule that gives each tile of
the cut a number of bands could. It streams a scene from a directory with every band for every tile (no prefetch).
Then, tile by tile, it measures what the picture loses when one tile keeps fewer bands (k = top-1 .. 0). Each tile's
bands stay in the pool; the probe only changes how many of them the tile draws. The rules, each applied
cumulatively and rendered for real at each target saving:

* oracle: drops bands greedily, the most bytes per unit of measured loss first, a tile's highest band first.
* shares_default: the client's rule with its defaults, one point.
* area, box_area, weight: band 3 first from the tiles with the least measure per byte of the band, then band 2,
  then band 1. The measures: the bounding sphere's projected area (the client's), the projected 3-sigma box, and
  the alpha the tile adds over the rest of the cut (one render without the tile each).
* *_model: the oracle's greedy on a modelled loss, the measure times one constant per band fitted to the measured
  losses (median over tiles). The fit uses the oracle's data, so these are upper bounds for their measure.
* *_fixed: the same with no fitted constant: each band's loss is the measure times the band's share of the tile's
  band bytes.

Each result gives the PSNR against the all-bands frame and, with --full-detail, against the full-detail render
(8-bit, as bench_stream.py measures it), and its cost: the all-bands frame's PSNR against full detail minus the
rule's. Savings are counted against the session's downloaded bytes and against the cut's own bytes (bases and bands).

    python bench/probe_band_oracle.py --scene DIR --ply SCENE.ply --camera overview --full-detail --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench_stream import cameras, full_detail  # noqa: E402 (bench/ is on the path: scripts run from it)

from splatstream.metrics import psnr_from_mse  # noqa: E402

TARGETS = (0.1, 0.2, 0.3, 0.4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True, help="encoded scene directory")
    ap.add_argument("--ply", required=True, help="the scene's source PLY (for bench_stream's cameras)")
    ap.add_argument("--camera", default="overview", choices=["overview", "close-up"])
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--gpu-mem-mb", type=float, default=4096)
    ap.add_argument("--full-detail", action="store_true", help="also PSNR against `splatstream render` of every leaf")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()
    from client_gl.offscreen import create_context
    from client_gl.streaming import StreamingSession, ViewOptions

    w, h = (int(v) for v in args.size.split("x"))
    cam = cameras(args.ply, (w, h))[args.camera]
    ctx = create_context()
    t0 = time.perf_counter()
    session = StreamingSession.open(args.scene, ctx, ViewOptions(gpu_mem_mb=args.gpu_mem_mb, cache=False,
                                                                 band_area_share=(1.0, 1.0, 1.0), prefetch=False))
    while not session.converged:
        session.frame(cam)
        session.wait(0.01)
        if time.perf_counter() - t0 > 300:
            raise SystemExit("did not converge in 300 s")
    pool, m = session.pool, session.manifest
    a = m.arrays
    tiles = list(session.last.draw)
    downloaded = session.fetcher.stats().bytes_downloaded

    def render(draw: list[int] | None = None, channels: slice = slice(0, 3)) -> np.ndarray:
        session.renderer.render(cam, draw_set=tiles if draw is None else draw)
        return session.renderer.read_image()[..., channels].astype(np.float64)

    def draw_bands(tile: int, k: int) -> None:
        # a probe's reach into the pool: the tile's band texels stay uploaded, only the count it draws changes
        res = pool._tiles[tile]
        res.bands = k
        pool._update_state(res)

    top = {t: pool.tile_bands(t) for t in tiles}
    everything = render()
    idx = {t: m.index_of[t] for t in tiles}
    band_bytes = {t: [int(a.band_bytes[idx[t], b]) for b in range(3)] for t in tiles}
    cut_bytes = sum(int(m.tile(t).groups["base"].bytes) for t in tiles) + sum(sum(v) for v in band_bytes.values())
    print(f"{len(tiles)} tiles, {session.last.drawn_splats} splats, {downloaded / 1e6:.1f} MB downloaded, "
          f"cut {cut_bytes / 1e6:.1f} MB, bands {sum(sum(v) for v in band_bytes.values()) / 1e6:.1f} MB", flush=True)
    # the loss of each tile drawing k bands, the others all of theirs
    loss: dict[int, list[float]] = {}
    t1 = time.perf_counter()
    for t in tiles:
        row = [0.0] * (top[t] + 1)
        for k in range(top[t] - 1, -1, -1):
            draw_bands(t, k)
            row[k] = float(np.mean((render() - everything) ** 2))
        draw_bands(t, top[t])
        loss[t] = row
    print(f"per-tile losses: {sum(top.values())} renders in {time.perf_counter() - t1:.1f} s", flush=True)
    # each tile's weight in the picture: the alpha it adds over the rest of the cut, per pixel of the view
    alpha = render(channels=slice(3, 4))
    weight = {t: float(np.mean(alpha - render([u for u in tiles if u != t], slice(3, 4)))) for t in tiles}

    # drop steps (tile, band dropped) in each rule's order; a tile drops its highest band first
    def oracle_order(loss: dict[int, list[float]]) -> list[tuple[int, int]]:
        steps, nxt = [], {t: top[t] for t in tiles}
        while True:
            best, best_ratio = None, -1.0
            for t, k in nxt.items():
                if k == 0:
                    continue
                d_loss = max(loss[t][k - 1] - loss[t][k], 1e-15)
                ratio = band_bytes[t][k - 1] / d_loss
                if ratio > best_ratio:
                    best, best_ratio = t, ratio
            if best is None:
                return steps
            steps.append((best, nxt[best]))
            nxt[best] -= 1

    from client_gl.stream.selection import view_numbers

    view = view_numbers(a, cam, session.engine.options.selection)
    area = {t: float(view.area_px[idx[t]]) for t in tiles}
    # The projected 3-sigma box, clipped to the view (a tighter bound than the sphere; the eye inside: the view).
    box_area = {}
    for t in tiles:
        lo, hi = a.box_min[idx[t]], a.box_max[idx[t]]
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        uv, depth = cam.project(corners)
        if np.any(depth <= cam.near):
            box_area[t] = float(w * h)
            continue
        x0, y0 = np.clip(uv.min(0), 0, (w, h))
        x1, y1 = np.clip(uv.max(0), 0, (w, h))
        box_area[t] = float((x1 - x0) * (y1 - y0))

    def by_least(measure: dict[int, float]) -> list[tuple[int, int]]:
        # a band rule's order: band 3 goes first from the tiles with the least of the measure per byte, then 2, then 1
        return [(t, b) for b in (3, 2, 1) for t in sorted(
            (t for t in tiles if top[t] >= b), key=lambda t: measure[t] / max(1.0, band_bytes[t][b - 1]))]
    ref = full_detail(args.scene, cam, os.path.join("/tmp", f"oracle_full_{os.getpid()}.png")) \
        if args.full_detail else None

    def db8(img: np.ndarray, other: np.ndarray) -> float:
        x = np.round(np.clip(img, 0, 1) * 255) / 255
        return round(min(psnr_from_mse(float(np.mean((x - other) ** 2))), 99.0), 2)

    out: dict = {"scene": args.scene, "camera": args.camera, "size": [w, h], "tiles": len(tiles),
                 "drawn_splats": session.last.drawn_splats, "downloaded_bytes": downloaded, "cut_bytes": cut_bytes,
                 "band_bytes": sum(sum(v) for v in band_bytes.values()),
                 "all_bands_vs_full_detail_db": db8(everything, ref) if ref is not None else None, "rules": {}}
    out["per_tile"] = [{"tile": t, "level": int(a.level[idx[t]]), "splats": int(a.splats[idx[t]]), "area_px": area[t],
                        "sse": float(view.sse[idx[t]]), "distance": float(view.distance[idx[t]]),
                        "box_area_px": box_area[t], "band_bytes": band_bytes[t], "loss": loss[t], "weight": weight[t]}
                       for t in tiles]
    # Models of the loss: a measure per tile times one number per band (the median over tiles of the measured loss
    # of the band over the measure: what a scene-wide band energy would give), in the oracle's greedy order.
    def model(measure: dict[int, float]) -> dict[int, list[float]]:
        per_band = [float(np.median([(loss[t][b - 1] - loss[t][b]) / max(measure[t], 1e-12) for t in tiles
                                     if top[t] >= b])) for b in (1, 2, 3)]
        out = {}
        for t in tiles:
            row = [0.0] * (top[t] + 1)
            for k in range(top[t] - 1, -1, -1):
                row[k] = row[k + 1] + measure[t] * per_band[k]
            out[t] = row
        return out

    def fixed(measure: dict[int, float]) -> dict[int, list[float]]:
        # no fitted constants: a band's loss is the tile's measure times the band's share of the tile's band bytes
        # (the same loss per byte for every band of a tile: a rule a client can follow from the manifest alone)
        out = {}
        for t in tiles:
            total = max(1, sum(band_bytes[t][:top[t]]))
            row = [0.0] * (top[t] + 1)
            for k in range(top[t] - 1, -1, -1):
                row[k] = row[k + 1] + measure[t] * band_bytes[t][k] / total
            out[t] = row
        return out

    rules = (("oracle", oracle_order(loss)),
             ("area", by_least(area)), ("box_area", by_least(box_area)), ("weight", by_least(weight)),
             ("area_model", oracle_order(model(area))), ("box_area_model", oracle_order(model(box_area))),
             ("weight_model", oracle_order(model(weight))),
             ("area_fixed", oracle_order(fixed(area))), ("box_area_fixed", oracle_order(fixed(box_area))))
    def measure(name: str, target: float, saved: int, predicted_loss: float, steps: int) -> dict:
        img = render()
        row = {"target": target, "saved_of_downloaded": round(saved / downloaded, 3),
               "saved_of_cut": round(saved / cut_bytes, 3), "steps": steps,
               "psnr_vs_all_bands_db": round(psnr_from_mse(float(np.mean((img - everything) ** 2))), 2),
               "predicted_psnr_vs_all_bands_db": round(psnr_from_mse(max(predicted_loss, 1e-15)), 2)}
        if ref is not None:
            row["psnr_vs_full_detail_db"] = db8(img, ref)
            row["cost_vs_full_detail_db"] = round(out["all_bands_vs_full_detail_db"] - row["psnr_vs_full_detail_db"], 2)
        print(name, row, flush=True)
        return row

    # the client's rule as it is (format_spec/client.md 1.3: area shares, the defaults), for its saving and PSNR
    from client_gl.stream.selection import SelectionOptions, wanted_bands

    want = wanted_bands(a, view, [idx[t] for t in tiles], SelectionOptions(), m.sh_degree)
    kept = {t: min(top[t], want[idx[t]]) for t in tiles}
    saved = sum(band_bytes[t][b - 1] for t in tiles for b in range(kept[t] + 1, top[t] + 1))
    for t in tiles:
        draw_bands(t, kept[t])
    out["rules"]["shares_default"] = [measure("shares_default", 0.0, saved, sum(loss[t][kept[t]] for t in tiles),
                                              sum(top[t] - kept[t] for t in tiles))]
    for t in tiles:
        draw_bands(t, top[t])
    targets = sorted({round(saved / downloaded, 3), *TARGETS})
    for name, steps in rules:
        rows, saved, applied = [], 0, 0
        for target in targets:
            while applied < len(steps) and saved < target * downloaded:
                t, k = steps[applied]
                saved += band_bytes[t][k - 1]
                draw_bands(t, k - 1)
                applied += 1
            if saved < target * downloaded:
                break
            rows.append(measure(name, target, saved, sum(loss[t][k - 1] - loss[t][k] for t, k in steps[:applied]),
                                applied))
        for t in tiles:
            draw_bands(t, top[t])
        out["rules"][name] = rows
    session.close()
    print(json.dumps({k: v for k, v in out.items() if k != "rules"}))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
