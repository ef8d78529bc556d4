"""How many splats are near-isotropic or spheroidal, and what the rotation plane costs with and without canonical
rotations (issue 32, rot32; splatstream/rotation_canon.py).

    PYTHONPATH=. python bench/rot_canon_stats.py NAME=PATH [NAME=PATH ...] --json OUT.json [--markdown OUT.md]

Per scene: the share of splats whose three natural-log scales span at most t (isotropic) and whose closest two
differ by at most t (spheroids, the isotropic ones not counted), for each tolerance t; then, per preset rotation
format, each base plane (position, rotation, scale, colour) coded alone as the encoder codes it (the scene in 3D
Morton order, cut into tiles of 16,384 splats, each tile's plane one payload at the preset's zstd level, transport
and tile steps), so the rotation's share of the base planes' bytes; the rotation plane's bytes with the twist that
does not show taken out at each tolerance (canonical_rotations below: identity for isotropic splats, zero twist about
a spheroid's axis); and the rotation and scale planes' bytes in each canonical gauge (splatstream/rotation_canon.py:
of the 24 equivalent (rotation, scales) pairs, or of the 4 half turns, the rotation closest to the identity). A
proxy for the encoder's tiles (leaves of at most 16,384 splats in its own tree), not the encoder's files: `splatstream
eval` measures those.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.format import presets as P  # noqa: E402
from splatstream.format.codec import encode_plane, plane_values  # noqa: E402
from splatstream.format.container import pack_payload  # noqa: E402
from splatstream.format.layout import morton_order  # noqa: E402
from splatstream.format.planes import BASE_PLANES  # noqa: E402
from splatstream.format.steps import splat_sizes  # noqa: E402
from splatstream.gaussians import normalize_quaternions, rotation_matrices  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.rotation_canon import GAUGES, canonical_gauge  # noqa: E402

TOLERANCES = (0.005, 0.01, 0.02, 0.05, 0.1)
GENERAL, SPHEROID, ISOTROPIC = 0, 1, 2


def splat_shape_classes(log_scales: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(class (N,) of GENERAL / SPHEROID / ISOTROPIC, distinct axis (N,), -1 where not a spheroid) for (N, 3)
    natural-log scales: isotropic where the three span at most `tolerance`, else a spheroid where the closest two
    differ by at most `tolerance` (its distinct axis the third)."""
    ls = np.asarray(log_scales, np.float64)
    n = len(ls)
    spread = ls.max(axis=1) - ls.min(axis=1)
    pair_gap = np.stack([np.abs(ls[:, 1] - ls[:, 2]), np.abs(ls[:, 0] - ls[:, 2]), np.abs(ls[:, 0] - ls[:, 1])],
                        axis=1)
    distinct = np.argmin(pair_gap, axis=1)
    shape = np.full(n, GENERAL, np.int8)
    shape[pair_gap[np.arange(n), distinct] <= tolerance] = SPHEROID
    shape[spread <= tolerance] = ISOTROPIC
    return shape, np.where(shape == SPHEROID, distinct, -1)


def canonical_rotations(rotations: np.ndarray, log_scales: np.ndarray, tolerance: float) -> np.ndarray:
    """The rotations with the twist that does not show taken out: the identity for isotropic splats; for a
    spheroid, the shortest arc from e_c onto its symmetry axis a (R's column c, the sign with a_c >= 0), the
    quaternion (1 + a_c, e_c x a) normalised (its e_c component 0, w its largest). The covariance changes by at most
    s_max^2 (1 - exp(-2 t)) (s_max the largest of the scales taken as equal, t their span)."""
    q = normalize_quaternions(np.asarray(rotations))
    shape, axis = splat_shape_classes(log_scales, tolerance)
    q[shape == ISOTROPIC] = (1.0, 0.0, 0.0, 0.0)
    rows = np.flatnonzero(shape == SPHEROID)
    if len(rows):
        c, k = axis[rows], np.arange(len(rows))
        a = rotation_matrices(q[rows])[k, :, c]
        a *= np.where(a[k, c] < 0, -1.0, 1.0)[:, None]
        e = np.zeros_like(a)
        e[k, c] = 1.0
        arc = np.concatenate([1.0 + a[k, c][:, None], np.cross(e, a)], axis=1)
        arc[k, 1 + c] = 0.0
        q[rows] = normalize_quaternions(arc)
    return q
