"""Progress display on stderr: a redrawn bar on a terminal, a line per stage and 25% step otherwise."""
from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Callable


def count(n: int, noun: str, plural: str | None = None) -> str:
    """'1 tile', '11 tiles', '1 leaf' / '2 leaves' (with `plural`): a number a user reads, with its noun."""
    return f"{n:,} {noun if n == 1 else (plural or noun + 's')}"


def some_of(k: int, n: int, noun: str, verbs: tuple[str, str]) -> str:
    """'1 of 20,000 splats has' / '2 of 20,000 splats have' (`verbs`: singular, plural): how many of a whole do
    something, the verb agreeing with the count."""
    return f"{k:,} of {n:,} {noun} {verbs[0] if k == 1 else verbs[1]}"


def mib(nbytes: float) -> str:
    """A memory size given in MiB as a user reads it: '0.5', '1024', '1,000,000' (a plain .4g wrote '1e+06')."""
    value = nbytes / 2**20
    return f"{round(value):,}" if value >= 10_000 else f"{value:.4g}"


class Tally:
    """Units done of a known total, reported as the share done (0 when made, then at most 1 after each `add`): the
    progress of a slow loop over splats or chunks (the RAD and streamed SOG exporters'), where `report` may be None."""

    def __init__(self, report: Callable[[float], None] | None, total: int):
        self.report = report or (lambda fraction: None)
        self.total = max(1, total)
        self.done = 0
        self.report(0.0)

    def add(self, units: int) -> None:
        self.done += units
        self.report(min(1.0, self.done / self.total))

    def within(self, units: int, fraction: float) -> None:
        """Part of the next `units` done (a slow step inside them: a SOG unit's SH palette); `add` counts them."""
        self.report(min(1.0, (self.done + units * min(max(fraction, 0.0), 1.0)) / self.total))

    def finish(self) -> None:
        """All done (1), where the units counted may not reach the total."""
        self.report(1.0)


# The stream whose last line is a progress bar not yet ended by a newline (a terminal's "\r"-redrawn bar), or None: a
# command that fails mid-stage printed its one-line error glued onto the bar ("...  0.0%     0.0ssplatstream encode:
# error: ..."; newuser62), so the CLI ends that line first (end_open_line).
_open_line: list = [None]


def bar_drawn(stream, ended: bool) -> None:
    """Record that a redrawn status line was written to `stream`: left open (no newline yet), or `ended`."""
    _open_line[0] = None if ended else stream


def end_open_line() -> None:
    """End a progress bar left open on its terminal, so that what is printed next starts a line of its own."""
    stream, _open_line[0] = _open_line[0], None
    if stream is not None:
        with contextlib.suppress(OSError, ValueError):
            stream.write("\n")
            stream.flush()


class ProgressPrinter:
    def __init__(self, label: str, stream=None, enabled: bool = True):
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.perf_counter()
        self._last_stage = None
        self._last_step = -1
        self._last_draw = 0.0

    def __call__(self, stage: str, fraction: float) -> None:
        if not self.enabled:
            return
        fraction = min(max(fraction, 0.0), 1.0)
        elapsed = time.perf_counter() - self.start
        if self.tty:
            now = time.perf_counter()
            if fraction < 1.0 and now - self._last_draw < 0.1 and stage == self._last_stage:
                return
            self._last_draw = now
            bar = "#" * int(fraction * 30)
            self.stream.write(f"\r{self.label}: {stage:<8} [{bar:<30}] {fraction * 100:5.1f}%  {elapsed:6.1f}s")
            if fraction >= 1.0:
                self.stream.write("\n")
            self.stream.flush()
            bar_drawn(self.stream, ended=fraction >= 1.0)
            self._last_stage = stage
            return
        step = int(fraction * 4)
        if stage != self._last_stage or step > self._last_step:
            self.stream.write(f"{self.label}: {stage} {fraction * 100:.0f}% ({elapsed:.1f}s)\n")
            self.stream.flush()
            self._last_stage, self._last_step = stage, step

    def note(self, message: str) -> None:
        """A line of information between progress updates (on a terminal, above the bar)."""
        if not self.enabled:
            return
        self.stream.write(("\r\033[K" if self.tty else "") + f"{self.label}: {message}\n")
        self.stream.flush()
        if self.tty:
            bar_drawn(self.stream, ended=True)  # the bar was cleared: the note ends its line
        self._last_draw = 0.0

    @contextlib.contextmanager
    def library_notes(self, logger: str = "splatstream"):
        """Show the library's INFO messages (e.g. the up direction it chose) as notes while the block runs."""
        printer = self

        class _Handler(logging.Handler):
            def emit(self, record: logging.LogRecord) -> None:
                printer.note(record.getMessage())

        log = logging.getLogger(logger)
        handler, level = _Handler(logging.INFO), log.level
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        try:
            yield self
        finally:
            log.removeHandler(handler)
            log.setLevel(level)
