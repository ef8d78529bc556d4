"""Add preset rows of one `splatstream eval` report to another report of the same scene and cameras.

    python bench/eval_merge.py TARGET.json SOURCE.json [SOURCE.json ...] [--rename OLD=NEW ...]

A preset added after a full `bench/run_eval.sh` round is measured alone (`eval SCENE --presets NEW`, same views,
size and renderer) and merged here, instead of re-running every preset of every scene. The rows are added only when
both reports have the same input (path, bytes, splats), the same cameras (floats to 1e-12 relative), render size and
renderer; a row of the same label in TARGET is replaced. `--rename` relabels a row (a setting measured under a probe
name before it became a named preset; the settings must be the preset's). Every merged row keeps the source's commit
under `merged_from`, so the table says where each row was measured. Only rows of kind `preset` are merged, unless
`--peers`: then the peers' rows (kind `compare`, e.g. a SOG point encoded later on the GPU machine and compared
alone with `eval --presets none --compare ...`) too, after the presets.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys


def same_measurement(a: dict, b: dict) -> str | None:
    """None when reports `a` and `b` measured the same scene the same way, else what differs."""
    for key in ("bytes", "splats"):
        if a["input"][key] != b["input"][key]:
            return f"input {key}: {a['input'][key]} != {b['input'][key]}"
    if os.path.basename(a["input"]["path"]) != os.path.basename(b["input"]["path"]):
        return f"input {a['input']['path']} != {b['input']['path']}"
    for key in ("size", "renderer"):
        if a[key] != b[key]:
            return f"{key} differ"
    if not same_cameras(a["cameras"], b["cameras"]):
        return "cameras differ"
    return None


def same_cameras(a: list[dict], b: list[dict]) -> bool:
    """The same views: equal fields, floats to 1e-12 relative (the orbit's arithmetic has moved eyes and near planes
    by an ulp between commits, step32: fruit_drops' 8 views, every view's PSNR the same to the last digit)."""
    def close(x, y) -> bool:
        if isinstance(x, float) or isinstance(y, float):
            return isinstance(x, (int, float)) and isinstance(y, (int, float)) and math.isclose(x, y, rel_tol=1e-12,
                                                                                                  abs_tol=1e-15)
        if isinstance(x, list) and isinstance(y, list):
            return len(x) == len(y) and all(close(u, v) for u, v in zip(x, y, strict=True))
        if isinstance(x, dict) and isinstance(y, dict):
            return x.keys() == y.keys() and all(close(x[k], y[k]) for k in x)
        return x == y
    return close(a, b)


def merge(target: dict, source: dict, rename: dict[str, str], peers: bool = False) -> list[str]:
    """Rows of kind `preset` (and with `peers`, `compare`) of `source` into `target` (in place); the labels merged."""
    problem = same_measurement(target, source)
    if problem:
        raise ValueError(problem)
    merged = []
    for row in source["rows"]:
        if row["kind"] != "preset" and not (peers and row["kind"] == "compare"):
            continue
        row = dict(row)
        if row["kind"] == "compare":
            row["merged_from"] = source["source"]
            target["rows"] = [r for r in target["rows"] if not (r["kind"] == "compare" and r["label"] == row["label"])]
            target["rows"].append(row)
            merged.append(row["label"])
            continue
        label = rename.get(row["label"], row["label"])
        if label != row["label"]:
            row["probe_label"] = row["label"]
            row["label"] = row["preset"] = label
        row["merged_from"] = source["source"]
        target["rows"] = [r for r in target["rows"] if not (r["kind"] == "preset" and r["label"] == label)]
        # keep presets before peers, as eval writes them
        first_peer = next((i for i, r in enumerate(target["rows"]) if r["kind"] != "preset"), len(target["rows"]))
        target["rows"].insert(first_peer, row)
        merged.append(label)
    return merged


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("target")
    ap.add_argument("sources", nargs="+")
    ap.add_argument("--rename", nargs="*", default=[], metavar="OLD=NEW")
    ap.add_argument("--only", default="", help="comma-separated labels (after renaming) to merge; default: all")
    ap.add_argument("--peers", action="store_true", help="also merge the peers' rows (kind compare)")
    args = ap.parse_args(argv)
    rename = dict(r.split("=", 1) for r in args.rename)
    only = {x for x in args.only.split(",") if x}
    target = json.load(open(args.target))
    for path in args.sources:
        source = json.load(open(path))
        if only:
            source["rows"] = [r for r in source["rows"] if rename.get(r["label"], r["label"]) in only]
        try:
            labels = merge(target, source, rename, args.peers)
        except ValueError as e:
            print(f"{path}: not merged: {e}", file=sys.stderr)
            return 1
        print(f"{path}: merged {', '.join(labels) or 'nothing'}")
    with open(args.target + ".part", "w") as f:
        json.dump(target, f, indent=1)
    os.replace(args.target + ".part", args.target)
    return 0


if __name__ == "__main__":
    sys.exit(main())
