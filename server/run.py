"""Running the server: bind, optional pre-forked workers, graceful shutdown (`splatstream serve`)."""
from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import signal
import socket
import stat
import sys
from collections.abc import Iterable

from splatstream.format.names import DATA_DIR, MANIFEST_NAME, TILESET_NAME
from splatstream.writers.sog_lod import LOD_META_NAME

from .app import SHUTDOWN_TIMEOUT, AccessLog, create_app, create_runner, start_site
from .limits import FdLimitTooLow, Limits, accept_error_handler, fit_to_fd_limit
from .paths import SEGMENT_RE
from .scenes import SceneRoot, walk_root
from .throttle import Link
from .tilesets import find_tilesets

EXIT_OK = 0
EXIT_ERROR = 1  # a worker died, the server failed
EXIT_BAD_ROOT = 2  # usage (README "Exit codes"): ROOT missing or empty, a host or port that cannot be used


class ServeError(Exception):
    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


def setup_logging() -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("splatstream serve: %(levelname)s: %(name)s: %(message)s"))
    for name in ("splatstream.server", "aiohttp", "asyncio"):
        logger = logging.getLogger(name)
        logger.addHandler(handler)
        logger.setLevel(logging.WARNING)
        logger.propagate = False


def check_root(root: str) -> list[str]:
    """The scene ids under `root`; ServeError when there is nothing to serve."""
    if not os.path.exists(root):
        raise ServeError(f"{root}: no such directory", EXIT_BAD_ROOT)
    if not os.path.isdir(root):
        raise ServeError(f"{root}: not a directory", EXIT_BAD_ROOT)
    ids = [sid for sid, _ in SceneRoot(root).scan()]
    if not ids and not find_tilesets(root):
        hint = ""
        if os.path.isfile(os.path.join(root, MANIFEST_NAME)):
            hint = (f"; {root} is itself a scene directory: serve its parent and open it as "
                    f"/scenes/{os.path.basename(os.path.abspath(root))}/{MANIFEST_NAME}")
        elif os.path.isfile(os.path.join(root, TILESET_NAME)):
            hint = f"; {root} is itself a tileset directory: serve its parent"
        elif os.path.isfile(os.path.join(root, LOD_META_NAME)) or unserved_exports(root, 1)[1]:
            hint = ("; a streamed SOG (lod-meta.json) or a Spark .rad is not served by splatstream serve: serve it "
                    "with a static web server that answers Range requests (nginx, an object store)")
        raise ServeError(f"{root}: holds no scene (a scene is a directory with {MANIFEST_NAME}) and no tileset "
                         f"(a directory with tileset.json){hint}", EXIT_BAD_ROOT)
    return ids


def _listing(named: list[str], count: int) -> str:
    """The names a start-up warning shows, and ', ...' where more were counted than named."""
    return ", ".join(named) + (", ..." if count > len(named) else "")


class _Found:
    """At most `limit` names kept, every one counted."""

    def __init__(self, limit: int) -> None:
        self.limit, self.named, self.count = limit, [], 0

    def add(self, name: str) -> None:
        self.count += 1
        if len(self.named) < self.limit:
            self.named.append(name)

    def result(self) -> tuple[list[str], int]:
        return sorted(self.named), self.count


def unreadable_files(root: str, limit: int = 5) -> tuple[list[str], int]:
    """Scene files this process may not read (at most `limit` named, and how many scenes have some): each scene's
    manifest and first payload are checked, so a tree written by another user with mode 0600 is reported at
    start, not as a 403 per request."""
    found = _Found(limit)
    for _, directory in SceneRoot(root).scan():
        candidates = [os.path.join(directory, MANIFEST_NAME)]
        try:
            with os.scandir(os.path.join(directory, DATA_DIR)) as it:
                candidates += [e.path for e in it if e.name.endswith(".bin")][:1]
        except OSError:
            pass
        bad = [p for p in candidates if not os.access(p, os.R_OK)]
        if bad:
            try:
                st = os.stat(bad[0])
                why = f"mode {stat.S_IMODE(st.st_mode):04o}, owner uid {st.st_uid}"
            except OSError as exc:
                why = exc.strerror or str(exc)
            found.add(f"{os.path.relpath(bad[0], root)} ({why})")
    return found.named, found.count  # in the scan's order (by scene id)


