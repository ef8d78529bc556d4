"""The `splatstream` command. Each subcommand lives in cli/commands/<name>.py and exposes
`register(subparsers)`; this shell turns library errors into messages and exit codes."""
from __future__ import annotations

import argparse
import difflib
import errno
import importlib
import os
import re
import signal
import sys
import threading
import warnings

from splatstream import __version__
from splatstream.errors import SplatstreamError
from splatstream.progress import end_open_line

from .commands.edit_flags import attach_negative_values  # numpy-free: see the BLAS note below

# One BLAS thread per thread of ours, unless the environment says otherwise (numpy is not imported yet here). The
# encoder runs its own worker threads, and OpenBLAS's threads on top of them oversubscribed the cores, tripling the
# CPU time of an LOD encode (issue 32; BENCHMARKS.md, "Encode time with the LOD tree"). Library callers can do the
# same (threadpoolctl).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

COMMANDS = ["encode", "decode", "info", "convert", "render", "view", "eval", "serve", "export-3dtiles",
            "export-sog-lod", "export-rad"]

# Exit codes (README "Exit codes"): 0 success, 2 bad input or usage (the user can fix it: a file, an argument, a
# path, a port), 1 a failure inside splatstream or the machine (a bug, out of memory, a disk error), 130 Ctrl-C.
EXIT_FAILURE = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # 128 + SIGTERM, what a shell reports for a process SIGTERM ended
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: the reader of stdout closed it (a shell reports the same for `cmd | head`)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C, so every cleanup path (atomic outputs, worker pools) that
    runs on Ctrl-C runs on `kill`, `timeout` or a service manager's stop too."""


