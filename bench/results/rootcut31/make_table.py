#!/usr/bin/env python3
"""rootcut31's tables from runs/*.json (bench/small_budget_bytes.py --compare "A|B" output): per scene and budget,
both rows' downloaded / drawn, the cut's base bytes (per view: min-max), the medians of the first picture, the second
picture (the first frame whose drawn tiles differ from the first's) and converged, the median paired differences
(same view and repeat) of the second row against the first, and how long the first picture stays alone (second
picture - first; for a row whose second picture is the converged one, converged - first).

    python bench/results/rootcut31/make_table.py [PREFIX ...]     # writes bench/results/rootcut31/table.md
"""
from __future__ import annotations

import glob
import json
import os
import statistics
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", ".."))


def base_bytes(scene_dir: str) -> dict[int, int]:
    from small_budget_bytes import _whole_tree

    _, _, whole = _whole_tree(scene_dir)
    return {t.id: t.groups["base"].bytes for t in whole.tiles}


def med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def ms(x, sign=False):
    return "-" if x is None else (f"{1000 * x:+.0f}" if sign else f"{1000 * x:.0f}")


def alone(v):
    s = v.get("second_picture_s")
    return (s if s is not None else v["converged_s"]) - v["first_frame_s"]


def table(files: list[str]) -> str:
    out = ["| run, scene, budget | cut base B per view (tiles) | A: ratio, first / second / converged ms, alone ms "
           "| B: ratio, first / converged ms, alone ms | B - A: Δ first, Δ converged (paired medians) | rows |",
           "|---|---|---|---|---|---|"]
    for f in files:
        d = json.load(open(f))
        sizes = base_bytes(d["scene_dir"])
        rows = d["rows"]
        tag = os.path.basename(f).split("_")[0]
        for i in range(0, len(rows), 2):
            a, b = rows[i], rows[i + 1]
            cut = [sum(sizes[t] for t in v["draw"]) for v in a["views"]]
            cuts: dict[int, set] = {}  # every run of a view, both rows: the same cut
            for v in a["views"] + b["views"]:
                cuts.setdefault(v["view"], set()).add(tuple(v["draw"]))
            same = all(len(c) == 1 for c in cuts.values())
            pa = {(v["view"], v["repeat"]): v for v in a["views"]}
            dfirst = med([v["first_frame_s"] - pa[(v["view"], v["repeat"])]["first_frame_s"] for v in b["views"]])
            dconv = med([v["converged_s"] - pa[(v["view"], v["repeat"])]["converged_s"] for v in b["views"]])
            tiles = statistics.mean(v["drawn_tiles"] for v in a["views"])
            out.append(
                f"| {tag} {d['scene']} {100 * a['fraction']:g} % | {min(cut):,}-{max(cut):,} ({tiles:.0f})"
                f"{'' if same else ' **cuts differ**'} | {a['ratio']:.3f}, "
                f"{ms(med(v['first_frame_s'] for v in a['views']))}"
                f" / {ms(med(v.get('second_picture_s') for v in a['views']))}"
                f" / {ms(med(v['converged_s'] for v in a['views']))}, {ms(med(alone(v) for v in a['views']))}"
                f" | {b['ratio']:.3f}, {ms(med(v['first_frame_s'] for v in b['views']))}"
                f" / {ms(med(v['converged_s'] for v in b['views']))}, {ms(med(alone(v) for v in b['views']))}"
                f" | {ms(dfirst, True)}, {ms(dconv, True)} | {a['variant']} / {b['variant']} |")
    return "\n".join(out) + "\n"


def bytes_table(files: list[str]) -> str:
    """The directory runs (`bytes_*.json`, no link, one run a view): downloaded / drawn of both rows per scene and
    budget, whether every view drew the same cut in both, and the cut's base bytes per view."""
    out = ["| scene | budget | cut base B per view (tiles) | same cut | A: downloaded / drawn | B: downloaded / drawn "
           "| B: ancestors B (n) |", "|---|---|---|---|---|---|---|"]
    for f in files:
        d = json.load(open(f))
        sizes = base_bytes(d["scene_dir"])
        rows = d["rows"]
        for i in range(0, len(rows), 2):
            a, b = rows[i], rows[i + 1]
            cut = [sum(sizes[t] for t in v["draw"]) for v in a["views"]]
            same = all(va["draw"] == vb["draw"] for va, vb in zip(a["views"], b["views"], strict=True))
            tiles = statistics.mean(v["drawn_tiles"] for v in a["views"])
            anc = statistics.mean(v["ancestors"] for v in b["views"])
            nanc = statistics.mean(v["n_ancestors"] for v in b["views"])
            out.append(f"| {d['scene']} | {100 * a['fraction']:g} % | {min(cut):,}-{max(cut):,} ({tiles:.0f}) | "
                       f"{'yes' if same else '**no**'} | {a['ratio']:.3f} | {b['ratio']:.3f} | {anc:,.0f} "
                       f"({nanc:.1f}) |")
    return "\n".join(out) + "\n"


def main(argv: list[str]) -> int:
    prefixes = argv or ["chosen", "heldout", "recheck"]
    files = [f for p in prefixes for f in sorted(glob.glob(os.path.join(HERE, "runs", f"{p}_*_20-40.json")))]
    text = ("# rootcut31: the root, then the cut, against main's rule (20 Mbit/s, 40 ms)\n\n"
            "A: the first row (`--fill-root-kb 0`, main's rule), B: the second. Times from the manifest request, "
            "medians of 12 runs (4 views x 3 repeats); alone: how long the first picture stays the only one (A: "
            "second picture - first; B: converged - first where its second picture is the converged one). The cut's "
            "base bytes per view decide the band (64 KiB = 65,536; 128 KiB = 131,072; 256 KiB = 262,144; 512 KiB = "
            "524,288).\n\n" + table(files))
    byte_files = sorted(glob.glob(os.path.join(HERE, "runs", "bytes_*.json")))
    if byte_files:
        text += ("\n## Bytes at 2 / 6 / 25 / 50 % (directory, no link, `--no-prefetch`, one run a view)\n\n"
                 "A: `--fill-root-kb 0` (main's rule), B: `--fill-root-kb 512` (this branch's default).\n\n"
                 + bytes_table(byte_files))
    open(os.path.join(HERE, "table.md"), "w").write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