# Scenes whose manifests `serve` reads at start (to count and warn as /api/scenes will); above it, directories count.
START_CHECKED_SCENES = 256


def unservable_scene_names(root: str, limit: int = 5, max_dirs: int = 10_000) -> tuple[list[str], int]:
    """Scene directories (holding manifest.msgpack) that the server skips because a segment of their path is not a
    URL-safe name (`my scene`, `été`): at most `limit` named, and how many. Hidden directories are skipped on purpose
    and not counted; so is anything deeper than a scene id can be. Unlike the scene scan it descends below unsafe
    names (to find the scenes there) and never follows a symlinked directory."""
    found = _Found(limit)

    def visit(e: os.DirEntry, segs: tuple[str, ...]) -> bool:
        if not e.is_dir(follow_symlinks=False):
            return False
        if not os.path.isfile(os.path.join(e.path, MANIFEST_NAME)):
            return True
        if not all(SEGMENT_RE.match(s) for s in segs):
            found.add("/".join(segs))
        return False

    walk_root(root, visit, max_dirs)
    return found.result()


# What `export-sog-lod` and `export-rad` write (a streamed SOG's LOD_META_NAME; a .rad is one file): the server serves
# neither (README, "Viewing in PlayCanvas"), and a root holding them said nothing of them at start.
RAD_SUFFIX = ".rad"


def unserved_exports(root: str, limit: int = 5, max_dirs: int = 10_000) -> tuple[list[str], int]:
    """Streamed SOG directories (holding lod-meta.json, not a scene) and Spark .rad files under `root`, which this
    server does not serve: at most `limit` named (a directory with a trailing '/'), and how many. Hidden entries and
    scenes' insides are skipped, as the scene scan skips them."""
    found = _Found(limit)

    def visit(e: os.DirEntry, segs: tuple[str, ...]) -> bool:
        name = "/".join(segs)
        if e.is_file() and e.name.endswith(RAD_SUFFIX):
            found.add(f"{name} (a Spark .rad)")
        elif not e.is_dir(follow_symlinks=False) or os.path.isfile(os.path.join(e.path, MANIFEST_NAME)):
            pass
        elif os.path.isfile(os.path.join(e.path, LOD_META_NAME)):
            found.add(f"{name}/ (a PlayCanvas streamed SOG)")
        else:
            return True
        return False

    walk_root(root, visit, max_dirs)
    return found.result()


def tilesets_in_scenes(root: str, limit: int = 5) -> tuple[list[str], int]:
    """Scene directories that also hold tileset.json (a tileset copied into a scene): a scene directory serves its
    scene alone (http.md 14), so their tileset.json answered 404 with nothing said at start (polish64)."""
    found = _Found(limit)
    for sid, directory in SceneRoot(root).scan():
        if os.path.isfile(os.path.join(directory, TILESET_NAME)):
            found.add(f"{sid}/")
    return found.result()


def bind(host: str, port: int, backlog: int = 1024) -> socket.socket:
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ServeError(f"cannot resolve host {host!r}: {exc}", EXIT_BAD_ROOT) from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(backlog)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise ServeError(f"port {port} on {host} is already in use (another server is running there?); "
                             f"choose another with --port", EXIT_BAD_ROOT) from None
        if exc.errno == errno.EACCES:
            raise ServeError(f"no permission to listen on {host}:{port} (ports below 1024 need privileges)",
                             EXIT_BAD_ROOT) from None
        if exc.errno == errno.EADDRNOTAVAIL:
            raise ServeError(f"cannot listen on {host}:{port}: {host} is not an address of this machine "
                             f"(--host 127.0.0.1 for this machine only, 0.0.0.0 for every interface)",
                             EXIT_BAD_ROOT) from None
        raise ServeError(f"cannot listen on {host}:{port}: {exc.strerror}", EXIT_ERROR) from None
    sock.setblocking(False)
    return sock


