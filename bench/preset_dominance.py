"""Named presets against the peers' points (issues 15 and 32, "Done when"), from `splatstream eval` reports.

    python bench/preset_dominance.py REPORT.json ... [--markdown OUT.md] [--table OUT.md] [--plot OUT.png]
                                                      [--held-out OUT.md] [--columns N]

Each REPORT.json is one scene's eval (bench/run_eval.sh writes <scene>.json; reports of the same scene are merged,
later files winning on equal labels). For every peer point (rows of kind `compare`: splat-transform's
compressed.ply, SPZ, SOG) it names the smallest preset (rows of kind `preset`) whose mean PSNR is at least the
peer's, and the ratio of their disk bytes; the goal is a ratio of at most 0.90. Where it is not met the shortfall
is stated both ways: the smallest ratio at the peer's PSNR, and the best preset at 0.90 of its bytes or fewer with
its PSNR deficit. The plot has one panel per scene (the eval's rate-distortion plot of the presets and peers;
presets with identical points, e.g. the SH presets and their bases on an SH0 scene, share one label).

Held-out evaluation (--held-out): every choice below was made on some scenes (TUNED: the scenes whose
measurements chose a preset's settings, BENCHMARKS.md "Size against quality" and "SH coding on real captures";
CHOICES: the peer point a preset was made to dominate and where). For each choice it says whether it holds on every
other scene, and for every peer point the smallest dominating preset among those *not* tuned on that scene (leave
one scene out).
"""
from __future__ import annotations

import argparse
import json
import os
from collections import defaultdict

GOAL = 0.90

# Scenes (report input file names without extension) whose measurements chose each preset's settings. The seven
# presets of issue 15 and the tile-step presets were tuned on the four real bench scenes (and the synthetic s1m);
# the per-splat SH presets on flowers (G) and fruit_drops (the importance exponent), on top of bases tuned on the
# bench scenes. medium-12bit (medium with medium-low-12bit's position step) was chosen on two statue scans, between
# steps of 2047, 4095 and 8191 levels. medium-low-9bit's scale and opacity steps (low-plus-9bit's) were chosen on
# guitar against its SOG point, and medium's scale step on guitar against its compressed.ply point. very-high is
# lossless: tuned on nothing.
BENCH = ("fruit_drops_sh3", "donut_sh0_no_normals", "biker.compressed", "lod_tile_sh3_zero_rest", "s1m")
SH_TUNED = BENCH + ("flowers",)
STATUE_TUNED = ("statue-massa", "statue-angel")
# medium-low-palette (issue 32): its position step's K was chosen leave-one-statue-out (BENCHMARKS.md, "A position
# step from the splats' size"), but the preset's one K = 120, the palettes and SH0's merge were chosen looking at all
# seven statues, and its fallback on donut: so it counts as tuned on all of them.
STATUES = ("statue-angel", "statue-angel-kneeling", "statue-angel-with-candlestick", "statue-massa",
           "statue-narcissus", "statue-st-peter", "statue-trumpet")
TUNED: dict[str, tuple[str, ...]] = {
    "very-high": (),
    **{p: BENCH for p in ("high", "medium-low", "medium-low-12bit", "low-plus-9bit", "low-plus", "low", "very-low")},
    **{p: BENCH + ("guitar.compressed",) for p in ("medium", "medium-low-9bit")},
    **{p: SH_TUNED for p in ("high-sh255", "medium-high", "medium-low-sh16", "medium-low-sh8", "low-plus-9bit-sh6",
                             "low-plus-9bit-sh5", "low-plus-10bit-cb8")},
    # very-low-rgb127 (step32): its colour step chosen on flowers, on very-low's planes (tuned on the bench scenes)
    "very-low-rgb127": SH_TUNED,
    "medium-12bit": BENCH + STATUE_TUNED,
    "medium-low-palette": BENCH + STATUES,
}
# A per-splat SH preset on a scene without SH bands is its base (not measured again there)
SH_BASE = {"high-sh255": "high", "medium-high": "high", "medium-low-sh16": "medium-low", "medium-low-sh8": "medium-low",
           "low-plus-9bit-sh6": "low-plus-9bit", "low-plus-9bit-sh5": "low-plus-9bit"}
