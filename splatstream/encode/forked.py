"""Payload jobs on forked processes, beside the LOD tree's merges: the in-memory engine's use of a second core.

Most of an in-memory encode runs on one core: the payload jobs are many small numpy calls that hold the
interpreter lock (two threads hand it back and forth: BENCHMARKS.md, "Where the grid encode's CPU goes"), and so
are most of the tree's grouping rounds. A forked process has its own interpreter, so the payloads of the tree's
finished levels (the leaves first: half of the payload work) are encoded there while this process merges the
levels above; after the tree this process and the children share what is left.

The children are forked once, at a moment this process runs no other thread: when the leaves are laid out, before
the tree's merge pool starts (lod.build_subtree's first `on_level`), or, for a tree handed in, before the payloads.
A child forked beside running threads may inherit a lock some thread held (and Python 3.12 warns); numpy's
OpenBLAS keeps a thread pool, but its own fork handler (pthread_atfork) stops that pool before a fork, so the
child starts with one thread (BENCHMARKS.md, "Payload processes forked before the tree's threads"). If another
Python thread is running then (an encode called on a thread of its own), there are no children and this process
encodes every payload, as on one core.

The children see the tiles that exist at the fork (the leaves: slices of the tree's leaf-ordered copy) without a
copy; the tiles made afterwards reach them over their pipes one at a time, when a child asks for work, so a child
holds at most one such tile. Each child has a feeder thread here that answers its requests from one queue of
tiles in the tree's order; after the tree this process takes from the same queue. The bytes do not depend on who
encodes what: a payload job is a pure function of its tile and the context (jobs.py), its file is named by its
checksum, and the manifest lists the tiles in the tree's order. Only for a DirectoryWriter (files a child can
write beside this process), on Linux, where more than one core is available to this process, and not in a
daemonic process; otherwise the caller encodes every payload itself.
"""
from __future__ import annotations

import collections
import gc
import logging
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable

import numpy as np

from ..cores import available_cores
from ..format.manifest import PayloadEntry
from ..gaussians import Gaussians
from ..lod import Tile
from ..store import DirectoryPayloads, DirectoryWriter, SceneWriter
from .jobs import encode_group, tile_order
from .plan import TileContext

log = logging.getLogger(__name__)

# tile id -> its payloads, by group
TilePayloads = dict[int, dict[str, PayloadEntry]]

_FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh_dc", "sh_rest")

# At most this many children, whatever the cores. The tree is one serial producer of tiles (its grouping rounds hold
# the interpreter lock), and one child already keeps up with it: on the 1M scene the payloads left after the tree
# fell from 8.0 s to 0.04 s with one child (BENCHMARKS.md, "Payload processes forked before the tree's threads").
# Each child costs its own interpreter's pages and the parent's copy-on-write copies: the tree's peak PSS with
# 0/1/2/3/7 children (this 2-core VM, medium, two rounds) read 138/148-154/162-167/172-176/218-220 MB on biker and
# 770-778/805-822/828-893/858-876/947-972 MB at 1M (about +13 MB a child on biker, +25-30 MB at 1M). A second
# child is kept as slack (a level's backlog of tiles, a host whose cores are slower than its tree); a third and
# more only add memory: they wait for tiles the tree has not made (15 on the 16-core GPU machine before this cap).
MAX_PAYLOAD_PROCESSES = 2

# How often a feeder waiting on its child's pipe checks that the child still exists. Only a liveness check (a dead
# child whose pipe some other process still holds open would otherwise never send EOF), never a time limit: a
# child that is alive may take as long as its tile needs.
_LIVENESS_S = 1.0


