"""Reading and writing splat scenes in any supported format, chosen by content, not only by extension."""
from __future__ import annotations

import os

from .errors import InputError
from .gaussians import Gaussians


def sniff_format(path: str | os.PathLike) -> str:
    """Name of the format of a file, from its first bytes: 'ply' (standard 3DGS PLY)."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except IsADirectoryError:
        raise InputError(path, None, "is a directory (expected a splat file)") from None
    if not head:
        raise InputError(path, None, "file is empty")
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        return "ply"
    raise InputError(path, None, "unrecognised file format (expected a 3DGS PLY)")


def read_gaussians(path: str | os.PathLike, drop_invalid: bool = False) -> Gaussians:
    """Read any supported splat file into Gaussians."""
    from .ply import read_gaussians_ply

    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(path, None, "no such file")
    fmt = sniff_format(path)
    if fmt == "ply":
        return read_gaussians_ply(path, drop_invalid=drop_invalid)
    raise InputError(path, None, f"no reader for format {fmt!r}")


def write_gaussians(g: Gaussians, path: str | os.PathLike) -> None:
    """Write Gaussians to a file whose format follows the extension (.ply)."""
    from .ply import write_gaussians_ply

    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".ply":
        write_gaussians_ply(g, path)
        return
    raise InputError(path, None, f"cannot write {ext or 'extensionless'} files (expected .ply)")
