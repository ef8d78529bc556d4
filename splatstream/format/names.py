"""Names inside a scene and on the wire (format_spec/format.md 1, format_spec/http.md 2).

A scene is `manifest.msgpack` plus content-addressed payloads `data/<sha256>.bin`: named by the SHA-256 of their
bytes in full (64 hex digits), or, in a 1.15 tile table (format.md 6.2, "Short digests"), by its first 16 bytes (32
hex). Servers, stores, clients and
the encoder build and check every name here, so nothing else spells a file name or a URL pattern.
"""
from __future__ import annotations

import hashlib
import re

MANIFEST_NAME = "manifest.msgpack"
DATA_DIR = "data"
PAYLOAD_SUFFIX = ".bin"
SHA256_HEX_RE = re.compile(r"^[0-9a-f]{64}$")
# A payload's digest as its name carries it: the whole SHA-256 (64 lowercase hex) or, from 1.15, its first 16 bytes
DIGEST_HEX_RE = re.compile(r"^(?:[0-9a-f]{32}|[0-9a-f]{64})$")
DIGEST_HEX_PATTERN = r"[0-9a-f]{32}|[0-9a-f]{64}"  # for a server's route (a group of its own: wrap it)
PAYLOAD_NAME_RE = re.compile(r"^(?:[0-9a-f]{32}|[0-9a-f]{64})\.bin$")
# A payload's path relative to its scene: data/<64 or 32 lowercase hex>.bin
PAYLOAD_PATH_RE = re.compile(r"^data/(?:[0-9a-f]{32}|[0-9a-f]{64})\.bin$")
# Bytes of a short digest (format.md 6.2, version 1.15): the first 128 bits of the SHA-256
SHORT_DIGEST_BYTES = 16
SCENES_URL_PREFIX = "/scenes/"


def payload_name(sha256_hex: str, short: bool = False) -> str:
    """Relative path of a payload file: named by the SHA-256 of its bytes, so it is immutable; `short`: by the
    first 16 bytes of a whole SHA-256 (a 1.15 tile table's name, format.md 6.2: short_digest)."""
    return f"{DATA_DIR}/{short_digest(sha256_hex) if short else sha256_hex}{PAYLOAD_SUFFIX}"


def sha256_hex(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def short_digest(sha256_hex_: str) -> str:
    """A full SHA-256 (64 hex) as a 1.15 tile table names a file by it: its first 16 bytes (32 hex)."""
    return sha256_hex_[:2 * SHORT_DIGEST_BYTES]


def digest_hex(data: bytes | memoryview, short: bool) -> str:
    """The digest a file of these bytes is named by: its SHA-256, or (short, 1.15) the first 16 bytes of it."""
    h = hashlib.sha256(data).hexdigest()
    return short_digest(h) if short else h


def digest_matches(sha256_hex_: str, digest: str) -> bool:
    """Whether bytes of SHA-256 `sha256_hex_` are the file `digest` names: the whole hash, or its 16-byte prefix (a
    1.15 table's; format.md 5.3). Any other length matches nothing."""
    return len(digest) in (64, 2 * SHORT_DIGEST_BYTES) and sha256_hex_[:len(digest)] == digest


def is_payload_path(rel: str) -> bool:
    return isinstance(rel, str) and PAYLOAD_PATH_RE.match(rel) is not None


def manifest_url(base_url: str) -> str:
    """URL of a scene's manifest from the scene URL (`http://host/scenes/ID`, with or without a trailing slash,
    or the manifest URL itself)."""
    base = base_url.split("?", 1)[0].split("#", 1)[0]
    if base.endswith("/" + MANIFEST_NAME):
        return base
    return base.rstrip("/") + "/" + MANIFEST_NAME


def payload_url(manifest_url_: str, rel: str) -> str:
    """A payload's URL: its manifest path resolved against the manifest's URL (format_spec/http.md 2)."""
    return manifest_url_.rsplit("/", 1)[0] + "/" + rel


# An exported 3D Tiles tileset (format_spec/tiles3d.md, format_spec/http.md 14): `tileset.json` plus one glTF
# binary per tile, named by the SHA-256 of its bytes (immutable like payloads).
TILESET_NAME = "tileset.json"
TILESET_CONTENT_DIR = "tiles"
TILESET_CONTENT_SUFFIX = ".glb"
TILESET_CONTENT_NAME_RE = re.compile(r"^[0-9a-f]{64}\.glb$")
# External tilesets (3D Tiles 1.1), one per manifest page of a paged scene: `tiles/<sha256>.json`, named by the
# SHA-256 of their bytes like the content beside them (format_spec/tiles3d.md 3.1).
TILESET_EXTERNAL_SUFFIX = ".json"
TILESET_EXTERNAL_NAME_RE = re.compile(r"^[0-9a-f]{64}\.json$")


def tileset_content_name(sha256_hex_: str) -> str:
    """Relative path of a tile's content file in a tileset directory."""
    return f"{TILESET_CONTENT_DIR}/{sha256_hex_}{TILESET_CONTENT_SUFFIX}"


def tileset_external_name(sha256_hex_: str) -> str:
    """Relative path of an external tileset (one page's tiles) in a tileset directory."""
    return f"{TILESET_CONTENT_DIR}/{sha256_hex_}{TILESET_EXTERNAL_SUFFIX}"
