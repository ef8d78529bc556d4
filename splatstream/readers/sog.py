"""PlayCanvas SOG version 2 (as written by splat-transform / SuperSplat) and version 1, bundled or not, and
streamed SOG.

A SOG scene is a `meta.json` plus lossless WebP "textures" (one texel per splat, in texel order):

* `means_l.webp`, `means_u.webp`: low and high byte of a 16-bit value per axis; position = inverse log
  transform (sign(v) (e^|v| - 1)) of lerp(means.mins, means.maxs, value / 65535).
* `quats.webp`: smallest three of the (w, x, y, z) quaternion scaled by sqrt(2), bytes b -> (b / 255 * 2 - 1)
  / sqrt(2), alpha = 252 + index of the largest component (reconstructed as sqrt(1 - sum of squares)).
* `scales.webp`: per axis an index into scales.codebook (log scales).
* `sh0.webp`: per channel an index into sh0.codebook (f_dc), alpha = sigmoid(opacity) * 255.
* `shN_labels.webp` (optional): 16-bit palette index (R low, G high); `shN_centroids.webp`: 64 palette entries
  per row, each entry K texels (K = 3, 8, 15 coefficients), texel RGB = indices into shN.codebook per channel.

SOG version 1 (deprecated; meta.json without `version`, still read by PlayCanvas's engine and splat-transform's
readSogV1): the same planes, but no codebooks: the count is `means.shape[0]`; scales (log) and sh0 are bytes b
lerped per channel between `mins` and `maxs` (lo + (hi - lo) b / 255), sh0's alpha lerped between mins[3] and
maxs[3] being the opacity *logit*; shN has scalar `mins`/`maxs` for every coefficient byte, no `count` or
`bands` (the centroids' width, 64 K texels, says K).

Bundled `.sog` = a zip holding meta.json and the WebP files. Streamed SOG = `lod-meta.json` naming SOG units
(directories with a meta.json) and a tree whose nodes reference row ranges of units per LOD level; level 0 is
the finest, and that is what we import (plus the optional environment unit).

Positions and rotations are stored in the PLY's axes (splat-transform bakes its PLY transform before writing),
so no axis change is needed. Everything is validated before it is trusted: names stay inside the scene,
every texture must be lossless WebP of a size that holds `count` texels and is bounded by `count`, codebook
indices and palette labels in range, and `count` itself within the memory budget.
"""
from __future__ import annotations

import io
import json
import math
import os
import struct
import warnings
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..gaussians import SH_REST_COEFFS, Gaussians, normalize_quaternions
from ..reader_support import memory_budget, opacity_logits_from_unit, read_regular_file

SOG_META_NAME = "meta.json"  # an unbundled SOG scene's (version 1 or 2) description, beside its WebP planes
MAX_JSON_BYTES = 64 << 20
ZIP_PIECE = 1 << 20  # zip members are inflated this much at a time
# Bytes of memory a decoded splat costs at peak (six RGBA textures plus the float32 model and temporaries).
BYTES_PER_SPLAT = 6 * 4 + 4 * (3 + 4 + 3 + 1 + 3 + 45) * 3
MAX_LOD_NODES = 1 << 20
MAX_LOD_DEPTH = 256  # the tree is read recursively; splat-transform's kd trees are about log2(leaves) deep
# The low bytes of positions are close to noise: lossless WebP keeps about 3 bytes a splat of them (6 bytes a splat
# for both position textures on the fixture). A count beyond 16 splats per byte of the two is not a real scene.
MAX_SPLATS_PER_MEANS_BYTE = 16
QUAT_ORDER = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))  # the three stored components per largest index


class _Source:
    """Named files of one SOG scene: a zip (bundled .sog) or a directory. Names may not leave the scene."""

    def __init__(self, path: str, label: str, read: Callable[[str, str, int], bytes]):
        self.path = path
        self.label = label
        self._read = read

    def read(self, name: object, field: str, max_bytes: int | None = None) -> bytes:
        """A member's bytes; InputError beyond `max_bytes` (default: the memory budget), checked as it is read."""
        if not isinstance(name, str) or not name or name.startswith(("/", "\\")) or ".." in name.replace(
                "\\", "/").split("/") or "\x00" in name:
            raise InputError(self.label, field, f"file name {name!r} is not a relative name inside the scene")
        return self._read(name, field, memory_budget() if max_bytes is None else min(max_bytes, memory_budget()))


