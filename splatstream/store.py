"""Where a scene's bytes live: a directory on disk or memory (the HTTP client has its own, asynchronous side).

Readers take a `SceneStore` (manifest bytes, payload bytes by relative path) and never open files themselves;
the encoder writes through a `SceneWriter` (payloads streamed in, the manifest last, published atomically).
The byte layout and names come from splatstream.format; nothing here decodes.
"""
from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import BinaryIO, Protocol

from .atomic import atomic_directory
from .errors import FormatError, InputError, UsageError
from .format.manifest import (
    MAX_MANIFEST_BYTES,
    Manifest,
    PayloadEntry,
    pack_manifest,
    parse_manifest,
    resolve_pages,
    short_tile_names,
    split_pages,
)
from .format.names import DATA_DIR, MANIFEST_NAME, TILESET_NAME, is_payload_path


class SceneStore(Protocol):
    """Read access to one scene's files."""

    location: str  # the scene's path or URL, for messages

    def read_manifest(self) -> bytes: ...

    def read_payload(self, entry: PayloadEntry) -> bytes: ...

    def payload_source(self, entry: PayloadEntry) -> str:
        """Where a payload is, for messages."""
        ...


def _read_regular(path: str, limit: int) -> bytes:
    """A regular file's bytes; FIFOs, devices and directories are refused before any read could block."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise FormatError(path, None, "no such file") from None
    except IsADirectoryError:
        raise FormatError(path, None, "is a directory, expected a file") from None
    except OSError as exc:
        raise FormatError(path, None, f"cannot open ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FormatError(path, None, "not a regular file (a FIFO, device or socket cannot be a scene file)")
        if st.st_size > limit:
            raise FormatError(path, None, f"{st.st_size} bytes, more than the {limit} bytes expected")
        with os.fdopen(fd, "rb", closefd=False) as f:
            return f.read(limit + 1)
    finally:
        os.close(fd)


@dataclass
class DirectoryStore:
    """A scene directory on the local file system."""

    path: str

    def __post_init__(self) -> None:
        self.path = os.fspath(self.path)
        # `info scene/manifest.msgpack` (a path completed one step too far) names the scene it is the manifest of
        if os.path.basename(self.path) == MANIFEST_NAME and os.path.isfile(self.path):
            self.path = os.path.dirname(self.path) or "."
        if not os.path.isdir(self.path):
            what = "no such directory" if not os.path.exists(self.path) else "not a directory"
            # `info playbot/lod-meta.json` is a new user's first try: say which commands read such a file
            hint = ("; a splat file or a streamed SOG's lod-meta.json is read by `splatstream encode`, `convert`, "
                    "`view`, `render` and `eval`" if os.path.isfile(self.path) else "")
            raise FormatError(self.path, None, f"{what} (expected a scene directory holding {MANIFEST_NAME}{hint})")

    @property
    def location(self) -> str:
        return self.path

    @property
    def manifest_path(self) -> str:
        return os.path.join(self.path, MANIFEST_NAME)

    def read_manifest(self) -> bytes:
        path = self.manifest_path
        if not os.path.lexists(path):
            # Another tool's scene directory (a streamed SOG, an unbundled SOG) is a likely mistake: say what reads it.
            foreign = [n for n in ("lod-meta.json", "meta.json") if os.path.isfile(os.path.join(self.path, n))]
            hint = (f" ({foreign[0]} here: a SOG scene, which `splatstream encode` or `convert` reads)"
                    if foreign else "")
            if not foreign and os.path.isfile(os.path.join(self.path, TILESET_NAME)):
                # export-3dtiles' output (`info tiles/garden`): said only 'not a splatstream scene directory'
                hint = (f" ({TILESET_NAME} here: a 3D Tiles tileset written by `splatstream export-3dtiles`, which "
                        "CesiumJS draws; the scene directory it was exported from is read here)")
            raise FormatError(path, None, f"no such file: not a splatstream scene directory{hint}")
        return _read_regular(path, MAX_MANIFEST_BYTES)

    def payload_source(self, entry: PayloadEntry) -> str:
        return os.path.join(self.path, entry.file)

    def read_payload(self, entry: PayloadEntry) -> bytes:
        if not is_payload_path(entry.file):  # a validated manifest never names another path; belt and braces
            raise FormatError(self.manifest_path, "file", f"unsafe payload path {entry.file!r}")
        path = self.payload_source(entry)
        if not os.path.lexists(path):
            raise FormatError(path, None, "payload file named in the manifest is missing")
        return _read_regular(path, entry.bytes)


@dataclass
class MemoryStore:
    """A scene held in memory (encoded from a splat file for viewing, or built by tests)."""

    manifest_bytes: bytes
    payloads: dict[str, bytes] = field(default_factory=dict)  # relative path -> bytes
    location: str = "<memory>"

    def read_manifest(self) -> bytes:
        return self.manifest_bytes

    def payload_source(self, entry: PayloadEntry) -> str:
        return f"{self.location}/{entry.file}"

    def read_payload(self, entry: PayloadEntry) -> bytes:
        try:
            return self.payloads[entry.file]
        except KeyError:
            raise FormatError(self.payload_source(entry), None, "payload named in the manifest is missing") from None


def is_url(location: str | os.PathLike) -> bool:
    """A location given as an fsspec URL (`s3://`, `gs://`, `memory://`, ...), not a local path."""
    return isinstance(location, str) and "://" in location and not location.startswith("file://")


def local_path(location: str | os.PathLike) -> str:
    """A local path, `file://` URLs included."""
    location = os.fspath(location)
    return location[len("file://"):] if location.startswith("file://") else location


def fsspec_filesystem(url: str):
    """(filesystem, root path) of an fsspec URL; fsspec is optional (`pip install 'splatstream[cluster]'`)."""
    try:
        import fsspec  # an optional extra, imported only for URLs
    except ImportError:
        raise UsageError(f"{url}: object-store and fsspec URLs need fsspec "
                         "(pip install 'splatstream[cluster]', plus s3fs or gcsfs for s3:// or gs://)") from None
    try:
        fs, root = fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as exc:
        raise UsageError(f"{url}: cannot open this URL ({exc})") from None
    return fs, root.rstrip("/")


def check_store_reachable(url: str) -> None:
    """List an output URL's prefix once before an encode's work, so that a store the encode cannot reach (no
    credentials, access denied, no such host) is one line naming the URL at the start, not an unexpected exception
    from the first payload's write after the whole encode. A prefix that does not exist yet is fine: the encode
    creates it."""
    fs, root = fsspec_filesystem(url)
    try:
        fs.ls(root, detail=False)
    except FileNotFoundError:
        return
    except Exception as exc:  # each store's client raises its own classes (botocore, google.auth, ...)
        raise InputError(url, None, f"cannot reach the object store ({type(exc).__name__}: {exc}); check the URL "
                         "and the store's credentials (for s3://, AWS_PROFILE or AWS_ACCESS_KEY_ID)") from None


class FsspecStore:
    """A scene under an fsspec URL (an object store bucket prefix, `memory://` in tests): the layout of a scene
    directory (format_spec/format.md 1), read object by object."""

    def __init__(self, url: str):
        self.url = url.rstrip("/")
        self.fs, self.root = fsspec_filesystem(url)

    @property
    def location(self) -> str:
        return self.url

    def _read(self, name: str, limit: int, what: str) -> bytes:
        path = f"{self.root}/{name}"
        try:
            data = self.fs.cat_file(path)
        except FileNotFoundError:
            raise FormatError(f"{self.url}/{name}", None, f"no such object{what}") from None
        except OSError as exc:
            raise FormatError(f"{self.url}/{name}", None, f"cannot read ({exc})") from None
        if len(data) > limit:
            raise FormatError(f"{self.url}/{name}", None, f"{len(data)} bytes, more than the {limit} bytes expected")
        return data

    def read_manifest(self) -> bytes:
        return self._read(MANIFEST_NAME, MAX_MANIFEST_BYTES, ": not a splatstream scene")

    def payload_source(self, entry: PayloadEntry) -> str:
        return f"{self.url}/{entry.file}"

    def read_payload(self, entry: PayloadEntry) -> bytes:
        if not is_payload_path(entry.file):
            raise FormatError(f"{self.url}/{MANIFEST_NAME}", "file", f"unsafe payload path {entry.file!r}")
        return self._read(entry.file, entry.bytes, " (payload named in the manifest is missing)")


def open_store(source: str | os.PathLike | SceneStore) -> SceneStore:
    if isinstance(source, (str, os.PathLike)):
        if is_url(source):
            return FsspecStore(source)
        return DirectoryStore(local_path(source))
    return source


def read_manifest(store: SceneStore) -> Manifest:
    """The validated manifest of a scene, its whole tree: a paged scene's pages are read and checked too (format.md
    6.1; a streaming client reads them when its cut reaches them instead)."""
    source = store.manifest_path if isinstance(store, DirectoryStore) else f"{store.location}/{MANIFEST_NAME}"
    raw = store.read_manifest()
    return resolve_pages(parse_manifest(raw, source), store.read_payload, source, len(raw))


def load_manifest(scene: str | os.PathLike | SceneStore) -> Manifest:
    """The validated manifest of a scene directory (or store), with every tile (a paged scene's pages read)."""
    return read_manifest(open_store(scene))


def is_scene_dir(path: str | os.PathLike) -> bool:
    return os.path.isfile(os.path.join(path, MANIFEST_NAME))


# --------------------------------------------------------------------------------------------------------------
# Writing


class SceneWriter(Protocol):
    """Where the encoder puts a scene: payloads first (content-addressed, any order, from any worker thread),
    then the manifest, which publishes the scene."""

    def payload_file(self) -> contextlib.AbstractContextManager[tuple[BinaryIO, callable]]: ...

    def write_manifest(self, m: Manifest) -> None: ...

    def payload_writer(self) -> PayloadWriter:
        """What a worker (another thread, process or machine) writes payloads through: small and picklable."""
        ...


class PayloadWriter(Protocol):
    def payload_file(self) -> contextlib.AbstractContextManager[tuple[BinaryIO, callable]]: ...


def write_scene_manifest(writer: SceneWriter, m: Manifest, page_tiles: int, page_levels: int,
                         compact_table: bool = False, short_digests: bool = True, *, short_names: bool,
                         relative_boxes: bool = True) -> Manifest:
    """Publish a scene's manifest: as it is, or, for a tree of more than `page_tiles` tiles (0: never), as a root
    manifest and its pages (format.md 6.1), the pages written like payloads before the root that names them.
    compact_table: a tree's tiles as the compact tile table (format.md 6.2: Manifest.compacted), its files named by
    short digests (version 1.15: `data/<32 hex>.bin`) unless short_digests is False (1.12), its boxes relative to
    their parents' (1.16) unless relative_boxes is False (1.15; each page's top tiles are its table's anchors:
    Manifest.compacted's page_levels). short_names: the tile
    payloads were written under their short digests' names (the payload jobs', TileContext.short_names): nothing is
    renamed here, so it must be what these options make of `m` (table.short_tile_names; a ValueError otherwise).
    Returns the whole manifest as a reader of the scene gets it (load_manifest: every tile; a paged scene's version,
    `paged` and `bytes_on_disk` from its root)."""
    short = short_tile_names(len(m.tiles) > 1, compact_table, short_digests)
    if short != short_names:
        raise ValueError(f"{m.name}: the tile payloads were written under {'short' if short_names else 'whole'} "
                         f"digests' names, the manifest would name them by {'short' if short else 'whole'} ones")
    if compact_table and len(m.tiles) > 1:
        paging = page_tiles and len(m.tiles) > page_tiles
        compact = m.compacted(short_digests, relative_boxes, page_levels if paging else 0)
        if short:
            _check_short_names(m, compact)
        m = compact
    if not page_tiles or len(m.tiles) <= page_tiles:
        writer.write_manifest(m)
        return m
    paged = split_pages(m, page_levels)
    for ref, raw in paged.pages:
        with writer.payload_file() as (f, finish):
            f.write(raw)
            f.flush()
            finish(ref)
    writer.write_manifest(paged.root)
    root = paged.root
    return replace(m, version=root.version, paged=root.paged, bytes_on_disk=root.bytes_on_disk)


def _check_short_names(whole: Manifest, short: Manifest) -> None:
    """That no two tile payloads share a short name (Manifest.compacted(short)): two whose SHA-256 share their first
    16 bytes (a 128-bit prefix collision, never seen) were written as one file, so they refuse the scene."""
    named: dict[str, str] = {}
    for a, b in zip(whole.tiles, short.tiles, strict=True):
        for name, e in a.groups.items():
            file = b.groups[name].file
            if named.setdefault(file, e.sha256) != e.sha256:
                raise FormatError(whole.name, "tile_table", f"two payloads whose SHA-256 share their first 16 bytes "
                                  f"({file}): the scene cannot be named by short digests (encode --no-short-digests)")


@dataclass
class DirectoryPayloads:
    """Payload files written straight into a scene directory's `data/` (under a DirectoryWriter's temporary
    directory): a temporary name, then a rename to the checksum's name, so a worker that dies halfway leaves no
    payload under a real name, and two workers writing the same payload write the same bytes."""

    directory: str
    mode: int = 0o644

    @contextlib.contextmanager
    def payload_file(self) -> Iterator[tuple[BinaryIO, callable]]:
        """(file to stream into, finish(entry)): finish names the file by its checksum."""
        fd, tmp_path = tempfile.mkstemp(prefix=".payload.", dir=os.path.join(self.directory, DATA_DIR))
        done = False

        def finish(entry: PayloadEntry) -> None:
            nonlocal done
            os.chmod(tmp_path, self.mode)
            os.replace(tmp_path, os.path.join(self.directory, entry.file))  # identical content, identical name
            done = True

        try:
            with os.fdopen(fd, "wb") as f:
                yield f, finish
        finally:
            if not done:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(tmp_path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class DirectoryWriter:
    """Builds a scene under a hidden temporary directory and swaps it into place when the manifest is written.

    Use as a context manager: leaving it with an exception removes everything written."""

    def __init__(self, out_dir: str | os.PathLike):
        self.out_dir = os.fspath(out_dir)
        self._atomic = atomic_directory(self.out_dir, holds=MANIFEST_NAME)
        self._mode = 0o666 & ~_umask()  # payloads as readable as any file the user writes (mkstemp gives 0600)
        self.tmp = ""
        self.published = False

    def __enter__(self) -> DirectoryWriter:
        self.tmp = self._atomic.__enter__()
        os.makedirs(os.path.join(self.tmp, DATA_DIR))
        return self

    def __exit__(self, *exc) -> bool | None:
        return self._atomic.__exit__(*exc)

    def payload_writer(self) -> DirectoryPayloads:
        return DirectoryPayloads(self.tmp, self._mode)

    def payload_file(self) -> contextlib.AbstractContextManager[tuple[BinaryIO, callable]]:
        return self.payload_writer().payload_file()

    def write_manifest(self, m: Manifest) -> None:
        path = os.path.join(self.tmp, MANIFEST_NAME)
        with open(path, "wb") as f:
            f.write(pack_manifest(m))
        os.chmod(path, self._mode)


class MemoryWriter:
    """Collects a scene in memory; `store()` gives it back as a MemoryStore."""

    def __init__(self, location: str = "<memory>"):
        self.payloads: dict[str, bytes] = {}
        self.manifest: Manifest | None = None
        self.location = location

    def __enter__(self) -> MemoryWriter:
        return self

    def __exit__(self, *exc) -> None:
        return None

    @contextlib.contextmanager
    def payload_file(self) -> Iterator[tuple[BinaryIO, callable]]:
        import io

        buf = io.BytesIO()

        def finish(entry: PayloadEntry) -> None:
            self.payloads[entry.file] = buf.getvalue()

        yield buf, finish

    def write_manifest(self, m: Manifest) -> None:
        self.manifest = m

    def payload_writer(self) -> MemoryWriter:
        return self  # in this process only

    def store(self) -> MemoryStore:
        if self.manifest is None:
            raise InputError(self.location, None, "the scene has no manifest yet")
        return MemoryStore(pack_manifest(self.manifest), dict(self.payloads), self.location)



class FsspecWriter:
    """Writes a scene under an fsspec URL (`s3://bucket/scene`, `gs://...`, `memory://...`).

    Payloads are written first, each as one object named by its checksum (an object store's PUT is atomic, so a
    reader never sees half a payload; workers on any machine write them with no coordination); the manifest is
    written last and only after every payload it names is listed under the prefix, so the scene appears, or
    changes to the new version, in one step. An interrupted encode writes no manifest: payloads it wrote stay
    as unreferenced objects (named by content, harmless; `delete_unreferenced` can remove them). Payloads of an
    earlier scene at the same URL are kept (clients may still be streaming it)."""

    def __init__(self, url: str):
        self.url = url.rstrip("/")
        self.fs, self.root = fsspec_filesystem(url)
        if not getattr(self.fs, "auto_mkdir", True):
            # a filesystem of real directories (local://, file://) does not make a file's parent as an object
            # store's key does: data/ first, or the first payload's write fails
            self.fs.makedirs(f"{self.root}/{DATA_DIR}", exist_ok=True)

    def __enter__(self) -> FsspecWriter:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def __getstate__(self) -> dict:
        return {"url": self.url}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["url"])

    def payload_writer(self) -> FsspecWriter:
        return self

    @contextlib.contextmanager
    def payload_file(self) -> Iterator[tuple[BinaryIO, callable]]:
        import io

        buf = io.BytesIO()

        def finish(entry: PayloadEntry) -> None:
            self.fs.pipe_file(f"{self.root}/{entry.file}", buf.getvalue())

        yield buf, finish

    def written_payloads(self) -> set[str]:
        try:
            found = self.fs.find(f"{self.root}/{DATA_DIR}")
        except FileNotFoundError:
            return set()
        return {f"{DATA_DIR}/{p.rstrip('/').rsplit('/', 1)[-1]}" for p in found}

    def write_manifest(self, m: Manifest) -> None:
        named = {p.file for _, _, p in m.payloads()} | {t.page.file for t in m.tiles if t.page is not None}
        missing = named - self.written_payloads()
        if missing:
            raise FormatError(self.url, None, f"{len(missing)} payloads named by the manifest are not in the store "
                              f"(e.g. {sorted(missing)[0]}); the manifest is not written")
        self.fs.pipe_file(f"{self.root}/{MANIFEST_NAME}", pack_manifest(m))


def open_writer(location: str | os.PathLike) -> DirectoryWriter | FsspecWriter:
    """The SceneWriter for a local directory (atomic directory swap) or an fsspec URL (manifest last)."""
    if is_url(location):
        return FsspecWriter(os.fspath(location))
    return DirectoryWriter(local_path(location))
