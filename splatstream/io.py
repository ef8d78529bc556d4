"""Reading and writing splat scenes in any supported format, chosen by content, not only by extension.

Readable: standard 3DGS PLY, PlayCanvas compressed PLY, Niantic SPZ (versions 2, 3, 4), antimatter15 .splat,
PlayCanvas SOG (bundled .sog, unbundled meta.json directory, streamed lod-meta.json), Spark .rad (finest
level), glTF/GLB with
KHR_gaussian_splatting (plain or SPZ-compressed).
Writable, chosen by the output's extension: .ply (standard 3DGS), .splat, .spz (SPZ v4 or v3), .glb
(KHR_gaussian_splatting, plain or SPZ-compressed), .sog (PlayCanvas SOG version 2, bundled). See
format_spec/foreign_formats.md for what each format keeps.
"""
from __future__ import annotations

import math
import os
import re
import stat
import warnings
import zlib
from collections.abc import Callable
from dataclasses import dataclass

from .errors import InputError
from .format.limits import describe_violations, domain_violations
from .format.names import MANIFEST_NAME, TILESET_NAME
from .gaussians import Gaussians
from .orientation import UpChoice, detect_up
from .ply import (
    MAX_HEADER_BYTES,
    PlyHeader,
    VertexLayout,
    read_gaussians_ply,
    read_header,
    vertex_layout,
    write_gaussians_ply,
)
from .reader_support import DROP_INVALID_HINT
from .readers.compressed_ply import is_compressed_ply, read_compressed_ply
from .readers.gltf import read_gltf
from .readers.rad import read_rad
from .readers.sog import read_sog, sog_kind
from .readers.splat import read_splat, write_splat
from .readers.spz import read_spz
from .writers.glb import write_glb
from .writers.sog import write_sog
from .writers.spz import write_spz

FORMAT_NAMES = {
    "ply": "standard 3DGS PLY",
    "compressed_ply": "PlayCanvas compressed PLY",
    "spz": "Niantic SPZ",
    "splat": "antimatter15 .splat",
    "sog": "PlayCanvas SOG",
    "lod_sog": "PlayCanvas streamed SOG (finest level)",
    "rad": "Spark RAD (finest level)",
    "gltf": "glTF with KHR_gaussian_splatting",
}
WRITABLE_EXTENSIONS = {".ply": "ply", ".splat": "splat", ".spz": "spz", ".glb": "gltf", ".sog": "sog"}
# Writable formats that hold fewer SH bands than the scene may have (.splat: colour alone, no bands).
WRITTEN_MAX_SH_DEGREE = {"splat": 0}
SPLAT_RECORD_BYTES = 32