def _starts_as_zip(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"PK\x03\x04"
    except OSError:
        return False


def _zip_source(path: str) -> _Source:
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        if _starts_as_zip(path):
            # a .sog cut short keeps its first members but loses the directory at the end, which zipfile reads
            # first: it said "File is not a zip file" of what is one, truncated
            raise InputError(path, "zip archive", "starts as a zip file but its central directory (at the end) "
                             f"is missing: truncated? ({exc})") from None
        raise InputError(path, "zip archive", f"not a readable zip file ({exc})") from None
    total = os.path.getsize(path)

    def read(name: str, field: str, max_bytes: int) -> bytes:
        try:
            info = archive.getinfo(name)
        except KeyError:
            raise InputError(path, field, f"the archive has no member {name!r}") from None
        # A stored member cannot be larger than the archive; a deflated one at most 1032 times its compressed
        # size. Either way it must fit what the caller allows for it (a JSON document: MAX_JSON_BYTES) and the
        # memory budget (zip bomb guard, checked before reading; the bytes are then read in bounded pieces, so a
        # member that inflates beyond its declared size is cut off there too).
        limit = min(max_bytes, max(total, 1032 * info.compress_size))
        if info.file_size > limit:
            raise InputError(path, field, f"member {name!r} declares {info.file_size} bytes (more than the "
                             f"{limit} its compressed size, its kind and the memory budget allow)")
        pieces, got = [], 0
        try:
            with archive.open(info) as f:
                while got <= info.file_size:
                    piece = f.read(min(ZIP_PIECE, info.file_size + 1 - got))
                    if not piece:
                        break
                    pieces.append(piece)
                    got += len(piece)
        except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
            raise InputError(path, field, f"member {name!r} is corrupt ({exc})") from None
        data = b"".join(pieces)
        if len(data) != info.file_size:
            raise InputError(path, field, f"member {name!r} holds {len(data)} bytes, its header says "
                             f"{info.file_size}")
        return data

    return _Source(path, path, read)


def _dir_source(directory: str, label: str) -> _Source:
    root = os.path.realpath(directory)

    def read(name: str, field: str, max_bytes: int) -> bytes:
        full = os.path.realpath(os.path.join(root, name))
        if os.path.commonpath([root, full]) != root:
            raise InputError(label, field, f"file name {name!r} leads outside the scene directory")
        if not os.path.lexists(full):
            raise InputError(label, field, f"names {name!r}, which does not exist in {directory}")
        return read_regular_file(full, max_bytes, label, field)

    return _Source(directory, label, read)


def _json(source: _Source, name: str, what: str, named_by: str | None = None) -> dict:
    """The JSON object of file `name` (a `what`); `named_by` is the field that names the file, which an error for
    a missing file names (default: `what`)."""
    data = source.read(name, named_by or what, MAX_JSON_BYTES)
    if len(data) > MAX_JSON_BYTES:
        raise InputError(source.label, name, f"{len(data)} bytes (a {what} is at most {MAX_JSON_BYTES})")
    try:
        value = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(source.label, name, f"not valid JSON ({exc})") from None
    if not isinstance(value, dict):
        raise InputError(source.label, name, f"a {what} must be a JSON object")
    return value


def _int(label: str, field: str, value: object, low: int = 0, high: int | None = None) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < low or (high is not None and value > high):
        bound = f" and at most {high}" if high is not None else ""
        raise InputError(label, field, f"{value!r} (expected an integer of at least {low}{bound})")
    return value


def _floats(label: str, field: str, value: object, length: int | None = None, max_length: int = 1 << 20) -> np.ndarray:
    ok = isinstance(value, list) and (length is None or len(value) == length) and 0 < len(value) <= max_length \
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    arr = np.asarray(value, np.float64) if ok else None
    if arr is None or not np.isfinite(arr).all():
        size = f"{length}" if length is not None else f"1 to {max_length}"
        raise InputError(label, field, f"expected a list of {size} finite numbers")
    return arr


def _files(label: str, field: str, section: dict, count: int) -> list[str]:
    files = section.get("files")
    if not isinstance(files, list) or len(files) != count or not all(isinstance(f, str) for f in files):
        raise InputError(label, f"{field}.files", f"{files!r} (expected a list of {count} file names)")
    return files


def webp_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of a lossless WebP (VP8L bitstream, simple or extended file), or None if it is lossy
    or not WebP; read from the headers without decoding."""
    if len(data) < 30 or data[:4] != b"RIFF" or data[8:12] != b"WEBP":
        return None
    offset = 12
    while offset + 8 <= len(data):
        fourcc = data[offset:offset + 4]
        size = struct.unpack_from("<I", data, offset + 4)[0]
        if fourcc == b"VP8L":
            if offset + 13 > len(data) or data[offset + 8] != 0x2F:
                return None
            bits = struct.unpack_from("<I", data, offset + 9)[0]
            return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
        if fourcc in (b"VP8 ", b"ALPH"):
            return None  # lossy: the values would not be the ones written
        offset += 8 + size + (size & 1)
    return None


def _texture(source: _Source, name: str, field: str, count: int, max_texels: int,
             width: int | None = None, data: bytes | None = None) -> np.ndarray:
    """Decode a lossless WebP into (texels, 4) uint8 after checking its size against what `count` implies."""
    from PIL import Image

    if data is None:  # a lossless WebP is never much larger than its texels stored raw (4 bytes each)
        data = source.read(name, field, 5 * max_texels + (1 << 16))
    size = webp_size(data)
    if size is None:
        raise InputError(source.label, f"{field} ({name})", "not a lossless WebP image (SOG textures must be "
                         "lossless: lossy WebP would change the stored indices)")
    w, h = size
    if w * h < count or w * h > max_texels or (width is not None and w != width):
        expect = f"width {width}, " if width is not None else ""
        raise InputError(source.label, f"{field} ({name})", f"{w}x{h} texels (expected {expect}at least {count} and "
                         f"at most {max_texels} texels)")
    try:
        with Image.open(io.BytesIO(data)) as img:
            img.load()
            rgba = np.asarray(img.convert("RGBA"))
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(source.label, f"{field} ({name})", f"corrupt WebP ({exc})") from None
    if rgba.shape[:2] != (h, w):
        raise InputError(source.label, f"{field} ({name})", f"decodes to {rgba.shape[1]}x{rgba.shape[0]}, its header "
                         f"says {w}x{h}")
    return rgba.reshape(-1, 4)


def _codebook_lookup(label: str, field: str, codebook: np.ndarray, indices: np.ndarray) -> np.ndarray:
    if len(indices) and int(indices.max()) >= len(codebook):
        raise InputError(label, field, f"texel index {int(indices.max())} is past the {len(codebook)}-entry codebook")
    with np.errstate(over="ignore"):  # beyond float32: reported by the value screen of io.read_gaussians
        return codebook[indices].astype(np.float32)


def _lerp_bytes(texels: np.ndarray, lo: np.ndarray | float, hi: np.ndarray | float) -> np.ndarray:
    """SOG version 1's dequantiser: lo + (hi - lo) * byte / 255, in float64 then float32 (as splat-transform's
    readSogV1 and the engine compute it, so the values are theirs to float rounding)."""
    with np.errstate(over="ignore"):  # beyond float32: reported by the value screen of io.read_gaussians
        return (lo + (np.asarray(hi, np.float64) - lo) * (texels.astype(np.float64) / 255.0)).astype(np.float32)


def _v1_count(label: str, meta: dict, high: int) -> int:
    """The splat count of a SOG version 1 meta.json (at most `high`): `means.shape[0]` (what the engine and
    splat-transform read); every other section's `shape`, where given, must say the same count."""
    shape = meta["means"].get("shape")
    if not isinstance(shape, list) or not shape:
        got = "missing" if shape is None else repr(shape)
        raise InputError(label, "means.shape", f"{got} (a SOG version 1 meta.json gives the splat count as "
                         "means.shape [count, 3])")
    count = _int(label, "means.shape[0]", shape[0], 0, high)
    for key in ("scales", "quats", "sh0"):
        other = meta[key].get("shape")
        if other is not None and (not isinstance(other, list) or not other or other[0] != count):
            raise InputError(label, f"{key}.shape", f"{other!r} (expected [{count}, ...]: means.shape says "
                             f"{count} splats)")
    return count


