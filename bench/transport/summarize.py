"""Per scene and preset, bytes per splat of each attribute under each measured candidate (candidates.py JSON)."""
from __future__ import annotations

import json
import sys
from collections import defaultdict

CANDS = ("gpu", "today", "zstd19", "split_zstd3", "best_entropy", "pred_zstd3", "pred_zstd19", "pred_zstd3_perfield",
         "pred_rans")


def attribute(r: dict) -> str:
    name = r["name"].split(".")[0]
    if r["key"].startswith("codebook"):
        return "sh_codebook"
    return "sh" if name.startswith("sh") else name


def main() -> None:
    rows = []
    for path in sys.argv[1:]:
        rows += json.load(open(path))
    table = defaultdict(lambda: defaultdict(float))
    for r in rows:
        key = (r["scene"], r["preset"], attribute(r) + (".range" if r["kind"] == "range" else ""))
        for c in CANDS:
            v = r.get(c)
            # candidates that do not apply (BC, ranges) fall back to today's coding
            table[key][c] += (v if v is not None else r["today"]) / r["splats"]
    print("| scene | preset | attribute | " + " | ".join(CANDS) + " |")
    print("|---" * (3 + len(CANDS)) + "|")
    for (scene, preset, attr), v in table.items():
        print(f"| {scene} | {preset} | {attr} | " + " | ".join(f"{v[c]:.2f}" for c in CANDS) + " |")


if __name__ == "__main__":
    main()
