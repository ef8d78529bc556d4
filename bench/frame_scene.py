"""What the viewer's F key frames, before (the root tile's bounding sphere, stray splats included) and after (the
framing box of the root tile's splats, camera.framing_box: the suggested camera's rule), on encoded scenes.

For each scene directory: the box of the root tile against the box of the full detail (how far the coarse root
stands in for the scene), the distance F puts the eye at before and after from the suggested camera's direction, and
headless renders of both views (`--shots DIR`, small PNGs).

    PYTHONPATH=. python bench/frame_scene.py SCENE_DIR... [--shots bench/results/frame31]
"""
from __future__ import annotations

import argparse
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from splatstream.camera import framing_box, framing_view
from splatstream.scene_decode import decode_scene
from splatstream.store import open_store, read_manifest

FOV_ASPECT = 4.0 / 3.0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--shots", default=None)
    ap.add_argument("--size", default="320x240")
    a = ap.parse_args()
    print("| scene | splats | root splats | root box / full box (diagonal) | centre offset / full diagonal "
          "| F distance before | after | after / before |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for scene in a.scenes:
        store = open_store(scene)
        m = read_manifest(store)
        root = m.tile(m.root)
        rg = decode_scene(store, 0, [root.id], m)
        full = decode_scene(store, 0, "leaves", m)
        rlo, rhi = framing_box(rg.positions, rg.opacity_logits)
        flo, fhi = framing_box(full.positions, full.opacity_logits)
        fd = float(np.linalg.norm(fhi - flo))
        ratio = float(np.linalg.norm(rhi - rlo)) / fd
        offset = float(np.linalg.norm((rhi + rlo) / 2 - (fhi + flo) / 2)) / fd
        cam = m.camera
        direction = np.subtract(cam.eye, cam.target)
        direction = direction / np.linalg.norm(direction)
        half = math.radians(cam.fov_y) / 2.0
        half = min(half, math.atan(math.tan(half) * FOV_ASPECT))
        before_t, before_d = np.array(root.sphere_center), float(root.sphere_radius) / math.sin(half)
        after_t, after_d = framing_view(rlo, rhi, direction, cam.up, cam.fov_y, FOV_ASPECT)
        name = Path(scene).name
        print(f"| {name} | {len(full):,} | {root.splats:,} | {ratio:.3f} | {offset:.3f} | {before_d:.3g} | "
              f"{after_d:.3g} | {after_d / before_d:.3f} |", flush=True)
        if a.shots:
            for tag, t, d in (("before", before_t, before_d), ("after", after_t, after_d)):
                eye = t + direction * d
                out = Path(a.shots) / f"{name}_{tag}.png"
                subprocess.run([sys.executable, "-m", "cli.main", "view", scene, "--headless", "--size", a.size,
                                "--eye=" + ",".join(map(str, eye)), "--target=" + ",".join(map(str, t)),
                                "--up=" + ",".join(map(str, cam.up)), "--fov-y", str(cam.fov_y),
                                "--screenshot", str(out), "-q"], check=True)


if __name__ == "__main__":
    main()