V1_SH_BANDS_BY_WIDTH = {64 * k: bands for bands, k in enumerate(SH_REST_COEFFS) if k}  # 192, 512, 960


def _v1_sh_rest(source: _Source, label: str, shn: dict, name_of: Callable[[str], str], count: int,
                max_texels: int) -> np.ndarray:
    """SOG version 1's SH palette: no band count (the centroids' width says it: 64 entries a row, K texels each) and
    no palette size (every stored entry counts); texel bytes lerped between the scalar `shN.mins` and `shN.maxs`."""
    lo = float(_floats(label, "shN.mins", [shn.get("mins")], 1)[0])
    hi = float(_floats(label, "shN.maxs", [shn.get("maxs")], 1)[0])
    centroids_name, labels_name = _files(label, "shN", shn, 2)
    data = source.read(name_of(centroids_name), "shN.files[0]", 5 * 64 * 15 * 1024 + (1 << 16))
    size = webp_size(data)
    width = size[0] if size is not None else 0
    bands = V1_SH_BANDS_BY_WIDTH.get(width)
    if size is not None and bands is None:
        raise InputError(label, f"shN.files[0] ({centroids_name})", f"{width} texels wide (a version 1 palette is "
                         f"{', '.join(map(str, V1_SH_BANDS_BY_WIDTH))} wide, for SH bands 1, 2, 3)")
    k = SH_REST_COEFFS[bands or 1]
    centroids = _texture(source, name_of(centroids_name), "shN.files[0]", 0, 64 * k * 1024, width=64 * k,
                         data=data)
    labels = _texture(source, name_of(labels_name), "shN.files[1]", count, max_texels)[:count]
    index = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
    stored_entries = len(centroids) // k
    if len(index) and int(index.max()) >= stored_entries:
        raise InputError(label, "shN.files[1]", f"palette label {int(index.max())} is past the palette "
                         f"({stored_entries} entries stored)")
    return _lerp_bytes(centroids[:, :3].reshape(-1, k, 3)[index], lo, hi)


