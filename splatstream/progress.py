"""Progress display on stderr: a redrawn bar on a terminal, a line per stage and 25% step otherwise."""
from __future__ import annotations

import sys
import time


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
            self._last_stage = stage
            return
        step = int(fraction * 4)
        if stage != self._last_stage or step > self._last_step:
            self.stream.write(f"{self.label}: {stage} {fraction * 100:.0f}% ({elapsed:.1f}s)\n")
            self.stream.flush()
            self._last_stage, self._last_step = stage, step
