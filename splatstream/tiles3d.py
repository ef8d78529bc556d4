"""Export a splatstream scene as an OGC 3D Tiles 1.1 tileset whose tiles are glTF KHR_gaussian_splatting content
(format_spec/tiles3d.md).

One tile of ours is one tile of the tileset, with the same tree, REPLACE refinement, our geometric errors (world
units, taken as metres) and bounding boxes from our 3-sigma boxes. Each tile's content is a `.glb` written by
`splatstream.writers.glb` (SPZ-compressed by default), named by the SHA-256 of its bytes. The pure functions here
(frames, boxes, the tileset map) are what the tests pin down; `export_tileset` wires them to a scene store and an
output directory written atomically.

Frames (format_spec/tiles3d.md 2): our scene's model axes (RDF, with the manifest's `up`); the tileset's local frame
L (x east, y north, z up: the scene's up turned onto +z by the shortest rotation); the glTF content, which is
y-up: 3D Tiles runtimes turn glTF content into the tile's z-up frame F with the fixed rotation Y_UP_TO_Z_UP. The
splats themselves only get a sign turn (exact, and what CesiumJS draws correctly); the rotation from F to L, the
anchor, the heading and the east-north-up frame at a longitude, latitude and height make the root tile's
transform (F -> ECEF).

A paged scene (format.md 6.1) is written by default as a root tileset of the root manifest's levels and one
external tileset per manifest page (`tiles/<sha256>.json`, format_spec/tiles3d.md 3.1), so that a client reads
the tree page by page as our streaming client does instead of one JSON of every tile.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from .atomic import atomic_directory, check_output
from .axes import RDF_TO_LUF, turn
from .errors import FormatError, UsageError
from .format.decode import decode_planes
from .format.manifest import Manifest, page_heads
from .format.names import TILESET_CONTENT_DIR, TILESET_NAME, tileset_content_name, tileset_external_name
from .gaussians import Gaussians, covariances, normalize_quaternions
from .readers.gltf import sh_rotation
from .readers.spz import decode_spz
from .scene_decode import decode_tile, read_codebook
from .sh import warn_sh_degree_above
from .store import SceneStore, open_store, read_manifest
from .writers.glb import DEFAULT_SPZ_VERSION, glb_bytes

CONTENT_KINDS = ("spz", "plain")
# auto: external tilesets for a paged scene (one per manifest page), one tileset.json for an unpaged one; always:
# an unpaged scene split too, at the levels the encoder would page it (`ExportOptions.page_levels`); never: one
# tileset.json listing every tile.
EXTERNAL_MODES = ("auto", "always", "never")
DEFAULT_PAGE_LEVELS = 6  # the encoder's default (EncodeOptions.page_levels)
SPZ_AXES = ("luf", "rub")
# How SPZ content stores glTF's axes. "luf": the glTF values unconverted, which is what CesiumJS (1.145) reads:
# its loader decodes SPZ without any axis conversion. Settled by the browser test (tests/test_cesium_browser.py):
# with "rub" (the extension text's "pack from LUF") CesiumJS draws the scene turned 180 degrees about its up.
DEFAULT_SPZ_AXES = "luf"
ANCHORS = ("origin", "ground")
TILES_VERSION = "1.1"
EXTENSION = "KHR_gaussian_splatting"
SPZ_EXTENSION = "KHR_gaussian_splatting_compression_spz_2"
CONTENT_GLTF = "3DTILES_content_gltf"
# 3-sigma: the reference rasteriser's and the extension's `ellipse` kernel's cut-off (format_spec/lod.md 2).
SIGMAS = 3.0
# A box half-axis is never zero (a flat tile, a single splat): runtimes normalise the axes.
MIN_HALF_AXIS = 1e-6

# WGS84 (3D Tiles' Earth-fixed frame).
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

# glTF content (y-up) -> a 3D Tiles tile's frame (z-up): +90 degrees about x, (x, y, z) -> (x, -z, y) (3D Tiles
# 1.1, "glTF transforms"; CesiumJS's Axis.Y_UP_TO_Z_UP).
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# Our model axes (RDF) -> what splatstream.writers.glb stores as glTF (LUF): 180 degrees about z.
MODEL_TO_GLTF = np.diag(np.asarray(RDF_TO_LUF, np.float64))


# --------------------------------------------------------------------------------------------------------------
# Frames


def up_to_z(up: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking the unit vector `up` onto +z by the shortest arc (180 degrees about x when up = -z).

    For the 3DGS convention up = -y this is (x, y, z) -> (x, z, -y): the capture's right is east, its forward
    (+z, where the cameras looked) north. A z-up scene keeps its axes."""
    u = np.asarray(up, np.float64)
    norm = float(np.linalg.norm(u))
    if not math.isfinite(norm) or norm == 0.0:
        raise UsageError(f"the scene's up vector {tuple(u)} is not a direction")
    u = u / norm
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, z)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    r = np.eye(3) + vx + vx @ vx / (1.0 + c)
    return np.where(np.abs(r) < 1e-15, 0.0, r)


