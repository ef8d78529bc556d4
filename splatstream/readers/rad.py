"""Spark 2's RAD file (format_spec/foreign_formats.md, "RAD"), read whole: its splats in file order and its LoD
tree (`child_count`, `child_start`), following Spark's decoder (rust/spark-lib/src/rad.rs, RadDecoder).

`read_rad` gives the finest level (the splats without children: the tree's full detail) for `convert`;
`read_rad_tree` gives every splat with its tree for `view` (splatstream/rad_import.py). Encodings read: every one
Spark's RadDecoder reads (f32, f16, f32_lebytes, f16_lebytes, r8, r8_delta, s8, s8_delta, ln_f16, ln_0r8, oct88r8,
u16, u32); SH by cluster codes (sh*_code in chunk 0, one row per cluster, and a per-splat sh_label: Spark's
`build-lod --cluster-sh`); chunks in separate .radc files beside the header file (`build-lod --rad-chunked`), by a
plain file name only.
"""
from __future__ import annotations

import json
import os
import struct
import zlib

import numpy as np

from ..errors import InputError
from ..gaussians import SH_C0, SH_REST_COEFFS, Gaussians
from ..reader_support import (
    check_memory,
    memory_budget,
    model_bytes_per_splat,
    opacity_logits_from_unit,
    read_regular_file,
)
from ..writers.rad import RAD_CHUNK_MAGIC, RAD_MAGIC, RadTree

_DIMS = {"center": 3, "alpha": 1, "rgb": 3, "scales": 3, "orientation": 3, "sh1": 9, "sh2": 15, "sh3": 21,
         "child_count": 1, "child_start": 1, "sh1_code": 9, "sh2_code": 15, "sh3_code": 21, "sh_label": 1}
_CODES = ("sh1_code", "sh2_code", "sh3_code")  # one row per SH cluster (header shCodeCount), not per splat


def is_rad(head: bytes) -> bool:
    return len(head) >= 4 and struct.unpack_from("<I", head)[0] == RAD_MAGIC


def _round8(n: int) -> int:
    return (n + 7) & ~7


def _json(data: bytes, path: str, field: str) -> dict:
    try:
        value = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise InputError(path, field, f"expected JSON ({e})") from None
    if not isinstance(value, dict):
        raise InputError(path, field, "expected a JSON object")
    return value


def _int(d: dict, key: str, path: str, field: str) -> int:
    value = d.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InputError(path, f"{field} {key}", f"{value!r}, expected a non-negative integer")
    return value


def _decode(data: bytes, prop: dict, count: int, path: str, field: str) -> np.ndarray:
    """One property's values, (count, dims), from its planar bytes."""
    enc = prop.get("encoding")
    dims = _DIMS[prop["property"]]
    n = count * dims

    def need(size: int) -> bytes:
        if len(data) < size:
            raise InputError(path, field, f"{enc} data of {len(data)} bytes, expected {size}")
        return data[:size]

    def planes(v: np.ndarray) -> np.ndarray:
        return v.reshape(dims, count).T

    def minmax() -> tuple[float, float]:
        if "min" not in prop or "max" not in prop:
            raise InputError(path, field, f"{enc} without min and max")
        return float(prop["min"]), float(prop["max"])

    if enc in ("f32", "f16", "u16", "u32"):
        dtype = {"f32": "<f4", "f16": "<f2", "u16": "<u2", "u32": "<u4"}[enc]
        size = np.dtype(dtype).itemsize
        return planes(np.frombuffer(need(n * size), dtype))
    if enc in ("f32_lebytes", "f16_lebytes"):
        size = 4 if enc == "f32_lebytes" else 2
        raw = np.frombuffer(need(n * size), np.uint8).reshape(size, n).T.copy()
        return planes(raw.view("<f4" if size == 4 else "<f2").reshape(n))
    if enc == "ln_0r8":
        lo, hi = minmax()
        raw = planes(np.frombuffer(need(n), np.uint8)).astype(np.float64)
        # splat_encode::decode_scale8: 0 is a flat axis (scale 0), else ln scale min + (code - 1) steps of 1/254.
        return np.where(raw == 0, 0.0, np.exp(lo + (raw - 1) * ((hi - lo) / 254.0)))
    if enc == "oct88r8":
        if prop["property"] != "orientation":
            raise InputError(path, field, "oct88r8 is an orientation encoding")
        raw = np.frombuffer(need(count * 3), np.uint8).reshape(count, 3).astype(np.float64)
        # splat_encode::decode_quat_oct888: an octahedral axis (two bytes) and the angle 0..pi (third byte).
        x, y = raw[:, 0] / 255.0 * 2 - 1, raw[:, 1] / 255.0 * 2 - 1
        z = 1 - np.abs(x) - np.abs(y)
        t = np.maximum(-z, 0.0)
        x, y = np.where(x >= 0, x - t, x + t), np.where(y >= 0, y - t, y + t)
        axis = np.column_stack([x, y, z])
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        return axis * np.sin(raw[:, 2] / 255.0 * 0.5 * np.pi)[:, None]  # x, y, z; w = cos >= 0 is rebuilt
    if enc == "ln_f16":
        return np.exp(planes(np.frombuffer(need(n * 2), "<f2").astype(np.float64)))
    if enc in ("r8", "r8_delta", "s8", "s8_delta"):
        raw = planes(np.frombuffer(need(n), np.uint8))
        if enc.endswith("_delta"):
            raw = np.cumsum(raw, axis=0, dtype=np.uint64).astype(np.uint8)  # deltas wrap modulo 256
        if enc.startswith("r"):
            lo, hi = minmax()
            return raw.astype(np.float64) / 255.0 * (hi - lo) + lo
        if "max" not in prop:
            raise InputError(path, field, f"{enc} without max")
        return raw.view(np.int8).astype(np.float64) / 127.0 * float(prop["max"])
    raise InputError(path, field, f"encoding {enc!r} is not read (expected f32, f16, f32_lebytes, f16_lebytes, "
                     "r8, r8_delta, s8, s8_delta, ln_f16, ln_0r8, oct88r8, u16 or u32)")


