"""The thread and worker counts' default follows the cores this process may run on, not the host's."""

import os
import subprocess
import sys

import pytest

from splatstream.cores import available_cores


def test_available_cores_is_the_affinity():
    assert available_cores() == len(os.sched_getaffinity(0)) >= 1


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_a_process_pinned_to_one_core_counts_one():
    """Pinned to one core (as taskset or a container's cpuset pins it), the encoder's default thread count is 1
    whatever os.cpu_count() says (on a 16-core host pinned to 2 cores the LOD tree had run 16 threads)."""
    one = min(os.sched_getaffinity(0))
    code = (f"import os; os.sched_setaffinity(0, {{{one}}}); from splatstream.cores import available_cores; "
            "print(available_cores(), os.cpu_count())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "1" and int(out[1]) >= 1
