"""`splatstream encode`: Gaussians -> scene directory (manifest + content-addressed payloads).

The encoder wires the pure pieces together: LOD tiles (lod.py), Morton order (layout.py), quantisation
(codec.py), payload packing (container.py) and the manifest (manifest.py). Output goes to a temporary
directory that replaces the target only when everything is written.
"""
from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from . import __version__
from .atomic import atomic_directory
from .camera import suggested_camera
from .codec import (
    BASE_PLANES,
    SH_INDEX_FORMAT,
    EncodedPlane,
    band_plane,
    codebook_band_values,
    codebook_rows,
    codebook_weights,
    encode_index_plane,
    encode_plane,
    groups_for_degree,
    plane_values,
)
from .container import write_group
from .errors import UsageError
from .gaussians import Gaussians
from .layout import CHUNK_SIZE, MAX_BLOCK_ROWS, MAX_BLOCKS_PER_ROW, morton_order, order_within_chunks, texture_size
from .lod import Tile, build_tiles, extent_bounds
from .manifest import BASE_VERSION, DATA_DIR, FORMAT_NAME, FORMAT_VERSION, MANIFEST_NAME, pack_manifest, payload_name
from .texformats import FORMATS, VALUE_FORMATS, get_format
from .vq import Codebook, build_codebook, parse_entries

ATTRIBUTES = ("position", "rotation", "scale", "color", "sh")

# Texel format per attribute. The seed's table (Very High .. Very Low) is the baseline these must beat.
PRESETS: dict[str, dict[str, str]] = {
    "very-high": {"position": "f32x4", "rotation": "f32x4", "scale": "f32x4", "color": "f32x4", "sh": "f32x4"},
    "high": {"position": "f16x4", "rotation": "norm10_2", "scale": "norm11", "color": "f16x4", "sh": "norm11"},
    "medium": {"position": "norm11", "rotation": "norm10_2", "scale": "norm11", "color": "norm8x4", "sh": "norm565"},
    # low and very-low keep SH1..SH3 in a scene-wide codebook (PRESET_SH_CODEBOOK; sh is the codebook's format).
    # On fruit_drops low went from 35.2 dB at 19.4 B/splat (BC1 SH, norm11/norm10_2/norm565 for position,
    # rotation, scale) to 35.9 dB at 11.2 B/splat (manifest included): the codebook frees 6 B/splat, part of which
    # buys 8-bit scales (+1.7 dB on fruit); 8-bit positions cost under 0.1 dB there. 8-bit smallest-three
    # rotations would add 2.3 dB on fruit (0.75 on the 1M scene) for 1.2 B/splat more, past 12 B/splat on fruit.
    "low": {"position": "norm8x4", "rotation": "norm565", "scale": "norm8x4", "color": "bc7", "sh": "norm565"},
    # The seed's very-low (BC7 for position, rotation and scale) measured 18 dB on fruit_drops: BC7 scales are
    # the worst of it. Packed 16-bit scales and rotations gave 31 dB at fewer bytes (SH1 in BC1); the codebook
    # keeps all three bands for less.
    "very-low": {"position": "norm8x4", "rotation": "norm565", "scale": "norm565", "color": "bc7", "sh": "norm565"},
}
# Highest SH band a preset keeps (a lower --sh-degree still wins).
PRESET_MAX_SH_DEGREE: dict[str, int] = {}
# Presets whose SH bands go through a scene-wide codebook ("auto": sized from the splat count; see vq.py).
PRESET_SH_CODEBOOK: dict[str, str] = {"low": "auto", "very-low": "auto"}
DEFAULT_PRESET = "medium"

Progress = Callable[[str, float], None]


@dataclass
class EncodeOptions:
    preset: str = DEFAULT_PRESET
    overrides: dict[str, str] = field(default_factory=dict)
    sh_degree: int | None = None  # drop bands above this
    zstd_level: int = 3
    shuffle: bool = True
    lod: bool = True
    max_leaf_splats: int = 65536
    reduction: float = 4.0
    name: str | None = None
    up: tuple[float, float, float] | None = None
    chunk_order: str = "auto"  # "morton", "luminance", or "auto" (luminance when only colour/SH are BC-compressed)
    # SH codebook: None = the preset's choice, "off", "auto" or an entry count (format_spec/format.md 4.7).
    sh_codebook: str | int | None = None
    # Let the LOD builder permute the input's arrays in place instead of copying the scene (saves one copy of
    # the whole scene). Only for callers that own the Gaussians and do not need their order afterwards.
    reorder_input: bool = False


CHUNK_ORDERS = ("auto", "morton", "luminance")