def model_to_local(up: tuple[float, float, float]) -> np.ndarray:
    """(3, 3) rotation from our model axes to the tileset's local frame L (x east, y north, z up)."""
    return up_to_z(up)


# The sign turns (180 degrees about a model axis, or none) the content may get: exact for every attribute (SH
# coefficients only change sign), unlike a general rotation.
_TURNS = [np.eye(3), np.diag([-1.0, 1.0, -1.0]), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]


def content_rotation(up: tuple[float, float, float]) -> np.ndarray:
    """(3, 3) sign turn A applied to a tile's splats (model axes) before the glTF writer's own RDF -> LUF turn: the
    one that brings the content closest to L once a runtime applies Y_UP_TO_Z_UP (exactly for up = +-y: the
    content is then y-up; for up = -y, A = diag(-1, 1, -1), the scene in RUB axes, its cameras' side facing +z,
    glTF's front). What is left (`residual_rotation`) goes into the root tile's transform, never into the splats:
    CesiumJS 1.145 draws SPZ content whose splat rotations were composed with a rotation other than a sign turn
    with wrongly oriented splats (format_spec/tiles3d.md 2), while it applies tile transforms correctly."""
    target = model_to_local(up)
    best = max(_TURNS, key=lambda a: float(np.trace(target.T @ Y_UP_TO_Z_UP @ MODEL_TO_GLTF @ a)))
    return best.copy()


def tile_frame(up: tuple[float, float, float]) -> np.ndarray:
    """(3, 3) rotation from model axes to the frame F in which a runtime holds the content after Y_UP_TO_Z_UP:
    the frame of the tileset's bounding volumes, below the root transform."""
    return Y_UP_TO_Z_UP @ MODEL_TO_GLTF @ content_rotation(up)


def residual_rotation(up: tuple[float, float, float]) -> np.ndarray:
    """(3, 3) rotation from F to L, part of the root transform (identity for up = -y)."""
    r = model_to_local(up) @ tile_frame(up).T
    return np.where(np.abs(r) < 1e-15, 0.0, r)


def _signed_diagonal(r: np.ndarray) -> tuple[float, float, float] | None:
    if np.allclose(r, np.diag(np.diag(r)), atol=1e-12, rtol=0) and np.allclose(np.abs(np.diag(r)), 1.0):
        return tuple(float(s) for s in np.diag(r))  # type: ignore[return-value]
    return None


