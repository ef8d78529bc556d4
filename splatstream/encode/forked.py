"""Payload jobs on forked processes, beside the LOD tree's merges: the in-memory engine's use of a second core.

Most of an in-memory encode runs on one core: the payload jobs are many small numpy calls that hold the
interpreter lock (two threads hand it back and forth: BENCHMARKS.md, "Where the grid encode's CPU goes"), and so
are most of the tree's grouping rounds. A forked process has its own interpreter and sees the tiles made so far
without a copy (its pages are the parent's until one side writes them), so the payloads of the tree's finished
levels (the leaves first: half of the payload work) are encoded there while this process merges the levels above,
and the last levels' payloads are shared between this process and a child. BENCHMARKS.md, "The default encode on
two cores".

The bytes do not depend on it: a payload job is a pure function of its tile and the context (jobs.py), its file is
named by its checksum, and the manifest lists the tiles in the tree's order whoever encoded them. Only for a
DirectoryWriter (files a child can write beside this process), on Linux, where more than one core is available
to this process; otherwise the caller encodes every payload itself, as before.
"""
from __future__ import annotations

import gc
import os
import sys
import traceback
from collections.abc import Callable

from ..format.manifest import PayloadEntry
from ..lod import Tile
from ..store import DirectoryPayloads, DirectoryWriter, SceneWriter
from .jobs import encode_group, tile_order
from .plan import TileContext

# tile id -> its payloads, by group
TilePayloads = dict[int, dict[str, PayloadEntry]]


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity: `taskset`, a container's cpuset), else os.cpu_count()."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def payload_processes(writer: SceneWriter, cores: int | None = None) -> int:
    """How many child processes encode payloads beside this one: one less than the cores available, none where a
    child cannot write the payloads (a writer other than a DirectoryWriter), and off Linux (macOS's system
    libraries are not safe to use in a forked child; Windows has no fork)."""
    if not isinstance(writer, DirectoryWriter) or not sys.platform.startswith("linux") or _in_daemon():
        return 0
    return max(0, (available_cores() if cores is None else cores) - 1)


def _die_with(parent: int) -> None:
    """In a forked child: be killed when the parent dies (Linux's PR_SET_PDEATHSIG), so that a parent killed outright
    (SIGKILL, the OOM killer) leaves no child writing into its temporary directory while the next encode removes it
    (tests/test_hardening.py); exit at once if the parent is gone already."""
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(1)


def _release_free_heap() -> None:
    """In a forked child: give back the heap pages malloc holds free (glibc's malloc_trim). The child shares them
    with the parent, which reuses them as it merges; each page it writes while the child still maps it is copied.
    Without this the 1M encode's peak PSS (parent and children) was 891-937 MB, with it 779 MB, against 750-762 MB
    in one process (BENCHMARKS.md, "The default encode on two cores")."""
    try:
        import ctypes

        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to give back this way
        pass


def _in_daemon() -> bool:
    """Whether this is a daemonic multiprocessing process (a Dask worker's, say), which may not start children."""
    import multiprocessing

    return bool(multiprocessing.current_process().daemon)


def encode_tiles(tiles: list[Tile], groups: list[str], ctx: TileContext, writer) -> TilePayloads:
    """Every payload of these tiles, in order (the jobs of one process)."""
    out: TilePayloads = {}
    for tile in tiles:
        order = tile_order(tile.gaussians, ctx)
        out[tile.id] = {group: encode_group(tile.gaussians, order, group, ctx, writer) for group in groups}
    return out


def balanced_split(tiles: list[Tile], parts: int) -> list[list[Tile]]:
    """`tiles` in `parts` lists of about equal splat counts (a payload job's work follows its splats), each in the
    given order; the largest first onto the lightest list."""
    bins: list[list[Tile]] = [[] for _ in range(parts)]
    loads = [0] * parts
    for tile in sorted(tiles, key=lambda t: -len(t.gaussians)):
        k = loads.index(min(loads))
        bins[k].append(tile)
        loads[k] += len(tile.gaussians)
    rank = {id(t): i for i, t in enumerate(tiles)}
    return [sorted(b, key=lambda t: rank[id(t)]) for b in bins if b]


