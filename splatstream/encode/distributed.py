"""The partitioned encoder (encode/partitioned.py) on Dask (`dask.distributed`): a local cluster sized to this
machine, or an existing cluster by its scheduler address (Kubernetes, SLURM, cloud: whatever Dask runs on).

Dask is an optional extra (`pip install 'splatstream[cluster]'`), imported only here and only when used. Tasks are
pure functions of their arguments that write content-addressed payloads and whole scratch objects, so when a
worker dies Dask runs its tasks again elsewhere and the output is unchanged. Progress: each task's completion
reaches the caller's progress display; partition tasks also report their own progress from the worker
(`log_event`), so a long partition moves the bar.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
import uuid

from ..cores import available_cores
from ..errors import UsageError
from .options import Progress

PROGRESS_TOPIC = "splatstream-progress"


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise UsageError("--workers and --scheduler need Dask: pip install 'splatstream[cluster]'") from None
    return distributed


class DaskEngine:
    """Maps the encoder's tasks on a Dask cluster; results come back in the order of the arguments."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None,
                 memory_per_worker: int | None = None, processes: bool = True):
        distributed = _import_distributed()
        self.cluster = None
        self._config = None
        if scheduler:
            try:
                self.client = distributed.Client(scheduler, timeout="30s")
            except (OSError, TimeoutError) as exc:
                raise UsageError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
        else:
            n = workers or available_cores()
            _keep_malloc_adaptive()
            self._config = _fork_workers()
            # env: a forked worker would otherwise see the environment of the first engine in this process
            # (the fork server's), not today's (e.g. object-store credentials set since)
            # preload: the worker processes ignore a terminal's Ctrl-C, which the encode handles (dask_worker_setup)
            extra = {"env": dict(os.environ), "preload": [f"{__package__}.dask_worker_setup"]} if processes else {}
            # A Ctrl-C while the cluster starts is held until it has started, then raised here, where the cluster
            # is closed whole; one raised inside the start left Dask's start-up tracebacks (newuser64)
            with _sigint_held() as held:
                try:
                    if processes and self._config is not None:
                        _start_fork_server_ignoring_sigint()
                    # The scheduler's HTTP server on a free port of this machine only: dashboard_address=None still
                    # bound 0.0.0.0:8787 (every interface), and a second encode, or a test's cluster left running,
                    # printed Dask's "Port 8787 is already in use" warning into a one-line stderr.
                    # Workers' own logs only at CRITICAL: a task's failure reaches us through its future (and is
                    # reported once, as a one-line error), while a worker's heartbeat racing the shutdown on a loaded
                    # machine logged a traceback at ERROR after a successful encode (seen in 2 of 6 runs of the
                    # README's --workers 8 line).
                    self.cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=processes,
                                                            dashboard_address="127.0.0.1:0",
                                                            silence_logs=logging.CRITICAL, **extra)
                    self.client = distributed.Client(self.cluster)
                except BaseException:
                    self._close_started()
                    raise
            if held.interrupted:
                self._close_started()
                raise KeyboardInterrupt
        info = self.client.scheduler_info(n_workers=-1)["workers"] if _takes_n_workers(self.client) else \
            self.client.scheduler_info()["workers"]
        self.workers = max(1, len(info))
        limits = [w.get("memory_limit") or 0 for w in info.values()]
        limit = min(limits) if limits and min(limits) > 0 else 4 << 30
        # Partitions are sized to half the worker's limit unless told: Dask restarts a worker near its limit.
        self.memory_per_worker = int(memory_per_worker or limit * 0.5)
        self.threads_per_task = 1
        self._progress: dict[str, float] = {}
        self._behind: list = []

    def map(self, fn, args: list[tuple], stage: str, progress: Progress, heavy: bool = False,
            task_progress: bool = False) -> list:
        distributed = _import_distributed()
        token = uuid.uuid4().hex[:8]
        keys = [f"{stage}-{fn.__name__}-{i}-{token}" for i in range(len(args))]
        partial: dict[str, float] = {}
        lock = threading.Lock()
        finished = [0]

        def show() -> None:
            progress(stage, (finished[0] + sum(partial.values())) / len(keys))

        def on_event(event) -> None:  # runs on the client's event loop thread
            key, fraction = event[1]
            with lock:
                if key in partial:
                    partial[key] = float(fraction)
                    show()

        if task_progress:
            partial.update(dict.fromkeys(keys, 0.0))
            args = [(*a, WorkerProgress(k)) for a, k in zip(args, keys, strict=True)]
            self.client.subscribe_topic(PROGRESS_TOPIC, on_event)
        progress(stage, 0.0)  # the stage starts now (a long first task would otherwise show the stage before)
        futures = [self.client.submit(fn, *a, key=k, pure=False) for k, a in zip(keys, args, strict=True)]
        try:
            for future in distributed.as_completed(futures):
                if future.status == "error":
                    future.result()  # raises the task's own exception (an InputError stays one)
                with lock:
                    partial.pop(future.key, None)
                    finished[0] += 1
                    show()
            return self.client.gather(futures)
        except BaseException:
            self.client.cancel(futures)
            raise
        finally:
            if task_progress:
                self.client.unsubscribe_topic(PROGRESS_TOPIC)

    def map_behind(self, fn, args: list[tuple], stage: str) -> None:
        """Below the default priority: the scheduler gives them to a worker only when no task of `map` waits, so
        they fill the ends of the stages that follow (the last partitions, the narrow rounds of the upper tiles)
        instead of being rounds of their own."""
        token = uuid.uuid4().hex[:8]
        self._behind += [self.client.submit(fn, *a, key=f"{stage}-{fn.__name__}-{i}-{token}", pure=False,
                                            priority=-1) for i, a in enumerate(args)]

    def settle(self) -> None:
        behind, self._behind = self._behind, []
        if behind:
            self.client.gather(behind)

    def _close_started(self) -> None:
        """Close what a start interrupted or failed part-way has started (the engine is not returned)."""
        with contextlib.suppress(Exception):
            if getattr(self, "client", None) is not None:
                self.client.close()
        with contextlib.suppress(Exception):
            if self.cluster is not None:
                self.cluster.close()
        if self._config is not None:
            self._config.__exit__(None, None, None)
            self._config = None

    def close(self) -> None:
        self._behind = []
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()
            if self._config is not None:
                self._config.__exit__(None, None, None)
                self._config = None