# (preset, peer label, scenes the choice was made on, what was chosen there)
CHOICES: list[tuple[str, str, tuple[str, ...], str]] = [
    ("medium", "st-compressed.ply", ("biker.compressed", "guitar.compressed"),
     "opacity grid and input chunk order (biker); scale tile step G 1023 (guitar)"),
    ("medium-12bit", "st-compressed.ply", STATUE_TUNED, "12-bit tile-step positions on medium (two statues)"),
    ("medium-low", "st-sog", ("lod_tile_sh3_zero_rest",), "zstd level 9 (lod_tile at 0.904 before)"),
    ("medium-low-9bit", "st-sog", ("biker.compressed", "guitar.compressed"),
     "9-bit positions, zstd 16 (biker); scale and opacity steps of low-plus-9bit (guitar)"),
    ("medium-low-12bit", "st-sog", ("donut_sh0_no_normals",), "tile steps G 4095/180/255/55 (donut)"),
    ("low-plus-9bit", "st-sog", ("s1m",), "9-bit positions on tile steps (s1m)"),
    ("medium-low-palette", "st-sog", STATUES,
     "scene palettes, SH0's merged pairwise, position step m / 120, keyed (the statues; K leave-one-statue-out)"),
    ("low", "st-spz", BENCH, "issue 15's low (the bench scenes)"),
    ("low-plus-9bit-sh5", "st-spz", ("flowers", "fruit_drops_sh3"),
     "one zero-anchored SH step per band, G 5, exponent 0.3 (flowers; exponent on fruit_drops)"),
    ("low-plus-10bit-cb8", "st-sog", ("flowers",),
     "SH codebook of one entry per 8 splats (65,536), two-cell search, 1023-level keyed positions (flowers)"),
]


def _name(report: dict) -> str:
    return os.path.basename(report["input"]["path"])


def load(paths: list[str]) -> dict[str, dict]:
    scenes: dict[str, dict] = defaultdict(lambda: {"presets": {}, "peers": {}, "input": None})
    for path in paths:
        report = json.load(open(path))
        s = scenes[_name(report)]
        s["input"] = report["input"]
        for row in report["rows"]:
            if row["kind"] == "compare":
                s["peers"][row["label"]] = row
            elif row["kind"] == "preset":
                s["presets"][row["label"]] = row
    return dict(scenes)


def _psnr(row: dict) -> float:
    return float("inf") if row["psnr_mean"] is None else float(row["psnr_mean"])


def best_within(presets: dict[str, dict], budget: float) -> tuple[str, float, float] | None:
    """The preset with the highest PSNR at `budget` B/splat or fewer: (name, bytes, PSNR)."""
    fits = [(_psnr(r), -r["disk_bytes_per_splat"], n) for n, r in presets.items()
            if r["disk_bytes_per_splat"] <= budget]
    if not fits:
        return None
    p, neg_b, n = max(fits)
    return n, -neg_b, p


def verdicts(s: dict) -> list[dict]:
    out = []
    for label, peer in s["peers"].items():
        peer_b, peer_p = peer["disk_bytes_per_splat"], _psnr(peer)
        ok = sorted((r["disk_bytes_per_splat"], -_psnr(r), n) for n, r in s["presets"].items() if _psnr(r) >= peer_p)
        v = {"peer": label, "peer_bytes": peer_b, "peer_psnr": peer_p, "preset": None, "ratio": None, "met": False,
             "best_within_goal": best_within(s["presets"], GOAL * peer_b)}
        if ok:
            b, neg_p, n = ok[0]
            v.update(preset=n, preset_bytes=b, preset_psnr=-neg_p, ratio=b / peer_b, met=b / peer_b <= GOAL)
        out.append(v)
    return out


def markdown(scenes: dict[str, dict]) -> str:
    lines = ["| scene | peer | peer B/splat | peer PSNR dB | smallest preset at >= its PSNR | ratio | goal <= 0.90 |",
             "|---|---|---|---|---|---|---|"]
    for name, s in scenes.items():
        short = _short(name, s)
        for v in verdicts(s):
            found = "none" if v["preset"] is None else \
                f"{v['preset']} ({v['preset_bytes']:.2f} B, {v['preset_psnr']:.2f} dB)"
            ratio = "" if v["ratio"] is None else f"{v['ratio']:.2f}"
            if v["met"]:
                verdict = "met"
            else:
                best = v["best_within_goal"]
                verdict = "**not met**: at <= 0.90 of its bytes the best is " + \
                    ("none" if best is None else f"{best[0]} ({best[1]:.2f} B, {best[2]:.2f} dB, "
                     f"{best[2] - v['peer_psnr']:+.2f} dB)")
            lines.append(f"| {short} | {v['peer']} | {v['peer_bytes']:.2f} | {v['peer_psnr']:.2f} | {found} | "
                         f"{ratio} | {verdict} |")
    return "\n".join(lines)


def _stem(name: str) -> str:
    return os.path.splitext(name)[0]


