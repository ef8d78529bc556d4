"""The partitioned encoder (encode/partitioned.py) on Dask (`dask.distributed`): a local cluster sized to this
machine, or an existing cluster by its scheduler address (Kubernetes, SLURM, cloud: whatever Dask runs on).

Dask is an optional extra (`pip install 'splatstream[cluster]'`), imported only here and only when used. Tasks are
pure functions of their arguments that write content-addressed payloads and whole scratch objects, so when a
worker dies Dask runs its tasks again elsewhere and the output is unchanged. Progress: each task's completion
reaches the caller's progress display; partition tasks also report their own progress from the worker
(`log_event`), so a long partition moves the bar.
"""
from __future__ import annotations

import os
import uuid

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
        if scheduler:
            try:
                self.client = distributed.Client(scheduler, timeout="30s")
            except (OSError, TimeoutError) as exc:
                raise UsageError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
        else:
            n = workers or os.cpu_count() or 1
            self.cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=processes,
                                                    dashboard_address=None, silence_logs=40)
            self.client = distributed.Client(self.cluster)
        info = self.client.scheduler_info(n_workers=-1)["workers"] if _takes_n_workers(self.client) else \
            self.client.scheduler_info()["workers"]
        self.workers = max(1, len(info))
        limits = [w.get("memory_limit") or 0 for w in info.values()]
        limit = min(limits) if limits and min(limits) > 0 else 4 << 30
        # Partitions are sized to half the worker's limit unless told: Dask restarts a worker near its limit.
        self.memory_per_worker = int(memory_per_worker or limit * 0.5)
        self.threads_per_task = 1
        self._progress: dict[str, float] = {}

    def map(self, fn, args: list[tuple], stage: str, progress: Progress, heavy: bool = False) -> list:
        distributed = _import_distributed()
        token = uuid.uuid4().hex[:8]
        keys = [f"{stage}-{fn.__name__}-{i}-{token}" for i in range(len(args))]
        futures = [self.client.submit(fn, *a, key=k, pure=False) for k, a in zip(keys, args, strict=True)]
        done = 0
        try:
            for future in distributed.as_completed(futures):
                if future.status == "error":
                    future.result()  # raises the task's own exception (an InputError stays one)
                done += 1
                progress(stage, done / len(futures))
            return self.client.gather(futures)
        except BaseException:
            self.client.cancel(futures)
            raise

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()


def _takes_n_workers(client) -> bool:
    import inspect

    return "n_workers" in inspect.signature(client.scheduler_info).parameters