def _chunk(buf: bytes, at: int, path: str, index: int, codes: int) -> tuple[int, int, dict[str, np.ndarray], int]:
    field = f"chunk {index}"
    if len(buf) < at + 8 or struct.unpack_from("<I", buf, at)[0] != RAD_CHUNK_MAGIC:
        raise InputError(path, field, "expected the RADC magic")
    length = struct.unpack_from("<I", buf, at + 4)[0]
    meta_end = at + 8 + _round8(length)
    if len(buf) < meta_end + 8:
        raise InputError(path, field, "truncated chunk header")
    meta = _json(buf[at + 8:at + 8 + length], path, field)
    if meta.get("version") != 1:
        raise InputError(path, f"{field} version", f"{meta.get('version')!r}, expected 1")
    payload = meta_end + 8
    base, count = _int(meta, "base", path, field), _int(meta, "count", path, field)
    out: dict[str, np.ndarray] = {}
    for prop in meta.get("properties", []):
        name = prop.get("property")
        pfield = f"{field} {name}"
        if name not in _DIMS:
            raise InputError(path, pfield, f"property {name!r} is not read (expected one of {sorted(_DIMS)})")
        start = payload + _int(prop, "offset", path, pfield)
        end = start + _int(prop, "bytes", path, pfield)
        if end > len(buf):
            # said before as the DEFLATE error of the bytes that were there ("incomplete or truncated stream")
            raise InputError(path, pfield, f"needs bytes {start:,}..{end:,}, past the end of its file "
                             f"({len(buf):,} bytes): truncated?")
        data = buf[start:end]
        if prop.get("compression") == "gz":
            try:
                data = zlib.decompress(data, -15)
            except zlib.error as e:
                raise InputError(path, pfield, f"expected raw DEFLATE data ({e})") from None
        elif prop.get("compression") is not None:
            raise InputError(path, pfield, f"compression {prop['compression']!r}, expected gz or none")
        out[name] = _decode(data, prop, codes if name in _CODES else count, path, pfield)
    return base, count, out, payload + _int(meta, "payloadBytes", path, field)


