"""Imported first by the fork server of `encode --workers`'s local cluster (a multiprocessing preload, set by
encode/distributed.py), and only there: it ignores SIGINT.

The fork server keeps the SIGINT handler it had when its preloads were imported as the one its children, the Dask
worker processes, start with. Ignored from their first instruction, a terminal's Ctrl-C (SIGINT to the whole
process group) during the cluster's start no longer interrupts a worker half-way through its start-up, which
printed the fork server's and Dask's tracebacks (newuser64). The encode answers the Ctrl-C and closes the cluster.
dask_worker_setup does the same for a worker forked without this (a fork server started before, by another engine).
"""
from __future__ import annotations

import signal
import threading

if threading.current_thread() is threading.main_thread():  # (only a main thread may set a handler)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