def payload_processes(writer: SceneWriter, cores: int | None = None) -> int:
    """How many child processes encode payloads beside this one: one less than the cores available, at most
    MAX_PAYLOAD_PROCESSES, none where a
    child cannot write the payloads (a writer other than a DirectoryWriter), off Linux (macOS's system libraries
    are not safe to use in a forked child; Windows has no fork) and in a daemonic process (a Dask worker's)."""
    if not isinstance(writer, DirectoryWriter) or not sys.platform.startswith("linux") or _in_daemon():
        return 0
    return max(0, min(MAX_PAYLOAD_PROCESSES, (available_cores() if cores is None else cores) - 1))


def _exit_status(pid: int, wait_s: float = 0.0) -> str | None:
    """How a child of this process ended ('killed by SIGKILL', 'exited with status 1'), read without reaping it
    (waitid's WNOWAIT: multiprocessing reaps it later); None while it still runs after `wait_s` seconds."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            info = os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
        except ChildProcessError:  # reaped already (close() stopped it)
            return "ended"
        if info is not None:
            if info.si_code in (os.CLD_KILLED, os.CLD_DUMPED):
                return f"was killed by {signal.Signals(info.si_status).name}"
            return f"exited with status {info.si_status}"
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.01)


def _in_daemon() -> bool:
    """Whether this is a daemonic multiprocessing process (a Dask worker's, say), which may not start children."""
    import multiprocessing

    return bool(multiprocessing.current_process().daemon)


def only_thread() -> bool:
    """Whether this process runs no Python thread but this one (the moment a fork is safe for Python's locks)."""
    return threading.active_count() == 1


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
    with the parent, which reuses them as it merges; each page it writes while the child still maps it is copied."""
    try:
        import ctypes

        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to give back this way
        pass


def encode_tile(g: Gaussians, groups: list[str], ctx: TileContext, writer) -> dict[str, PayloadEntry]:
    """Every payload of one tile's splats (the jobs of whichever process takes it)."""
    order = tile_order(g, ctx)
    return {group: encode_group(g, order, group, ctx, writer) for group in groups}


def _send_gaussians(conn, tile_id: int, g: Gaussians) -> None:
    """A tile's splats down a pipe: a small header, then each array's bytes as they lie (no pickled copy)."""
    arrays = [np.ascontiguousarray(getattr(g, name)) for name in _FIELDS]
    conn.send(("tile", tile_id, [(a.dtype.str, a.shape) for a in arrays]))
    for a in arrays:
        conn.send_bytes(memoryview(a).cast("B") if a.nbytes else b"")  # (no SH bands: an empty sh_rest)


def _receive_gaussians(conn, header: list) -> Gaussians:
    arrays = []
    for dtype, shape in header:
        a = np.empty(shape, dtype=np.dtype(dtype))
        if a.nbytes:
            conn.recv_bytes_into(memoryview(a).cast("B"))
        else:
            conn.recv_bytes()
        arrays.append(a)
    return Gaussians(*arrays)


def _child(conn, shared: list[Tile], groups: list[str], ctx: TileContext, payloads: DirectoryPayloads,
           parent: int) -> None:
    """A child's loop: ask for work, encode it, until told to stop; then hand back every payload entry."""
    _die_with(parent)
    _release_free_heap()
    out: TilePayloads = {}
    try:
        while True:
            conn.send(("ready", None))
            msg = conn.recv()
            if msg[0] == "shared":  # a tile that existed at the fork: this process has it already
                tile = shared[msg[1]]
                out[tile.id] = encode_tile(tile.gaussians, groups, ctx, payloads)
            elif msg[0] == "tile":
                out[msg[1]] = encode_tile(_receive_gaussians(conn, msg[2]), groups, ctx, payloads)
            else:
                break
        conn.send(("ok", out))
    except BaseException:  # noqa: BLE001 -- said to the parent, which raises it
        try:
            conn.send(("error", traceback.format_exc(limit=8)))
        finally:
            os._exit(1)


class PayloadChildren:
    """Children that encode payloads beside this process, forked once when `start` is first called.

    `start(tiles)`: fork the children now (only where this process runs no other thread; otherwise there are none
    and `started` stays False), the tiles that exist now queued (the children read them from their own copy).
    `offer(tiles)`: queue more finished tiles (sent to a child when it asks); raises a child's failure at once.
    `finish(tiles, here, progress)`: queue what is not queued yet, encode from the queue here (`here(tile)` returns
    its payloads) while the children do too, wait for them and return every tile's payloads; `progress(f)` gets the
    share of the tiles' splats whose payloads are done, the children's included. `close()`: stop children still
    running (an encode that failed or was interrupted); call it before the writer removes its directory."""

    def __init__(self, processes: int, groups: list[str], ctx: TileContext, payloads: DirectoryPayloads):
        self.processes = processes
        self.groups = groups
        self.ctx = ctx
        self.payloads = payloads
        self.started = False
        self.queued: set[int] = set()  # ids of the tiles queued so far
        self.queue: collections.deque[tuple[int, Tile]] = collections.deque()  # (index into shared or -1, tile)
        self.cond = threading.Condition()
        self.closed = False  # nothing more will be queued
        self.children: list[tuple] = []  # (process, this end of its pipe)
        self.feeders: list[threading.Thread] = []
        self.feeding = 0  # feeders still running
        self.done: TilePayloads = {}
        self.done_splats = 0  # splats of the tiles the children have finished (their payloads written)
        self.errors: list[Exception] = []
        self._frozen = False  # this object froze the collector's objects (gc.freeze) and unfreezes them at the end

    def start(self, tiles: list[Tile]) -> bool:
        """Fork the children, `tiles` shared with them; False (and none forked) where another thread runs."""
        if self.started or self.processes < 1:
            return self.started
        if not only_thread():
            log.debug("payload processes: %d threads run here, none forked", threading.active_count())
            self.processes = 0
            return False
        import multiprocessing  # only where children are forked

        mp = multiprocessing.get_context("fork")
        shared = list(tiles)
        # Python's objects out of the collector's sight while children share them: a collection walks (and so
        # writes) every tracked object, which copies its page into whichever process walks it.
        self._frozen = gc.get_freeze_count() == 0
        gc.freeze()
        parent = os.getpid()
        for _ in range(self.processes):
            here, there = mp.Pipe(duplex=True)
            proc = mp.Process(target=_child, args=(there, shared, self.groups, self.ctx, self.payloads, parent),
                              daemon=True)
            proc.start()
            there.close()  # before the next fork: only this child holds its end, so its death is an EOF here
            self.children.append((proc, here))
        self.started = True
        log.debug("payload processes: %d forked, %d tiles shared", self.processes, len(shared))
        # Threads only now, every child forked: one feeder per child answers its requests.
        self.feeding = len(self.children)
        for proc, conn in self.children:
            feeder = threading.Thread(target=self._feed, args=(proc, conn), daemon=True, name="payload-feeder")
            feeder.start()
            self.feeders.append(feeder)
        with self.cond:
            self.queue.extend((i, t) for i, t in enumerate(shared))
            self.queued.update(t.id for t in shared)
            self.cond.notify_all()
        return True

    def offer(self, tiles: list[Tile]) -> None:
        if not self.started:
            return
        with self.cond:
            if self.errors:  # a child failed: the encode stops now, not after the tree
                raise self.errors[0]
            self.queue.extend((-1, t) for t in tiles if t.id not in self.queued)
            self.queued.update(t.id for t in tiles)
            self.cond.notify_all()

    def _take(self, wait: bool) -> tuple[int, Tile] | None:
        with self.cond:
            while wait and not self.queue and not self.closed:
                self.cond.wait()
            return self.queue.popleft() if self.queue else None

    def _receive(self, proc, conn):
        """The child's next message; EOFError if the child is gone (its pipe closed, or checked dead)."""
        while not conn.poll(_LIVENESS_S):
            if _exit_status(proc.pid) is not None:
                raise EOFError
        return conn.recv()

    def _feed(self, proc, conn) -> None:
        """One child's requests answered from the queue, until it is empty and closed; then its payloads taken."""
        sent: Tile | None = None  # the tile the child is encoding
        try:
            while True:
                status, value = self._receive(proc, conn)
                if status != "ready":
                    self._failed(RuntimeError(f"a payload process failed: {value}"))
                    return
                if sent is not None:  # "ready" again: the tile sent before is done
                    with self.cond:
                        self.done_splats += len(sent.gaussians)
                        self.cond.notify_all()
                    sent = None
                item = self._take(wait=True)
                if item is None:
                    conn.send(("stop", None))
                    status, value = self._receive(proc, conn)
                    if status != "ok":
                        self._failed(RuntimeError(f"a payload process failed: {value}"))
                        return
                    with self.cond:
                        self.done.update(value)
                    return
                index, sent = item
                if index >= 0:
                    conn.send(("shared", index))
                else:
                    _send_gaussians(conn, sent.id, sent.gaussians)
        except (EOFError, OSError):
            how = _exit_status(proc.pid, wait_s=5.0) or "closed its pipe"
            self._failed(ChildProcessError(f"payload process {proc.pid} {how} before its payloads were done"))
        except BaseException:  # noqa: BLE001 -- a fault here: said by finish, which stops the child
            self._failed(RuntimeError(f"a payload process failed: {traceback.format_exc(limit=8)}"))
        finally:
            with self.cond:
                self.feeding -= 1
                self.cond.notify_all()

    def _failed(self, error: Exception) -> None:
        with self.cond:
            self.errors.append(error)
            self.closed = True  # the others stop after their tile; this process encodes no more
            self.queue.clear()
            self.cond.notify_all()

    def finish(self, tiles: list[Tile], here: Callable[[Tile], dict[str, PayloadEntry]],
               progress: Callable[[float], None] = lambda done: None) -> TilePayloads:
        """Every tile's payloads, the children's and this process's."""
        total = max(1, sum(len(t.gaussians) for t in tiles))
        if not self.started:
            out: TilePayloads = {}
            splats = 0
            for tile in tiles:
                out[tile.id] = here(tile)
                splats += len(tile.gaussians)
                progress(splats / total)
            return out
        self.offer(tiles)
        mine: TilePayloads = {}
        mine_splats = 0
        reported = -1.0

        def report() -> None:  # this thread calls `progress`: the children's count read under the lock
            nonlocal reported
            with self.cond:
                share = min(1.0, (mine_splats + self.done_splats) / total)
            if share > reported:
                reported = share
                progress(share)

        report()
        while not self.errors and (item := self._take(wait=False)) is not None:
            mine[item[1].id] = here(item[1])
            mine_splats += len(item[1].gaussians)
            report()
        with self.cond:
            self.closed = True
            self.cond.notify_all()
        while True:  # the children's last tiles: the bar moves as each is done
            with self.cond:
                if self.feeding == 0:
                    break
                self.cond.wait()
            report()
        for feeder in self.feeders:
            feeder.join()
        if self.errors:  # a child may still wait for a tile that will not come: stopped
            self.close()
            raise self.errors[0]
        for proc, conn in self.children:
            conn.close()
            proc.join()
        self.children = []
        self._unfreeze()
        missing = [t.id for t in tiles if t.id not in mine and t.id not in self.done]
        if missing:  # a child stopped without saying why
            raise RuntimeError(f"a payload process failed: no payloads for {len(missing)} tiles")
        return self.done | mine

    def _unfreeze(self) -> None:
        if self._frozen:
            gc.unfreeze()
            self._frozen = False

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.queue.clear()
            self.cond.notify_all()
        for proc, conn in self.children:
            proc.terminate()
            proc.join()
            conn.close()
        for feeder in self.feeders:
            feeder.join(timeout=5)
        self.children = []
        self._unfreeze()