def resolve_chunk_order(chunk_order: str, formats: dict[str, str]) -> str:
    """In-chunk order: luminance groups similar colours into the same 4x4 BC block (on fruit_drops, BC7 colour
    went from 34.1 to 41.1 dB PSNR), but BC-compressed positions need spatially coherent blocks instead."""
    if chunk_order not in CHUNK_ORDERS:
        raise UsageError(f"unknown chunk order {chunk_order!r} (expected one of {', '.join(CHUNK_ORDERS)})")
    if chunk_order != "auto":
        return chunk_order
    bc = {a for a, f in formats.items() if get_format(f).block > 1}
    return "luminance" if bc & {"color", "sh"} and not bc & {"position", "rotation", "scale"} else "morton"


def splat_order(g: Gaussians, chunk_order: str) -> np.ndarray:
    """Order of a tile's splats: 3D Morton, then optionally re-sorted inside each chunk."""
    order = morton_order(g.positions)
    if chunk_order == "luminance":
        order = order_within_chunks(order, g.base_colors @ np.array([0.299, 0.587, 0.114], np.float32))
    return order


def resolve_formats(preset: str, overrides: dict[str, str]) -> dict[str, str]:
    if preset not in PRESETS:
        raise UsageError(f"unknown preset {preset!r} (choose one of {', '.join(PRESETS)})")
    formats = dict(PRESETS[preset])
    for attr, fmt in overrides.items():
        if attr not in ATTRIBUTES:
            raise UsageError(f"unknown attribute {attr!r} in a format override (expected one of "
                             f"{', '.join(ATTRIBUTES)})")
        get_format(fmt)
        if fmt not in VALUE_FORMATS:
            raise UsageError(f"{fmt} holds codebook indices, not attribute values (choose one of "
                             f"{', '.join(VALUE_FORMATS)})")
        if attr == "color" and FORMATS[fmt].components < 4:
            raise UsageError(f"color holds SH0 and opacity and needs a 4-component format; {fmt} has 3 "
                             f"(use one of {', '.join(n for n, f in FORMATS.items() if f.components == 4)})")
        formats[attr] = fmt
    return formats


def fit_sh_codebook(g: Gaussians, preset: str, choice: str | int | None, sh_degree: int) -> Codebook | None:
    """The SH codebook the encoder stores for these splats (None: no codebook). `choice`: None (the preset's),
    "off", "auto" or an entry count. The one place that decides how a codebook is fitted (client_gl uses it too)."""
    if choice is None:
        choice = PRESET_SH_CODEBOOK.get(preset, "off")
    entries = parse_entries(choice, len(g)) if sh_degree >= 1 else 0
    if not entries:
        return None
    if sh_degree < g.sh_degree:
        g = g.with_sh_degree(sh_degree)
    return build_codebook(codebook_rows(g), entries, weights=codebook_weights(g))


def assign_sh_codebook(codebook: Codebook, g: Gaussians, block: int = 1 << 16) -> np.ndarray:
    """Codebook index of every splat, a block of rows at a time (never a second copy of all SH rows)."""
    labels = np.empty(len(g), np.int64)
    for i in range(0, len(g), block):
        labels[i:i + block] = codebook.assign(codebook_rows(g.subset(slice(i, i + block))))
    return labels


def codebook_planes(codebook: Codebook, sh_degree: int, fmt: str, lazy: bool = False) -> dict[str, EncodedPlane]:
    """The codebook's band planes sh1..sh{sh_degree} (K entries each) in texel format `fmt`."""
    return {f"sh{b}": encode_plane(codebook_band_values(codebook.entries, b), band_plane(b), fmt, lazy=lazy)
            for b in range(1, sh_degree + 1)}


def _build_tiles(g: Gaussians, opts: EncodeOptions, progress: Progress) -> list[Tile]:
    if opts.lod and len(g) > opts.max_leaf_splats:
        return build_tiles(g, max_leaf_splats=opts.max_leaf_splats, reduction=opts.reduction, progress=progress,
                           reorder_input=opts.reorder_input)
    limit = MAX_BLOCKS_PER_ROW * MAX_BLOCK_ROWS * CHUNK_SIZE
    if len(g) > limit:
        raise UsageError(f"{len(g)} splats do not fit one tile (at most {limit}); encode with LOD (drop --no-lod)")
    # Bounds (None here) are filled in by encode_gaussians, on the worker pool, alongside the payload jobs.
    return [Tile(0, 0, [], g, 0.0, None, None, None, 0.0)]


def _suggested_camera(g: Gaussians, up: np.ndarray) -> dict:
    cam = suggested_camera(g.positions, up=tuple(float(u) for u in up))
    return {"eye": [float(v) for v in cam.eye], "target": [float(v) for v in cam.target],
            "up": [float(v) for v in cam.up], "fov_y": float(cam.fov_y_deg)}