def _read_unit(source: _Source, meta_name: str, named_by: str | None = None) -> Gaussians:
    """Decode one SOG scene (version 2, or the deprecated version 1) whose meta.json is `meta_name` inside `source`
    (named by the field `named_by`: a unit of a streamed SOG missing is lod-meta.json's fault, not its own
    meta.json's)."""
    label = source.label if meta_name == "meta.json" else f"{source.label}/{meta_name}"
    meta = _json(source, meta_name, "SOG meta.json", named_by)
    base = os.path.dirname(meta_name)

    def name_of(file: str) -> str:
        return f"{base}/{file}" if base else file

    version = meta.get("version")
    if version is not None and version != 2:
        raise InputError(label, "version", f"{version!r} (expected 2, or none: version 1)")
    v1 = version is None  # the deprecated layout: per-channel mins/maxs instead of codebooks (module docstring)
    for key in ("means", "scales", "quats", "sh0"):
        if not isinstance(meta.get(key), dict):
            raise InputError(label, key, "missing or not an object")
    most = max(0, memory_budget() // BYTES_PER_SPLAT)
    count = _v1_count(label, meta, most) if v1 else _int(label, "count", meta.get("count"), 0, most)
    model = meta.get("model", "default")
    if model != "default":
        warnings.warn(f"{label}: splat model {model!r} (trained with a special kernel) is read as ordinary "
                      "Gaussians", stacklevel=4)
    means = meta["means"]
    mins = _floats(label, "means.mins", means.get("mins"), 3)
    maxs = _floats(label, "means.maxs", means.get("maxs"), 3)
    if v1:
        quats_encoding = meta["quats"].get("encoding", "quaternion_packed")
        if quats_encoding != "quaternion_packed":
            raise InputError(label, "quats.encoding", f"{quats_encoding!r} (expected 'quaternion_packed')")
        scale_lo = _floats(label, "scales.mins", meta["scales"].get("mins"), 3)
        scale_hi = _floats(label, "scales.maxs", meta["scales"].get("maxs"), 3)
        color_lo = _floats(label, "sh0.mins", meta["sh0"].get("mins"), 4)
        color_hi = _floats(label, "sh0.maxs", meta["sh0"].get("maxs"), 4)
    else:
        scale_book = _floats(label, "scales.codebook", meta["scales"].get("codebook"), max_length=256)
        color_book = _floats(label, "sh0.codebook", meta["sh0"].get("codebook"), max_length=256)
    # The writer lays texels out on a width of ceil(sqrt(count) / 4) * 4 and pads the height to a multiple of 4;
    # twice the count plus slack is a generous ceiling that still bounds the decoded size by `count`.
    max_texels = 2 * count + 4096
    lo_name, hi_name = _files(label, "means", means, 2)
    lo_data, hi_data = source.read(name_of(lo_name), "means.files[0]"), source.read(name_of(hi_name), "means.files[1]")
    plausible = MAX_SPLATS_PER_MEANS_BYTE * (len(lo_data) + len(hi_data)) + 4096
    if count > plausible:
        raise InputError(label, "count", f"{count} splats, but the two position textures hold only "
                         f"{len(lo_data) + len(hi_data)} bytes (at most {plausible} splats: positions of real "
                         "scenes never compress that far; a corrupt count or a decompression bomb)")
    lo = _texture(source, name_of(lo_name), "means.files[0]", count, max_texels, data=lo_data)[:count]
    hi = _texture(source, name_of(hi_name), "means.files[1]", count, max_texels, data=hi_data)[:count]
    del lo_data, hi_data
    value = (lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]) / 65535.0
    span = np.where(maxs - mins == 0, 1.0, maxs - mins)
    logged = mins + span * value
    with np.errstate(over="ignore"):  # beyond float32: reported by the value screen of io.read_gaussians
        positions = (np.sign(logged) * np.expm1(np.abs(logged))).astype(np.float32)
    del lo, hi, value, logged

    quats = _texture(source, name_of(_files(label, "quats", meta["quats"], 1)[0]), "quats.files[0]", count,
                     max_texels)[:count]
    tags = quats[:, 3].astype(np.int64) - 252
    bad = (tags < 0) | (tags > 3)
    if bad.any():
        first = int(np.argmax(bad))
        raise InputError(label, "quats.files[0]", f"{int(bad.sum())} texels have an alpha outside 252..255 (the index "
                         f"of the largest quaternion component), first at texel {first}: {int(quats[first, 3])}")
    stored = (quats[:, :3].astype(np.float32) / np.float32(255.0) * 2 - 1) / np.float32(math.sqrt(2))
    wxyz = np.zeros((count, 4), np.float32)
    for largest, others in enumerate(QUAT_ORDER):
        rows = tags == largest
        wxyz[np.ix_(rows, others)] = stored[rows]
        wxyz[rows, largest] = np.sqrt(np.maximum(0, 1 - (stored[rows] ** 2).sum(axis=1)))
    del quats, stored

    scales = _texture(source, name_of(_files(label, "scales", meta["scales"], 1)[0]), "scales.files[0]", count,
                      max_texels)[:count]
    log_scales = _lerp_bytes(scales[:, :3], scale_lo, scale_hi) if v1 else \
        _codebook_lookup(label, "scales.files[0]", scale_book, scales[:, :3])
    del scales
    sh0 = _texture(source, name_of(_files(label, "sh0", meta["sh0"], 1)[0]), "sh0.files[0]", count,
                   max_texels)[:count]
    if v1:  # colour and the opacity logit itself (not its sigmoid) lerped per channel
        sh_dc = _lerp_bytes(sh0[:, :3], color_lo[:3], color_hi[:3])
        opacity_logits = _lerp_bytes(sh0[:, 3], color_lo[3], color_hi[3])
    else:
        sh_dc = _codebook_lookup(label, "sh0.files[0]", color_book, sh0[:, :3])
        opacity_logits = opacity_logits_from_unit(sh0[:, 3].astype(np.float32) / np.float32(255.0))
    del sh0

    sh_rest = np.zeros((count, 0, 3), np.float32)
    shn = meta.get("shN")
    if shn is not None and v1:
        if not isinstance(shn, dict):
            raise InputError(label, "shN", "not an object")
        sh_rest = _v1_sh_rest(source, label, shn, name_of, count, max_texels)
    elif shn is not None:
        if not isinstance(shn, dict):
            raise InputError(label, "shN", "not an object")
        bands = _int(label, "shN.bands", shn.get("bands"), 0, 3)
        if bands:
            k = SH_REST_COEFFS[bands]
            palette = _int(label, "shN.count", shn.get("count"), 1, 1 << 16)
            sh_book = _floats(label, "shN.codebook", shn.get("codebook"), max_length=256)
            centroids_name, labels_name = _files(label, "shN", shn, 2)
            # 64 palette entries per row, each k texels wide; at most 65536 entries (16-bit labels).
            centroids = _texture(source, name_of(centroids_name), "shN.files[0]", 0, 64 * k * 1024, width=64 * k)
            labels = _texture(source, name_of(labels_name), "shN.files[1]", count, max_texels)[:count]
            index = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
            del labels
            stored_entries = len(centroids) // k  # texels are (row, 64 entries x k coefficients)
            limit = min(palette, stored_entries)
            if len(index) and int(index.max()) >= limit:
                raise InputError(label, "shN.files[1]", f"palette label {int(index.max())} is past the palette "
                                 f"({palette} entries declared, {stored_entries} stored)")
            entry_texels = centroids[:, :3].reshape(-1, k, 3)  # entry e = row e // 64, texels (e % 64) * k ...
            sh_rest = _codebook_lookup(label, "shN.files[0]", sh_book, entry_texels[index])
    return Gaussians(positions=positions, rotations=normalize_quaternions(wxyz), log_scales=log_scales,
                     opacity_logits=opacity_logits, sh_dc=sh_dc, sh_rest=sh_rest)