def _short(name: str, s: dict) -> str:
    return f"{_stem(name)} ({s['input']['splats']:,}, SH{s['input']['sh_degree']})"


def held_out_presets(name: str, presets: dict[str, dict]) -> dict[str, dict]:
    """The presets whose settings were not chosen on scene `name` (a preset not in TUNED counts as tuned on all)."""
    return {p: r for p, r in presets.items() if p in TUNED and _stem(name) not in TUNED[p]}


def summary(scenes: dict[str, dict]) -> dict:
    """Counts of peer points met: all, on scenes no preset was tuned on, and leave-one-scene-out."""
    tuned_any = {t for ts in TUNED.values() for t in ts}
    out = {"points": 0, "met": 0, "held_out_points": 0, "held_out_met": 0, "loo_met": 0}
    for name, s in scenes.items():
        held = _stem(name) not in tuned_any
        loo = verdicts({**s, "presets": held_out_presets(name, s["presets"])})
        for v, w in zip(verdicts(s), loo, strict=True):
            out["points"] += 1
            out["met"] += v["met"]
            out["loo_met"] += w["met"]
            out["held_out_points"] += held
            out["held_out_met"] += held and v["met"]
    return out


def held_out_markdown(scenes: dict[str, dict]) -> str:
    """The choices made on some scenes, checked on the others; then every peer point against the presets not tuned
    on its scene (leave one scene out)."""
    lines = ["| choice | chosen on | there | other scenes: holds on | where it does not (preset / peer bytes, dB) |",
             "|---|---|---|---|---|"]
    for preset, peer, chosen, what in CHOICES:
        there, held, fails = [], [], []
        for name, s in scenes.items():
            r, q = s["presets"].get(preset), s["peers"].get(peer)
            if r is None or q is None or (TUNED.get(preset) == SH_TUNED and not s["input"]["sh_degree"]):
                continue  # a per-splat SH preset is its base on a scene without SH bands
            ratio = r["disk_bytes_per_splat"] / q["disk_bytes_per_splat"]
            gain = _psnr(r) - _psnr(q)
            ok = ratio <= GOAL and gain >= 0
            cell = f"{_stem(name)} {ratio:.2f}, {gain:+.2f} dB"
            if _stem(name) in chosen:
                there.append(cell + ("" if ok else " (not met)"))
            else:
                held.append(ok)
                if not ok:
                    fails.append(cell)
        lines.append(f"| `{preset}` against {peer}: {what} | {', '.join(chosen)} | {'; '.join(there) or 'not run'} | "
                     f"{sum(held)} of {len(held)} | {'; '.join(fails) or '-'} |")
    lines += ["", "| scene | peer | peer B/splat | peer PSNR dB | smallest preset not tuned on this scene at >= its "
              "PSNR | ratio | goal <= 0.90 |", "|---|---|---|---|---|---|---|"]
    for name, s in scenes.items():
        presets = held_out_presets(name, s["presets"])
        for v in verdicts({**s, "presets": presets}):
            found = "none" if v["preset"] is None else \
                f"{v['preset']} ({v['preset_bytes']:.2f} B, {v['preset_psnr']:.2f} dB)"
            ratio = "" if v["ratio"] is None else f"{v['ratio']:.2f}"
            if not set(presets) - {"very-high"}:
                found, ratio, verdict = "-", "", "every lossy preset was tuned on this scene"
            elif v["met"]:
                verdict = "met"
            else:
                best = v["best_within_goal"]
                verdict = "**not met**: at <= 0.90 of its bytes the best is " + \
                    ("none" if best is None else f"{best[0]} ({best[1]:.2f} B, {best[2]:.2f} dB, "
                     f"{best[2] - v['peer_psnr']:+.2f} dB)")
            lines.append(f"| {_short(name, s)} | {v['peer']} | {v['peer_bytes']:.2f} | {v['peer_psnr']:.2f} | "
                         f"{found} | {ratio} | {verdict} |")
    n = summary(scenes)
    lines += ["", f"Peer points met: {n['met']} of {n['points']}; on the scenes no preset was tuned on "
              f"{n['held_out_met']} of {n['held_out_points']}; leave one scene out (presets not tuned on the "
              f"point's scene only) {n['loo_met']} of {n['points']}."]
    return "\n".join(lines)