def _matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a proper rotation matrix."""
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return np.array([w, x, y, z])


def rotate_gaussians(g: Gaussians, r: np.ndarray) -> Gaussians:
    """`g` turned by the proper rotation `r` (3, 3): positions, orientations and view-dependent colour (SH)."""
    r = np.asarray(r, np.float64)
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-9 or np.linalg.det(r) < 0:
        raise ValueError("not a proper rotation")
    if np.array_equal(r, np.eye(3)):
        return g
    signs = _signed_diagonal(r)
    if signs is not None:  # a 180-degree turn about an axis: exact sign flips
        return turn(g, signs)
    positions = (g.positions.astype(np.float64) @ r.T).astype(np.float32)
    w0, x0, y0, z0 = _matrix_to_quaternion(r)
    q = g.rotations.astype(np.float64)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    composed = np.stack([w0 * w - x0 * x - y0 * y - z0 * z, w0 * x + x0 * w + y0 * z - z0 * y,
                         w0 * y - x0 * z + y0 * w + z0 * x, w0 * z + x0 * y - y0 * x + z0 * w], axis=1)
    rest = g.sh_rest
    if rest.shape[1]:
        rest = np.einsum("jk,nkc->njc", sh_rotation(r, g.sh_degree), rest.astype(np.float64)).astype(np.float32)
    return Gaussians(positions, normalize_quaternions(composed.astype(np.float32)), g.log_scales,
                     g.opacity_logits, g.sh_dc, rest)


def geodetic_to_ecef(longitude: float, latitude: float, height: float) -> np.ndarray:
    lon, lat = math.radians(longitude), math.radians(latitude)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
    return np.array([(n + height) * math.cos(lat) * math.cos(lon), (n + height) * math.cos(lat) * math.sin(lon),
                     (n * (1.0 - WGS84_E2) + height) * math.sin(lat)])


def enu_frame(longitude: float, latitude: float, height: float) -> np.ndarray:
    """(4, 4) east-north-up frame at a WGS84 position, as a matrix from ENU to ECEF (CesiumJS's
    Transforms.eastNorthUpToFixedFrame)."""
    lon, lat = math.radians(longitude), math.radians(latitude)
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)])
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = east, north, up, geodetic_to_ecef(longitude, latitude, height)
    return m


def heading_rotation(heading_deg: float) -> np.ndarray:
    """(4, 4) turn about the local up by a compass heading: the local +y (north) ends up at bearing `heading`
    (degrees clockwise from north, seen from above)."""
    h = math.radians(heading_deg)
    m = np.eye(4)
    m[:2, :2] = [[math.cos(h), math.sin(h)], [-math.sin(h), math.cos(h)]]
    return m


@dataclass(frozen=True)
class Placement:
    """Where the scene goes on the globe. `anchor`: which point of the scene sits at the position: `origin` (the
    scene's own coordinate origin: a georeferenced capture) or `ground` (the centre of the bottom of its box)."""

    longitude: float = 0.0
    latitude: float = 0.0
    height: float = 0.0
    heading: float = 0.0
    anchor: str = "ground"
    georeferenced: bool = False

    def __post_init__(self) -> None:
        for name, lo, hi in (("longitude", -180.0, 180.0), ("latitude", -90.0, 90.0), ("heading", -360.0, 360.0),
                             ("height", -1e7, 1e8)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
                raise UsageError(f"--{name}: expected a number in [{lo:g}, {hi:g}], got {value!r}")
        if self.anchor not in ANCHORS:
            raise UsageError(f"--anchor: expected one of {', '.join(ANCHORS)}, got {self.anchor!r}")


def root_transform(placement: Placement, anchor_local: np.ndarray, residual: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) matrix from F (or L when `residual` is None) to ECEF: `residual` (F -> L), `anchor_local` (a point
    of L) moved to the origin, the heading, the ENU frame at the placement."""
    shift = np.eye(4)
    shift[:3, 3] = -np.asarray(anchor_local, np.float64)
    turn_to_local = np.eye(4)
    if residual is not None:
        turn_to_local[:3, :3] = residual
    return enu_frame(placement.longitude, placement.latitude, placement.height) @ heading_rotation(
        placement.heading) @ shift @ turn_to_local


def model_to_fixed(tileset: dict, up: tuple[float, float, float]) -> np.ndarray:
    """(4, 4) matrix from a scene's model coordinates to ECEF for a tileset exported from it (the root transform
    after the model -> F rotation): puts a camera of ours into a 3D Tiles viewer's world."""
    m = np.eye(4)
    m[:3, :3] = tile_frame(up)
    return np.asarray(tileset["root"]["transform"], np.float64).reshape(4, 4).T @ m


def column_major(m: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(m, np.float64).T.reshape(-1)]


# --------------------------------------------------------------------------------------------------------------
# Boxes


def extent_box(g: Gaussians) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of the splats' 3-sigma ellipsoids (format_spec/lod.md 2), float64."""
    cov = covariances(g).astype(np.float64)
    half = SIGMAS * np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    p = g.positions.astype(np.float64)
    return (p - half).min(axis=0), (p + half).max(axis=0)


def rotated_box(lo: np.ndarray, hi: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box containing the box [lo, hi] turned by `r` (exact when r permutes axes with signs)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    center, half = (lo + hi) / 2, (hi - lo) / 2
    c, h = r @ center, np.abs(r) @ half
    return c - h, c + h


def box_volume(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    """3D Tiles `box` (centre, then the x, y, z half-axis vectors) of an axis-aligned box."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    center, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, MIN_HALF_AXIS)
    return [float(v) for v in (*center, half[0], 0, 0, 0, half[1], 0, 0, 0, half[2])]


def _content_gaussians(glb: bytes) -> bytes:
    """The SPZ bytes of buffer view 0 of one of our GLBs."""
    json_len = struct.unpack_from("<I", glb, 12)[0]
    gltf = json.loads(glb[20:20 + json_len])
    view = gltf["bufferViews"][0]
    start = 20 + json_len + 8 + view.get("byteOffset", 0)
    return glb[start:start + view["byteLength"]]


# SPZ content decoded by our reader (which turns SPZ's RUB into RDF) -> the splats handed to the GLB writer.
_SPZ_READBACK = {"rub": (1.0, 1.0, 1.0), "luf": (-1.0, 1.0, -1.0)}


# --------------------------------------------------------------------------------------------------------------
# The tileset


@dataclass(frozen=True)
class ExportOptions:
    content: str = "spz"
    spz_axes: str = DEFAULT_SPZ_AXES
    spz_version: int = DEFAULT_SPZ_VERSION
    placement: Placement = field(default_factory=Placement)
    sh_degree: int | None = None  # None: the scene's
    external_tilesets: str = "auto"
    page_levels: int = DEFAULT_PAGE_LEVELS  # levels to an external tileset where the scene has no pages (always)

    def __post_init__(self) -> None:
        if self.external_tilesets not in EXTERNAL_MODES:
            raise UsageError(f"--external-tilesets: expected one of {', '.join(EXTERNAL_MODES)}, "
                             f"got {self.external_tilesets!r}")
        if not (isinstance(self.page_levels, int) and self.page_levels >= 1):
            raise UsageError(f"page_levels: expected an integer of at least 1, got {self.page_levels!r}")
        if self.content not in CONTENT_KINDS:
            raise UsageError(f"--content: expected one of {', '.join(CONTENT_KINDS)}, got {self.content!r}")
        if self.spz_axes not in SPZ_AXES:
            raise UsageError(f"--spz-axes: expected one of {', '.join(SPZ_AXES)}, got {self.spz_axes!r}")


@dataclass(frozen=True)
class TileContent:
    uri: str  # relative to tileset.json
    data: bytes
    box_min: np.ndarray  # 3-sigma box of what the content holds, in the content's splat axes (A @ model)
    box_max: np.ndarray


def tile_content(g: Gaussians, options: ExportOptions) -> TileContent:
    """One tile's `.glb` (g already turned by `content_rotation`), its content-addressed name and its box."""
    compression = "spz" if options.content == "spz" else "none"
    data = glb_bytes(g, compression, options.spz_version, generator="splatstream export-3dtiles",
                     spz_axes=options.spz_axes)
    if compression == "spz":
        # The box of what a runtime decodes: SPZ rounds positions and log scales (a step of 1/16).
        stored = decode_spz("<tile content>", _content_gaussians(data))
        lo, hi = extent_box(turn(stored, _SPZ_READBACK[options.spz_axes]))
        lo2, hi2 = extent_box(g)
        lo, hi = np.minimum(lo, lo2), np.maximum(hi, hi2)
    else:
        lo, hi = extent_box(g)
    name = tileset_content_name(hashlib.sha256(data).hexdigest())
    return TileContent(name, data, lo, hi)


def tile_boxes(manifest: Manifest, content_boxes: dict[int, tuple[np.ndarray, np.ndarray]],
               rotation: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per tile id, the box in the content's splat axes: our manifest box turned by `rotation`, grown to hold what
    the content holds (SPZ rounding), and every parent grown to hold its children (3D Tiles needs a parent's
    volume to contain its children's for culling)."""
    boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for tile in sorted(manifest.tiles, key=lambda t: -t.level):  # children before parents
        lo, hi = rotated_box(np.asarray(tile.box.min), np.asarray(tile.box.max), rotation)
        if tile.id in content_boxes:
            clo, chi = content_boxes[tile.id]
            lo, hi = np.minimum(lo, clo), np.maximum(hi, chi)
        for child in tile.children:
            lo, hi = np.minimum(lo, boxes[child][0]), np.maximum(hi, boxes[child][1])
        boxes[tile.id] = (lo, hi)
    return boxes


def external_heads(manifest: Manifest, options: ExportOptions) -> dict[int, str | None]:
    """The tiles whose descendants go into an external tileset, each with the SHA-256 of the manifest page holding
    them (None where `always` splits an unpaged scene at `options.page_levels`)."""
    mode = options.external_tilesets
    if mode == "never":
        return {}
    if manifest.paged is not None:
        return {t.id: t.page.sha256 for t in manifest.tiles if t.page is not None}
    if mode == "always":
        return {t.id: None for t in page_heads(manifest, options.page_levels)}
    return {}


@dataclass(frozen=True)
class Tilesets:
    """A tileset's JSON files: the root (tileset.json) and the external tilesets, by their path in the tileset
    directory (`tiles/<sha256>.json`)."""

    root: dict
    external: dict[str, bytes]


def _dumps(d: dict) -> bytes:
    return json.dumps(d, separators=(",", ":")).encode("utf-8")


def build_tileset(manifest: Manifest, uris: dict[int, str], boxes: dict[int, tuple[np.ndarray, np.ndarray]],
                  options: ExportOptions, generator: str = "splatstream") -> dict:
    """One tileset.json listing every tile (`build_tilesets` without external tilesets)."""
    return build_tilesets(manifest, uris, boxes, options, generator, heads={}).root


def build_tilesets(manifest: Manifest, uris: dict[int, str], boxes: dict[int, tuple[np.ndarray, np.ndarray]],
                   options: ExportOptions, generator: str = "splatstream",
                   heads: Mapping[int, str | None] | None = None) -> Tilesets:
    """The tileset.json map and the external tilesets. `boxes` are in the content's splat axes (`content_rotation`
    applied); `uris` name each tile's content file (relative to tileset.json); `heads` (default:
    `external_heads`) the tiles whose children go into an external tileset.

    A head tile H keeps its own content and gets one child E without content whose `content.uri` is the external
    tileset; that tileset's root R has no content either and H's children as its children. E and R have H's box
    and geometric error, so a runtime refines them exactly when it refines H (same volume, same error: the same
    screen-space error) and never stops at a tile without content. No external tileset has a transform: its
    tiles are in F below the referencing tile's (3D Tiles 1.1, external tilesets inherit the parent's frame)."""
    heads = external_heads(manifest, options) if heads is None else heads
    to_frame = Y_UP_TO_Z_UP @ MODEL_TO_GLTF  # content splat axes -> F (content_rotation already applied)
    framed = {tid: rotated_box(lo, hi, to_frame) for tid, (lo, hi) in boxes.items()}  # a signed permutation: exact
    residual = residual_rotation(manifest.up)
    root_lo, root_hi = rotated_box(*framed[manifest.root], residual)  # the root's box in L
    placement = options.placement
    if placement.anchor == "origin":
        anchor = np.zeros(3)
    else:
        anchor = np.array([(root_lo[0] + root_hi[0]) / 2, (root_lo[1] + root_hi[1]) / 2, root_lo[2]])
    transform = root_transform(placement, anchor, residual)

    used = [EXTENSION] + ([SPZ_EXTENSION] if options.content == "spz" else [])
    # glTF extensions the content needs, declared for runtimes (CesiumJS picks its splat renderer from this), in
    # every tileset JSON: each declares what its own tiles use.
    declared = {"extensionsUsed": [CONTENT_GLTF],
                "extensions": {CONTENT_GLTF: {"extensionsUsed": used, "extensionsRequired": used}}}
    external: dict[str, bytes] = {}
    inner = TILESET_CONTENT_DIR + "/"

    def relative(uri: str, nested: bool) -> str:
        # External tilesets live in tiles/ beside the content: their URIs are relative to that folder.
        return uri[len(inner):] if nested and uri.startswith(inner) else uri

    def tile_json(tile_id: int, nested: bool) -> dict:
        t = manifest.tile(tile_id)
        d: dict = {"boundingVolume": {"box": box_volume(*framed[tile_id])},
                   "geometricError": float(t.geometric_error), "refine": "REPLACE",
                   "content": {"uri": relative(uris[tile_id], nested)}}
        if t.children:
            d["children"] = [external_tile(tile_id, nested)] if tile_id in heads else \
                [tile_json(c, nested) for c in t.children]
        return d

    def external_tile(tile_id: int, nested: bool) -> dict:
        t = manifest.tile(tile_id)
        volume, error = {"box": box_volume(*framed[tile_id])}, float(t.geometric_error)
        page = heads[tile_id]
        data = _dumps({
            "asset": {"version": TILES_VERSION, "generator": generator, "extras": {"splatstream": {
                "scene": manifest.name, "parent": tile_id, "page": page}}},
            **declared,
            "geometricError": error,
            "root": {"boundingVolume": volume, "geometricError": error, "refine": "REPLACE",
                     "children": [tile_json(c, True) for c in t.children]},
        })
        name = tileset_external_name(hashlib.sha256(data).hexdigest())
        external[name] = data
        return {"boundingVolume": volume, "geometricError": error, "refine": "REPLACE",
                "content": {"uri": relative(name, nested)}}

    root = tile_json(manifest.root, False)
    root["transform"] = column_major(transform)
    # The tileset's error is the error of drawing nothing: at least the scene's size (its box diagonal), so a
    # runtime draws the root as soon as the scene covers a pixel or so, never less than the root's own error.
    diagonal = float(np.linalg.norm(framed[manifest.root][1] - framed[manifest.root][0]))
    return Tilesets({
        "asset": {
            "version": TILES_VERSION, "generator": generator,
            "extras": {"splatstream": {
                "scene": manifest.name, "splats": manifest.splats, "sh_degree": manifest.sh_degree,
                "content": options.content, "spz_axes": options.spz_axes if options.content == "spz" else None,
                "up": list(manifest.up), "model_to_local": [list(map(float, row)) for row in
                                                            model_to_local(manifest.up)],
                "anchor": [float(v) for v in anchor], "georeferenced": placement.georeferenced,
                "longitude": placement.longitude, "latitude": placement.latitude, "height": placement.height,
                "heading": placement.heading,
                # How the tree was built (format.md 6, 1.9; None: not recorded): tilesets of two encodes compare.
                "lod_merge": manifest.lod.merge,
                "viewing_scale_px": list(manifest.lod.viewing_scale_px) if manifest.lod.viewing_scale_px else None,
                # The merged levels' refinement (format.md 6, 1.11; encode --lod-refine), only where there is one.
                **({"lod_refinement": manifest.lod.refinement.to_dict()} if manifest.lod.refinement else {})}},
        },
        **declared,
        "geometricError": max(diagonal, float(manifest.tile(manifest.root).geometric_error)),
        "root": root,
    }, external)


@dataclass(frozen=True)
class ExportReport:
    tiles: int
    files: int  # distinct content files
    content_bytes: int
    tileset_bytes: int  # tileset.json (the root tileset)
    external_tilesets: int
    external_bytes: int
    splats: int  # full-detail splats (leaves)
    transform: list[float]


def export_tileset(scene: str | os.PathLike | SceneStore, out_dir: str | os.PathLike,
                   options: ExportOptions | None = None,
                   progress: Callable[[str, float], None] | None = None) -> ExportReport:
    """Write the tileset of `scene` into `out_dir` (replaced atomically: built under a hidden temporary name)."""
    options = options or ExportOptions()
    store = open_store(scene)
    manifest = read_manifest(store)
    out = os.fspath(out_dir)
    if isinstance(scene, (str, os.PathLike)) and os.path.exists(out) and \
            os.path.realpath(out) == os.path.realpath(os.fspath(scene)):
        raise UsageError(f"{out}: the output directory is the scene itself")
    check_output(out, directory=True, holds=TILESET_NAME)
    warn_sh_degree_above(options.sh_degree, manifest.sh_degree, store.location)
    degree = manifest.sh_degree if options.sh_degree is None else max(0, min(options.sh_degree, manifest.sh_degree))
    planes = read_codebook(store, manifest, degree) if degree >= 1 else None
    codebook = decode_planes(planes, manifest.sh_codebook.entries) if planes is not None else None
    rotation = content_rotation(manifest.up)
    uris: dict[int, str] = {}
    content_boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    written: dict[str, int] = {}
    report = progress or (lambda stage, fraction: None)
    with atomic_directory(out, holds=TILESET_NAME) as tmp:
        os.makedirs(os.path.join(tmp, TILESET_CONTENT_DIR))
        for done, tile in enumerate(manifest.tiles):
            g = decode_tile(store, manifest, tile, degree, codebook)
            if len(g) == 0:
                raise FormatError(store.location, f"tiles[{tile.id}]", "a tile without splats cannot be glTF content")
            content = tile_content(rotate_gaussians(g, rotation), options)
            uris[tile.id] = content.uri
            content_boxes[tile.id] = (content.box_min, content.box_max)
            if content.uri not in written:
                with open(os.path.join(tmp, content.uri), "wb") as f:
                    f.write(content.data)
                written[content.uri] = len(content.data)
            report("tiles", (done + 1) / len(manifest.tiles))
        boxes = tile_boxes(manifest, content_boxes, rotation)
        tilesets = build_tilesets(manifest, uris, boxes, options)
        tileset = tilesets.root
        for name, raw in tilesets.external.items():  # before tileset.json, which names them
            with open(os.path.join(tmp, name), "wb") as f:
                f.write(raw)
        data = _dumps(tileset)
        with open(os.path.join(tmp, TILESET_NAME), "wb") as f:  # last: a tileset directory is complete with it
            f.write(data)
        for name in os.listdir(os.path.join(tmp, TILESET_CONTENT_DIR)):
            os.chmod(os.path.join(tmp, TILESET_CONTENT_DIR, name), 0o644)
        os.chmod(os.path.join(tmp, TILESET_CONTENT_DIR), 0o755)
        os.chmod(os.path.join(tmp, TILESET_NAME), 0o644)
    return ExportReport(tiles=len(manifest.tiles), files=len(written), content_bytes=sum(written.values()),
                        tileset_bytes=len(data), external_tilesets=len(tilesets.external),
                        external_bytes=sum(map(len, tilesets.external.values())), splats=manifest.splats,
                        transform=tileset["root"]["transform"])