def read_rad_tree(path: str | os.PathLike) -> RadTree:
    """Every splat of a .rad file in file order, with its LoD tree (a flat file reads as a tree of leaves)."""
    path = os.fspath(path)
    buf = read_regular_file(path, memory_budget())
    if not is_rad(buf):
        raise InputError(path, "magic", "expected RAD0")
    if len(buf) < 8:
        raise InputError(path, "header", f"needs 8 bytes (magic and header length), the file has {len(buf)}: "
                         "truncated?")
    length = struct.unpack_from("<I", buf, 4)[0]
    if len(buf) < 8 + length:
        # said before as the JSON error of the bytes that were there ("Expecting property name ...: char 92")
        raise InputError(path, "header", f"needs bytes 8..{8 + length:,}, past the end of its file ({len(buf):,} "
                         "bytes): truncated?")
    meta = _json(buf[8:8 + length], path, "header")
    if meta.get("version") != 1 or meta.get("type") != "gsplat":
        raise InputError(path, "header", f"version {meta.get('version')!r} type {meta.get('type')!r}, "
                         "expected version 1 type gsplat")
    chunks_start = 8 + _round8(length)
    n = _int(meta, "count", path, "header")
    sh_degree = _int(meta, "maxSh", path, "header") if "maxSh" in meta else 0
    if sh_degree > 3:
        raise InputError(path, "header maxSh", f"{sh_degree}, expected 0 to 3")
    # Columns are decoded in float64 before the model's float32: about twice the model's bytes per splat.
    check_memory(path, "header count", n, 2 * model_bytes_per_splat(sh_degree) + 16)
    codes = _int(meta, "shCodeCount", path, "header") if "shCodeCount" in meta else 0
    cols: dict[str, np.ndarray] = {}
    for index, rng in enumerate(meta.get("chunks", [])):
        offset = _int(rng, "offset", path, f"chunk {index}")
        if rng.get("filename"):
            base, count, props, _ = _chunk(_radc(path, rng["filename"], index), offset, path, index, codes)
        else:
            base, count, props, _ = _chunk(buf, chunks_start + offset, path, index, codes)
        if base + count > n:
            raise InputError(path, f"chunk {index}", f"splats {base}..{base + count} beyond count {n}")
        for name, values in props.items():
            if name in _CODES:
                cols[name] = values
                continue
            if name not in cols:
                cols[name] = np.zeros((n, values.shape[1]), np.float64)
            cols[name][base:base + count] = values
    if "sh_label" in cols:
        labels = cols.pop("sh_label")[:, 0].astype(np.int64)
        for band, code in enumerate(_CODES, start=1):
            if code in cols:
                book = cols.pop(code)
                if len(labels) and (labels.min() < 0 or labels.max() >= len(book)):
                    raise InputError(path, "sh_label", f"labels up to {int(labels.max())}, expected below "
                                     f"{len(book)} (shCodeCount)")
                cols[f"sh{band}"] = book[labels]
    for name in ("center", "alpha", "rgb", "scales", "orientation"):
        if name not in cols:
            raise InputError(path, name, "missing (expected in every chunk)")
    xyz = cols["orientation"]
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz ** 2).sum(axis=1)))
    rest = np.zeros((n, SH_REST_COEFFS[sh_degree], 3), np.float32)
    for band, (lo, hi) in zip((1, 2, 3), ((0, 3), (3, 8), (8, 15)), strict=True):
        if band <= sh_degree and f"sh{band}" in cols:
            rest[:, lo:hi, :] = cols[f"sh{band}"].reshape(n, hi - lo, 3)
    g = Gaussians(
        positions=cols["center"].astype(np.float32),
        rotations=np.column_stack([w, xyz]).astype(np.float32),
        log_scales=np.log(np.maximum(cols["scales"], 1e-30)).astype(np.float32),
        opacity_logits=opacity_logits_from_unit(cols["alpha"][:, 0]),
        sh_dc=((cols["rgb"] - 0.5) / SH_C0).astype(np.float32),
        sh_rest=rest)
    count = cols.get("child_count", np.zeros((n, 1)))[:, 0].astype(np.uint16)
    start = cols.get("child_start", np.zeros((n, 1)))[:, 0].astype(np.uint32)
    return RadTree(g, count, start, _depths(count, start, path))


def _radc(path: str, filename, index: int) -> bytes:
    """A chunk held in a separate file beside the header file (Spark's `build-lod --rad-chunked`)."""
    field = f"chunk {index} filename"
    if not isinstance(filename, str) or os.path.basename(filename) != filename or filename in (".", ".."):
        raise InputError(path, field, f"{filename!r}, expected a file name beside the .rad")
    return read_regular_file(os.path.join(os.path.dirname(path), filename), memory_budget(), path, field)


def _depths(count: np.ndarray, start: np.ndarray, path: str) -> np.ndarray:
    """Depth of every splat below splat 0 (breadth-first); a flat file (no children) is all depth 0."""
    n = len(count)
    depth = np.zeros(n, np.int64)
    if n == 0 or count[0] == 0:
        return depth
    seen = np.zeros(n, bool)
    seen[0] = True
    frontier = np.array([0])
    d = 0
    while len(frontier):
        d += 1
        parents = frontier[count[frontier] > 0]
        if not len(parents):
            break
        c = count[parents].astype(np.int64)
        # The runs start[p] .. start[p] + count[p] of every parent, laid end to end.
        kids = np.repeat(start[parents].astype(np.int64) - np.concatenate([[0], np.cumsum(c)[:-1]]), c) + \
            np.arange(int(c.sum()))
        if kids.max() >= n or seen[kids].any():
            raise InputError(path, "child_start", "children outside the file or reached twice (expected a tree)")
        seen[kids] = True
        depth[kids] = d
        frontier = kids
    if not seen.all():
        raise InputError(path, "child_start", f"{int((~seen).sum())} splats not reached from splat 0")
    return depth


def read_rad(path: str | os.PathLike) -> Gaussians:
    """The full detail of a .rad file: its splats without children (all of them in a file without a tree)."""
    tree = read_rad_tree(path)
    return tree.splats.subset(np.flatnonzero(tree.child_count == 0))