async def _serve_socket(sock: socket.socket, root: str, cors_origins: Iterable[str], access_log: bool,
                        shutdown_timeout: float, limits: Limits, throttle: Link | None = None) -> None:
    loop = asyncio.get_running_loop()
    loop.set_exception_handler(accept_error_handler)
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    runner = create_runner(create_app(root, cors_origins, throttle), access_log=access_log,
                           shutdown_timeout=shutdown_timeout, limits=limits)
    await runner.setup()
    guard = await start_site(runner, sock)
    flusher = loop.create_task(_flush_access_log()) if access_log else None
    try:
        await stop.wait()
    finally:
        # Stop accepting; in-flight responses finish (up to shutdown_timeout); idle keep-alives close.
        guard.close()
        await runner.cleanup()
        if flusher:
            flusher.cancel()
        AccessLog.flush()


async def _flush_access_log() -> None:
    while True:
        await asyncio.sleep(AccessLog.FLUSH_SECONDS)
        AccessLog.flush()


def _run_worker(sock: socket.socket, root: str, cors: list[str], access_log: bool, shutdown_timeout: float,
                limits: Limits, throttle: Link | None = None) -> None:
    asyncio.run(_serve_socket(sock, root, cors, access_log, shutdown_timeout, limits, throttle))


def serve(root: str, host: str = "127.0.0.1", port: int = 8000, cors_origins: Iterable[str] = (),
          workers: int = 1, access_log: bool = True, shutdown_timeout: float = SHUTDOWN_TIMEOUT,
          limits: Limits | None = None, throttle: Link | None = None) -> int:
    """Serve every scene under `root` until SIGTERM/SIGINT; the exit code. `throttle`: a simulated link
    (server/throttle.py; one process only, so that its rate is shared by every connection)."""
    cors = list(cors_origins)
    setup_logging()
    requested = (limits or Limits()).with_reserve()
    try:
        if throttle is not None and workers > 1:
            raise ServeError("a throttled link needs --workers 1 (each worker would get the whole rate)", EXIT_ERROR)
        ids = check_root(root)
        try:
            limits, fd_limit, lowered = fit_to_fd_limit(requested)
        except FdLimitTooLow as exc:
            raise ServeError(str(exc), EXIT_ERROR) from None
        sock = bind(host, port)
    except ServeError as exc:
        print(f"splatstream serve: error: {exc}", file=sys.stderr)
        return exc.code
    named, scenes = unreadable_files(root)
    if scenes:
        print(f"splatstream serve: warning: {scenes} scene{'s' if scenes != 1 else ''} with files this server "
              f"(uid {os.geteuid()}) may not read; they answer 403: {_listing(named, scenes)}",
              file=sys.stderr, flush=True)
    named, unsafe = unservable_scene_names(root)
    if unsafe:
        # A scene under 'my scene/' was left out of /api/scenes without a word.
        print(f"splatstream serve: warning: {unsafe} scene director{'ies' if unsafe != 1 else 'y'} not served: a "
              f"name in the path is not URL-safe (letters, digits, '.', '_', '-'; not starting with '.'): "
              f"{_listing([repr(n) for n in named], unsafe)}; rename "
              f"{'them' if unsafe != 1 else 'it'}", file=sys.stderr, flush=True)
    named, exports = unserved_exports(root)
    if exports:
        # `serve exports/` beside `sog/garden` and `garden.rad` answered their URLs 404 without a word at start.
        print(f"splatstream serve: note: {exports} export{'s' if exports != 1 else ''} not served (this server serves "
              f"scene directories and 3D Tiles tilesets): {_listing(named, exports)};"
              f" serve {'them' if exports != 1 else 'it'} with a static web server that answers Range requests "
              f"(nginx, an object store)", file=sys.stderr, flush=True)
    named, mixed = tilesets_in_scenes(root)
    if mixed:
        print(f"splatstream serve: note: {mixed} scene director{'ies' if mixed != 1 else 'y'} also "
              f"hold{'s' if mixed == 1 else ''} tileset.json, not served (a scene directory serves its scene alone): "
              f"{_listing(named, mixed)}; export the tileset into a directory of its own (splatstream export-3dtiles "
              f"SCENE_DIR OUT_DIR)", file=sys.stderr, flush=True)
    if lowered:
        print(f"splatstream serve: warning: --max-connections lowered from {requested.max_connections} to "
              f"{limits.max_connections} per worker to fit the file descriptor limit {fd_limit} (ulimit -n)",
              file=sys.stderr, flush=True)
    bound = sock.getsockname()
    shown = f"[{bound[0]}]" if sock.family == socket.AF_INET6 else bound[0]
    # The scenes /api/scenes lists: a scene whose manifest does not parse was counted here and skipped there, its
    # warning only at the first request ('2 scenes from ...' and a list of 1); read now, the warning comes now.
    # Up to START_CHECKED_SCENES: a root of thousands is not held up reading every manifest before it serves.
    if len(ids) <= START_CHECKED_SCENES:
        ids = [scene["id"] for scene in SceneRoot(root).list_scenes()]
    # A root of exported tilesets alone said '0 scenes from ...', which reads as nothing served: they are counted.
    tilesets = find_tilesets(root)
    also = f" and {len(tilesets)} 3D Tiles tileset{'s' if len(tilesets) != 1 else ''}" if tilesets else ""
    print(f"splatstream serve: {len(ids)} scene{'s' if len(ids) != 1 else ''}{also} from {os.path.abspath(root)} at "
          f"http://{shown}:{bound[1]}/ ({workers} worker{'s' if workers != 1 else ''} of at most "
          f"{limits.max_connections} connections; scene list at /api/scenes; "
          f"SIGTERM or Ctrl-C stops)", file=sys.stderr, flush=True)
    if throttle is not None:
        print(f"splatstream serve: {throttle.describe()} (a test tool)", file=sys.stderr, flush=True)
    if workers <= 1:
        _run_worker(sock, root, cors, access_log, shutdown_timeout, limits, throttle)
        print("splatstream serve: stopped", file=sys.stderr, flush=True)
        return EXIT_OK
    return _prefork(sock, root, cors, access_log, shutdown_timeout, limits, workers)


