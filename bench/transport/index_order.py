"""SH codebook index planes under relabelled codebooks: bytes of the tile index plane (fields-zstd / shuffle-zstd)
when the entries are renumbered by first use in splat order, or by falling frequency. A relabelling changes the
indices and the codebook's entry order, never the decoded scene (equal as a set of splats).

    python bench/transport/index_order.py SEC_DIR scene:preset ...
"""
from __future__ import annotations

import json
import sys

import numpy as np

from splatstream.transport import encode_section, encode_shuffle_zstd, slot_to_texel


def relabel(index: np.ndarray, how: str) -> np.ndarray:
    if how == "stored":
        return index
    if how == "first-use":
        _, first = np.unique(index, return_index=True)
        order = np.argsort(first, kind="stable")  # entries ordered by where they first appear
    else:  # frequency
        counts = np.bincount(index)
        order = np.argsort(-counts, kind="stable")
        order = order[counts[order] > 0]
    used = np.unique(index)
    new = np.zeros(int(index.max()) + 1, np.int64)
    new[used[order] if how == "first-use" else order] = np.arange(len(order))
    return new[index]


def main() -> None:
    sec = sys.argv[1]
    for spec in sys.argv[2:]:
        scene, preset = spec.split(":")
        meta = json.load(open(f"{sec}/{scene}/{preset}.sections.json"))
        arrays = np.load(f"{sec}/{scene}/{preset}.sections.npz")
        s = next(m for m in meta["sections"] if m["name"] == "sh_index")
        w, h = s["width"], s["height"]
        texels = arrays[s["key"]].view("<u2")
        order = slot_to_texel(w, h)
        slots = texels[order].astype(np.int64)
        for how in ("stored", "first-use", "frequency"):
            relabelled = relabel(slots, how)
            out = np.empty(w * h, "<u2")
            out[order] = relabelled
            coded, d = encode_section(out.view(np.uint8), "index16", w, h, 1)
            shuffled = encode_shuffle_zstd(out.view(np.uint8), 2)
            counts = np.bincount(relabelled)
            counts = counts[counts > 0]
            h0 = float((counts * np.log2(counts.sum() / counts)).sum() / 8)
            print(f"{scene} {preset} {how:10s}: shuffle-zstd {len(shuffled) / meta['splats']:.3f}, "
                  f"transport {len(coded) / meta['splats']:.3f} ({d['coding']}), order-0 entropy "
                  f"{h0 / meta['splats']:.3f} B/splat")


if __name__ == "__main__":
    main()
