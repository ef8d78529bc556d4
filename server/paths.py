"""Pure validation of request paths and scene ids (format_spec/http.md, "URLs").

Works on the raw, still percent-encoded URL path, so encoded separators and double encoding can be told apart
from ordinary characters. Nothing here touches the file system; `server.scenes` opens what this accepts and
checks, on the opened file, that it lies inside the root.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass

from splatstream.format.names import DATA_DIR, DIGEST_HEX_PATTERN, MANIFEST_NAME, PAYLOAD_NAME_RE, PAYLOAD_SUFFIX

SCENES_PREFIX = "/scenes/"
SEGMENT_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]*$")  # a scene-id segment: safe characters, no leading dot
MAX_SCENE_DEPTH = 8  # segments in a scene id
MAX_SEGMENT_CHARS = 255
MAX_PATH_CHARS = 2048
_HEX = frozenset("0123456789abcdefABCDEF")
_BAD_CHAR_RE = re.compile(r"[^\x20-\x7e]")
# The common case in one match: plain characters, a valid scene id, one of the two served file names.
_FAST_RE = re.compile(rf"/scenes/((?:[A-Za-z0-9_-][A-Za-z0-9._-]{{0,254}}/){{1,{MAX_SCENE_DEPTH}}})"
                      rf"({re.escape(MANIFEST_NAME)}|{re.escape(DATA_DIR)}/({DIGEST_HEX_PATTERN})\.bin)")


class PathRejected(ValueError):
    """The path can never name a file this server serves; `status` is the HTTP status to answer with."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass(frozen=True)
class ScenePath:
    scene_id: str  # "a/b": segments joined with "/"
    rel: str  # path inside the scene directory: "manifest.msgpack" or "data/<digest>.bin" (64 or 32 hex, names.py)
    kind: str  # "manifest" or "payload"
    sha256: str | None = None  # payloads: the content hash their name carries (whole, or its 1.15 16-byte prefix)

    @property
    def segments(self) -> list[str]:
        return self.scene_id.split("/") + self.rel.split("/")


def percent_decode(raw: str) -> str:
    """Decode %XX escapes once. Rejects what no file we serve can contain: encoded '/', '\\', '%' (double
    encoding), NUL and other control characters, malformed escapes and non-ASCII bytes."""
    if "%" not in raw:
        decoded = raw
    else:
        out = []
        i = 0
        n = len(raw)
        while i < n:
            c = raw[i]
            if c != "%":
                out.append(c)
                i += 1
                continue
            hx = raw[i + 1:i + 3]
            if len(hx) != 2 or not set(hx) <= _HEX:
                raise PathRejected(400, "malformed percent-encoding in the path")
            ch = chr(int(hx, 16))
            if ch in "/\\":
                raise PathRejected(400, "encoded path separators (%2F, %5C) are not allowed")
            if ch == "%":
                raise PathRejected(400, "double percent-encoding (%25) is not allowed")
            out.append(ch)
            i += 3
        decoded = "".join(out)
    bad = _BAD_CHAR_RE.search(decoded)
    if bad:
        if ord(bad.group()) < 0x20 or bad.group() == "\x7f":
            raise PathRejected(400, "control characters (NUL, ...) are not allowed in the path")
        raise PathRejected(400, "non-ASCII characters are not allowed in the path")
    if "\\" in decoded:
        raise PathRejected(400, "backslashes are not allowed in the path")
    return decoded


def unservable_path(raw_path: str) -> str | None:
    """Why a raw path outside the served URLs can never name a file (http.md 9: answered 400, not 404): control
    characters (also encoded, as a smuggled CR LF), malformed or double escapes, encoded separators, non-ASCII,
    backslashes, '.' and '..' segments, over MAX_PATH_CHARS. None when it is merely unknown (404)."""
    if len(raw_path) > MAX_PATH_CHARS:
        return f"path longer than {MAX_PATH_CHARS} characters"
    if "\\" in raw_path:
        return "backslashes are not allowed in the path"
    for seg in raw_path.split("/"):
        try:
            decoded = percent_decode(seg)
        except PathRejected as exc:
            return exc.message
        if decoded in (".", ".."):
            return "'.' and '..' path segments are not allowed"
    return None