def _prefork(sock: socket.socket, root: str, cors: list[str], access_log: bool, shutdown_timeout: float,
             limits: Limits, workers: int) -> int:
    """`workers` processes accept on the one listening socket; the parent forwards SIGTERM/SIGINT and waits."""
    children: list[int] = []
    stopping = False

    def forward(signum, frame):
        nonlocal stopping
        stopping = True
        for pid in children:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGTERM)

    old = {s: signal.signal(s, forward) for s in (signal.SIGTERM, signal.SIGINT)}
    for _ in range(workers):
        pid = os.fork()
        if pid == 0:
            code = EXIT_OK
            try:
                for s, handler in old.items():
                    signal.signal(s, handler)
                _run_worker(sock, root, cors, access_log, shutdown_timeout, limits)
            except BaseException:
                code = EXIT_ERROR
            finally:
                os._exit(code)
        children.append(pid)
    sock.close()
    code = EXIT_OK
    while children:
        try:
            pid, status = os.wait()
        except ChildProcessError:
            break
        except InterruptedError:
            continue
        if pid in children:
            children.remove(pid)
        rc = os.waitstatus_to_exitcode(status)
        if rc != 0 and not stopping:
            print(f"splatstream serve: worker {pid} exited with {rc}; stopping", file=sys.stderr, flush=True)
            code = EXIT_ERROR
            forward(signal.SIGTERM, None)
    print("splatstream serve: stopped", file=sys.stderr, flush=True)
    return code
