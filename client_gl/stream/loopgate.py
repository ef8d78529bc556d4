"""The frame loop's gate: when the threads that run Python beside the frame loop (decode threads, the fetcher's event
loop) may run.

A CPython thread that waits for the interpreter lock takes it from the thread holding it only after a switch
interval (5 ms); the frame loop's numpy calls release the lock over arrays of more than 500 elements, so a background
thread running Python during the frame's CPU work took the lock at each of them and the frame waited up to 5 ms each
time (BENCHMARKS.md, "Manifest pages": update frames whose wall was 2-4x their own CPU at 250M splats). The gate is set
while the frame loop waits for the GPU or the display; background threads run a step of their work only then
(`enter`, between steps), and say when a step ends (`leave`). A step under way when the frame loop starts its work
would still run into it, so the frame loop, starting (`close`), first waits a bounded time for those steps to end:
they then run at once, without the frame's numpy calls to take turns with, instead of in 5 ms turns inside it.
"""
from __future__ import annotations

import threading
import time


class LoopGate(threading.Event):
    """Set while the frame loop is not in its CPU work (an Event, so that plain waits work as before), with the
    background threads' steps under way counted."""

    def __init__(self) -> None:
        super().__init__()
        self.set()
        self._steps = threading.Condition(threading.Lock())
        self._running: set[int] = set()  # threads in a step now

    def enter(self, timeout_s: float) -> None:
        """A background thread about to run a step: waits until the frame loop is idle (at most timeout_s)."""
        self.wait(timeout_s)
        with self._steps:
            self._running.add(threading.get_ident())

    def leave(self) -> None:
        """A background thread's step ended (it waits, for the gate or for I/O, or has nothing to do)."""
        with self._steps:
            self._running.discard(threading.get_ident())
            if not self._running:
                self._steps.notify_all()

    def between(self, timeout_s: float) -> None:
        """Between two steps of one piece of work: the step ends; the next starts once the frame loop is idle."""
        self.leave()
        self.enter(timeout_s)

    def close(self, drain_s: float) -> float:
        """The frame loop starts its CPU work: background threads start no new step, and this waits up to drain_s
        for the steps under way to end. Returns the seconds waited."""
        self.clear()
        if not self._running:
            return 0.0
        t0 = time.perf_counter()
        with self._steps:
            self._steps.wait_for(lambda: not self._running, drain_s)
        return time.perf_counter() - t0