def encode_gaussians(g: Gaussians, out_dir: str | os.PathLike, opts: EncodeOptions | None = None,
                     progress: Progress | None = None, source_name: str | None = None) -> dict:
    """Encode Gaussians into a scene directory; returns the manifest written."""
    opts = opts or EncodeOptions()
    progress = progress or (lambda stage, fraction: None)
    formats = resolve_formats(opts.preset, opts.overrides)
    chunk_order = resolve_chunk_order(opts.chunk_order, formats)
    if len(g) == 0:
        raise UsageError("the input holds no splats; nothing to encode")
    cap = opts.sh_degree if opts.sh_degree is not None else PRESET_MAX_SH_DEGREE.get(opts.preset, 3)
    sh_degree = min(cap, g.sh_degree)
    if sh_degree != g.sh_degree:
        g = g.with_sh_degree(sh_degree)
    t0 = time.perf_counter()
    progress("codebook", 0.0)
    codebook = fit_sh_codebook(g, opts.preset, opts.sh_codebook, sh_degree)
    progress("codebook", 1.0)
    progress("tiles", 0.0)
    tiles = _build_tiles(g, opts, progress)
    progress("tiles", 1.0)
    up = np.array(opts.up if opts.up is not None else (0.0, 0.0, 1.0), np.float64)
    total_splats = sum(len(t.gaussians) for t in tiles)
    out_dir = os.fspath(out_dir)
    tile_entries = []
    attr_gpu = dict.fromkeys(ATTRIBUTES, 0)
    attr_disk = dict.fromkeys(ATTRIBUTES, 0)
    bytes_on_disk = 0
    leaf_gpu = 0
    leaf_disk = 0
    done = 0
    with atomic_directory(out_dir) as tmp:
        os.makedirs(os.path.join(tmp, DATA_DIR))
        written: set[str] = set()

        def order_tile(tile):
            return tile, splat_order(tile.gaussians, chunk_order)

        group_names = groups_for_degree(sh_degree, codebook is not None)

        def write_payload(planes, chunks: int) -> dict:
            fd, tmp_path = tempfile.mkstemp(prefix=".payload.", dir=os.path.join(tmp, DATA_DIR))
            with os.fdopen(fd, "wb") as f:
                entry = write_group(planes, f, chunks=chunks, level=opts.zstd_level, shuffle=opts.shuffle)
            final = os.path.join(tmp, payload_name(entry["sha256"]))
            os.replace(tmp_path, final)  # identical content has an identical name
            return entry

        def encode_group(job):
            (tile, order), group = job
            if codebook is not None and group == "sh1":
                planes = [encode_index_plane(assign_sh_codebook(codebook, tile.gaussians), order)]
            else:
                specs = BASE_PLANES if group == "base" else (band_plane(int(group[2:])),)
                planes = [encode_plane(plane_values(tile.gaussians, s), s, formats[s.attribute], order, lazy=True)
                          for s in specs]
            return write_payload(planes, -(-len(order) // CHUNK_SIZE))

        codebook_entry = None
        if codebook is not None:
            k = len(codebook.entries)
            codebook_entry = {"entries": k, "format": formats["sh"], "index_format": SH_INDEX_FORMAT, "groups": {}}
            for band, plane in codebook_planes(codebook, sh_degree, formats["sh"], lazy=True).items():
                entry = write_payload([plane], -(-k // CHUNK_SIZE))
                rel = payload_name(entry["sha256"])
                if rel not in written:
                    written.add(rel)
                    bytes_on_disk += entry["bytes"]
                codebook_entry["groups"][band] = {"file": rel, **entry}
                leaf_gpu += entry["gpu_bytes"]
                leaf_disk += entry["bytes"]
                attr_gpu["sh"] += entry["gpu_bytes"]
                attr_disk["sh"] += entry["bytes"]

        # Tiles and groups are independent; numpy, zstd and etcpak release the GIL, so two workers keep both
        # cores busy. Results come back in submission order, so the output is deterministic.
        with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
            ordered = list(pool.map(order_tile, tiles))
            camera = pool.submit(_suggested_camera, g, up)
            unbounded = [t for t in tiles if t.box_min is None]
            bounds = [pool.submit(extent_bounds, t.gaussians) for t in unbounded]
            jobs = [(t, group) for t in ordered for group in group_names]
            results = iter(pool.map(encode_group, jobs))
            for tile, future in zip(unbounded, bounds, strict=True):
                tile.box_min, tile.box_max, tile.sphere_center, tile.sphere_radius = future.result()
            for tile in tiles:
                groups = [(group, next(results)) for group in group_names]
                n = len(tile.gaussians)
                chunks = -(-n // CHUNK_SIZE)
                width, height = texture_size(chunks)
                group_entries = {}
                for group, entry in groups:
                    rel = payload_name(entry["sha256"])
                    if rel not in written:
                        written.add(rel)
                        bytes_on_disk += entry["bytes"]
                    entry = {"file": rel, **entry}
                    group_entries[group] = entry
                    attrs = [p.attribute for p in BASE_PLANES] if group == "base" else ["sh"]
                    # Per-attribute sizes: GPU exactly per section; disk shared out by raw size.
                    for sec in entry["sections"] if not tile.children else ():
                        attr = "sh" if sec["name"].startswith("sh") else sec["name"].split(".")[0]
                        if attr in attrs:
                            attr_gpu[attr] += sec["size"]
                            attr_disk[attr] += entry["bytes"] * sec["size"] / max(1, entry["raw_bytes"])
                    if not tile.children:
                        leaf_gpu += entry["gpu_bytes"]
                        leaf_disk += entry["bytes"]
                tile_entries.append({
                    "id": int(tile.id), "level": int(tile.level), "children": [int(c) for c in tile.children],
                    "splats": n, "chunks": chunks, "texture": [width, height],
                    "box": {"min": [float(v) for v in tile.box_min], "max": [float(v) for v in tile.box_max]},
                    "sphere": {"center": [float(v) for v in tile.sphere_center], "radius": float(tile.sphere_radius)},
                    "geometric_error": float(tile.geometric_error),
                    "groups": group_entries,
                })
                done += n
                progress("encode", done / total_splats)
        tile_entries.sort(key=lambda t: t["id"])
        leaf_splats = sum(t["splats"] for t in tile_entries if not t["children"])
        lo = g.positions.min(axis=0)
        hi = g.positions.max(axis=0)
        root = tile_entries[0]
        manifest = {
            "format": FORMAT_NAME,
            "version": list(FORMAT_VERSION if codebook is not None else BASE_VERSION),
            "generator": f"splatstream {__version__}",
            "name": opts.name or (os.path.splitext(os.path.basename(source_name))[0] if source_name else
                                  os.path.basename(os.path.abspath(out_dir))),
            "splats": len(g),
            "leaf_splats": leaf_splats,
            "sh_degree": sh_degree,
            "preset": opts.preset,
            "formats": formats,
            "chunk_size": CHUNK_SIZE,
            "chunk_order": chunk_order,
            "bounds": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]},
            "extent_bounds": root["box"],
            "up": [float(v) for v in up],
            "camera": camera.result(),
            **({"sh_codebook": codebook_entry} if codebook_entry else {}),
            "lod": {"enabled": len(tiles) > 1, "max_leaf_splats": opts.max_leaf_splats,
                    "reduction": opts.reduction, "refine": "replace"},
            "root": 0,
            "tiles": tile_entries,
            "gpu_bytes": int(leaf_gpu),
            "gpu_bytes_per_splat": leaf_gpu / len(g),
            "leaf_bytes_on_disk": int(leaf_disk),
            "attributes": {a: {"format": formats[a], "gpu_bytes": int(attr_gpu[a]), "disk_bytes": int(attr_disk[a])}
                           for a in ATTRIBUTES if a != "sh" or sh_degree > 0},
            "encode_seconds": round(time.perf_counter() - t0, 3),
        }
        raw_manifest = pack_manifest(manifest)
        # bytes_on_disk counts the manifest too; its own size changes the msgpack length, so settle it twice.
        for _ in range(2):
            manifest["bytes_on_disk"] = bytes_on_disk + len(raw_manifest)
            raw_manifest = pack_manifest(manifest)
        with open(os.path.join(tmp, MANIFEST_NAME), "wb") as f:
            f.write(raw_manifest)
    return manifest


def encode_file(input_path: str | os.PathLike, out_dir: str | os.PathLike, preset: str = DEFAULT_PRESET,
                drop_invalid: bool = False, progress: Progress | None = None, **options) -> dict:
    """Read any supported splat file and encode it into `out_dir`."""
    from .io import read_gaussians

    opts = EncodeOptions(preset=preset, reorder_input=True, **options)
    resolve_formats(opts.preset, opts.overrides)  # fail before the (possibly long) read
    if opts.sh_codebook is not None:
        parse_entries(opts.sh_codebook, 1)
    if progress:
        progress("read", 0.0)
    g = read_gaussians(input_path, drop_invalid=drop_invalid)
    if progress:
        progress("read", 1.0)
    return encode_gaussians(g, out_dir, opts, progress, source_name=os.fspath(input_path))
