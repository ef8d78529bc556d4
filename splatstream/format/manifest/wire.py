"""The manifest file's bytes (format.md 6): msgpack packing, the 1.2 checksum, and the guard against msgpack bombs.

Nothing here knows the manifest's fields beyond `version` and `checksum`: `validate.py` reads the map these
functions unpack, `model.py` gives the map `pack_manifest` writes.
"""
from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING

import msgpack
import numpy as np

from ...errors import FormatError
from ..names import SHA256_HEX_RE
from .versions import CHECKSUM_VERSION

if TYPE_CHECKING:
    from .model import Manifest

CHECKSUM_KEY = "checksum"
CHECKSUM_PLACEHOLDER = b"0" * 64
MAX_MANIFEST_BYTES = 64 << 20


def pack_manifest(m: Manifest) -> bytes:
    """The manifest file's bytes (with its checksum from version 1.2 on)."""
    return pack_manifest_dict(m.to_dict())


def pack_manifest_dict(d: dict) -> bytes:
    """A manifest map as the file of its version: from 1.2 on `checksum` is moved to the end and computed (the
    map is packed with 64 ASCII '0' as its value, hashed, and the digest patched in); before 1.2 it is left out."""
    d = {k: v for k, v in d.items() if k != CHECKSUM_KEY}
    version = d.get("version")
    two_ints = isinstance(version, (list, tuple)) and len(version) == 2 and all(
        isinstance(v, int) and not isinstance(v, bool) for v in version)
    if not (two_ints and tuple(version) >= CHECKSUM_VERSION):
        return msgpack.packb(d, use_bin_type=True)
    d[CHECKSUM_KEY] = CHECKSUM_PLACEHOLDER.decode()
    packed = msgpack.packb(d, use_bin_type=True)
    assert packed.endswith(CHECKSUM_PLACEHOLDER)  # a 64-character str is the last thing in the map
    return packed[:-64] + manifest_checksum(packed).encode()


def manifest_checksum(raw: bytes) -> str:
    """SHA-256 (hex) of manifest bytes whose last 64 bytes are the checksum value, read as 64 ASCII '0'."""
    return hashlib.sha256(raw[:-64] + CHECKSUM_PLACEHOLDER).hexdigest()


def verify_checksum(raw: bytes, d: dict, source: str) -> None:
    """format.md 6, Checksum: a 1.2+ manifest's last key is `checksum`, its value the file's last 64 bytes."""
    keys = list(d)
    if CHECKSUM_KEY not in d:
        raise FormatError(source, CHECKSUM_KEY, f"missing (a version {d['version'][0]}.{d['version'][1]} manifest "
                          "ends with its checksum)")
    value = d[CHECKSUM_KEY]
    if not isinstance(value, str) or not SHA256_HEX_RE.match(value):
        raise FormatError(source, CHECKSUM_KEY, f"expected 64 lowercase hex digits, got {value!r}")
    if keys[-1] != CHECKSUM_KEY or raw[-64:] != value.encode():
        raise FormatError(source, CHECKSUM_KEY, "not the manifest's last key and value")
    actual = manifest_checksum(raw)
    if actual != value:
        raise FormatError(source, CHECKSUM_KEY, f"checksum mismatch: the manifest is corrupt (it records {value}, "
                          f"its bytes hash to {actual})")


def _object_bytes_bound() -> np.ndarray:
    """Per msgpack lead byte: about the bytes of Python objects the value it starts becomes (with its pointer in
    its container). A map or array of one byte is a 64-byte object; a small int, nil or a bool only a pointer."""
    cost = np.full(256, 8, np.int64)
    cost[0x80:0xA0] = cost[0xDC:0xE0] = 80      # fixmap, fixarray, array16/32, map16/32
    cost[0xA0:0xC0] = cost[0xD9:0xDC] = 64      # strings
    cost[0xC4:0xC7] = 64                        # bin
    cost[0xCA:0xCC] = 32                        # floats
    cost[0xCC:0xD4] = 40                        # ints beyond the cached small ones
    return cost


_OBJECT_BYTES = _object_bytes_bound()
# The Python objects a manifest may unpack into, estimated from its bytes before anything is built (real manifests
# estimate 17 bytes per byte and make a third of that: one of 44 MB passes; a 64 MiB array of empty maps, 4.9 GB
# unpacked, does not).
MAX_MANIFEST_OBJECT_BYTES = 768 << 20


def check_msgpack_bomb(raw: bytes, source: str) -> None:
    """Refuse manifest bytes that would unpack into more objects than MAX_MANIFEST_OBJECT_BYTES (counting every
    byte as the lead byte of a value bounds what any parse builds), or whose top level is not a map."""
    if not raw or not (0x80 <= raw[0] <= 0x8F or raw[0] in (0xDE, 0xDF)):
        raise FormatError(source, None, "not a msgpack manifest (expected a map at the top)")
    counts = np.zeros(256, np.int64)
    view = np.frombuffer(raw, np.uint8)
    for start in range(0, len(view), 1 << 22):  # bincount widens to int64: 8 bytes per byte, so in 4 MiB pieces
        counts += np.bincount(view[start:start + (1 << 22)], minlength=256)
    estimate = int(counts @ _OBJECT_BYTES)
    if estimate > MAX_MANIFEST_OBJECT_BYTES:
        containers = int(counts[0x80:0xA0].sum() + counts[0xDC:0xE0].sum())
        raise FormatError(source, None, f"{len(raw)} bytes that would unpack into about {estimate >> 20} MiB of "
                          f"objects (up to {containers} maps and arrays; at most {MAX_MANIFEST_OBJECT_BYTES >> 20} "
                          "MiB): not a manifest")


def unpack_manifest(raw: bytes, source: str) -> dict:
    """The manifest file's map, unpacked after the bomb check (its fields are validate.py's business)."""
    check_msgpack_bomb(raw, source)
    try:
        return msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise FormatError(source, None, f"not a msgpack manifest ({exc.__class__.__name__}: {exc})") from None
