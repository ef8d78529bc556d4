"""Serving exported 3D Tiles tilesets beside scenes (format_spec/http.md 14).

A **tileset** is a directory below the root that holds `tileset.json` and is not a scene (no `manifest.msgpack`).
It serves exactly `tileset.json` (revalidated: `no-cache`, strong ETag from its bytes), `tiles/<sha256>.glb` and
the external tilesets `tiles/<sha256>.json` (named by the SHA-256 of their bytes: immutable), under the same URL,
segment, containment, conditional, range and CORS rules as scenes. Self-contained: `parse_tileset_path` answers
None for any path that is not a tileset file (the scene rules then apply), and `open_tileset_file` opens what it
accepts with the checks of `SceneRoot.open`.
"""
from __future__ import annotations

import hashlib
import os
import stat
from dataclasses import dataclass

from splatstream.format.names import (
    MANIFEST_NAME,
    TILESET_CONTENT_DIR,
    TILESET_CONTENT_NAME_RE,
    TILESET_EXTERNAL_NAME_RE,
    TILESET_EXTERNAL_SUFFIX,
    TILESET_NAME,
)

from .paths import (
    MAX_PATH_CHARS,
    MAX_SCENE_DEPTH,
    SCENES_PREFIX,
    SEGMENT_RE,
    PathRejected,
    check_segment,
    is_inside,
    percent_decode,
)
from .scenes import (
    SMALL_FILE_BYTES,
    NotFound,
    OpenedFile,
    SceneRoot,
    read_first_bytes,
    real_path_of_fd,
    walk_root,
)

TILESET_TYPE = "application/json"
CONTENT_TYPE = "model/gltf-binary"
MAX_TILESET_BYTES = 64 << 20  # as a manifest: a tileset.json of a million tiles is far below this


@dataclass(frozen=True)
class TilesetPath:
    tileset_id: str  # "a/b": segments joined with "/"
    rel: str  # "tileset.json", "tiles/<sha256>.glb" or "tiles/<sha256>.json"
    kind: str  # "tileset", "content" or "external" (an external tileset)
    sha256: str | None = None  # content and external: the hash its name carries


def parse_tileset_path(raw_path: str) -> TilesetPath | None:
    """A raw request path naming a tileset file ('/scenes/<id>/tileset.json', '/scenes/<id>/tiles/<sha>.glb',
    '/scenes/<id>/tiles/<sha>.json'), or None when it names no such file. Raises PathRejected for what no served
    path may contain (the rules of server.paths: encoded separators, dot segments, hidden names, ...)."""
    if len(raw_path) > MAX_PATH_CHARS or not raw_path.startswith(SCENES_PREFIX):
        return None
    if not (raw_path.endswith(".glb") or raw_path.endswith(TILESET_EXTERNAL_SUFFIX)):
        return None  # the common case (scene files) costs one comparison
    if "\\" in raw_path:
        raise PathRejected(400, "backslashes are not allowed in the path")
    decoded = [percent_decode(s) for s in raw_path[len(SCENES_PREFIX):].split("/")]
    for seg in decoded:
        check_segment(seg)
    if decoded[-1] == TILESET_NAME:
        ids, rel, kind, sha = decoded[:-1], TILESET_NAME, "tileset", None
    elif len(decoded) >= 2 and decoded[-2] == TILESET_CONTENT_DIR and TILESET_CONTENT_NAME_RE.match(decoded[-1]):
        ids, rel, kind, sha = decoded[:-2], f"{TILESET_CONTENT_DIR}/{decoded[-1]}", "content", decoded[-1][:64]
    elif len(decoded) >= 2 and decoded[-2] == TILESET_CONTENT_DIR and TILESET_EXTERNAL_NAME_RE.match(decoded[-1]):
        ids, rel, kind, sha = decoded[:-2], f"{TILESET_CONTENT_DIR}/{decoded[-1]}", "external", decoded[-1][:64]
    else:
        return None
    if not ids:
        raise PathRejected(404, "no tileset id in the path")
    if len(ids) > MAX_SCENE_DEPTH:
        raise PathRejected(404, f"tileset ids have at most {MAX_SCENE_DEPTH} segments")
    return TilesetPath("/".join(ids), rel, kind, sha)


def _is_regular(path: str) -> bool:
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def open_tileset_file(root: SceneRoot, tp: TilesetPath) -> OpenedFile:
    """Open a validated tileset file; NotFound unless it is a regular file of a tileset (a directory with
    tileset.json and without manifest.msgpack), inside the root."""
    directory = f"{root.root}/{tp.tileset_id}"
    missing = f"no tileset {tp.tileset_id!r}" if tp.kind == "tileset" else \
        f"no file {tp.rel!r} in tileset {tp.tileset_id!r}"
    if _is_regular(f"{directory}/{MANIFEST_NAME}"):  # a scene: serves only its own two kinds of file
        raise NotFound(f"{tp.tileset_id!r} is a scene, not a tileset")
    if tp.kind != "tileset" and not _is_regular(f"{directory}/{TILESET_NAME}"):
        raise NotFound(f"no tileset {tp.tileset_id!r}")
    path = f"{directory}/{tp.rel}"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)  # (a FIFO must not hang the server)
    except OSError:
        raise NotFound(missing) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotFound(missing)
        real = real_path_of_fd(fd, path)
        if not root.contains_real_path(real):
            raise NotFound(missing)
        size, data = st.st_size, None
        if tp.kind != "tileset":  # content-addressed: the name is the ETag
            token = tp.sha256
            if size <= SMALL_FILE_BYTES:
                data = read_first_bytes(fd, size)
                size = len(data)
        else:
            if size > MAX_TILESET_BYTES:
                raise NotFound(f"tileset.json of {tp.tileset_id!r} is larger than {MAX_TILESET_BYTES} bytes")
            data = read_first_bytes(fd, size)  # hashed for its ETag (small, and fetched once per view)
            size = len(data)
            token = hashlib.sha256(data).hexdigest()
        assert token is not None
        return OpenedFile(fd, size, token, data)
    except BaseException:
        os.close(fd)
        raise


def find_tilesets(root: str, limit: int = 10_000) -> list[str]:
    """Ids of the tilesets under `root` (for `splatstream serve`'s start check), sorted: directories with safe
    names, at most MAX_SCENE_DEPTH deep, not hidden, not inside a scene or a tileset, links only inside the root."""
    real_root = os.path.realpath(root)
    found: list[str] = []

    def visit(e: os.DirEntry, segs: tuple[str, ...]) -> bool:
        if not SEGMENT_RE.match(e.name) or not e.is_dir() or (
                e.is_symlink() and not is_inside(os.path.realpath(e.path), real_root)):
            return False
        if _is_regular(os.path.join(e.path, MANIFEST_NAME)):
            return False
        if _is_regular(os.path.join(e.path, TILESET_NAME)):
            found.append("/".join(segs))
            return False
        return True

    walk_root(root, visit, limit)
    return sorted(found)