class ForkedPayloads:
    """Children that encode the payloads of tiles offered to them, up to `processes` at a time.

    `offer(tiles)` hands finished tiles over: split among the free children at once (forked then, so they see
    the tiles as they are now), kept pending while none is free. `finish(here)` shares what is pending between
    the free children and this process (`here` encodes its part), waits for every child and returns every tile's
    payloads. `close()` stops children still running (an encode that failed or was interrupted): call it before
    the writer removes its directory."""

    def __init__(self, processes: int, groups: list[str], ctx: TileContext, payloads: DirectoryPayloads):
        import multiprocessing  # only where children are forked

        self._mp = multiprocessing.get_context("fork")
        self.processes = processes
        self.groups = groups
        self.ctx = ctx
        self.payloads = payloads
        self.pending: list[Tile] = []
        self.offered: set[int] = set()  # ids of the tiles offered so far
        self.running: list[tuple] = []  # (process, receiving end of its pipe)
        self.done: TilePayloads = {}
        self._frozen = False  # this object froze the collector's objects (gc.freeze) and unfreezes them at the end

    def _reap(self, block: bool) -> None:
        still = []
        for proc, conn in self.running:
            if block or conn.poll():
                self._collect(proc, conn)
            else:
                still.append((proc, conn))
        self.running = still

    def _collect(self, proc, conn) -> None:
        try:
            status, value = conn.recv()
        except EOFError:
            status, value = "error", "the payload process ended without a result"
        conn.close()
        proc.join()
        if status != "ok" or proc.exitcode != 0:
            raise RuntimeError(f"a payload process failed (exit code {proc.exitcode}): {value}")
        self.done.update(value)

    def _start(self, tiles: list[Tile]) -> None:
        receive, send = self._mp.Pipe(duplex=False)
        groups, ctx, payloads = self.groups, self.ctx, self.payloads

        parent = os.getpid()

        def run() -> None:
            receive.close()
            _die_with(parent)
            _release_free_heap()
            try:
                result = ("ok", encode_tiles(tiles, groups, ctx, payloads))
            except BaseException:  # noqa: BLE001 -- said to the parent, which raises it
                result = ("error", traceback.format_exc(limit=8))
            send.send(result)
            send.close()
            if result[0] != "ok":
                os._exit(1)

        proc = self._mp.Process(target=run, daemon=True)
        if not self._frozen:
            # Python's objects out of the collector's sight while children share them: a collection walks (and so
            # writes) every tracked object, which copies its page into whichever process walks it
            self._frozen = gc.get_freeze_count() == 0
            gc.freeze()
        proc.start()
        send.close()
        self.running.append((proc, receive))

    def offer(self, tiles: list[Tile]) -> None:
        self.pending.extend(tiles)
        self.offered.update(t.id for t in tiles)
        self._reap(block=False)
        free = self.processes - len(self.running)
        if free > 0 and self.pending:
            for part in balanced_split(self.pending, free):
                self._start(part)
            self.pending = []

    def finish(self, here: Callable[[list[Tile]], TilePayloads]) -> TilePayloads:
        self._reap(block=False)
        if self.pending:
            free = self.processes - len(self.running)
            parts = balanced_split(self.pending, free + 1)
            self.pending = []
            for part in parts[1:]:
                self._start(part)
            self.done.update(here(parts[0]))
        self._reap(block=True)
        self._unfreeze()
        return self.done

    def _unfreeze(self) -> None:
        if self._frozen:
            gc.unfreeze()
            self._frozen = False

    def close(self) -> None:
        for proc, conn in self.running:
            proc.terminate()
            proc.join()
            conn.close()
        self.running = []
        self._unfreeze()
