"""Estimate, not built (issue 31, box16): a 1.16 table with `geometric_error` as u8 steps of the parent's error
rounded up (`error8`, the rows whose parent is in the table; `anchor_error` f32 for the others), packed at zstd 19:
its bytes against the 1.16 table's. Bytes only: no cut was run with it.

    python bench/results/box16/error8_estimate.py ENC_AFTER/SCENE ... > error8_estimate.txt
"""
import os
import sys

import msgpack
import numpy as np
import zstandard

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
from splatstream.format.manifest.table import COMPACT_TABLE_ZSTD_LEVEL, table_parents  # noqa: E402


def z(d: dict) -> int:
    raw = msgpack.packb(d, use_bin_type=True)
    return len(zstandard.ZstdCompressor(level=COMPACT_TABLE_ZSTD_LEVEL, write_content_size=True).compress(raw))


def main() -> None:
    for scene in sys.argv[1:]:
        d = msgpack.unpackb(open(os.path.join(scene, "manifest.msgpack"), "rb").read(), strict_map_key=False)
        t = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)
        ids = np.frombuffer(t["id"], "<u4")
        parent = table_parents(ids, np.frombuffer(t["children"], "<u4"), np.frombuffer(t["child_ids"], "<u4"))
        e = np.frombuffer(t["geometric_error"], "<f4").astype(np.float64)
        child = parent >= 0
        pe = e[np.maximum(parent, 0)]
        with np.errstate(divide="ignore", invalid="ignore"):
            q = np.clip(np.where(pe > 0, np.ceil(e / pe * 255), 0), 0, 255).astype(np.uint8)
        above = int((e > pe)[child].sum())  # a child's error above its parent's (lod.md 3 says none)
        t2 = {k: v for k, v in t.items() if k != "geometric_error"}
        t2["anchor_error"] = np.asarray(e[~child], "<f4").tobytes()
        t2["error8"] = q[child].tobytes()
        print(f"{os.path.basename(scene.rstrip('/'))}: table {z(t):,} B -> {z(t2):,} B with error8 ({z(t) - z(t2):,} B "
              f"less); children above their parent's error {above}; leaves (error 0) {int((e == 0).sum())} of {len(e)}")


if __name__ == "__main__":
    main()
