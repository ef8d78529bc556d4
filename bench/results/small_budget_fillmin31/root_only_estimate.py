"""What a view would read with the root drawn first and then the cut itself (no ancestors between), for the
cuts of today's run (bench/results/small_budget_smallroot31/unpaged, the same cuts at every threshold): the
manifest, the drawn tiles' payloads and the root's (where the cut is not the root),
over the drawn tiles' bytes as small_budget_bytes.py counts them; and with neither the root nor
the ancestors (a threshold above the cut). An estimate from the logged bytes, not a stream: no client builds the
root-only list. `PYTHONPATH=. python bench/results/small_budget_fillmin31/root_only_estimate.py` (the encodes in
/tmp/pages31_ours, for the root's payload bytes)."""
import json
import os
import statistics

from splatstream.format.manifest import parse_manifest

HERE = os.path.dirname(os.path.abspath(__file__))
BEFORE = os.path.join(HERE, "..", "small_budget_smallroot31", "unpaged")
SCENES = ["donut", "biker", "statue-massa", "statue-st-peter", "statue-angel", "statue-angel-with-candlestick",
          "statue-narcissus", "statue-trumpet", "guitar", "statue-angel-kneeling", "winter_fountain", "flowers",
          "playbot"]


def main() -> None:
    print("| scene | root B | manifest B | 6 %: today | no ancestors, no root | the root only |")
    print("|---|---:|---:|---|---|---|")
    for s in SCENES:
        d = json.load(open(os.path.join(BEFORE, f"{s}_np.json")))
        m = parse_manifest(open(f"/tmp/pages31_ours/{s}/manifest.msgpack", "rb").read())
        root = sum(g.bytes for g in m.tile(m.root).groups.values())
        r = next(r for r in d["rows"] if r["fraction"] == 0.06)
        v = r["views"]
        none = statistics.mean((x["drawn"] + x["manifest"]) / x["drawn_tile_bytes"] for x in v)
        only = statistics.mean((x["drawn"] + x["manifest"] + (0 if m.root in x["draw"] else root))
                               / x["drawn_tile_bytes"] for x in v)
        print(f"| {s} | {root:,} | {v[0]['manifest']:,} | {r['ratio']:.3f} | {none:.3f} | {only:.3f} |")


if __name__ == "__main__":
    main()
