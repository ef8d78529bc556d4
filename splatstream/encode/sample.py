"""Scene-wide statistics from deterministic samples of the input, so an encode that never holds the whole scene
(a partitioned one, encode/partitioned.py) decides exactly what the single-process encoder decides.

Samples are rows chosen by their index in the input (after dropped invalid rows), the same rule everywhere:

* the orientation sample: orientation.SAMPLE rows evenly spaced (np.linspace), for the up direction (flat splats'
  normals) and the side the default camera looks from;
* the position sample: every ceil(N / POSITION_SAMPLE)-th centre (all of them up to 2M splats), for the
  robust bounds of the suggested camera and the extent test of the up detection;
* the codebook sample: CODEBOOK_SAMPLE rows evenly spaced (all of them up to that many), the rows the SH
  codebook is fitted on (format_spec/format.md 4.7);
* the palette values (only for a scene with pal8x4 planes): not a sample but every row, reduced part by part to
  what the scene's palettes are fitted from (codec.PaletteValues: the distinct values up to 256, else the least and
  largest; format.md 4.3.2), so a partitioned encode fits the palettes the single-process one does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import suggested_camera, turn_about_up
from ..format.codec import PaletteValues, palette_values, plane_values
from ..format.manifest import CameraEntry
from ..format.planes import BASE_PLANES
from ..gaussians import Gaussians
from ..orientation import SAMPLE as ORIENT_SAMPLE
from ..orientation import UpChoice, detect_up, view_side
from ..vq import Codebook, build_codebook, parse_entries, probes_for
from .codebook import codebook_rows, codebook_weights, order_by_use

POSITION_SAMPLE = 2_000_000
# 2M rows of 45 SH values (360 MB): about 32 rows per entry of the largest codebook (65,536), where the k-means
# of vq.py samples at most 64 per centroid anyway.
CODEBOOK_SAMPLE = 1 << 21


def orient_indices(n: int) -> np.ndarray:
    return np.linspace(0, n - 1, ORIENT_SAMPLE).astype(np.int64) if n > ORIENT_SAMPLE else np.arange(n)


def position_indices(n: int) -> np.ndarray:
    return np.arange(0, n, max(1, math.ceil(n / POSITION_SAMPLE)))


def codebook_indices(n: int) -> np.ndarray:
    return (np.arange(CODEBOOK_SAMPLE, dtype=np.int64) * n) // CODEBOOK_SAMPLE if n > CODEBOOK_SAMPLE else np.arange(n)


@dataclass
class SceneSample:
    """The samples of one scene of `splats` splats (or the part of them a chunk of the input holds)."""

    splats: int
    orient: Gaussians  # SH degree 0
    positions: np.ndarray  # (M, 3) float32
    codebook_rows: np.ndarray | None  # (K, 3 x coefficients) float32, None without SH bands
    codebook_weights: np.ndarray | None
    # Per palette plane (format.md 4.3.2) the PaletteValues of each of its palettes; None without palette planes.
    palettes: dict[str, list[PaletteValues]] | None = None

    @staticmethod
    def part(g: Gaussians, offset: int, splats: int, with_codebook: bool,
             palette_planes: tuple[str, ...] = ()) -> SceneSample:
        """The sample rows among `g`, the rows offset..offset+len(g) of a scene of `splats` splats."""

        def local(idx: np.ndarray) -> np.ndarray:
            a, b = np.searchsorted(idx, [offset, offset + len(g)])
            return idx[a:b] - offset

        o = local(orient_indices(splats))
        orient = Gaussians(g.positions[o], g.rotations[o], g.log_scales[o], g.opacity_logits[o], g.sh_dc[o],
                           np.zeros((len(o), 0, 3), np.float32))
        rows = weights = None
        if with_codebook:
            picked = local(codebook_indices(splats))
            # Every row of this part (a scene below the sample size): its own arrays, not a copy of them.
            sub = g if len(picked) == len(g) else g.subset(picked)
            rows, weights = codebook_rows(sub), codebook_weights(sub)
        palettes = {s.name: palette_values(plane_values(g, s), s) for s in BASE_PLANES if s.name in palette_planes}
        return SceneSample(splats, orient, g.positions[local(position_indices(splats))], rows, weights,
                           palettes or None)

    @staticmethod
    def join(parts: list[SceneSample]) -> SceneSample:
        """The parts of consecutive chunks, in input order."""
        rows = None if parts[0].codebook_rows is None else np.concatenate([p.codebook_rows for p in parts])
        weights = None if parts[0].codebook_weights is None else np.concatenate([p.codebook_weights for p in parts])
        palettes = None
        if parts[0].palettes is not None:
            palettes = {name: [PaletteValues.join([p.palettes[name][i] for p in parts]) for i in range(len(groups))]
                        for name, groups in parts[0].palettes.items()}
        return SceneSample(parts[0].splats, Gaussians.concatenate([p.orient for p in parts]),
                           np.concatenate([p.positions for p in parts]), rows, weights, palettes)

    @staticmethod
    def of(g: Gaussians, with_codebook: bool, palette_planes: tuple[str, ...] = ()) -> SceneSample:
        return SceneSample.part(g, 0, len(g), with_codebook, palette_planes)

    def up(self) -> UpChoice:
        return detect_up(self.orient, self.positions)

    def camera(self, up: tuple[float, float, float], azimuth_deg: float = 0.0) -> CameraEntry:
        """The suggested initial camera (format_spec/camera.md), turned by `azimuth_deg` about up
        (camera.turn_about_up; `encode --camera-azimuth`)."""
        if len(self.orient) >= 16:  # framed by the splats that are not nearly transparent (camera.framing_box)
            cam = suggested_camera(self.orient.positions, up=up, side=view_side(self.orient, up),
                                   opacity_logits=self.orient.opacity_logits, log_scales=self.orient.log_scales)
        else:  # (splats all at one point are framed by their size: the orientation sample's scales)
            cam = suggested_camera(self.positions, up=up, side=view_side(self.orient, up),
                                   log_scales=self.orient.log_scales)
        eye = turn_about_up(cam.eye, cam.target, cam.up, azimuth_deg) if azimuth_deg else cam.eye
        return CameraEntry(tuple(float(v) for v in eye), tuple(float(v) for v in cam.target),
                           tuple(float(v) for v in cam.up), float(cam.fov_y_deg))

    def codebook(self, choice: str | int) -> Codebook | None:
        """The SH codebook fitted on the codebook sample (`choice`: "off", "auto" or an entry count)."""
        entries = parse_entries(choice, self.splats) if self.codebook_rows is not None else 0
        if not entries:
            return None
        return order_by_use(build_codebook(self.codebook_rows, entries, weights=self.codebook_weights,
                                           probes=probes_for(entries)),
                            self.codebook_rows)
