"""Rate-distortion evaluation of the encoder presets (and of other tools' outputs) on one scene.

The original scene and every encoded version are rendered from the same orbit cameras (camera.scene_orbit_views);
PSNR and SSIM are taken against the render of the original. Sizes: bytes per splat of the full-detail data in GPU
memory and on disk, and the compression ratio against the input file. Everything needed to reproduce the
numbers (cameras, renderer, formats, options) goes into the JSON.
"""
from __future__ import annotations

import math
import os
import platform
import shutil
import subprocess
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from . import __version__
from .axes import RDF_TO_RUB, turn, turned_against
from .camera import Camera, scene_orbit_views
from .encode import EncodeOptions, encode_gaussians
from .encode.options import no_progress
from .encode.plan import plan_tiles
from .errors import InputError, UsageError
from .format.presets import ATTRIBUTES, PRESETS, resolve_formats
from .gaussians import Gaussians
from .io import read_gaussians, scene_up, sniff_format
from .metrics import psnr_from_mse, ssim
from .ply import InfiniteOpacityWarning
from .progress import count
from .readers.sog import finest_level_units, sog_kind
from .render_ref import render
from .scene_decode import decode_scene
from .sh import warn_sh_degree_above
from .vq import parse_entries

Renderer = Callable[[Gaussians | str, Camera], np.ndarray]

LOSSLESS_FORMAT = "f32x4"
PRESET_ORDER = tuple(PRESETS)  # largest files first

# The seed's published table (Aras P., "Making Gaussian Splats smaller", 2023; bike scene, SH3, 248-byte PLY).
# bytes_sh3 = 248 / Compr. `texels` are the seed's formats; their sizes give a seed-equivalent at other SH degrees.
SEED = {
    "very-high": {"compr": 0.8, "psnr": None, "formats": ("F32x4", "F32x4", "F32x4", "F32x4", "F32x4")},
    "high": {"compr": 2.9, "psnr": 54.82, "formats": ("F16x4", "Norm10_2", "Norm11", "F16x4", "Norm11")},
    "medium": {"compr": 5.2, "psnr": 47.82, "formats": ("Norm11", "Norm10_2", "Norm11", "Norm8x4", "Norm565")},
    "low": {"compr": 12.2, "psnr": 34.79, "formats": ("Norm11", "Norm10_2", "Norm565", "BC7", "BC1")},
    "very-low": {"compr": 18.7, "psnr": 24.02, "formats": ("BC7", "BC7", "BC7", "BC7", "BC1")},
}
SEED_TEXEL_BYTES = {"F32x4": 16.0, "F16x4": 8.0, "Norm10_2": 4.0, "Norm11": 4.0, "Norm8x4": 4.0, "Norm565": 2.0,
                    "BC7": 1.0, "BC1": 0.5}


def seed_bytes_per_splat(preset: str, sh_degree: int) -> float:
    """The seed's bytes per splat for a scene of `sh_degree`: its SH3 figure minus the SH texels it would not need."""
    s = SEED[preset]
    full = 248.0 / s["compr"]
    sh_fmt = s["formats"][4]
    sh_texel = SEED_TEXEL_BYTES[sh_fmt]
    coeffs = {0: 0, 1: 3, 2: 8, 3: 15}[sh_degree]
    return full - (15 - coeffs) * sh_texel


# --- renderers --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class EvalRenderer:
    """What evaluate() renders with: handed in by the caller (the CLI picks the GL client or the reference).

    `render(source, camera)` -> (H, W, 3) float32; `source` is Gaussians or, when `draws_scenes`, an encoded scene
    directory (drawn from its own textures, as the client does); otherwise encoded scenes are decoded first."""

    render: Renderer
    name: str
    kind: str  # "gl" or "ref"
    draws_scenes: bool = False


def reference_renderer() -> EvalRenderer:
    return EvalRenderer(lambda src, cam: render(src, cam), "numpy reference (splatstream.render_ref)", "ref")


# --- evaluation ---------------------------------------------------------------------------------------------------

@dataclass
class EvalOptions:
    presets: Sequence[str] = PRESET_ORDER
    views: int = 8
    width: int = 512
    height: int = 512
    up: tuple[float, float, float] | None = None  # None: detected (splatstream.orientation)
    elevation_deg: float = 25.0
    encoded_dir: str | None = None     # keep encoded scenes here (default: a temporary directory)
    compare: Sequence[str] = ()        # other tools' outputs: "[LABEL=]FILE[@SIZE_FILE_OR_DIR]"
    lod: bool = False                  # encode the LOD tree too (its bytes then count on disk)
    # Further EncodeOptions fields every encode takes (the LOD tree's shape, transport, chunk order, pages), so a
    # caller that will encode with them measures the bytes it will write: `encode --target-size` passes its own.
    encode_options: dict = field(default_factory=dict)
    attribution: Sequence[str] = ()    # presets whose error is attributed to attributes
    variants: Sequence[str] = ()       # extra encodes: "NAME:PRESET[,ATTRIBUTE=FORMAT...][,sh_degree=D]"
    zstd_level: int | None = None
    # SPZ compares: "rub" read as the format says (Niantic's reference; splat-transform 2.x), "rdf" as stored without
    # the axis turn (splat-transform 3.x), "auto" as whichever matches the input; a turned one is warned about.
    spz_axes: str = "rub"
    drop_invalid: bool = False  # the input's invalid splats dropped (a warning), not refused (io.read_gaussians)
    extra: dict = field(default_factory=dict)