PRESETS = ("medium", "medium-low", "low")  # rotation formats norm10_2, norm8x4, norm565
TILE = 16384


def plane_bytes(g, spec, preset: str, order: np.ndarray, rotations: np.ndarray | None = None,
                scales: np.ndarray | None = None) -> int:
    fmt = P.PRESETS[preset][spec.attribute]
    step = P.PRESET_STEPS.get(preset, {}).get(spec.name, P.PRESET_STEPS.get(preset, {}).get(spec.attribute))
    level = P.PRESET_ZSTD_LEVEL.get(preset, 1)
    transport = P.PRESET_TRANSPORT.get(preset, "fields")
    values = plane_values(g, spec)
    if rotations is not None:
        values = rotations[:, None, :]
    if scales is not None:
        values = scales[:, None, :]
    total = 0
    for start in range(0, len(order), TILE):
        o = order[start:start + TILE]
        sizes = splat_sizes(g.log_scales[o], step.size_axis) if step is not None and step.per_size else None
        plane = encode_plane(values[o], spec, fmt, None, step=step, sizes=sizes)
        total += len(pack_payload([plane], level, "fields" if transport == "keyed" else transport)[0])
    return total


def scene_stats(name: str, path: str) -> dict:
    g = read_gaussians(path)
    n = len(g)
    out = {"scene": name, "splats": n, "classes": {}, "presets": {}}
    for t in TOLERANCES:
        shape, _ = splat_shape_classes(g.log_scales, t)
        out["classes"][str(t)] = {"isotropic": float((shape == ISOTROPIC).mean()),
                                  "spheroid": float((shape == SPHEROID).mean())}
    order = morton_order(g.positions)
    for preset in PRESETS:
        row = {p.name: plane_bytes(g, p, preset, order) / n for p in BASE_PLANES}
        for gauge in GAUGES:
            q, ls = canonical_gauge(g.rotations, g.log_scales, gauge)
            row[gauge] = {"rotation": plane_bytes(g, BASE_PLANES[1], preset, order, q) / n,
                          "scale": plane_bytes(g, BASE_PLANES[2], preset, order, scales=ls) / n}
        row["rotation_canon"] = {str(t): plane_bytes(g, BASE_PLANES[1], preset, order,
                                                     canonical_rotations(g.rotations, g.log_scales, t)) / n
                                 for t in TOLERANCES}
        out["presets"][preset] = row
        print(name, preset, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return out


def markdown(rows: list[dict]) -> str:
    lines = ["| scene | splats | " + " | ".join(f"iso / sph at {t}" for t in TOLERANCES) + " |",
             "|---|---:|" + "---|" * len(TOLERANCES)]
    for r in rows:
        cells = [f"{100 * r['classes'][str(t)]['isotropic']:.1f} / {100 * r['classes'][str(t)]['spheroid']:.1f} %"
                 for t in TOLERANCES]
        lines.append(f"| {r['scene']} | {r['splats']:,} | " + " | ".join(cells) + " |")
    lines += ["", "| scene | preset | base B/splat (pos / rot / scale / colour) | rotation share | rotation B/splat "
              "canonical at " + " / ".join(str(t) for t in TOLERANCES) + " | "
              + " | ".join(f"{gauge} gauge: rotation / scale B/splat (their change)" for gauge in GAUGES) + " |",
              "|---|---|---|---:|---|" + "---|" * len(GAUGES)]
    for r in rows:
        for preset, p in r["presets"].items():
            base = [p["position"], p["rotation"], p["scale"], p["color"]]
            canon = " / ".join(f"{p['rotation_canon'][str(t)]:.3f}" for t in TOLERANCES)
            lines.append(f"| {r['scene']} | {preset} | {' / '.join(f'{b:.3f}' for b in base)} | "
                         f"{100 * p['rotation'] / sum(base):.1f} % | {p['rotation']:.3f} -> {canon} | "
                         + " | ".join(f"{p[gauge]['rotation']:.3f} / {p[gauge]['scale']:.3f} "
                                      f"({p[gauge]['rotation'] + p[gauge]['scale'] - p['rotation'] - p['scale']:+.3f})"
                                      for gauge in GAUGES) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="NAME=PATH")
    ap.add_argument("--json", required=True)
    ap.add_argument("--markdown")
    args = ap.parse_args()
    rows = [scene_stats(*s.split("=", 1)) for s in args.scenes]
    with open(args.json, "w") as f:
        json.dump(rows, f, indent=1)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