def _on_sigterm(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the cleanup short
    raise Terminated()


def _is_number_list(text: str) -> bool:
    """'-2.9,-1.7,0', '-8.5', '-1e3': one or more comma-separated numbers."""
    try:
        for part in text.split(","):
            float(part)
    except ValueError:
        return False
    return True


def _single_value_options(parser: argparse.ArgumentParser) -> set[str]:
    """The option strings of `parser` and of all its subcommands that take exactly one value."""
    found: set[str] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found |= _single_value_options(sub)
        elif action.option_strings and action.nargs is None:
            found.update(action.option_strings)
    return found


def join_negative_values(argv: list[str], options: set[str]) -> list[str]:
    """`--eye -2.9,-1.7,0` as typed: argparse takes a value that starts with '-' and is not a plain negative
    number for an option, so a number list after an option that takes one value is joined to it
    (`--eye=-2.9,-1.7,0`). Everything after `--` is left alone."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--":
            out.extend(argv[i:])
            break
        nxt = argv[i + 1] if i + 1 < len(argv) else None
        if arg in options and nxt is not None and nxt.startswith("-") and _is_number_list(nxt):
            out.append(f"{arg}={nxt}")
            i += 2
            continue
        out.append(arg)
        i += 1
    return out


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line naming the command (exit 2), like every other error of the CLI; negative numbers
    and vectors (`--eye -2.9,-1.7,0`) are taken as typed."""

    def error(self, message: str):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        if args is None:
            args = sys.argv[1:]
        return super().parse_known_args(join_negative_values(list(args), _single_value_options(self)), namespace)


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {s for action in parser._actions for s in action.option_strings if s.startswith("--")}


def unrecognized_message(parser: argparse.ArgumentParser, command: str, extra: list[str]) -> str:
    """'unrecognized arguments: ...' for the subcommand that was given them, with the option meant where one is
    close (`--max-splat`), or the command that has it (`eval --target-psnr`: an option of encode). argparse's own
    message came from the top-level parser: `splatstream: error: ... (see splatstream --help)`, naming no command."""
    commands = _subcommands(parser)
    own = _options(commands[command])
    hints = []
    for arg in extra:
        if not arg.startswith("--"):
            continue
        name = arg.split("=", 1)[0]
        close = difflib.get_close_matches(name, sorted(own), n=1, cutoff=0.75)
        if close:
            hints.append(f"{name}: did you mean {close[0]}?")
            continue
        elsewhere = [other for other, sub in commands.items() if other != command and name in _options(sub)]
        if elsewhere:
            hints.append(f"{name} is an option of {', '.join(elsewhere[:3])}" + (", ..." if len(elsewhere) > 3
                                                                                   else ""))
    return f"unrecognized arguments: {' '.join(extra)}" + (f" ({'; '.join(hints)})" if hints else "")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="splatstream",
        description="Compact, streamable 3D Gaussian Splatting scenes.",
    )
    parser.add_argument("--version", action="version", version=f"splatstream {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        try:
            module = importlib.import_module(f".commands.{name.replace('-', '_')}", __package__)
        except ModuleNotFoundError as exc:
            if exc.name == f"{__package__}.commands.{name.replace('-', '_')}":
                continue
            raise
        module.register(sub)
    return parser


# A write that found no room: its OSError names no file (write(2) has only a descriptor), and "error: No space left
# on device" did not say which output of the command's filled the disk. numpy's tofile says it without an errno
# ("Not enough free space to write N bytes after offset M", "N requested and M written").
_OUT_OF_ROOM = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
_NUMPY_SHORT_WRITE = re.compile(r"^Not enough free space to write |^\d+ requested and \d+ written$")


def _output_named(args: argparse.Namespace, exc: OSError) -> str:
    """'writing OUT: ' for an out-of-room error naming no file, where the command has one output; else ''."""
    if exc.filename or not (exc.errno in _OUT_OF_ROOM or (exc.errno is None and _NUMPY_SHORT_WRITE.match(str(exc)))):
        return ""
    outputs = [str(v) for name in ("output_dir", "output", "out") if (v := getattr(args, name, None))]
    return f"writing {outputs[0]}: " if len(outputs) == 1 else ""


def _show_warning(message, category, filename, lineno, file=None, line=None):
    end_open_line()
    print(f"splatstream: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    warnings.showwarning = _show_warning
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        parser = build_parser()  # imports every command's modules (numpy and the core): a second on a busy machine
    except KeyboardInterrupt:  # a Ctrl-C meanwhile printed the import's traceback (polish64)
        named = next((a for a in argv if not a.startswith("-")), None)
        print(f"splatstream{f' {named}' if named in COMMANDS else ''}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    args, extra = parser.parse_known_args(attach_negative_values(argv))
    if extra:
        _subcommands(parser)[args.command].error(unrecognized_message(parser, args.command, extra))
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)  # `serve` installs its own (aiohttp's graceful shutdown)
    try:
        try:
            rc = args.func(args)
        finally:
            end_open_line()  # a progress bar left mid-line on a terminal: a failure's line starts a line of its own
    except SplatstreamError as exc:
        print(f"splatstream {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Terminated:
        # 'partial output removed' only where there was output: `serve` stopped before its start line, or `view`
        # with no --screenshot/--record/--frames-dir, said so too.
        writes = args.command not in ("info", "serve") and not (args.command == "view" and not any(
            getattr(args, name, None) for name in ("screenshot", "record", "frames_dir")))
        print(f"splatstream {args.command}: terminated (SIGTERM)" + ("; partial output removed" if writes else ""),
              file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"splatstream {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except MemoryError:
        print(f"splatstream {args.command}: error: out of memory", file=sys.stderr)
        return EXIT_FAILURE
    except BrokenPipeError:
        # The reader of our output went away (`splatstream info ... | head`): nothing to report. Later writes to
        # stdout, at interpreter exit too, go nowhere instead of raising again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else _output_named(args, exc)
        print(f"splatstream {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_FAILURE
    except Exception as exc:  # a bug: one line, not a traceback (SPLATSTREAM_DEBUG=1 shows it)
        if os.environ.get("SPLATSTREAM_DEBUG"):
            raise
        print(f"splatstream {args.command}: internal error: {exc.__class__.__name__}: {exc} (please report it; "
              "SPLATSTREAM_DEBUG=1 shows the traceback)", file=sys.stderr)
        return EXIT_FAILURE
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
