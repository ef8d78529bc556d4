"""LoopGate (client_gl/stream/loopgate.py): the frame loop's gate for the threads that run Python beside it."""
from __future__ import annotations

import threading
import time

from client_gl.stream.loopgate import LoopGate


def test_close_lets_the_step_under_way_end_first():
    """A step under way when the frame loop starts its work ends before close() returns (the step sees the gate
    closed, then leaves); a thread waiting to start a step starts it only once the gate opens again."""
    gate = LoopGate()
    in_step, left = threading.Event(), threading.Event()
    saw_closed = []

    def step() -> None:
        gate.enter(10.0)
        in_step.set()
        deadline = time.monotonic() + 10
        while gate.is_set() and time.monotonic() < deadline:  # runs on until the frame loop starts
            time.sleep(0.001)
        saw_closed.append(not gate.is_set())
        left.set()
        gate.leave()

    worker = threading.Thread(target=step)
    worker.start()
    assert in_step.wait(10)
    waited = gate.close(10.0)
    assert left.is_set() and saw_closed == [True]  # close() returned after the step ended
    assert 0.0 < waited < 10.0
    worker.join(10)

    entered = threading.Event()

    def next_step() -> None:
        gate.enter(10.0)
        entered.set()
        gate.leave()

    waiting = threading.Thread(target=next_step)
    waiting.start()
    time.sleep(0.1)
    assert not entered.is_set()  # the frame loop is in its work: no new step
    gate.set()
    assert entered.wait(10)
    waiting.join(10)
    assert gate.close(10.0) == 0.0  # nothing under way: no wait


def test_between_ends_a_step_and_waits_for_the_gate():
    gate = LoopGate()
    gate.enter(0.0)
    gate.clear()
    t0 = time.perf_counter()
    gate.between(0.01)  # closed: waits its bounded time, then runs on (a frame loop that never opens only delays)
    assert time.perf_counter() - t0 >= 0.009
    gate.leave()
    assert gate.close(0.0) == 0.0
