"""The scene manifest (format_spec/format.md, section "Manifest"): reading, validation and summaries.

A scene directory holds `manifest.msgpack` and content-addressed payload files under `data/`. This is
the one place that knows the manifest's names and version rules; encoder, server and client import it.
"""
from __future__ import annotations

import hashlib
import os
import re

import msgpack

from .errors import FormatError

FORMAT_NAME = "splatstream"
FORMAT_VERSION = (1, 1)  # (major, minor): readers accept any minor of their major and ignore unknown keys
# Scenes without 1.1 features (the SH codebook) are written as 1.0, so 1.0 readers still read them.
BASE_VERSION = (1, 0)
MANIFEST_NAME = "manifest.msgpack"
DATA_DIR = "data"
PAYLOAD_SUFFIX = ".bin"
MAX_MANIFEST_BYTES = 64 << 20
PAYLOAD_NAME_RE = re.compile(r"^[0-9a-f]{64}\.bin$")


def payload_name(sha256_hex: str) -> str:
    """Relative path of a payload file: named by the SHA-256 of its bytes, so it is immutable."""
    return f"{DATA_DIR}/{sha256_hex}{PAYLOAD_SUFFIX}"


def sha256_hex(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def is_scene_dir(path: str | os.PathLike) -> bool:
    return os.path.isfile(os.path.join(path, MANIFEST_NAME))


def parse_manifest(raw: bytes, source: str = MANIFEST_NAME) -> dict:
    try:
        m = msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise FormatError(source, None, f"not a msgpack manifest ({exc.__class__.__name__}: {exc})") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT_NAME:
        raise FormatError(source, "format", f"expected {FORMAT_NAME!r}; this is not a splatstream manifest")
    version = m.get("version")
    if not (isinstance(version, list) and len(version) == 2 and all(isinstance(v, int) for v in version)):
        raise FormatError(source, "version", f"expected [major, minor], got {version!r}")
    if version[0] != FORMAT_VERSION[0]:
        raise FormatError(source, "version", f"format major version {version[0]} is not supported by this "
                          f"reader (it reads major version {FORMAT_VERSION[0]}); upgrade splatstream")
    for key, kind in (("splats", int), ("sh_degree", int), ("preset", str), ("tiles", list), ("bounds", dict)):
        if not isinstance(m.get(key), kind):
            raise FormatError(source, key, f"missing or not a {kind.__name__}")
    return m


def load_manifest(scene_dir: str | os.PathLike) -> dict:
    if not os.path.isdir(scene_dir):
        what = "no such directory" if not os.path.exists(scene_dir) else "not a directory"
        raise FormatError(scene_dir, None, f"{what} (expected a scene directory holding {MANIFEST_NAME})")
    path = os.path.join(os.fspath(scene_dir), MANIFEST_NAME)
    try:
        size = os.path.getsize(path)
    except FileNotFoundError:
        raise FormatError(path, None, "no such file: not a splatstream scene directory") from None
    if size > MAX_MANIFEST_BYTES:
        raise FormatError(path, None, f"{size} bytes; a manifest is at most {MAX_MANIFEST_BYTES} bytes")
    with open(path, "rb") as f:
        return parse_manifest(f.read(), path)


def pack_manifest(m: dict) -> bytes:
    return msgpack.packb(m, use_bin_type=True)


def iter_payloads(m: dict):
    """Yield (tile, group_name, group) for every payload group the manifest references (tile None: codebook)."""
    for tile in m["tiles"]:
        for name, group in tile["groups"].items():
            yield tile, name, group
    for name, group in (m.get("sh_codebook") or {}).get("groups", {}).items():
        yield None, name, group


def scene_summary(m: dict) -> dict:
    """JSON-ready facts about a scene, as `splatstream info` and the server's /api/scenes give them."""
    return {
        "name": m.get("name", ""),
        "splats": m["splats"],
        "sh_degree": m["sh_degree"],
        "preset": m["preset"],
        "bounds": m["bounds"],
        "bytes_on_disk": m.get("bytes_on_disk"),
        "gpu_bytes": m.get("gpu_bytes"),
        "gpu_bytes_per_splat": m.get("gpu_bytes_per_splat"),
        "tiles": len(m["tiles"]),
        "levels": 1 + max((t.get("level", 0) for t in m["tiles"]), default=0),
        "sh_codebook_entries": (m.get("sh_codebook") or {}).get("entries"),
        "version": m["version"],
    }