@dataclass(frozen=True)
class LodNode:
    """A node of a streamed SOG's tree: its bound and either children or, on a leaf, per LOD level (0 the finest)
    the (file, offset, count) reference of its rows."""

    bound_min: np.ndarray
    bound_max: np.ndarray
    children: tuple[LodNode, ...] = ()
    lods: dict[int, tuple[int, int, int]] = field(default_factory=dict)

    def leaves(self) -> list[LodNode]:
        """The leaves in depth-first order (what PlayCanvas's engine reads; interior nodes only group them)."""
        out: list[LodNode] = []
        stack = [self]
        while stack:
            node = stack.pop()
            if node.children:
                stack.extend(reversed(node.children))
            else:
                out.append(node)
        return out


@dataclass(frozen=True)
class LodMeta:
    levels: int
    filenames: list[str]
    environment: str | None
    counts: list[int] | None
    tree: LodNode


def _bound(label: str, node: dict) -> tuple[np.ndarray, np.ndarray]:
    bound = node.get("bound")
    if bound is None:  # optional for our purposes: the engine needs it, the splats do not
        return np.zeros(3), np.zeros(3)
    if not isinstance(bound, dict):
        raise InputError(label, "tree bound", "expected {min: [3 numbers], max: [3 numbers]}")
    return _floats(label, "tree bound.min", bound.get("min"), 3), _floats(label, "tree bound.max", bound.get("max"), 3)