def preset_table(scenes: dict[str, dict], columns: int = 0) -> str:
    """Disk B/splat and mean PSNR of every preset and peer, one column per scene (in tables of at most `columns`
    scenes each, when given)."""
    if columns and len(scenes) > columns:
        names = list(scenes)
        return "\n\n".join(preset_table({n: scenes[n] for n in names[i:i + columns]})
                            for i in range(0, len(names), columns))
    from splatstream.format.presets import PRESETS, rotation_choices

    def cell(r: dict | None, preset: str = "", s: dict | None = None) -> str:
        if r is None and s is not None and not s["input"]["sh_degree"] and preset in SH_BASE:
            base = s["presets"].get(SH_BASE[preset])
            # a rotation format the base preset's encoder measured (format 1.14: medium-low's cube8x4) is the SH
            # preset's too where it measures the same candidates (medium-low-sh16, -sh8 since shvariants32): the
            # same sample, the same choice; otherwise it is the base's planes but for the rotations
            if base is not None and base["formats"]["rotation"] != PRESETS[preset]["rotation"] \
                    and base["formats"]["rotation"] not in rotation_choices(preset):
                return f"= {SH_BASE[preset]} with {PRESETS[preset]['rotation']} rotations (no SH bands)"
            return f"= {SH_BASE[preset]} (no SH bands)"
        if r is None:
            return "not run"
        return f"{r['disk_bytes_per_splat']:.2f} B, " + \
            ("identical render" if r["psnr_mean"] is None else f"{r['psnr_mean']:.1f} dB")

    head = [_short(n, s) for n, s in scenes.items()]
    lines = ["| preset | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for p in PRESETS:
        lines.append(f"| {p} | " + " | ".join(cell(s["presets"].get(p), p, s) for s in scenes.values()) + " |")
    for peer in sorted({k for s in scenes.values() for k in s["peers"]}):
        lines.append(f"| {peer.replace('st-', 'splat-transform ')} | "
                     + " | ".join(cell(s["peers"].get(peer)) for s in scenes.values()) + " |")
    return "\n".join(lines)


def _merged_points(presets: dict[str, dict]) -> list[dict]:
    """The preset rows by bytes; those at the same PSNR (0.01 dB) within 1 % of each other's bytes (the per-splat
    SH presets and their bases on a scene without SH bands) as one row, labelled "base = -sh16 = -sh8"."""
    groups: list[list[dict]] = []
    for r in sorted(presets.values(), key=lambda r: (len(r["label"]), r["label"])):
        for g in groups:
            if g[0]["psnr_mean"] is not None and r["psnr_mean"] is not None \
                    and abs(g[0]["psnr_mean"] - r["psnr_mean"]) < 0.01 \
                    and abs(g[0]["disk_bytes_per_splat"] / r["disk_bytes_per_splat"] - 1) < 0.01:
                g.append(r)
                break
        else:
            groups.append([r])
    rows = []
    for g in groups:
        base = g[0]["label"]
        rest = ["-" + r["label"][len(base) + 1:] if r["label"].startswith(base + "-") else r["label"] for r in g[1:]]
        rows.append({**g[0], "label": " = ".join([base, *rest])})
    return sorted(rows, key=lambda r: r["disk_bytes_per_splat"])


def plot(scenes: dict[str, dict], out: str) -> None:
    """One panel per scene (splatstream.evaluate's rate-distortion plot of its presets and peers), in a grid."""
    import tempfile

    from PIL import Image

    from splatstream.evaluate import plot_rate_distortion

    panels = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, s in enumerate(scenes.values()):
            report = {"input": s["input"], "rows": _merged_points(s["presets"]) + list(s["peers"].values())}
            path = os.path.join(tmp, f"{i}.png")
            plot_rate_distortion(report, path)
            with Image.open(path) as im:
                panels.append(im.convert("RGB"))
    cols = min(3, len(panels))
    rows = (len(panels) + cols - 1) // cols
    w, h = panels[0].size
    grid = Image.new("RGB", (cols * w, rows * h), "white")
    for i, panel in enumerate(panels):
        grid.paste(panel, ((i % cols) * w, (i // cols) * h))
    grid.save(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--markdown")
    ap.add_argument("--plot")
    ap.add_argument("--table", help="also write the presets' and peers' bytes and PSNR per scene (Markdown) here")
    ap.add_argument("--columns", type=int, default=0, help="--table: at most this many scenes a table")
    ap.add_argument("--held-out", help="also write the held-out checks (choices on other scenes, leave one scene "
                    "out; Markdown) here")
    args = ap.parse_args()
    scenes = load(args.reports)
    text = markdown(scenes)
    print(text)
    if args.markdown:
        open(args.markdown, "w").write(text + "\n")
    if args.table:
        open(args.table, "w").write(preset_table(scenes, args.columns) + "\n")
    if args.held_out:
        open(args.held_out, "w").write(held_out_markdown(scenes) + "\n")
    if args.plot:
        plot(scenes, args.plot)


if __name__ == "__main__":
    main()
