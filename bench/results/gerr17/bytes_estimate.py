"""gerr17 (issue 31): the compact table's bytes with `geometric_error` as the probe's u8 codes
(bench/probe_error_steps.py: `lin255`, box16's coding but quantised against the parent's decoded error; `log16`),
packed the way box16's error8_estimate.py packs it (`error8` for the rows whose parent is in the table,
`anchor_error` f32 for the others, zstd at the table's level). Estimate, not built.

    PYTHONPATH=. python bench/results/gerr17/bytes_estimate.py /tmp/psnr16_ours/SCENE ... > bytes_estimate.json
"""
import json
import os
import sys

import msgpack
import numpy as np
import zstandard

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
from probe_error_steps import stepped_errors  # noqa: E402

from splatstream.format.manifest.table import COMPACT_TABLE_ZSTD_LEVEL, table_parents  # noqa: E402


def z(d: dict) -> int:
    raw = msgpack.packb(d, use_bin_type=True)
    return len(zstandard.ZstdCompressor(level=COMPACT_TABLE_ZSTD_LEVEL, write_content_size=True).compress(raw))


def main() -> None:
    out = {}
    for scene in sys.argv[1:]:
        raw = open(os.path.join(scene, "manifest.msgpack"), "rb").read()
        d = msgpack.unpackb(raw, strict_map_key=False)
        t = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(d["tile_table_zstd"]), strict_map_key=False)
        ids = np.frombuffer(t["id"], "<u4").astype(np.int64)
        parent = table_parents(ids, np.frombuffer(t["children"], "<u4"), np.frombuffer(t["child_ids"], "<u4"))
        e = np.frombuffer(t["geometric_error"], "<f4").astype(np.float64)
        child = parent >= 0
        parent_of = {int(ids[i]): int(ids[parent[i]]) for i in range(len(ids)) if parent[i] >= 0}
        err = {int(ids[i]): float(e[i]) for i in range(len(ids))}
        row = {"manifest": len(raw), "table": z(t), "stored_table": len(d["tile_table_zstd"])}
        for v in ("lin255", "log16"):
            codes: dict = {}
            stepped_errors([int(i) for i in ids], parent_of, err, v, codes)
            t2 = {k: val for k, val in t.items() if k != "geometric_error"}
            t2["anchor_error"] = np.asarray(e[~child], "<f4").tobytes()
            t2["error8"] = np.array([codes[int(i)] for i in ids[child]], np.uint8).tobytes()
            row[v] = z(t2)
            row[v + "_less"] = row["table"] - row[v]
        out[os.path.basename(scene.rstrip("/"))] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
