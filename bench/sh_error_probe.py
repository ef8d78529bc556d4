"""SH bytes and weighted SH error per band of SH codings on a scene (issue 32, "A 64k SH codebook on flowers").

    python bench/sh_error_probe.py SCENE OUT_DIR CONFIG ...      (CONFIG as bench/sh_coding_probe.py's)
    python bench/sh_error_probe.py SCENE --decoded PEER.ply       (a peer's decode, matched to the input by position)

Each config is encoded without LOD with lossless positions (`position=f32x4` appended: decoded splats then match
input splats exactly; the SH planes do not depend on the position format), decoded, and compared with the input:
SH B/splat and the RMS error per band, plain and weighted like the codebook fit (opacity x footprint). Results
are cached as OUT_DIR/LABEL.json.
"""
import json
import os
import shutil
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from sh_coding_probe import parse_config, register  # noqa: E402

from splatstream.encode import EncodeOptions, encode_gaussians  # noqa: E402
from splatstream.encode.codebook import codebook_weights  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.orientation import detect_up  # noqa: E402
from splatstream.scene_decode import decode_scene  # noqa: E402


def peer_error(g, peer_path: str, grid: float = 2e-4) -> dict:
    """SH error of a peer's decoded splats, matched to input splats by position on a grid (unique cells only)."""
    s = read_gaussians(peer_path)

    def key(p):
        k = np.round(p / grid).astype(np.int64)
        return (k[:, 0] * 1000003 + k[:, 1]) * 1000033 + k[:, 2]

    kg, ks = key(g.positions), key(s.positions)
    ug, cg = np.unique(kg, return_counts=True)
    o = np.argsort(kg)
    pos = np.minimum(np.searchsorted(kg[o], ks), len(kg) - 1)
    hit = (kg[o][pos] == ks) & np.isin(ks, ug[cg == 1])
    gi, si = o[pos[hit]], np.flatnonzero(hit)
    w = codebook_weights(g)[gi]
    w = w / w.sum()
    e = s.sh_rest[si] - g.sh_rest[gi]
    out = {"peer": peer_path, "matched": int(hit.sum())}
    for b in range(1, g.sh_degree + 1):
        sl = B[b]
        out[f"band{b}_wrms"] = float(np.sqrt((w[:, None, None] * e[:, sl] ** 2).sum() / e[0, sl].size))
        out[f"band{b}_rms"] = float(np.sqrt((e[:, sl] ** 2).mean()))
    return out


B = {1: slice(0, 3), 2: slice(3, 8), 3: slice(8, 15)}
scene = sys.argv[1]
if sys.argv[2] == "--decoded":
    print(json.dumps(peer_error(read_gaussians(scene), sys.argv[3]), indent=1))
    sys.exit(0)
out = sys.argv[2]
os.makedirs(out, exist_ok=True)
g = read_gaussians(scene)
up = detect_up(g).up
w = codebook_weights(g)
w = w / w.sum()


def rowkey(p):
    return np.ascontiguousarray(p, np.float32).view(np.dtype((np.void, 12))).reshape(-1)


kg = rowkey(g.positions)
og = np.argsort(kg)
skg = kg[og]
for spec in sys.argv[3:]:
    label, preset, extra = parse_config(spec + ",position=f32x4")
    res_path = os.path.join(out, f"{label}.json")
    if os.path.exists(res_path):
        print(open(res_path).read())
        continue
    name = register(label, preset, extra)
    d = os.path.join(out, "enc_" + label)
    t = time.perf_counter()
    m = encode_gaussians(g, d, EncodeOptions(preset=name, lod=False, up=tuple(up)), source_name=scene)
    enc = time.perf_counter() - t
    dg = decode_scene(d)
    kd = rowkey(dg.positions)
    pos = np.minimum(np.searchsorted(skg, kd), len(skg) - 1)
    hit = skg[pos] == kd
    gi, di = og[pos[hit]], np.flatnonzero(hit)
    e = dg.sh_rest[di] - g.sh_rest[gi]
    ww = w[gi] / w[gi].sum()
    r = {"spec": spec, "matched": int(hit.sum()), "encode_s": round(enc, 1),
         "attr_bytes": {a: round(s.disk_bytes / len(g), 3) for a, s in m.attributes.items()},
         "total_minus_pos": round((m.bytes_on_disk - m.attributes["position"].disk_bytes) / len(g), 3),
         "entries": m.sh_codebook.entries if m.sh_codebook else None}
    for b in range(1, g.sh_degree + 1):
        sl = B[b]
        r[f"band{b}_wrms"] = float(np.sqrt((ww[:, None, None] * e[:, sl] ** 2).sum() / e[0, sl].size))
        r[f"band{b}_rms"] = float(np.sqrt((e[:, sl] ** 2).mean()))
    r["all_wrms"] = float(np.sqrt((ww[:, None, None] * e ** 2).sum() / e[0].size))
    json.dump(r, open(res_path, "w"), indent=1)
    print(json.dumps(r), flush=True)
    shutil.rmtree(d, ignore_errors=True)
