"""Dask preload for a local cluster's worker processes (encode/distributed.py): they leave Ctrl-C to the encode.

A terminal's Ctrl-C reaches every process of the foreground group, the workers included: each printed its own
KeyboardInterrupt traceback ('Process Dask Worker process (from Nanny): Traceback ...', 60-odd lines) under the
encode's 'interrupted' (newuser64). Ignoring SIGINT in the workers leaves it to the encode, which closes the cluster
(its nannies end the workers) and removes its partial output, as on any other interrupt. A Ctrl-C in the cluster's
first second or so, before a worker has run this, is covered by forkserver_setup (the fork server's preload: its
workers ignore SIGINT from their start) and by the engine holding SIGINT while the cluster starts (distributed.py)."""
from __future__ import annotations

import signal
import threading


def dask_setup(worker: object) -> None:
    # Only a worker process's main thread may set a handler (an in-process worker runs on a thread: left alone)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
