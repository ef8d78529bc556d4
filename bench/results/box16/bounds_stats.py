"""Format 1.16's bounds on real trees (issue 31, branch box16): each scene encoded with `--no-compact-table` (its
tree's f64 bounds in the 1.8 table), coded as a 1.16 writer codes it (table.relative_columns, unpaged) and as 1.15
(table.compact_columns): how many boxes grew to hold their children, how many radii took `radius_far`, the
radius over the half diagonal, whether every decoded bound holds the tree's, and how much larger 1.16's boxes and
radii are than 1.15's (the steps' rounding, against the f32 rounding).

    PYTHONPATH=. python bench/results/box16/bounds_stats.py /tmp/box16_enc/f64/SCENE ... [--out bounds.json]
"""
import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))))
from splatstream.format.manifest.table import (  # noqa: E402
    RADIUS_FAR,
    bounds_columns,
    compact_columns,
    encode_relative,
    half_diagonals,
    table_parents,
)
from splatstream.store import load_manifest  # noqa: E402


def stats(scene_dir: str) -> dict:
    m = load_manifest(scene_dir)
    tiles = m.tiles
    box, sphere, error = bounds_columns(tiles)
    ids = np.array([t.id for t in tiles], np.int64)
    level = np.array([t.level for t in tiles], np.int64)
    parent = table_parents(ids, [len(t.children) for t in tiles], [c for t in tiles for c in t.children])
    _, box8, radius8, far, dec, dec_sphere, grown = encode_relative(box, sphere, parent, level)
    b15, s15, _ = compact_columns(box, sphere, error, centre_from_box=True)
    holds_box = bool((dec[:, :3] <= box[:, :3]).all() and (dec[:, 3:] >= box[:, 3:]).all())
    moved = np.linalg.norm(dec_sphere[:, :3] - sphere[:, :3], axis=1)
    holds_sphere = bool((dec_sphere[:, 3] >= sphere[:, 3] + moved).all())
    h_tree = half_diagonals(box)
    ext = box[:, 3:] - box[:, :3]
    grow16 = np.concatenate([box[:, :3] - dec[:, :3], dec[:, 3:] - box[:, 3:]], axis=1) / np.maximum(
        np.concatenate([ext, ext], axis=1), 1e-30)
    return {"scene": os.path.basename(scene_dir.rstrip("/")), "tiles": len(tiles), "version": list(m.version),
            "grown_boxes": grown, "radius_far": int((radius8 == RADIUS_FAR).sum()),
            "radius_over_half_diagonal": {"max": float((sphere[:, 3] / h_tree).max()),
                                          "median": float(np.median(sphere[:, 3] / h_tree)),
                                          "above_1": int((sphere[:, 3] > h_tree).sum())},
            "holds_tree_boxes": holds_box, "holds_tree_spheres": holds_sphere,
            "box_side_growth_of_extent": {"max": float(grow16.max()), "mean": float(grow16.mean())},
            "radius_1_16_over_1_15": {"max": float((dec_sphere[:, 3] / s15[:, 3]).max()),
                                      "mean": float((dec_sphere[:, 3] / s15[:, 3]).mean())},
            "radius_1_16_over_tree": {"max": float((dec_sphere[:, 3] / sphere[:, 3]).max()),
                                      "mean": float((dec_sphere[:, 3] / sphere[:, 3]).mean())},
            "box_volume_1_16_over_1_15": {"max": float((np.prod(dec[:, 3:] - dec[:, :3], axis=1)
                                                        / np.prod(b15[:, 3:] - b15[:, :3], axis=1)).max())},
            "box8_zero_steps": float((box8 == 0).mean())}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--out")
    args = ap.parse_args()
    rows = [stats(s) for s in args.scenes]
    for r in rows:
        print(json.dumps(r))
    if args.out:
        json.dump(rows, open(args.out, "w"), indent=1)


if __name__ == "__main__":
    main()