@dataclass
class Row:
    label: str
    kind: str                           # "preset", "variant", "attribution" or "compare"
    formats: dict[str, str]
    splats: int
    gpu_bytes_per_splat: float | None
    disk_bytes: int
    disk_bytes_per_splat: float
    compression: float
    psnr: list[float]
    ssim: list[float]
    encode_seconds: float | None = None
    info: dict = field(default_factory=dict)

    @property
    def psnr_mean(self) -> float:
        """PSNR of the mean MSE over the views (so one identical view does not make it infinite)."""
        mses = [10 ** (-p / 10) if math.isfinite(p) else 0.0 for p in self.psnr]
        return psnr_from_mse(float(np.mean(mses)))

    @property
    def psnr_worst(self) -> float:
        return min(self.psnr)

    @property
    def ssim_mean(self) -> float:
        return float(np.mean(self.ssim))

    @property
    def ssim_worst(self) -> float:
        return min(self.ssim)

    def to_json(self) -> dict:
        def num(v):
            return None if v is None or not math.isfinite(v) else round(float(v), 6)

        return {
            "label": self.label, "kind": self.kind, "formats": self.formats, "splats": self.splats,
            "gpu_bytes_per_splat": num(self.gpu_bytes_per_splat), "disk_bytes": self.disk_bytes,
            "disk_bytes_per_splat": num(self.disk_bytes_per_splat), "compression": num(self.compression),
            "psnr_mean": num(self.psnr_mean), "psnr_worst": num(self.psnr_worst),
            "ssim_mean": num(self.ssim_mean), "ssim_worst": num(self.ssim_worst),
            "psnr_per_view": [num(p) for p in self.psnr], "ssim_per_view": [num(s) for s in self.ssim],
            "identical_views": sum(1 for p in self.psnr if not math.isfinite(p)),
            "encode_seconds": num(self.encode_seconds), **self.info,
        }


def parse_variant(spec: str) -> tuple[str, str, dict[str, str], int | None, str | None]:
    """"NAME:PRESET[,ATTRIBUTE=FORMAT...][,sh_degree=D][,sh_codebook=off|auto|N]"
    -> (name, preset, overrides, sh_degree, sh_codebook)."""
    name, sep, rest = spec.partition(":")
    parts = [p.strip() for p in rest.split(",") if p.strip()]
    if not sep or not name or not parts:
        raise UsageError(f"variant {spec!r}: expected NAME:PRESET[,ATTRIBUTE=FORMAT...][,sh_degree=D]")
    preset, overrides, sh_degree, sh_codebook = parts[0], {}, None, None
    for kv in parts[1:]:
        key, eq, value = kv.partition("=")
        if not eq:
            raise UsageError(f"variant {spec!r}: {kv!r} is not KEY=VALUE")
        if key == "sh_degree":
            if value not in ("0", "1", "2", "3"):
                raise UsageError(f"variant {spec!r}: sh_degree must be 0..3")
            sh_degree = int(value)
        elif key == "sh_codebook":
            parse_entries(value, 1)
            sh_codebook = value
        elif key in ATTRIBUTES:
            overrides[key] = value
        else:
            raise UsageError(f"variant {spec!r}: unknown key {key!r} (attributes: {', '.join(ATTRIBUTES)}; "
                             "sh_degree; sh_codebook)")
    resolve_formats(preset, overrides)
    return name, preset, overrides, sh_degree, sh_codebook


def path_size(path: str) -> int:
    """Bytes on disk of a splat input as eval reads it: a file's size; a directory's files; an unbundled SOG's
    meta.json with its directory (the WebP planes beside it); a streamed SOG's lod-meta.json (or its directory)
    with the units of its finest level, which eval reads: playbot's lod-meta.json alone is 1,040 bytes, and eval
    reported 0.0 B/splat and a compression of 0.0x against it."""
    if sog_kind(path) == "lod":
        lod_meta, units = finest_level_units(path)
        root = os.path.dirname(os.path.abspath(lod_meta))
        return os.path.getsize(lod_meta) + sum(_tree_bytes(os.path.join(root, u)) if u else 0 for u in units)
    if os.path.basename(path).lower() == "meta.json" and os.path.isfile(path):
        return _tree_bytes(os.path.dirname(os.path.abspath(path)))
    if os.path.isdir(path):
        return _tree_bytes(path)
    return os.path.getsize(path)


def _tree_bytes(directory: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(directory) for f in files)


def parse_compare(spec: str) -> tuple[str, str, str]:
    """"[LABEL=]FILE[@SIZE_PATH]" -> (label, file to read, path whose size counts)."""
    label = None
    if "=" in spec and not os.path.exists(spec):
        label, spec = spec.split("=", 1)
    size_path = None
    if "@" in spec and not os.path.exists(spec):
        spec, size_path = spec.rsplit("@", 1)
    if not os.path.exists(spec):
        raise InputError(spec, None, "no such file to compare")
    if size_path is not None and not os.path.exists(size_path):
        raise InputError(size_path, None, "no such file (size of the compared encoding)")
    name = os.path.basename(size_path or spec)
    return label or name, spec, size_path or spec