def _lod_meta(label: str, meta: dict) -> LodMeta:
    """Validate a lod-meta.json into its tree with every level's references."""
    version = meta.get("version")
    if version not in (None, 1):
        raise InputError(label, "version", f"{version!r} (expected 1)")
    levels = _int(label, "lodLevels", meta.get("lodLevels"), 1, 1 << 16)
    filenames = meta.get("filenames")
    if not isinstance(filenames, list) or not all(isinstance(f, str) for f in filenames):
        raise InputError(label, "filenames", "expected a list of file names")
    environment = meta.get("environment")
    if environment is not None and not isinstance(environment, str):
        raise InputError(label, "environment", f"{environment!r} (expected a file name)")
    counts = meta.get("counts")
    if counts is not None and (not isinstance(counts, list) or len(counts) != levels):
        raise InputError(label, "counts", f"expected a list of {levels} counts (one per LOD level)")
    tree = meta.get("tree")
    if not isinstance(tree, dict):
        raise InputError(label, "tree", "missing or not an object")
    visited = 0

    def node(data: object, depth: int) -> LodNode:
        nonlocal visited
        visited += 1
        if visited > MAX_LOD_NODES or depth > MAX_LOD_DEPTH or not isinstance(data, dict):
            raise InputError(label, "tree", f"not a tree of objects (or more than {MAX_LOD_NODES} nodes or "
                             f"{MAX_LOD_DEPTH} levels)")
        lods = data.get("lods", {})
        children = data.get("children", [])
        if not isinstance(lods, dict) or not isinstance(children, list):
            raise InputError(label, "tree", "a node's 'lods' must be an object and 'children' a list")
        refs: dict[int, tuple[int, int, int]] = {}
        for key, ref in lods.items():
            if not key.isdigit() or int(key) >= levels or not isinstance(ref, dict):
                raise InputError(label, "tree", f"LOD reference {key!r}: expected a level 0..{levels - 1} "
                                 "mapping to {file, offset, count}")
            file = _int(label, "tree lods.file", ref.get("file"), 0, len(filenames) - 1)
            refs[int(key)] = (file, _int(label, "tree lods.offset", ref.get("offset", 0)),
                              _int(label, "tree lods.count", ref.get("count", 0)))
        lo, hi = _bound(label, data)
        return LodNode(lo, hi, tuple(node(c, depth + 1) for c in children), refs)

    root = node(tree, 0)
    if counts is not None:
        sums = [0] * levels
        for leaf in root.leaves():
            for level, (_, _, count) in leaf.lods.items():
                sums[level] += count
        for level in range(levels):
            if counts[level] != sums[level]:
                raise InputError(label, f"counts[{level}]", f"{counts[level]!r}, but the tree's level-{level} "
                                 f"references add up to {sums[level]}")
    return LodMeta(levels, filenames, environment, counts, root)