def check_regular_file(path: str) -> None:
    """Refuse what is not a regular file before anything reads it (a FIFO or a device would block or never end)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(path, None, "no such file") from None
    except OSError as exc:
        raise InputError(path, None, f"cannot read ({exc.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(path, None, "is a directory (expected a splat file)")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(path, None, "not a regular file (a FIFO, device or socket cannot be read as a splat file)")
    if not os.access(path, os.R_OK):
        raise InputError(path, None, "cannot read (permission denied)")


@dataclass(frozen=True)
class SplatInput:
    """A splat input opened once: its format, from its content, and a PLY's parsed header. Every later step of a
    command (the reader, the up direction the header states, the rows a partitioned encode reads by byte ranges)
    takes this instead of opening and parsing the file again."""

    path: str
    format: str  # a FORMAT_NAMES key
    header: PlyHeader | None = None  # for 'ply' and 'compressed_ply'

    def vertex_layout(self) -> VertexLayout | None:
        """The row layout of a binary 3DGS PLY (ply.vertex_layout), None for any other input."""
        return vertex_layout(self.path, self.header) if self.format == "ply" else None

    def declared_up(self) -> UpChoice | None:
        """The up direction the file itself states: a comment in a PLY header naming it (up_from_comments); None
        for other formats (their readers apply what the format specifies) and for PLY files that say nothing."""
        if self.format != "ply" or self.header is None:
            return None
        up = up_from_comments(self.header.comments)
        if up is None:
            return None
        return UpChoice(up, f"{','.join(f'{v:g}' for v in up)} as the PLY header's comment says")


def open_input(path: str | os.PathLike) -> SplatInput:
    """Sniff a splat input (sniff_format) and keep what sniffing read (a PLY's header)."""
    path = os.fspath(path)
    fmt, header = _sniff(path)
    return SplatInput(path, fmt, header)


def sniff_format(path: str | os.PathLike) -> str:
    """Name of the format of a file, from its content: 'ply', 'compressed_ply', 'spz' or 'splat'.

    PLY and SPZ are recognised by their magic bytes whatever the file is called. A .splat file has no magic
    at all, so it is recognised only as "none of the above, named .splat, length a multiple of 32"; its
    reader then checks that the records are plausible.
    """
    return _sniff(os.fspath(path))[0]


# export-3dtiles' output given to convert, render, encode or eval: said 'unrecognised file format' (tileset.json) or
# 'a directory without meta.json or lod-meta.json', no word of what it is. Its tiles' .glb files are read.
_TILESET_SAID = (f"is a 3D Tiles tileset ({TILESET_NAME}, written by `splatstream export-3dtiles`), which CesiumJS "
                 "draws: not read as one scene (each tiles/<sha256>.glb is one tile, read as a glTF file); give the "
                 "scene it was exported from")


def _sniff(path: str) -> tuple[str, PlyHeader | None]:
    if os.path.isdir(path):
        kind = sog_kind(path)
        if kind is None and os.path.isfile(os.path.join(path, MANIFEST_NAME)):
            # Re-encoding one of our scenes at another preset (`encode out/logo out/logo_low --preset low`) said
            # only 'a directory without meta.json or lod-meta.json'.
            raise InputError(path, None, f"is a splatstream scene ({MANIFEST_NAME}), not a splat file: `splatstream "
                             f"decode {path} scene.ply` writes its full detail as a file that encode and convert read")
        if kind is None and os.path.isfile(os.path.join(path, TILESET_NAME)):
            raise InputError(path, None, _TILESET_SAID)
        if kind is None:
            raise InputError(path, None, "is a directory without meta.json or lod-meta.json (expected a splat file "
                             "or a SOG scene directory)")
        return ("lod_sog" if kind == "lod" else "sog"), None
    check_regular_file(path)
    with open(path, "rb") as f:
        head = f.read(MAX_HEADER_BYTES)
    if not head:
        raise InputError(path, None, "file is empty")
    if head.startswith(b"glTF"):
        return "gltf", None
    if head.startswith(b"RAD0"):
        return "rad", None
    kind = sog_kind(path) if head.startswith(b"PK\x03\x04") or head.lstrip().startswith(b"{") else None
    if kind is not None:
        return ("lod_sog" if kind == "lod" else "sog"), None
    if head.lstrip().startswith(b"{") and os.path.splitext(path)[1].lower() == ".gltf":
        return "gltf", None
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        header = read_header(path, head)
        return ("compressed_ply" if is_compressed_ply(header) else "ply"), header
    is_splat_name = os.path.splitext(path)[1].lower() == ".splat"
    if head.startswith(b"NGSP"):
        return "spz", None
    if head.startswith(b"\x1f\x8b"):
        # A .splat record can begin with these two bytes by chance (1 in 65536 for the first x coordinate), so
        # for a .splat-named file only a gzip stream that really holds an SPZ header counts as SPZ. Otherwise
        # the SPZ reader reports what is wrong with the gzip stream.
        if not is_splat_name or _gzip_starts_with(head, b"NGSP"):
            return "spz", None
    if is_splat_name:
        size = os.path.getsize(path)
        if size % SPLAT_RECORD_BYTES:
            raise InputError(path, "file length", f"{size} bytes is not a multiple of 32 (a .splat file is a sequence "
                             f"of 32-byte records; {size % 32} bytes left over: truncated?)")
        return "splat", None
    if os.path.basename(path) == TILESET_NAME:
        raise InputError(path, None, _TILESET_SAID)
    raise InputError(path, None, "unrecognised file format (expected a 3DGS PLY, a PlayCanvas compressed PLY, an "
                     "SPZ file, a .splat file, a SOG scene (.sog, meta.json, lod-meta.json), a Spark .rad or a "
                     "glTF/GLB file with KHR_gaussian_splatting)")


def _gzip_starts_with(head: bytes, prefix: bytes) -> bool:
    try:
        return zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, len(prefix)) == prefix
    except zlib.error:
        return False


def read_gaussians(source: str | os.PathLike | SplatInput, drop_invalid: bool = False) -> Gaussians:
    """Read any supported splat file (a path, or an input open_input has sniffed) into Gaussians, screened
    against the scene format's value domain (so whatever is read can be encoded and written again:
    format_spec/format.md 4.8)."""
    inp = source if isinstance(source, SplatInput) else open_input(source)
    return screen_gaussians(_read_any(inp, drop_invalid), inp.path, drop_invalid)


def read_merged(sources: list[SplatInput], drop_invalid: bool = False) -> Gaussians:
    """Merged inputs (splat-transform's combine): their splats one after the other, in the order given. SH bands an
    input lacks are zeros up to the highest degree among them (Gaussians.concatenate), so every input looks as it
    did; --sh-degree lowers them all."""
    return Gaussians.concatenate([read_gaussians(s, drop_invalid=drop_invalid) for s in sources])


def screen_gaussians(g: Gaussians, path: str, drop_invalid: bool = False) -> Gaussians:
    """`g` if every splat lies in the value domain of format.md 4.8; otherwise an InputError naming the file,
    each offending field and its splat count, or with `drop_invalid` `g` without those splats (a warning)."""
    violations = domain_violations(g)
    if not violations:
        return g
    bad, message = describe_violations(violations, len(g))
    if not drop_invalid:
        raise InputError(path, None, f"{message}; {DROP_INVALID_HINT}")
    warnings.warn(f"{path}: {message}; dropped", stacklevel=3)
    return g.subset(~bad)


