"""How many cores this process may run on: the thread and worker counts' default."""

from __future__ import annotations

import os


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity where the OS has one (taskset, a container's cpuset),
    else os.cpu_count(). os.cpu_count() counts the host's cores: pinned to 2 of a 16-core host's, the LOD tree's
    16 threads took 62.6 CPU s of the 1M scene's encode where one core took 47.9 (BENCHMARKS.md, "The default
    encode on two cores"; bench/results/enc2core31_h200)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity on this OS
        return max(1, os.cpu_count() or 1)
