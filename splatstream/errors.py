"""Errors raised by the library. Only the CLI and the HTTP handlers turn them into exit codes and statuses."""
from __future__ import annotations

import os


class SplatstreamError(Exception):
    """Base class of every error the library raises on purpose (bad input, bad arguments)."""


class InputError(SplatstreamError):
    """An input file is not what it claims to be.

    The message names the file, the field (property, header line, chunk, ...) and what was expected,
    so a user can fix the input without reading our code.
    """

    def __init__(self, path: str | os.PathLike | None, field: str | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.field = field
        self.problem = problem
        where = self.path or "<input>"
        super().__init__(f"{where}: {field}: {problem}" if field else f"{where}: {problem}")


class FormatError(InputError):
    """An encoded splatstream scene (manifest or payload) violates format_spec/."""


class UsageError(SplatstreamError):
    """Arguments that cannot work together (unknown preset, bad override, ...)."""