@dataclass(frozen=True)
class StreamedSog:
    """A streamed SOG read whole: the tree with, per leaf and level, the splats of its reference."""

    levels: int
    tree: LodNode
    splats: dict[int, dict[int, Gaussians]]  # id(leaf) -> level -> splats
    environment: Gaussians | None

    def level(self, level: int) -> Gaussians:
        """Every splat of one level, leaves in depth-first order."""
        parts = [self.splats[id(leaf)][level] for leaf in self.tree.leaves() if level in self.splats[id(leaf)]]
        return Gaussians.concatenate(parts) if parts else Gaussians.empty()


def _load_streamed(directory: str, label: str, meta_name: str, levels: set[int] | None) -> StreamedSog:
    """Read the references of the given levels (None: all) of a streamed SOG; each unit is decoded once."""
    source = _dir_source(directory, label)
    lod = _lod_meta(label, _json(source, meta_name, "lod-meta.json"))
    leaves = lod.tree.leaves()
    wanted = [(leaf, level, ref) for leaf in leaves for level, ref in leaf.lods.items()
              if (levels is None or level in levels) and ref[2] > 0]
    if sum(ref[2] for _, _, ref in wanted) * BYTES_PER_SPLAT > memory_budget():
        raise InputError(label, "tree", "the levels read hold more splats than the memory budget allows")
    base = os.path.dirname(meta_name)

    def inside(name: str) -> str:
        return f"{base}/{name}" if base else name

    units: dict[int, Gaussians] = {}
    splats: dict[int, dict[int, Gaussians]] = {id(leaf): {} for leaf in leaves}
    for leaf, level, (file, offset, count) in wanted:
        if file not in units:
            units[file] = _read_unit(source, inside(lod.filenames[file]), f"lod-meta.json filenames[{file}]")
        unit = units[file]
        if offset + count > len(unit):
            raise InputError(label, "tree", f"reference to rows {offset}..{offset + count} of "
                             f"{lod.filenames[file]}, which holds {len(unit)} splats")
        splats[id(leaf)][level] = unit.subset(slice(offset, offset + count))
    environment = _read_unit(source, inside(lod.environment), "lod-meta.json environment") \
        if lod.environment else None
    return StreamedSog(lod.levels, lod.tree, splats, environment)