class WorkerProgress:
    """A task's progress reporter on a worker: events on PROGRESS_TOPIC, at most a few a second."""

    def __init__(self, key: str):
        self.key = key
        self.last = 0.0

    def __call__(self, fraction: float) -> None:
        now = time.monotonic()
        if now - self.last < 0.5 and fraction < 1.0:
            return
        self.last = now
        try:
            from distributed import get_worker

            get_worker().log_event(PROGRESS_TOPIC, (self.key, fraction))
        except ValueError:  # not on a worker (a task run in the client by a test)
            pass


def _keep_malloc_adaptive() -> None:
    """Dask starts workers with MALLOC_TRIM_THRESHOLD_=65536, which also switches off glibc's adaptive mmap
    threshold: every large numpy temporary is then a fresh mmap, zero-filled page by page. Measured on a 250k-splat
    LOD build: 3.1 s in a worker against 1.7 s without the variable. The encoder's workers hold a partition at a
    time and free it whole, so they do without it (for an existing cluster, set this in its own config)."""
    import dask

    key = "distributed.nanny.pre-spawn-environ"
    env = dict(dask.config.get(key, {}) or {})
    if "MALLOC_TRIM_THRESHOLD_" in env:
        env.pop("MALLOC_TRIM_THRESHOLD_")
        dask.config.set({key: env})


def _fork_workers():
    """A local cluster's worker processes forked from a server process that has imported Dask and its packages
    (Dask sets that preload list itself), where the platform has one (Linux, macOS), instead of spawned: each
    spawned process starts a fresh interpreter and imports them again. Measured: 16 workers started in 4.5 s spawned
    and 1.3 s forked on a 2-core machine; the cluster's start was 16 % of a 16-worker encode on a 16-core one
    (BENCHMARKS.md). Each worker imports the encoder with its first task (0.1 s). Returns the config setting, undone
    when the engine closes (a worker the nanny restarts is forked the same way until then)."""
    import multiprocessing

    import dask

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return None
    return dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"})


class _Held:
    interrupted = False


@contextlib.contextmanager
def _sigint_held():
    """SIGINT recorded instead of raised while the block runs (in the main thread, where Python delivers it); the
    caller raises KeyboardInterrupt after it where `interrupted`. Elsewhere, or where SIGINT is not Python's default
    handler (ignored, or an embedding application's own), nothing is changed."""
    held = _Held()
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield held
        return

    def record(signum, frame) -> None:
        held.interrupted = True

    signal.signal(signal.SIGINT, record)
    try:
        yield held
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


FORKSERVER_SETUP = f"{__package__}.forkserver_setup"


def _start_fork_server_ignoring_sigint() -> None:
    """Start the fork server that Dask's worker processes are forked from (Dask names its preloads) with
    forkserver_setup first among them, so that each worker ignores SIGINT from its first instruction (a worker
    interrupted in its own start printed Dask's start-up tracebacks). SIGINT is blocked in this thread while the
    server is spawned, so that the server, which inherits the mask, is not interrupted before that preload runs
    either; a Ctrl-C meanwhile stays pending here and reaches _sigint_held when unblocked. The resource tracker,
    started first, ignores SIGINT itself (and unblocks the caller's signals after its own spawn). No-op where the
    fork server already runs (its workers' preload, dask_worker_setup, still ignores SIGINT once it runs)."""
    from multiprocessing import forkserver, resource_tracker

    from distributed.utils import get_mp_context

    get_mp_context()  # Dask sets the fork server's preloads here (once per process)
    # (the list as set: the module's own state, as read since Python 3.4; ['__main__'] is its default)
    preload = list(getattr(forkserver._forkserver, "_preload_modules", ["__main__"]))
    forkserver.set_forkserver_preload([FORKSERVER_SETUP] + [m for m in preload if m != FORKSERVER_SETUP])
    resource_tracker.ensure_running()
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def _takes_n_workers(client) -> bool:
    import inspect

    return "n_workers" in inspect.signature(client.scheduler_info).parameters