_NUM = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?)"
_UP_VECTOR = re.compile(r"\bup(?:[ _-]?(?:axis|vector))?\s*[:=]?\s*\(?\s*" + r"\s*[, ]\s*".join([_NUM] * 3), re.I)
_UP_AFTER = re.compile(r"\bup(?:[ _-]?(?:axis|vector))?\s*(?:[:=]|is)?\s*([-+]?)([xyz])\b", re.I)
_UP_BEFORE = re.compile(r"(?:^|[^\w+-])([-+]?)([xyz])[ _-]?up\b", re.I)


def up_from_comments(comments: list[str]) -> tuple[float, float, float] | None:
    """The up direction a PLY header comment names: 'up 0 0 1', 'up_axis: z', 'z-up', 'Z_UP', 'up = -y' ..."""
    for text in comments:
        m = _UP_VECTOR.search(text)
        if m:
            v = tuple(float(x) for x in m.groups())
            if any(v) and all(math.isfinite(x) for x in v):
                n = math.sqrt(sum(x * x for x in v))
                return tuple(x / n + 0.0 for x in v)  # type: ignore[return-value]
        m = _UP_AFTER.search(text) or _UP_BEFORE.search(text)
        if m:
            sign = -1.0 if m.group(1) == "-" else 1.0
            axis = "xyz".index(m.group(2).lower())
            return tuple(sign if a == axis else 0.0 for a in range(3))  # type: ignore[return-value]
    return None


def declared_up(path: str | os.PathLike) -> UpChoice | None:
    """The up direction a splat file itself states (SplatInput.declared_up); None also for a file that cannot be
    opened (its reader reports that)."""
    try:
        return open_input(path).declared_up()
    except (InputError, OSError):
        return None


def scene_up(path: str | os.PathLike, g: Gaussians, positions=None) -> UpChoice:
    """The up direction of the scene in a file: what the file states (declared_up), else detected from the
    splats (orientation.detect_up)."""
    return declared_up(path) or detect_up(g, positions)


def _read_any(inp: SplatInput, drop_invalid: bool) -> Gaussians:
    path, fmt = inp.path, inp.format
    if fmt == "ply":
        return read_gaussians_ply(path, drop_invalid=drop_invalid, header=inp.header)
    if fmt == "compressed_ply":
        return read_compressed_ply(path, drop_invalid=drop_invalid, header=inp.header)
    if fmt == "spz":
        return read_spz(path, drop_invalid=drop_invalid)
    if fmt == "splat":
        return read_splat(path, drop_invalid=drop_invalid)
    if fmt in ("sog", "lod_sog"):
        return read_sog(path, drop_invalid=drop_invalid)
    if fmt == "rad":
        return read_rad(path)
    if fmt == "gltf":
        return read_gltf(path, drop_invalid=drop_invalid)
    raise InputError(path, None, f"no reader for format {fmt!r}")


def output_format(path: str | os.PathLike) -> str:
    """Writer for an output path, from its extension; raises InputError for extensions we cannot write."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if os.fspath(path).lower().endswith(".compressed.ply"):
        # PlayCanvas's name for its compressed PLY, which we read but do not write: `convert x.spz x.compressed.ply`
        # wrote a standard 3DGS PLY (4x the bytes) under that name.
        raise InputError(path, None, "cannot write PlayCanvas compressed PLY (the .compressed.ply name; it is read, "
                         "not written): name it .ply for a standard 3DGS PLY, or write .sog or .spz for a compact "
                         "file")
    if ext not in WRITABLE_EXTENSIONS:
        raise InputError(path, None, f"cannot write {ext or 'extensionless'} files (expected one of "
                         f"{', '.join(WRITABLE_EXTENSIONS)})")
    return WRITABLE_EXTENSIONS[ext]


def written_sh_degree(fmt: str, sh_degree: int) -> int:
    """The SH degree a file of writable format `fmt` holds when Gaussians of `sh_degree` are written to it."""
    return min(sh_degree, WRITTEN_MAX_SH_DEGREE.get(fmt, sh_degree))


def write_gaussians(g: Gaussians, path: str | os.PathLike, spz_version: int = 4,
                    glb_compression: str = "none", progress: Callable[[float], None] | None = None) -> None:
    """Write Gaussians (atomically) to a file whose format follows the extension (.ply, .splat, .spz, .glb, .sog).

    spz_version: 3 or 4 for .spz outputs. glb_compression: "none" or "spz" for .glb outputs. `progress`: the share
    of a .sog written (its SH palette's fit takes seconds; the other formats are written in one step).
    """
    fmt = output_format(path)
    if fmt == "ply":
        write_gaussians_ply(g, path)
    elif fmt == "spz":
        write_spz(g, path, spz_version)
    elif fmt == "gltf":
        write_glb(g, path, glb_compression)
    elif fmt == "sog":
        write_sog(g, path, progress)
    else:
        write_splat(g, path)
