"""Pure HTTP rules the handlers apply (format_spec/http.md): ranges, entity tags, content negotiation, caching.

No I/O and no aiohttp here, so each rule has plain unit tests (tests/test_server_paths.py).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

CACHE_IMMUTABLE = "public, max-age=31536000, immutable"  # data/<sha256>.bin: the name is the content hash
CACHE_REVALIDATE = "no-cache"  # manifest, /api/*: may be stored, must be revalidated (ETag -> 304) before use
CACHE_NONE = "no-store"  # errors, /healthz
MANIFEST_TYPE = "application/vnd.msgpack"
PAYLOAD_TYPE = "application/octet-stream"
JSON_TYPE = "application/json"
ALLOWED_METHODS = "GET, HEAD, OPTIONS"
CORS_ALLOW_HEADERS = "Range, If-None-Match, If-Match, If-Range, Accept-Encoding"
CORS_EXPOSE_HEADERS = "ETag, Content-Range, Content-Length, Content-Encoding, Accept-Ranges"
CORS_MAX_AGE = "86400"
GZIP_MIN_BYTES = 256  # smaller JSON bodies are sent as they are: gzip would not make them shorter

_ETAG_RE = re.compile(r'\s*(W/)?"([\x21\x23-\x7e\x80-\xff]*)"\s*(?:,|$)')
# Any number of digits (a start of 2^64 or more is a valid range beyond any file: 416, not ignored); longer
# numbers than _RANGE_DIGITS digits are not converted (they exceed any file anyway).
_RANGE_SPEC_RE = re.compile(r"^(\d*)-(\d*)$")
_RANGE_DIGITS = 4000  # below Python's int() digit limit (4300); a header line holds at most 8190 bytes


def _range_number(digits: str) -> int:
    digits = digits.lstrip("0") or "0"
    return int(digits) if len(digits) <= _RANGE_DIGITS else 10 ** _RANGE_DIGITS


def strong_etag(token: str) -> str:
    return f'"{token}"'


def weak_etag(token: str) -> str:
    return f'W/"{token}"'


def parse_etags(header: str) -> list[tuple[bool, str]] | None:
    """'W/"a", "b"' -> [(True, 'a'), (False, 'b')]; '*' -> None (any). Unparsable parts end the list."""
    header = header.strip()
    if header == "*":
        return None
    out = []
    pos = 0
    while pos < len(header):
        m = _ETAG_RE.match(header, pos)
        if not m or m.end() == pos:
            break
        out.append((bool(m.group(1)), m.group(2)))
        pos = m.end()
    return out


def _opaque(etag: str) -> tuple[bool, str]:
    weak = etag.startswith("W/")
    return weak, etag[2:].strip('"') if weak else etag.strip('"')


def none_match(header: str | None, etag: str) -> bool:
    """If-None-Match (weak comparison): True when the client's copy is current, i.e. answer 304."""
    if header is None:
        return False
    tags = parse_etags(header)
    if tags is None:
        return True
    _, value = _opaque(etag)
    return any(v == value for _, v in tags)


def match(header: str | None, etag: str) -> bool:
    """If-Match (strong comparison): False means answer 412. No header: True."""
    if header is None:
        return True
    tags = parse_etags(header)
    if tags is None:
        return True
    weak, value = _opaque(etag)
    return not weak and any(not w and v == value for w, v in tags)


def if_range_allows(header: str | None, etag: str) -> bool:
    """If-Range: the Range applies only if the validator is this strong ETag (dates never match: we send no
    Last-Modified). No header: True."""
    if header is None:
        return True
    header = header.strip()
    weak, value = _opaque(etag)
    return not weak and header.startswith('"') and header == f'"{value}"'


@dataclass(frozen=True)
class ByteRange:
    start: int
    end: int  # inclusive

    @property
    def length(self) -> int:
        return self.end - self.start + 1

    def content_range(self, size: int) -> str:
        return f"bytes {self.start}-{self.end}/{size}"


class RangeNotSatisfiable(ValueError):
    pass


def parse_range(header: str | None, size: int) -> ByteRange | None:
    """One 'bytes=' range of a `size`-byte representation.

    None: serve the whole representation (no header, another unit, several ranges, or invalid syntax, which
    RFC 9110 lets a server ignore). Raises RangeNotSatisfiable (answer 416 with 'Content-Range: bytes */size')
    when the syntax is valid but no byte of the range exists.
    """
    if header is None:
        return None
    unit, sep, spec = header.partition("=")
    if not sep or unit.strip().lower() != "bytes":
        return None
    spec = spec.strip()
    if "," in spec:
        return None
    m = _RANGE_SPEC_RE.match(spec)
    if not m:
        return None
    first, last = m.group(1), m.group(2)
    if first == "":
        if last == "":
            return None
        suffix = _range_number(last)
        if suffix == 0 or size == 0:
            raise RangeNotSatisfiable(spec)
        return ByteRange(max(0, size - suffix), size - 1)
    start = _range_number(first)
    if last != "" and _range_number(last) < start:
        return None
    if start >= size:
        raise RangeNotSatisfiable(spec)
    end = size - 1 if last == "" else min(_range_number(last), size - 1)
    return ByteRange(start, end)


def accepts_gzip(header: str | None) -> bool:
    """Accept-Encoding allows gzip (q > 0 for 'gzip', 'x-gzip' or '*' when gzip is not named)."""
    if not header:
        return False
    star = None
    for part in header.split(","):
        name, _, params = part.partition(";")
        name = name.strip().lower()
        q = 1.0
        for p in params.split(";"):
            k, _, v = p.partition("=")
            if k.strip().lower() == "q":
                try:
                    q = float(v.strip())
                except ValueError:
                    q = 0.0
        if name in ("gzip", "x-gzip"):
            return q > 0
        if name == "*":
            star = q > 0
    return bool(star)


def error_body(status: int, message: str) -> dict:
    return {"error": {"status": status, "message": message}}