def _read_streamed(directory: str, label: str, meta_name: str) -> Gaussians:
    sog = _load_streamed(directory, label, meta_name, {0})
    parts = [sog.level(0)] if any(0 in s for s in sog.splats.values()) else []
    if sog.environment is not None:
        parts.append(sog.environment)
    if not parts:
        return Gaussians.empty()
    return Gaussians.concatenate(parts)


def _streamed_location(path: str) -> tuple[str, str]:
    """(directory, name of the lod-meta.json) of a streamed SOG given as the file or its directory."""
    if sog_kind(path) != "lod":
        raise InputError(path, None, "not a streamed SOG (expected a lod-meta.json or a directory holding one)")
    if os.path.isdir(path):
        return path, "lod-meta.json"
    return os.path.dirname(path) or ".", os.path.basename(path)


def read_sog_level(path: str | os.PathLike, level: int) -> Gaussians:
    """One LOD level of a streamed SOG (0 the finest), leaves in depth-first order; only that level's units are
    read."""
    path = os.fspath(path)
    directory, name = _streamed_location(path)
    sog = _load_streamed(directory, path, name, {level})
    if not 0 <= level < sog.levels:
        raise InputError(path, "lodLevels", f"{sog.levels} levels (0..{sog.levels - 1}); level {level} asked for")
    return sog.level(level)


def read_streamed_sog(path: str | os.PathLike) -> StreamedSog:
    """Every level of a streamed SOG (a lod-meta.json or its directory), with its tree."""
    path = os.fspath(path)
    directory, name = _streamed_location(path)
    return _load_streamed(directory, path, name, None)


def finest_level_units(path: str | os.PathLike) -> tuple[str, list[str]]:
    """(the lod-meta.json's path, the directories of the units its level 0 names, relative to it, sorted) of a
    streamed SOG given as the file or its directory: what reading its finest level touches."""
    path = os.fspath(path)
    directory, name = _streamed_location(path)
    lod = _lod_meta(path, _json(_dir_source(directory, path), name, "lod-meta.json"))
    units, stack = set(), [lod.tree]
    while stack:
        node = stack.pop()
        stack.extend(node.children)
        if 0 in node.lods:
            units.add(os.path.dirname(lod.filenames[node.lods[0][0]]))
    return os.path.join(directory, name), sorted(units)


def sog_kind(path: str) -> str | None:
    """'sog' (bundled zip, meta.json file or a directory with meta.json), 'lod' (lod-meta.json file or a
    directory with one), or None."""
    if os.path.isdir(path):
        if os.path.isfile(os.path.join(path, "lod-meta.json")):
            return "lod"
        if os.path.isfile(os.path.join(path, SOG_META_NAME)):
            return "sog"
        return None
    name = os.path.basename(path).lower()
    if name == "lod-meta.json":
        return "lod"
    if name == SOG_META_NAME:
        return "sog"
    with open(path, "rb") as f:
        head = f.read(4)
    if head == b"PK\x03\x04":
        try:
            with zipfile.ZipFile(path) as archive:
                return "sog" if "meta.json" in archive.namelist() else None
        except (zipfile.BadZipFile, OSError):
            return "sog" if name.endswith(".sog") else None
    return None


def read_sog(path: str | os.PathLike, drop_invalid: bool = False) -> Gaussians:
    """Read a bundled .sog, an unbundled SOG (meta.json or its directory) or a streamed SOG (lod-meta.json or
    its directory; the finest level). Every byte pattern decodes to finite values (`drop_invalid` is accepted
    for a uniform signature)."""
    path = os.fspath(path)
    kind = sog_kind(path)
    if kind is None:
        raise InputError(path, None, "not a SOG scene (expected a .sog zip with meta.json, a meta.json or "
                         "lod-meta.json, or a directory holding one)")
    if os.path.isdir(path):
        directory, meta_name = path, "lod-meta.json" if kind == "lod" else "meta.json"
    elif os.path.basename(path).lower() in ("meta.json", "lod-meta.json"):
        directory, meta_name = os.path.dirname(path) or ".", os.path.basename(path)
    else:
        return _read_unit(_zip_source(path), "meta.json")
    if kind == "lod":
        return _read_streamed(directory, path, meta_name)
    return _read_unit(_dir_source(directory, path), meta_name)
