"""The `splatstream` command. Each subcommand lives in splatstream/commands/<name>.py and exposes
`register(subparsers)`; this shell turns library errors into messages and exit codes."""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from . import __version__
from .errors import SplatstreamError

COMMANDS = ["encode", "decode", "info", "convert", "render", "eval", "serve"]

EXIT_BAD_INPUT = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="splatstream",
        description="Compact, streamable 3D Gaussian Splatting scenes.",
    )
    parser.add_argument("--version", action="version", version=f"splatstream {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        try:
            module = importlib.import_module(f".commands.{name}", __package__)
        except ModuleNotFoundError as exc:
            if exc.name == f"{__package__}.commands.{name}":
                continue
            raise
        module.register(sub)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"splatstream: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    warnings.showwarning = _show_warning
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        rc = args.func(args)
    except SplatstreamError as exc:
        print(f"splatstream {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"splatstream {args.command}: interrupted", file=sys.stderr)
        return 130
    except (OSError, MemoryError) as exc:
        print(f"splatstream {args.command}: error: {exc}", file=sys.stderr)
        return 1
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