def read_compare(path: str) -> tuple[Gaussians, int]:
    """Read another tool's output; returns (Gaussians, number of opacity logits that were +-inf and got clamped).

    Tools that store opacity in 8 bits decode 0 and 255 to logits of -inf and +inf; a renderer reads them as opacity
    0 and 1, and so does our PLY reader (it clamps them to the finite logit +-13.8 and warns with the count).
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InfiniteOpacityWarning)
        g = read_gaussians(path)
    clamped = 0
    for w in caught:
        if isinstance(w.message, InfiniteOpacityWarning):
            clamped += w.message.count
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return g, clamped


def _spz_axes(other: Gaussians, g: Gaussians, path: str, axes: str) -> tuple[Gaussians, bool]:
    """An SPZ compare as `axes` says (EvalOptions.spz_axes); (Gaussians, whether they were turned back). A file
    that reads turned 180 degrees about x against the input (written without SPZ's RUB axis turn) is warned
    about unless it is turned back."""
    if sniff_format(path) != "spz":
        return other, False
    if axes == "rdf":
        return turn(other, RDF_TO_RUB), True
    if not turned_against(other, g, RDF_TO_RUB):
        return other, False
    if axes == "auto":
        warnings.warn(f"{path}: this SPZ reads turned 180 degrees about x against the input (it was written without "
                      "SPZ's RUB axis turn, as splat-transform 3.x writes SPZ); measured turned back (--spz-axes auto)",
                      stacklevel=2)
        return turn(other, RDF_TO_RUB), True
    warnings.warn(f"{path}: this SPZ reads turned 180 degrees about x against the input (it was written without SPZ's "
                  "RUB axis turn, as splat-transform 3.x writes SPZ), so its PSNR is that of a turned scene; "
                  "--spz-axes auto (or rdf) measures it turned back", stacklevel=2)
    return other, False


def _quality(renderer: Renderer, g: Gaussians | str, cameras: list[Camera],
             references: list[np.ndarray]) -> tuple[list[float], list[float], list[np.ndarray]]:
    ps, ss, imgs = [], [], []
    for cam, ref in zip(cameras, references, strict=True):
        img = renderer(g, cam)
        a = np.clip(img.astype(np.float64), 0, 1)
        b = np.clip(ref.astype(np.float64), 0, 1)
        ps.append(psnr_from_mse(float(np.mean((a - b) ** 2))))
        ss.append(ssim(a, b))
        imgs.append(img)
    return ps, ss, imgs


def evaluate(input_path: str, opts: EvalOptions | None = None, log: Callable[[str], None] | None = None,
             renderer: EvalRenderer | None = None) -> dict:
    """Run the evaluation; returns the JSON-ready report (see `report_markdown`, `plot_rate_distortion`).

    `renderer`: what draws the views (default: the numpy reference renderer)."""
    opts = opts or EvalOptions()
    log = log or (lambda msg: None)
    compares, variants = _checked_runs(opts)
    input_path = os.fspath(input_path)
    t = time.perf_counter()
    g = read_gaussians(input_path, drop_invalid=opts.drop_invalid)
    input_size = path_size(input_path)
    log(f"read {input_path}: {count(len(g), 'splat')}, SH degree {g.sh_degree} ({time.perf_counter() - t:.1f} s)")
    if len(g) == 0:
        raise InputError(input_path, None, "the scene holds no splats")
    for name, _, _, sh_degree, sh_codebook in variants:
        # refused by the encode (encode.codebook.check_codebook_option) after the presets' runs, naming --sh-codebook,
        # which eval has not: said at once, naming the variant (newuser62)
        warn_sh_degree_above(sh_degree, g.sh_degree, input_path, f"variant {name!r}: sh_degree={sh_degree}")
        kept = g.sh_degree if sh_degree is None else min(sh_degree, g.sh_degree)
        if sh_codebook not in (None, "off", "0") and kept < 1:
            raise UsageError(f"variant {name!r}: sh_codebook={sh_codebook} needs SH bands 1..3, and {input_path} keeps "
                             f"none (SH degree {g.sh_degree}" + (f", sh_degree={sh_degree}" if sh_degree is not None
                                                                 else "") + "); leave sh_codebook out")
    evr = renderer or reference_renderer()
    renderer, renderer_name, renderer_kind = evr.render, evr.name, evr.kind
    up = opts.up if opts.up is not None else scene_up(input_path, g).up
    cameras = scene_orbit_views(g.positions, opts.views, opts.width, opts.height, up=up,
                                elevation_deg=opts.elevation_deg)
    t = time.perf_counter()
    references = [renderer(g, cam) for cam in cameras]
    render_s = (time.perf_counter() - t) / len(cameras)
    log(f"rendered {count(len(cameras), 'reference view')} at {opts.width}x{opts.height} with {renderer_name} "
        f"({render_s:.2f} s per view)")
    coverage = float(np.mean([np.mean(r.max(axis=2) > 1e-3) for r in references]))

    tmp = None
    out_root = opts.encoded_dir
    if out_root is None:
        tmp = tempfile.mkdtemp(prefix="splatstream-eval-")
        out_root = tmp
    rows: list[Row] = []
    # Every row's label padded to the longest of this run's, so the numbers stand in columns (`encode --target-*`
    # printed them ragged where it stripped eval's fixed 28-character padding: newuser63)
    label_width = max([len(name) for name in opts.presets] + [len(v[0]) for v in variants]
                      + [len(c[0]) for c in compares]
                      + [len(a[0]) for preset in opts.attribution for a in _attribution_runs(preset, g.sh_degree)]
                      + [1])
    # The LOD tree depends on the splats and the LOD options only, not on the formats: built once, every encode
    # takes it (the same scenes to the byte as each building its own; the donut's tree is 0.3 CPU s with the grid
    # merge, 1.3 s with auto, saved for every preset but one: BENCHMARKS.md, "encode --target-size").
    tree, tree_s = None, None
    if opts.lod:
        t = time.perf_counter()
        tree = plan_tiles(g, EncodeOptions(lod=True, **opts.encode_options), no_progress)
        tree_s = time.perf_counter() - t
        log(f"built the LOD tree every encode takes: {count(len(tree), 'tile')} ({tree_s:.2f} s)")
    try:
        def encode_and_measure(label: str, kind: str, preset: str, overrides: dict[str, str],
                               sh_degree: int | None = None, sh_codebook: str | None = None) -> Row:
            out = os.path.join(out_root, label.replace(" ", "_").replace("=", "-").replace("+", "_"))
            eo = EncodeOptions(preset=preset, overrides=overrides, lod=opts.lod, up=tuple(up),
                               sh_degree=sh_degree, sh_codebook=sh_codebook, **opts.encode_options)
            if opts.zstd_level is not None:
                eo.zstd_level = opts.zstd_level
            t0 = time.perf_counter()
            m = encode_gaussians(g, out, eo, source_name=input_path, tiles=tree)
            enc_s = time.perf_counter() - t0
            # GL draws the encoded textures themselves (what the client shows); the reference renders the decode
            source = out if evr.draws_scenes else decode_scene(out)
            ps, ss, _ = _quality(renderer, source, cameras, references)
            disk = m.bytes_on_disk
            leaf = m.leaf_bytes_on_disk
            disk_counted = disk  # every file, the manifest included (with --lod: the coarse levels too)
            row = Row(label, kind, dict(m.formats), len(g), m.gpu_bytes_per_splat, disk_counted,
                      disk_counted / len(g), input_size / disk_counted, ps, ss, enc_s,
                      {"preset": preset, "overrides": overrides, "sh_degree": m.sh_degree,
                       "sh_codebook_entries": m.sh_codebook.entries if m.sh_codebook else None,
                       "bytes_on_disk_total": disk,
                       "leaf_bytes_on_disk": leaf, "gpu_bytes": m.gpu_bytes,
                       "attributes": {a: s.to_dict() for a, s in m.attributes.items()},
                       "encoded_dir": out if tmp is None else None})
            log(f"{label:>{label_width}}: {row.disk_bytes_per_splat:7.2f} B/splat disk, "
                f"{row.gpu_bytes_per_splat:7.2f} GPU, PSNR {row.psnr_mean:6.2f} dB (worst {row.psnr_worst:6.2f}), "
                f"SSIM {row.ssim_mean:.5f}, encode {enc_s:.2f} s")
            return row

        for preset in opts.presets:
            rows.append(encode_and_measure(preset, "preset", preset, {}))
        for name, preset, overrides, sh_degree, sh_codebook in variants:
            rows.append(encode_and_measure(name, "variant", preset, overrides, sh_degree, sh_codebook))
        for preset in opts.attribution:
            for label, overrides, sh_codebook in _attribution_runs(preset, g.sh_degree):
                rows.append(encode_and_measure(label, "attribution", preset, overrides, sh_codebook=sh_codebook))
        for label, path, size_path in compares:
            rows.append(_compare_row(label, path, size_path, g, input_size, opts.spz_axes, renderer, cameras,
                                     references, log, label_width))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)

    report = _report(input_path, input_size, g, opts, up, cameras, renderer_name, renderer_kind, render_s, coverage,
                     rows)
    if tree_s is not None:  # the rows' encode seconds leave out the tree they share
        report["lod_tree_seconds"] = round(tree_s, 4)
    return report


MAX_EVAL_VIEWS = 1024


def _checked_runs(opts: EvalOptions) -> tuple[list, list]:
    """The --compare and --variant runs of `opts`, parsed; every option checked (presets, views, size, the compared
    files readable) before any work, so a mistake fails at once, not after the long preset runs."""
    for p in list(opts.presets) + list(opts.attribution):
        resolve_formats(p, {})  # UsageError for unknown presets
    if opts.views < 1:
        raise UsageError("--views must be at least 1")
    # Each view renders the original and every encoded version: a slip like 8000 for 8 would run for days.
    if opts.views > MAX_EVAL_VIEWS:
        raise UsageError(f"--views must be at most {MAX_EVAL_VIEWS} (each view renders the original and every "
                         f"preset; got {opts.views})")
    if opts.width < 11 or opts.height < 11:
        raise UsageError("--size must be at least 11x11 (the SSIM window)")
    compares = [parse_compare(c) for c in opts.compare]
    variants = [parse_variant(v) for v in opts.variants]
    for _, path, _ in compares:
        read_compare(path)
    return compares, variants


def _attribution_runs(preset: str, sh_degree: int) -> list[tuple[str, dict[str, str], str | None]]:
    """(label, overrides, sh_codebook) of a preset's attribution rows: each lossy attribute made lossless alone,
    then each lossy attribute kept alone with the others lossless (SH skipped for SH0 scenes)."""
    formats = PRESETS[preset]
    lossy = [a for a, fmt in formats.items() if fmt != LOSSLESS_FORMAT and not (a == "sh" and sh_degree == 0)]
    # Lossless SH means no codebook either.
    runs = [(f"{preset} {a}={LOSSLESS_FORMAT}", {a: LOSSLESS_FORMAT}, "off" if a == "sh" else None) for a in lossy]
    runs += [(f"{preset} only {a}", {b: LOSSLESS_FORMAT for b in formats if b != a}, None) for a in lossy]
    return runs


def _compare_row(label: str, path: str, size_path: str, g: Gaussians, input_size: int, spz_axes: str,
                 renderer: Renderer, cameras: list[Camera], references: list[np.ndarray],
                 log: Callable[[str], None], label_width: int = 28) -> Row:
    """The row of another tool's output (--compare): read, turned back if its SPZ axes differ, measured; its label
    padded to `label_width` as the encodes' rows are."""
    other, clamped = read_compare(path)
    if len(other) != len(g):
        # `--compare other=guitar.spz` on the logo (another scene by mistake) gave 11.7 dB and 15.44 B/splat without
        # a word; a decimating tool's output is fine, but its bytes per splat are per its own splats.
        log(f"{label}: {count(len(other), 'splat')}, the input {len(g):,}: another scene, or a decimated one? (its "
            f"B/splat is per its own splats)")
    if clamped:
        log(f"{label}: {clamped} opacity logits of +-inf (8-bit opacity 0 or 1) read as +-13.8")
    other, spz_turned = _spz_axes(other, g, path, spz_axes)
    ps, ss, _ = _quality(renderer, other, cameras, references)
    size = path_size(size_path)
    row = Row(label, "compare", {}, len(other), None, size, size / max(1, len(other)), input_size / size,
              ps, ss, None, {"file": path, "size_of": size_path, "opacity_logits_clamped": clamped,
                             "spz_turned_back": spz_turned})
    log(f"{label:>{label_width}}: {row.disk_bytes_per_splat:7.2f} B/splat disk, PSNR {row.psnr_mean:6.2f} dB "
        f"(worst {row.psnr_worst:6.2f}), SSIM {row.ssim_mean:.5f}")
    return row


def _report(input_path: str, input_size: int, g: Gaussians, opts: EvalOptions, up, cameras: list[Camera],
            renderer_name: str, renderer_kind: str, render_s: float, coverage: float, rows: list[Row]) -> dict:
    """The JSON-ready report of an evaluation."""
    return {
        "tool": f"splatstream {__version__} eval",
        "source": source_version(),
        "input": {"path": input_path, "bytes": input_size, "splats": len(g), "sh_degree": g.sh_degree,
                  "bytes_per_splat": input_size / len(g)},
        "renderer": renderer_name,
        "renderer_note": ("GL: originals and --compare inputs are uploaded as very-high (f32x4) textures, encoded "
                          "scenes are drawn from their own textures" if renderer_kind == "gl" else
                          "numpy reference of the 3DGS forward pass (format_spec/camera.md); encoded scenes decoded "
                          "with splatstream.scene_decode"),
        "render_seconds_per_view": round(render_s, 4),
        "reference_coverage": round(coverage, 4),
        "size": [opts.width, opts.height],
        "metrics": {"psnr": "10 log10(1 / MSE) over RGB clamped to [0, 1]; 'mean' is the PSNR of the mean MSE over "
                            "views, 'worst' the lowest view",
                    "ssim": "Wang et al. 2004, 11x11 Gaussian window sigma 1.5, valid region, per RGB channel, "
                            "averaged; 'mean' over views"},
        "sizes": {"disk": "full-detail payloads + manifest" + (" + LOD levels" if opts.lod else
                                                                " (encoded without LOD levels)"),
                  "gpu": "bytes of the full-detail textures per splat (manifest gpu_bytes_per_splat)",
                  "compression": "input file bytes / disk bytes"},
        "cameras": [c.to_dict() for c in cameras],
        "camera_rule": {"function": "splatstream.camera.scene_orbit_views", "views": opts.views,
                        "up": list(up), "elevation_deg": opts.elevation_deg},
        "encode_options": {"lod": opts.lod, "zstd_level": opts.zstd_level, **opts.encode_options},
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
        "rows": [r.to_json() for r in rows],
        "reference_table": {
            "source": "Aras P., 'Making Gaussian Splats smaller' (2023): published presets of a Unity splat renderer, "
                      "bike scene, SH3, scaled to this scene's SH degree; a reference, not a measurement of this scene",
            "presets": {p: {"bytes_per_splat": round(seed_bytes_per_splat(p, g.sh_degree), 2),
                            "psnr": SEED[p]["psnr"], "formats": SEED[p]["formats"]} for p in SEED}},
    }


def preset_for_target(rows: Sequence[dict], target_psnr: float | None = None,
                      target_bytes: float | None = None) -> dict:
    """The preset row (a report's "rows" entry of kind "preset") a quality or size target picks.

    target_psnr: the smallest files (disk bytes per splat) among the presets whose mean PSNR is at least the target;
    target_bytes: the highest mean PSNR among those of at most that many bytes per splat (ties: the smaller files).
    An identical render (PSNR None in the JSON: infinite) meets every PSNR target. Raises UsageError when no preset
    meets the target, naming the closest one."""
    if (target_psnr is None) == (target_bytes is None):
        raise UsageError("give one target: a PSNR in dB or a size in bytes per splat")
    presets = [r for r in rows if r.get("kind") == "preset"]
    if not presets:
        raise UsageError("no preset was measured")

    def db(r: dict) -> float:
        return math.inf if r.get("psnr_mean") is None else float(r["psnr_mean"])

    if target_psnr is not None:
        meet = [r for r in presets if db(r) >= target_psnr]
        if not meet:
            best = max(presets, key=db)
            raise UsageError(f"--target-psnr {target_psnr:g}: no preset reaches it on this scene (the highest: "
                             f"{best['label']} at {db(best):.2f} dB)")
        return min(meet, key=lambda r: (r["disk_bytes_per_splat"], -db(r)))
    meet = [r for r in presets if r["disk_bytes_per_splat"] <= target_bytes]
    if not meet:
        small = min(presets, key=lambda r: r["disk_bytes_per_splat"])
        raise UsageError(f"--target-size {target_bytes:g}: no preset is that small on this scene (the smallest: "
                         f"{small['label']} at {small['disk_bytes_per_splat']:.2f} B/splat)")
    return max(meet, key=lambda r: (db(r), -r["disk_bytes_per_splat"]))


def source_version() -> dict:
    """Commit of the splatstream checkout (and whether it has local changes), so numbers can be tied to code."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "splatstream"],
                               cwd=root, capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"version": __version__}
    return {"version": __version__, "commit": commit, "local_changes": bool(dirty)}


# --- output -------------------------------------------------------------------------------------------------------

def _fmt_psnr(v: float | None) -> str:
    return "inf" if v is None or not math.isfinite(v) else f"{v:.2f}"


def report_markdown(report: dict, reference_table: bool = False) -> str:
    """The table of every row (and, on request, the published reference table for comparison)."""
    inp = report["input"]
    shown = os.path.basename(os.path.abspath(inp["path"]))
    if shown.lower() in ("lod-meta.json", "meta.json"):  # the format's name: its directory says which scene
        shown = f"{os.path.basename(os.path.dirname(os.path.abspath(inp['path'])))}/{shown}"
    lines = [f"Scene `{shown}`: {count(inp['splats'], 'splat')}, SH{inp['sh_degree']}, "
             f"{inp['bytes']:,} bytes ({inp['bytes_per_splat']:.1f} B/splat). "
             f"{count(len(report['cameras']), 'view')} at {report['size'][0]}x{report['size'][1]}, "
             f"renderer: {report['renderer']}. PSNR/SSIM: mean over views "
             f"(worst view in brackets). splatstream {report.get('source', {}).get('commit', '')[:10]}"
             + (" with local changes" if report.get("source", {}).get("local_changes") else "") + ".", "",
             "| Quality | Pos | Rot | Scl | Col | SH | bytes/splat GPU | disk | Compr | PSNR | SSIM | encode s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        f = r["formats"]
        cells = [f.get(a, "-") for a in ("position", "rotation", "scale", "color", "sh")]
        if inp["sh_degree"] == 0 and r["kind"] != "compare":
            cells[4] = "(none)"
        else:
            if r.get("sh_codebook_entries"):
                cells[4] = f"{cells[4]} VQ{r['sh_codebook_entries']}"
            if r.get("sh_degree") is not None and r["sh_degree"] < inp["sh_degree"]:
                cells[4] = f"{cells[4]} (SH{r['sh_degree']})"
        gpu = "-" if r["gpu_bytes_per_splat"] is None else f"{r['gpu_bytes_per_splat']:.2f}"
        enc = "-" if r["encode_seconds"] is None else f"{r['encode_seconds']:.2f}"
        psnr = f"{_fmt_psnr(r['psnr_mean'])} ({_fmt_psnr(r['psnr_worst'])})"
        ssim_s = f"{r['ssim_mean']:.4f} ({r['ssim_worst']:.4f})"
        lines.append(f"| {r['label']} | " + " | ".join(cells) + f" | {gpu} | {r['disk_bytes_per_splat']:.2f} | "
                     f"{r['compression']:.1f}x | {psnr} | {ssim_s} | {enc} |")
    lines += attribution_markdown(report)
    if reference_table:
        ref = report["reference_table"]
        lines += ["", f"Reference, not measured here: {ref['source']}.", "",
                  "| preset (reference) | bytes/splat | PSNR |", "|---|---|---|"]
        lines += [f"| {p} | {v['bytes_per_splat']:.1f} | {v['psnr'] if v['psnr'] else '-'} |"
                  for p, v in ref["presets"].items()]
    return "\n".join(lines) + "\n"


def attribution_markdown(report: dict) -> list[str]:
    """Per attribute of each attributed preset: its bytes, the PSNR with only it quantised (all else lossless), and
    the PSNR of the preset with it made lossless."""
    rows = {r["label"]: r for r in report["rows"]}
    splats = report["input"]["splats"]
    out: list[str] = []
    for preset in dict.fromkeys(r["preset"] for r in report["rows"] if r["kind"] == "attribution"):
        base = rows.get(preset)
        out += ["", f"Error attribution for {preset}"
                + (f" (preset: PSNR {_fmt_psnr(base['psnr_mean'])} dB, {base['disk_bytes_per_splat']:.2f} B/splat "
                   f"on disk)" if base else "") + ":", "",
                "| attribute | format | disk B/splat | GPU B/splat | PSNR, only this quantised | "
                "PSNR, this one lossless |", "|---|---|---|---|---|---|"]
        attrs = (base or {}).get("attributes", {})
        for attr in ("position", "rotation", "scale", "color", "sh"):
            only = rows.get(f"{preset} only {attr}")
            swap = rows.get(f"{preset} {attr}={LOSSLESS_FORMAT}")
            if only is None and swap is None:
                continue
            a = attrs.get(attr, {})
            disk = f"{a['disk_bytes'] / splats:.2f}" if "disk_bytes" in a else "-"
            gpu = f"{a['gpu_bytes'] / splats:.2f}" if "gpu_bytes" in a else "-"
            fmt = (only or swap)["formats"].get(attr, "-") if only else "-"
            out.append(f"| {attr} | {fmt} | {disk} | {gpu} | {_fmt_psnr(only['psnr_mean']) if only else '-'} | "
                       f"{_fmt_psnr(swap['psnr_mean']) if swap else '-'} |")
    return out


Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in pixels


def _overlap(a: Box, b: Box, pad: float = 2.0) -> float:
    """Area by which two boxes overlap (each grown by `pad`); 0 when apart."""
    w = min(a[2], b[2]) - max(a[0], b[0]) + 2 * pad
    h = min(a[3], b[3]) - max(a[1], b[1]) + 2 * pad
    return w * h if w > 0 and h > 0 else 0.0


def place_labels(anchors: list[tuple[float, float]], sizes: list[tuple[float, float]], bounds: Box,
                 obstacles: Sequence[Box] = (), apart: Sequence[bool] = ()) -> list[Box]:
    """Boxes for text labels beside points, none overlapping another label, a point (`obstacles`: the markers) or
    leaving `bounds`: greedy, each label in turn takes the nearest free place around its point (right and
    slightly above first, as a label usually sits), trying places further away until one is free. Where none is
    free within reach the least-overlapping place is taken. A label marked in `apart` (its point has close
    neighbours) is set at least 24 px away, so that the leader line the caller draws to it is unmistakable."""
    placed: list[Box] = []
    offsets = sorted(((dx, dy) for dx in (8, -8, 24, -24, 48, -48, 80, -80) for dy in range(-160, 161, 4)),
                     key=lambda o: (math.hypot(abs(o[0]) - 8, o[1] + 8), o[0] < 0))
    apart = list(apart) + [False] * (len(anchors) - len(apart))
    for (ax, ay), (w, h), away in zip(anchors, sizes, apart, strict=True):
        best, best_cost = None, math.inf
        for dx, dy in offsets:
            if away and abs(dx) < 24 and abs(dy) < 24 + h:
                continue
            x0 = ax + dx if dx > 0 else ax + dx - w
            y0 = ay + dy - h / 2
            box = (x0, y0, x0 + w, y0 + h)
            if box[0] < bounds[0] or box[1] < bounds[1] or box[2] > bounds[2] or box[3] > bounds[3]:
                continue
            cost = sum(_overlap(box, b) for b in placed) + sum(_overlap(box, o, 0.0) for o in obstacles)
            if cost == 0:
                best = box
                break
            if cost < best_cost:
                best, best_cost = box, cost
        if best is None:  # nothing inside the bounds at all: as a label usually sits
            best = (ax + 8, ay - 8 - h / 2, ax + 8 + w, ay - 8 + h / 2)
        placed.append(best)
    return placed


def _leader_end(anchor: tuple[float, float], box: Box) -> tuple[float, float]:
    """The point of `box` nearest to `anchor`."""
    return min(max(anchor[0], box[0]), box[2]), min(max(anchor[1], box[1]), box[3])


def plot_rate_distortion(report: dict, path: str, size: tuple[int, int] = (900, 600)) -> list[Box]:
    """PSNR (mean over views) against disk bytes per splat (log axis), drawn with Pillow. The labels of the points
    never overlap (place_labels; a grey leader line joins a label set apart to its point); returns their boxes."""
    from PIL import Image, ImageDraw, ImageFont

    rows = [r for r in report["rows"] if r["kind"] != "attribution"]  # those are diagnostics, not rate points
    w, h = size
    img = Image.new("RGB", (w, h), "white")
    d = ImageDraw.Draw(img)
    try:
        font = ImageFont.load_default(size=14)
    except TypeError:  # Pillow < 10.1
        font = ImageFont.load_default()
    left, right, top, bottom = 80, w - 210, 50, h - 70
    finite = [r["psnr_mean"] for r in rows if r["psnr_mean"] is not None]
    ymax_data = max(finite) if finite else 50.0
    ymin_data = min(finite) if finite else 20.0
    lossless_y = ymax_data + 5.0  # identical renders ("inf") are drawn on a line above the data
    y0 = 5.0 * math.floor(min(ymin_data, lossless_y) / 5.0 - 0.2)
    y1 = 5.0 * math.ceil(lossless_y / 5.0 + 0.2)
    xs = [r["disk_bytes_per_splat"] for r in rows if r["disk_bytes_per_splat"]]
    x0 = 10 ** math.floor(math.log10(min(xs)) if xs else 0)
    x1 = 10 ** math.ceil(math.log10(max(xs)) if xs else 3)

    def px(x: float) -> float:
        return left + (math.log10(x) - math.log10(x0)) / (math.log10(x1) - math.log10(x0)) * (right - left)

    def py(y: float) -> float:
        return bottom - (y - y0) / (y1 - y0) * (bottom - top)

    _plot_frame(d, font, (left, right, top, bottom), (x0, x1, y0, y1), px, py)
    if any(r["psnr_mean"] is None for r in rows):
        d.line([(left, py(lossless_y)), (right, py(lossless_y))], fill=(200, 200, 255))
        d.text((left + 4, py(lossless_y) - 18), "identical to the original (PSNR = inf)", fill=(120, 120, 200),
               font=font)
    d.rectangle([left, top, right, bottom], outline="black")
    d.text(((left + right) / 2 - 110, h - 30), "bytes per splat on disk (log scale)", fill="black", font=font)
    d.text((left - 70, top - 24), "PSNR (dB), mean over views", fill="black", font=font)  # under the title
    inp = report["input"]
    title = f"{os.path.basename(inp['path'])}: {count(inp['splats'], 'splat')}, SH{inp['sh_degree']}"
    d.text(((left + right) / 2 - d.textlength(title, font=font) / 2, 4), title, fill="black", font=font)

    ly = top
    markers: list[Box] = []
    marker_colours: list[tuple[int, int, int]] = []
    labels: list[tuple[tuple[float, float], str, tuple[int, int, int]]] = []
    for name, pts, colour, connect in _plot_series(rows):
        coords = [(px(r["disk_bytes_per_splat"]), py(r["psnr_mean"] if r["psnr_mean"] is not None else lossless_y))
                  for r in pts]
        if connect and len(coords) > 1:
            d.line([coords[i] for i in _frontier(coords)], fill=colour, width=2)
        for (cx, cy), r in zip(coords, pts, strict=True):
            d.ellipse([cx - 5, cy - 5, cx + 5, cy + 5], fill=colour, outline="black")
            markers.append((cx - 5, cy - 5, cx + 5, cy + 5))
            marker_colours.append(colour)
            if connect or r["kind"] == "variant":
                labels.append(((cx, cy), r["label"], (90, 90, 90) if r["kind"] == "variant" else colour))
        d.ellipse([right + 15, ly + 3, right + 25, ly + 13], fill=colour, outline="black")
        d.text((right + 32, ly), name[:24], fill="black", font=font)
        ly += 22
    boxes = _draw_labels(d, font, labels, markers, (left + 2, top + 2, right - 2, bottom - 2))
    for box, colour in zip(markers, marker_colours, strict=True):  # the points again, over the leader lines
        d.ellipse(list(box), fill=colour, outline="black")
    img.save(path)
    return boxes


def _plot_frame(d, font, area: tuple[float, float, float, float], limits: tuple[float, float, float, float],
                px: Callable[[float], float], py: Callable[[float], float]) -> None:
    """Grid, ticks and their labels (log x: 1, 2, 5 per decade; y every 5 or 10 dB)."""
    left, right, top, bottom = area
    x0, x1, y0, y1 = limits
    for dec in range(int(round(math.log10(x0))), int(round(math.log10(x1))) + 1):
        for m in (1, 2, 5):
            x = m * 10.0 ** dec
            if x0 <= x <= x1:
                xp = px(x)
                d.line([(xp, top), (xp, bottom)], fill=(225, 225, 225))
                d.line([(xp, bottom), (xp, bottom + 5)], fill="black")
                label = f"{x:g}"
                d.text((xp - d.textlength(label, font=font) / 2, bottom + 8), label, fill="black", font=font)
    step = 5.0 if y1 - y0 <= 60 else 10.0
    y = y0
    while y <= y1 + 1e-9:
        yp = py(y)
        d.line([(left, yp), (right, yp)], fill=(225, 225, 225))
        d.line([(left - 5, yp), (left, yp)], fill="black")
        label = f"{y:g}"
        d.text((left - 10 - d.textlength(label, font=font), yp - 8), label, fill="black", font=font)
        y += step


def _frontier(coords: list[tuple[float, float]]) -> list[int]:
    """The indices of the points on the rate-distortion frontier, smallest first: each point (x right with the
    bytes, y down with the PSNR, as drawn) that is higher than every point at or left of it. Why: joining the
    presets in their list order drew a zigzag (a codebook preset at 15 B/splat and 57 dB between two at 20 B and
    45 dB); the line is the best quality each size buys, the dominated presets stay dots."""
    order = sorted(range(len(coords)), key=lambda i: (coords[i][0], coords[i][1]))
    out: list[int] = []
    best = math.inf
    for i in order:
        if coords[i][1] < best:
            out.append(i)
            best = coords[i][1]
    return out


def _plot_series(rows: list[dict]) -> list[tuple[str, list[dict], tuple[int, int, int], bool]]:
    """(legend name, rows, colour, joined by a line) of each series: the presets, each compared file, the variants."""
    palette = [(220, 50, 47), (38, 139, 210), (133, 153, 0), (211, 54, 130), (181, 137, 0), (42, 161, 152),
               (108, 113, 196), (203, 75, 22)]
    series: list[tuple[str, list[dict], tuple[int, int, int], bool]] = []
    presets = [r for r in rows if r["kind"] == "preset"]
    if presets:
        series.append(("splatstream presets", presets, (0, 0, 0), True))
    for i, r in enumerate(r for r in rows if r["kind"] == "compare"):
        series.append((r["label"], [r], palette[i % len(palette)], False))
    variants = [r for r in rows if r["kind"] == "variant"]
    if variants:
        series.append(("splatstream variants", variants, (150, 150, 150), False))
    return series


def _draw_labels(d, font, labels: list[tuple[tuple[float, float], str, tuple[int, int, int]]], markers: list[Box],
                 area: Box) -> list[Box]:
    """Draw the point labels where place_labels puts them (a grey leader line to a label set apart from its point,
    or near other points); their boxes, in the order of `labels`."""
    # labels top to bottom, then left to right: the crowded corners are filled in a stable order
    order = sorted(range(len(labels)), key=lambda i: (labels[i][0][1], labels[i][0][0]))
    sizes = []
    for i in order:
        x0, y0, x1, y1 = d.textbbox((0, 0), labels[i][1], font=font)
        sizes.append((x1 - x0 + 2, y1 - y0 + 4))
    anchors = [labels[i][0] for i in order]
    crowded = [sum(math.dist(a, (m[0] + 5, m[1] + 5)) < 24 for m in markers) > 1 for a in anchors]
    boxes = place_labels(anchors, sizes, area, markers, crowded)
    for i, box, near in zip(order, boxes, crowded, strict=True):
        anchor, text, colour = labels[i]
        end = _leader_end(anchor, box)
        if near or math.dist(anchor, end) > 10:
            d.line([anchor, end], fill=(150, 150, 150), width=1)
        x0, y0, _, _ = d.textbbox((0, 0), text, font=font)
        d.text((box[0] + 1 - x0, box[1] + 2 - y0), text, fill=colour, font=font)
    return [boxes[order.index(i)] for i in range(len(labels))]


def cameras_from_report(report: dict) -> list[Camera]:
    """The evaluation cameras of a JSON report, to reproduce its renders."""
    return [Camera.from_dict(c) for c in report["cameras"]]