def check_segment(seg: str) -> None:
    if seg == "":
        raise PathRejected(404, "empty path segment (directories are not listed)")
    if seg in (".", ".."):
        raise PathRejected(400, "'.' and '..' path segments are not allowed")
    if seg.startswith("."):
        raise PathRejected(404, "hidden names (leading '.') are never served")
    if len(seg) > MAX_SEGMENT_CHARS or not SEGMENT_RE.match(seg):
        raise PathRejected(400, f"path segments use only the characters A-Z a-z 0-9 . _ - (got {seg[:64]!r})")


def parse_scene_path(raw_path: str) -> ScenePath:
    """Split a raw request path '/scenes/<scene id>/<file>' into scene id and file.

    Served files are exactly '<scene id>/manifest.msgpack' and '<scene id>/data/<digest>.bin' (the SHA-256 in 64
    hex digits, or its first 16 bytes in 32: format.md 6.2); anything else under /scenes/ is 404 (no directory
    listing, no other files). Raises PathRejected.
    """
    if len(raw_path) > MAX_PATH_CHARS:
        raise PathRejected(400, f"path longer than {MAX_PATH_CHARS} characters")
    m = _FAST_RE.fullmatch(raw_path)
    if m:
        kind = "payload" if m.group(3) else "manifest"
        return ScenePath(m.group(1)[:-1], m.group(2), kind, m.group(3))
    return parse_scene_path_general(raw_path)


def parse_scene_path_general(raw_path: str) -> ScenePath:
    """parse_scene_path without its fast path (which must agree with this wherever it matches)."""
    if len(raw_path) > MAX_PATH_CHARS:
        raise PathRejected(400, f"path longer than {MAX_PATH_CHARS} characters")
    if not raw_path.startswith(SCENES_PREFIX):
        raise PathRejected(404, "not under /scenes/")
    if "\\" in raw_path:
        raise PathRejected(400, "backslashes are not allowed in the path")
    segments = raw_path[len(SCENES_PREFIX):].split("/")
    decoded = [percent_decode(s) for s in segments]  # per segment: a decoded '/' never splits anything
    for seg in decoded:
        check_segment(seg)
    if decoded[-1] == MANIFEST_NAME:
        scene, rel, kind, sha = decoded[:-1], MANIFEST_NAME, "manifest", None
    elif len(decoded) >= 2 and decoded[-2] == DATA_DIR and PAYLOAD_NAME_RE.match(decoded[-1]):
        scene, rel, kind, sha = decoded[:-2], f"{DATA_DIR}/{decoded[-1]}", "payload", \
            decoded[-1].removesuffix(PAYLOAD_SUFFIX)
    else:
        raise PathRejected(404, f"a scene serves only {MANIFEST_NAME} and {DATA_DIR}/<sha256>.bin")
    if not scene:
        raise PathRejected(404, "no scene id in the path")
    if len(scene) > MAX_SCENE_DEPTH:
        raise PathRejected(404, f"scene ids have at most {MAX_SCENE_DEPTH} segments")
    return ScenePath("/".join(scene), rel, kind, sha)


def is_valid_scene_id(scene_id: str) -> bool:
    segs = scene_id.split("/")
    if not 1 <= len(segs) <= MAX_SCENE_DEPTH:
        return False
    try:
        for seg in segs:
            check_segment(seg)
    except PathRejected:
        return False
    return True


def is_inside(path: str, root: str) -> bool:
    """True when the resolved `path` lies strictly inside the resolved directory `root`."""
    root = root.rstrip(os.sep) or os.sep
    prefix = root if root == os.sep else root + os.sep
    return path.startswith(prefix) and len(path) > len(prefix)
