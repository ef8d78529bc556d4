#!/usr/bin/env python3
"""Full detail of an encoded scene against its source: every leaf drawn (`splatstream view --headless` as
bench/lod_vs_peers.py streams it, with --max-sse 0.001 px so that no merged tile stays drawn and no budget binding)
from a lod_vs_peers JSON's cameras, against that run's cached full-detail renders of the source; PSNR / SSIM as
lod_vs_peers measures them. The default threshold (1.5 px) leaves a few far tiles merged even in a near view.

    PYTHONPATH=. .venv/bin/python bench/lod_vs_peers_full_detail.py SCENE_DIR bench/results/DIR/SCENE.json \
        CACHE/SCENE/ref_KEY.npy WORKDIR
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import lod_vs_peers as lvp  # noqa: E402


def main(argv: list[str]) -> int:
    from cli.commands import view as view_cmd
    from splatstream.camera import Camera

    scene_out, bench_json, ref_path, workdir = argv
    parse_options = view_cmd._options
    view_cmd._options = lambda args: dataclasses.replace(parse_options(args), max_sse=0.001)  # every leaf
    res = json.load(open(bench_json))
    cams = [Camera.from_dict(c) for c in res["cameras"]]
    refs = list(np.load(ref_path))
    os.makedirs(workdir, exist_ok=True)
    cams_path = os.path.join(workdir, "cameras.json")
    json.dump([c.to_dict() for c in cams], open(cams_path, "w"))
    lvp.view_worker(scene_out, 10 * res["splats"], cams_path, workdir, res["size"][0])
    imgs = [np.load(os.path.join(workdir, f"view{i}.npy")) for i in range(len(cams))]
    recs = [json.load(open(os.path.join(workdir, f"view{i}.json"))) for i in range(len(cams))]
    print(json.dumps({"scene": scene_out, "max_sse": 0.001, "drawn_splats": [r["drawn_splats"] for r in recs],
                      "bytes_downloaded": [r["bytes_downloaded"] for r in recs], **lvp.measure(imgs, refs)}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
