"""Before and after pictures of cleaning a real capture (README, BENCHMARKS.md): the scene as read, what the edits
keep, and what they drop, each rendered by `splatstream render` from the original scene's suggested camera, side
by side.

    python bench/clean_capture.py tests/data/real/statues/st-peter.sog --out docs/images/clean_st_peter.png \\
        -- --filter-box -1,-1.5,-1,1,2.5,1 --filter-density 0.07,2
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np
from PIL import Image, ImageDraw

from cli.commands.args import add_edit_arguments, edits_from
from cli.commands.edit_flags import attach_negative_values
from splatstream.camera import suggested_camera
from splatstream.edit import Pipeline
from splatstream.io import read_gaussians, scene_up
from splatstream.ply import write_gaussians_ply


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", default="480x480")
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    args = ap.parse_args(argv[:split])
    edit_args = argv[split + 1:]  # after --: the edit options, as convert takes them (the CLI's own parser)
    parser = argparse.ArgumentParser()
    add_edit_arguments(parser)
    edits: Pipeline = edits_from(parser.parse_args(attach_negative_values(edit_args)))
    g = read_gaussians(args.input)
    kept_g, counts = edits.run(g)
    # which splats were dropped: every step keeps rows in order, so mark them by an index carried in a copy
    marked = g.subset(np.arange(len(g)))
    marked.opacity_logits[:] = np.arange(len(g), dtype=np.float32)  # exact below 2^24 splats
    keep = np.zeros(len(g), bool)
    keep[edits.apply(marked).opacity_logits.astype(np.int64)] = True
    w, h = (int(v) for v in args.size.split("x"))
    up = scene_up(args.input, g).up
    cam = suggested_camera(g.positions, up=up, width=w, height=h, opacity_logits=g.opacity_logits)
    fmt = ",".join
    view = ["--eye", fmt(f"{v:.6g}" for v in cam.eye), "--target", fmt(f"{v:.6g}" for v in cam.target), "--up",
            fmt(f"{v:.6g}" for v in up), "--size", args.size, "-q"]
    panels = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, part in ((f"as read: {len(g)} splats", g), (f"kept: {len(kept_g)}", g.subset(keep)),
                            (f"dropped: {int((~keep).sum())}", g.subset(~keep))):
            ply, png = os.path.join(tmp, "part.ply"), os.path.join(tmp, f"{len(panels)}.png")
            write_gaussians_ply(part, ply)
            r = subprocess.run([sys.executable, "-m", "cli", "render", ply, "--out", png, *view], capture_output=True,
                               text=True)
            if r.returncode:
                print(r.stderr, file=sys.stderr)
                return 1
            img = Image.open(png).convert("RGB")
            ImageDraw.Draw(img).text((8, 8), label, fill=(255, 255, 255))
            panels.append(img)
    sheet = Image.new("RGB", (w * len(panels), h))
    for i, img in enumerate(panels):
        sheet.paste(img, (i * w, 0))
    tmp_out = args.out + ".tmp.png"
    sheet.save(tmp_out)
    os.replace(tmp_out, args.out)
    for label, n in counts:
        print(f"{label}: keeps {n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
