#!/usr/bin/env python3
"""Issue 31's whole table for `encode --lod-refine cpu`: per scene and budget the default encode, the CPU-refined
encode and the best peer level of the same splat count, from bench/lod_vs_peers.py runs of the same cameras.

    python bench/cpurefine31_table.py \
        --default bench/results/lod_vs_peers_farpx31_g15c16 --default bench/results/lod_vs_peers_heldout \
        --refined bench/results/cpurefine31/refined --refined bench/results/cpurefine31/refined_rest \
        --refined bench/results/cpurefine31/refined_heldout --refined bench/results/cpurefine31/refined_heldout_small \
        --chosen-on statue-st-peter --markdown OUT.md --plot OUT.png

A scene's default rows and peer rows come from the first --default directory with its JSON; its refined rows from
every --refined directory with its JSON (the union of their budgets). "best peer": the highest of splat-transform's
adaptive level, Spark's cut (inflate or clamp) and a level the source ships itself with exactly that many splats;
"margin": refined - best peer (in brackets the default's); "fill": splats drawn / budget, lowest and highest view of
the refined run; "bytes": the refined run's bytes downloaded (`--no-prefetch`, root manifest file included) over the
bytes of the tiles drawn, mean of the views. Scenes in lod_vs_peers.SCENES order.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics

from lod_vs_peers import SCENES, plot  # bench/ is the script's directory

PEER_KEYS = (("peers", "splat-transform"), ("spark", "Spark"), ("spark_clamp", "Spark clamp"))


def best_peer(res: dict, n: int) -> tuple[float | None, str]:
    """(PSNR, who) of the best peer level of n splats in one lod_vs_peers JSON; (None, '-') if it has none."""
    cands = [(r["psnr_mean"], label) for key, label in PEER_KEYS for r in res.get(key, [])
             if r["budget"] == n and r["psnr_mean"] is not None]
    cands += [(r["psnr_mean"], f"shipped L{r['level']}") for r in res.get("shipped", [])
              if r["splats_drawn"] == n and r["psnr_mean"] is not None]
    return max(cands) if cands else (None, "-")


def load_scene(name: str, default_dirs: list[str], refined_dirs: list[str]) -> tuple[dict, dict] | None:
    """The default JSON of a scene and its refined rows by budget (later directories add budgets, never replace)."""
    default = next((json.load(open(p)) for d in default_dirs if os.path.exists(p := os.path.join(d, f"{name}.json"))),
                   None)
    refined: dict[int, dict] = {}
    for d in refined_dirs:
        p = os.path.join(d, f"{name}.json")
        if os.path.exists(p):
            for r in json.load(open(p))["ours"]:
                refined.setdefault(r["budget"], r)
    if default is None or not refined:
        return None
    return default, refined


def points(default: dict, refined: dict[int, dict]) -> list[dict]:
    """One row per refined budget: default, refined, gain, best peer, both margins, fill and byte ratio."""
    frac = dict(zip(default["budget_splats"], default["budgets"], strict=True))
    old = {r["budget"]: r for r in default["ours"]}
    out = []
    for n, r in refined.items():
        peer, who = best_peer(default, n)
        o = old.get(n)
        fills = [d / n for d in r["splats_drawn_per_view"]]
        out.append({"budget": n, "fraction": frac.get(n) if frac.get(n, 2) <= 1 else None,
                    "default": o["psnr_mean"] if o else None, "refined": r["psnr_mean"],
                    "gain": r["psnr_mean"] - o["psnr_mean"] if o else None, "best_peer": peer, "who": who,
                    "margin": r["psnr_mean"] - peer if peer is not None else None,
                    "margin_default": o["psnr_mean"] - peer if o and peer is not None else None,
                    "fill": (min(fills), max(fills)),
                    "bytes_ratio": r["bytes_downloaded_mean"] / r["drawn_tile_bytes_mean"]})
    order = {n: i for i, n in enumerate(default["budget_splats"])}
    return sorted(out, key=lambda p: order.get(p["budget"], len(order)))


def _f(v: float | None, sign: bool = False) -> str:
    return "-" if v is None else (f"{v:+.2f}" if sign else f"{v:.2f}")


def table(scenes: list[tuple[str, dict, list[dict]]], chosen_on: set[str]) -> str:
    rows = ["| scene | budget | default | refined on the CPU | gain | best peer | margin (default's) | fill | "
            "downloaded / drawn |", "|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    for name, default, pts in scenes:
        tag = "chosen on; nothing tuned" if name in chosen_on else "held out"
        for k, p in enumerate(pts):
            label = (f"{p['fraction'] * 100:g} % ({p['budget']:,})" if p["fraction"] is not None
                     else f"{p['budget']:,}")
            lo, hi = p["fill"]
            first = f"{name} ({tag}; {default['splats']:,} splats)" if k == 0 else ""
            rows.append(f"| {first} | {label} | "
                        f"{_f(p['default'])} | {_f(p['refined'])} | {_f(p['gain'], True)} | "
                        f"{_f(p['best_peer'])} ({p['who']}) | {_f(p['margin'], True)} "
                        f"({_f(p['margin_default'], True)}) | {lo:.3f}-{hi:.3f}{' (over)' if hi > 1 else ''} | "
                        f"{p['bytes_ratio']:.2f} |")
    return "\n".join(rows) + "\n"


def summary(pts: list[dict], what: str) -> str:
    m = [p["margin"] for p in pts if p["margin"] is not None]
    md = [p["margin_default"] for p in pts if p["margin_default"] is not None]
    g = [p["gain"] for p in pts if p["gain"] is not None]
    if not pts:
        return f"{what}: 0 points"
    if not m:
        return f"{what}: no point with a peer"
    return (f"{what}: {len(pts)} points; refined >= +1 dB above the best peer at {sum(x >= 1 for x in m)} of {len(m)} "
            f"(margin {min(m):+.2f} to {max(m):+.2f}, median {statistics.median(m):+.2f}); the default at "
            f"{sum(x >= 1 for x in md)} of {len(md)}; gain over the default {min(g):+.2f} to {max(g):+.2f} dB "
            f"(median {statistics.median(g):+.2f})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--default", action="append", required=True, help="lod_vs_peers out-dir of the default encode")
    ap.add_argument("--refined", action="append", required=True, help="lod_vs_peers out-dir of the refined encode")
    ap.add_argument("--chosen-on", default="statue-st-peter", help="comma list of the scenes the settings were "
                    "chosen on (the others are held out)")
    ap.add_argument("--markdown", default=None)
    ap.add_argument("--plot", default=None, help="PNG: PSNR against splats drawn per scene (lod_vs_peers.plot; "
                    "blue: refined, light blue: default)")
    args = ap.parse_args(argv)
    chosen = {s for s in args.chosen_on.split(",") if s}
    scenes, plotted = [], []
    for name in SCENES:
        got = load_scene(name, args.default, args.refined)
        if got is None:
            continue
        default, refined = got
        scenes.append((name, default, points(default, refined)))
        plotted.append(default | {"ours": sorted(refined.values(), key=lambda r: r["budget"]),
                                  "ours_default": default["ours"]})
    text = table(scenes, chosen)
    def pick(inside: bool, fraction: bool, held_out: bool = False) -> list[dict]:
        return [p for name, _, pts in scenes for p in pts if SCENES[name].outside != inside
                and (p["fraction"] is not None) == fraction and (not held_out or name not in chosen)]

    lines = [summary(pick(True, True), "the scenes of ../shared/data, budgets of 2 / 6 / 25 / 50 %"),
             summary(pick(True, True, held_out=True), "of which on scenes held out"),
             summary(pick(False, True), "outside it (playbot), 2 / 6 / 25 / 50 %"),
             summary(pick(False, False), "outside it, at the counts of its shipped levels")]
    text += "\n" + "\n\n".join(s for s in lines if not s.endswith(": 0 points")) + "\n"
    print(text)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(text)
    if args.plot:
        plot(plotted, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
