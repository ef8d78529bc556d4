"""What per-scene 1-D palettes for scales and colour (as SOG's codebooks) would give on SOG-sourced inputs (issue 32).

    python bench/sog_palette_probe.py INPUT ENCODED_DIR [ENCODED_DIR ...] [--level 16]

Each ENCODED_DIR is a one-tile scene (no LOD) encoded from INPUT with a preset whose `scale` and `color` are f32x4
(lossless: `bench/eval_probe.py ... --encoded DIR -- LABEL:PRESET,scale=f32x4,color=f32x4`), so its planes hold
the input's values in the encoder's slot order (to float rounding: f32x4 holds t in the chunk's range; each decoded
value is snapped to the nearest of INPUT's distinct values, and the largest snap is printed). A palette coding keeps
those values exactly when the input holds at most 256 distinct values per palette (a SOG file's log scales share
one 256-entry codebook over the three axes, its colours one over R, G and B; its opacities are 8-bit): the PSNR of
the f32x4 encode is then the palette coding's. Its bytes are estimated here: every value replaced by its index in
the scene's sorted distinct values (scale: one palette over the three axes; colour: one over R, G, B, and one for
opacity), laid out as a norm8x4 texel plane in the same texels, coded as the encoder codes a plane
(`transport.filter_texels`, fields1 or byte shuffle, whichever is smaller) and compressed alone with zstd at the
preset's level; plus the palettes (256 float32 each). An encode whose scale and colour are norm8x4 gives the same
estimator on its planes as stored, and its rotations (f32x4 rotations: as SOG's 8-bit smallest-three texels). Use
the figures differentially (BENCHMARKS.md, "Guitar's near misses ..."): the norm8x4 encode's measured bytes, minus
the estimator on its planes, plus the estimator on the palettes. (A manifest's per-attribute disk bytes are shares
of the payload's one zstd frame by section size, so they do not calibrate a per-plane estimate.)
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import zstandard

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from splatstream.format.decode import decode_payload, decode_planes  # noqa: E402
from splatstream.format.transport import filter_texels, slot_to_texel  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.readers.sog import QUAT_ORDER  # noqa: E402
from splatstream.store import open_store, read_manifest  # noqa: E402


def coded_bytes(layer: np.ndarray, width: int, height: int, level: int) -> int:
    """Stored bytes of one norm8x4 texel layer (H*W*4 uint8) coded and compressed as the encoder does."""
    _, parts = filter_texels([layer], "norm8x4", width, height, 1, level)
    blob = b"".join(bytes(memoryview(p)) for p in parts)
    return len(zstandard.ZstdCompressor(level=level).compress(blob))


def snap(values: np.ndarray, candidates: list[np.ndarray]) -> tuple[np.ndarray, int, float]:
    """Index of every decoded value in the palette (the sorted distinct input values) it lies nearest to, the
    palette's size and the largest snapping error relative to the palette's extent. `candidates`: the input's
    values in the representations the plane may hold (log scales; SH0 or base colour; opacity or its logit): the
    one the decoded values lie on is used."""
    best = None
    for cand in candidates:
        palette = np.unique(cand)
        i = np.clip(np.searchsorted(palette, values), 1, len(palette) - 1)
        lo, hi = palette[i - 1], palette[i]
        idx = np.where(np.abs(values - lo) <= np.abs(values - hi), i - 1, i)
        err = float(np.abs(values - palette[idx]).max() / max(float(np.ptp(palette)), 1e-30))
        if best is None or err < best[2]:
            best = (idx, len(palette), err)
    return best


def smallest_three(q: np.ndarray) -> tuple[np.ndarray, float]:
    """SOG's rotation texel of each (w, x, y, z) quaternion (readers/sog.py: the three smaller components times
    sqrt(2) on 255 steps, alpha 252 + the index of the largest), and the largest error of a component it decodes
    to, in steps of that grid (at most 0.5 when q lies on it up to float rounding; 0 error means SOG's own grid)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.abs(q).argmax(axis=1)
    q = q * np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    codes = np.zeros((len(q), 4), np.uint8)
    err = 0.0
    for i, others in enumerate(QUAT_ORDER):
        rows = largest == i
        t = (q[np.ix_(rows, others)] * np.sqrt(2) + 1) / 2 * 255
        b = np.clip(np.rint(t), 0, 255)
        codes[rows, :3] = b
        codes[rows, 3] = 252 + i
        if rows.any():
            err = max(err, float(np.abs(t - b).max()))
    return codes, err


def probe(scene: str, source: str, level: int) -> dict:
    g = read_gaussians(source)
    store = open_store(scene)
    m = read_manifest(store)
    (tile,) = m.leaves
    entry = tile.groups["base"]
    planes = decode_payload(store.read_payload(entry), entry, "base", scene)
    n = tile.splats
    values = decode_planes(planes, n)
    out = {"scene": scene, "splats": n}
    rot = planes["rotation"]
    if rot.format == "f32x4":  # lossless rotations: SOG's 8-bit smallest-three texels in the same slots
        codes = np.zeros((rot.width * rot.height, 4), np.uint8)
        c, err = smallest_three(values["rotation"][:, 0].astype(np.float64))
        codes[slot_to_texel(rot.width, rot.height)[:n]] = c
        out["rotation_s3_bytes"] = coded_bytes(codes.ravel(), rot.width, rot.height, level)
        out["rotation_s3_off_grid"] = err
    elif rot.format == "norm8x4":
        out["rotation_as_stored_bytes"] = coded_bytes(np.frombuffer(bytes(rot.layers[0]), np.uint8), rot.width,
                                                      rot.height, level)
    for name in ("scale", "color"):
        p = planes[name]
        if p.format == "norm8x4":  # calibration: the estimator on the plane as the encoder stored it
            out[f"{name}_as_stored_bytes"] = coded_bytes(np.frombuffer(bytes(p.layers[0]), np.uint8), p.width,
                                                         p.height, level)
            continue
        v = values[name][:, 0]
        codes = np.zeros((p.width * p.height, 4), np.uint8)
        texel = slot_to_texel(p.width, p.height)[:n]  # slot s (the splat order) lies at this texel (format.md 4.1)
        if name == "scale":
            idx, k, err = snap(v[:, :3], [g.log_scales, g.scales])
            codes[texel, :3] = idx
            out.update(scale_distinct=k, scale_snap=err)
            palettes = 1
        else:
            idx, k, err = snap(v[:, :3], [g.sh_dc, g.base_colors])
            codes[texel, :3] = idx
            oidx, ko, oerr = snap(v[:, 3], [g.opacities, g.opacity_logits])
            codes[texel, 3] = oidx
            out.update(color_distinct=k, opacity_distinct=ko, color_snap=max(err, oerr))
            palettes = 2
        if max(k, out.get("opacity_distinct", 0)) > 256:
            out[f"{name}_palette_bytes"] = None  # more than 256 values: not exact in an 8-bit palette
            continue
        out[f"{name}_palette_bytes"] = coded_bytes(codes.ravel(), p.width, p.height, level) + 256 * 4 * palettes
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("source", help="the input the scenes were encoded from (its values make the palettes)")
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--level", type=int, default=16)
    args = ap.parse_args()
    for s in args.scenes:
        r = probe(s, args.source, args.level)
        n = r["splats"]
        if "rotation_s3_bytes" in r:
            print(f"{s}: rotations as SOG's 8-bit smallest three: {r['rotation_s3_bytes'] / n:.3f} B/splat "
                  f"(estimate; largest distance to that grid {r['rotation_s3_off_grid']:.3f} steps)")
        if "rotation_as_stored_bytes" in r:
            print(f"{s}: norm8x4 rotations as stored, estimated: {r['rotation_as_stored_bytes'] / n:.3f} B/splat")
        if "scale_as_stored_bytes" in r:
            print(f"{s}: {n} splats; norm8x4 planes as stored, estimated: scale {r['scale_as_stored_bytes'] / n:.3f} "
                  f"B/splat, colour {r['color_as_stored_bytes'] / n:.3f} B/splat")
            continue
        if r["scale_palette_bytes"] is None or r["color_palette_bytes"] is None:
            print(f"{s}: more than 256 values (scale {r['scale_distinct']}, colour {r['color_distinct']}, opacity "
                  f"{r['opacity_distinct']}): no exact 8-bit palette")
            continue
        print(f"{s}: {n} splats; distinct scale {r['scale_distinct']}, colour {r['color_distinct']}, opacity "
              f"{r['opacity_distinct']} (largest snap {max(r['scale_snap'], r['color_snap']):.1e} of the extent); "
              f"palette planes scale {r['scale_palette_bytes'] / n:.3f} B/splat, colour "
              f"{r['color_palette_bytes'] / n:.3f} B/splat")


if __name__ == "__main__":
    main()
