"""Fuzz and fault campaign (issue 19): mutated inputs of every format splatstream reads, and corrupted scene
directories, run through the CLI in child processes under time and memory limits, outcomes counted per format.

    .venv/bin/python bench/fuzz.py --cases 1000 --seed 1 --jobs 2 [--formats ply_binary,spz_v4,...]
                                   [--render N] [--keep DIR] [--json OUT.json] [--spawn] [--only FORMAT:INDEX]

Inputs: the fixtures in tests/fixtures/foreign, small subsets of the real scenes in ../shared/data/real (when
present), what our own writers make of them (ASCII PLY, SPZ, GLB, .gltf + .bin), and encoded scenes. Each case
takes one seed of its format and applies one mutation: truncations, bit flips, byte and word overwrites,
insertions and deletions, header lies (counts, types, versions, offsets), numeric extremes (NaN, inf, 1e30,
+-7e4 beyond float16, +-2e38, the domain's edges), decompression bombs, non-regular files (FIFOs, directories,
symlink loops, /dev/zero), and for scenes manifest field edits (resealed with a valid checksum, so the schema is
what is tested, or not, so the checksum is), payload corruption (raw, or resealed with values such as NaN or
inverted ranges), missing files, FIFOs and symlinks.

Each command (`encode`, `convert`, `decode`, `info`, `render`) runs in a child process with RLIMIT_AS, no core
dumps, a wall-clock timeout and SPLATSTREAM_MEMORY_BUDGET set. By default the children are forked from a
"fork server" (one per job) that has imported splatstream once: a case then costs a fork (milliseconds) instead
of a Python start (0.3-0.5 s here); `--spawn` starts `python -m cli` per command instead
(subprocess with preexec_fn), which gives the same outcomes more slowly. Outcomes of a case (the worst of its
commands):

  clean_error      exit 2, one line `splatstream CMD: error: ...` naming a file of the case, no traceback
  success          exit 0, and the output checks out (below)
  traceback        a Python traceback or `internal error` (an exception the CLI did not expect)
  failure          exit 1 without a traceback (e.g. an OSError the CLI reports as a machine failure)
  oom              `out of memory`: a MemoryError under the memory limit (the reader did not bound it)
  hang             still running at the timeout (killed)
  crash            killed by a signal (segfault, abort)
  unclear_error    exit 2, but more than one line, or no file of the case named
  partial_output   a temporary (dot) name left beside an output, or an output left by a failed command
  unreadable       exit 0, but what it wrote is refused by our own reader (`decode` of an encoded scene,
                   `convert` back of a converted file)
  silent_nan       exit 0, but the written PLY (directly, or after reading back) holds NaN or inf
  inconsistent     `render` exit 0 on a scene that `decode` refuses (they load the same leaves)

Reproduce a case with --only FORMAT:INDEX (same --seed) and --keep DIR.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import gzip
import hashlib
import io
import json
import os
import pathlib
import random
import resource
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

ROOT = pathlib.Path(__file__).resolve().parents[1]
FOREIGN = ROOT / "tests" / "fixtures" / "foreign"
VECTORS = ROOT / "format_spec" / "vectors"
REAL = pathlib.Path(os.environ.get("SPLATSTREAM_SHARED", ROOT.parent / "shared")) / "data" / "real"

FORMATS = ["ply_binary", "ply_ascii", "compressed_ply", "spz_v2", "spz_v3", "spz_v4", "splat", "sog_bundle",
           "sog_dir", "sog_streamed", "glb", "gltf", "scene"]
GOOD = ("clean_error", "success")
BAD = ("traceback", "failure", "oom", "hang", "crash", "unclear_error", "partial_output", "unreadable",
       "silent_nan", "inconsistent")
OUTCOMES = GOOD + BAD
SEVERITY = {name: i for i, name in enumerate(OUTCOMES)}  # later = worse

MEMORY_LIMIT = 3 << 30  # RLIMIT_AS of each command (virtual memory)
MEMORY_BUDGET = 1 << 30  # SPLATSTREAM_MEMORY_BUDGET: readers must refuse before reaching the limit
TIMEOUT_S = 60.0
RENDER_SIZE = "32x24"

FLOAT_EXTREMES = [float("nan"), float("inf"), float("-inf"), 1e30, -1e30, 7e4, -7e4, 65504.0, 65520.0, 2e38, -2e38,
                  3.4e38, 1e18, -1e18, 1.1e18, 88.8, 40.5, -80.5, 0.0, -0.0, 1e-45, 1e-30]
INT_EXTREMES = [0, 1, -1, 2, 255, 256, 65535, 65536, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**40, 2**62, 2**63 - 1]
ASCII_TOKENS = ["1_000", "0x10", "nan", "inf", "-inf", "1e999", "-1e999", "1e-400", "+", ".", "-", "e5", "1e5e5",
                "--1", "1.5.2", "١٢", "1,5", "", "NaN", "Infinity", "0b1", "1j", "∞", "7e4", "2e38", "-0"]
JSON_VALUES = [0, -1, 1, 2**31, 2**53, 2**64, 1e308, -1e308, 1.5, "", "x", None, True, False, [], {}, [0, 0, 0],
               {"a": 1}, "../../etc/passwd", "/etc/passwd", "NaN!", float("nan"), float("inf")]
MSGPACK_VALUES = [0, -1, 1, 2**31, 2**63 - 1, -(2**63), 2**64 - 1, 1e308, float("nan"), float("inf"),
                  float("-inf"), 1.5, "", "x" * 300, None, True, False, [], {}, [1, 2, 3], {"a": 1}, b"bytes",
                  "../../etc/passwd", "shuffle0", "shuffle17", "none", "f32x4", "bc7", "index16"]


# ==============================================================================================================
# Running one command in a child process


@dataclasses.dataclass
class Run:
    argv: list[str]
    rc: int | None  # exit code (None: killed by a signal or the timeout)
    signal: int | None
    timed_out: bool
    seconds: float
    stdout: str
    stderr: str


def _limits(memory: int) -> None:
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def child_env(extra: dict | None = None) -> dict:
    env = dict(os.environ)
    env.update({"SPLATSTREAM_MEMORY_BUDGET": str(MEMORY_BUDGET), "SPLATSTREAM_DEBUG": "1",
                "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"})
    env.update(extra or {})
    return env


class Spawner:
    """One command = one `python -m cli` (subprocess with preexec_fn limits)."""

    def run(self, argv: list[str], cwd: str, timeout: float = TIMEOUT_S, memory: int = MEMORY_LIMIT) -> Run:
        t0 = time.monotonic()
        proc = subprocess.Popen([sys.executable, "-m", "cli", *argv], cwd=cwd, env=child_env(),
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                preexec_fn=lambda: (os.setpgid(0, 0), _limits(memory)))
        try:
            out, err = proc.communicate(timeout=timeout)
            timed_out = False
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            timed_out = True
        rc = proc.returncode
        return Run(argv, None if (rc < 0 or timed_out) else rc, -rc if rc < 0 and not timed_out else None,
                   timed_out, time.monotonic() - t0, out.decode(errors="replace"), err.decode(errors="replace"))

    def close(self) -> None:
        pass


class ForkServer:
    """A process that imported splatstream once and forks a child per command (see the module docstring)."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, str(pathlib.Path(__file__).resolve()), "--fork-server"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=child_env(), text=True,
                                     cwd=str(ROOT))
        self.lock = threading.Lock()
        ready = self.proc.stdout.readline()
        if ready.strip() != "ready":
            raise RuntimeError(f"fork server did not start: {ready!r}")

    def run(self, argv: list[str], cwd: str, timeout: float = TIMEOUT_S, memory: int = MEMORY_LIMIT) -> Run:
        with tempfile.TemporaryDirectory(prefix="fuzz-io-") as io_dir:
            request = {"argv": argv, "cwd": cwd, "timeout": timeout, "memory": memory,
                       "stdout": os.path.join(io_dir, "out"), "stderr": os.path.join(io_dir, "err")}
            with self.lock:
                self.proc.stdin.write(json.dumps(request) + "\n")
                self.proc.stdin.flush()
                reply = json.loads(self.proc.stdout.readline())
            out = pathlib.Path(request["stdout"]).read_bytes().decode(errors="replace")
            err = pathlib.Path(request["stderr"]).read_bytes().decode(errors="replace")
        return Run(argv, reply["rc"], reply["signal"], reply["timed_out"], reply["seconds"], out, err)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.proc.stdin.close()
            self.proc.wait(timeout=10)


def fork_server_main() -> None:
    """--fork-server: read requests (JSON lines) on stdin, answer each with the child's fate on stdout."""
    import numpy  # noqa: F401 - imported once here, shared by every child
    import PIL.Image  # noqa: F401
    import zstandard  # noqa: F401

    import cli.main as cli
    import splatstream.encode  # noqa: F401
    import splatstream.io  # noqa: F401
    import splatstream.readers.gltf  # noqa: F401
    import splatstream.readers.sog  # noqa: F401
    import splatstream.readers.spz  # noqa: F401
    import splatstream.scene_decode  # noqa: F401

    print("ready", flush=True)
    for line in sys.stdin:
        req = json.loads(line)
        out_fd = os.open(req["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        err_fd = os.open(req["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        sys.stdout.flush()
        sys.stderr.flush()
        t0 = time.monotonic()
        pid = os.fork()
        if pid == 0:  # the child: limits, its own process group, stdio to the files, then the CLI
            code = 99
            try:
                os.setpgid(0, 0)
                _limits(req["memory"])
                devnull = os.open(os.devnull, os.O_RDONLY)
                os.dup2(devnull, 0)
                os.dup2(out_fd, 1)
                os.dup2(err_fd, 2)
                os.chdir(req["cwd"])
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
                code = cli.main(req["argv"])
            except SystemExit as exc:  # argparse
                code = exc.code if isinstance(exc.code, int) else 2
            except BaseException:  # SPLATSTREAM_DEBUG=1: an unexpected exception leaves the CLI as a traceback
                import traceback

                traceback.print_exc()
                code = 98
            finally:
                with contextlib.suppress(Exception):
                    sys.stdout.flush()
                    sys.stderr.flush()
                os._exit(code if isinstance(code, int) else 99)
        os.close(out_fd)
        os.close(err_fd)
        status, timed_out = _wait(pid, req["timeout"])
        reply = {"rc": os.WEXITSTATUS(status) if os.WIFEXITED(status) and not timed_out else None,
                 "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) and not timed_out else None,
                 "timed_out": timed_out, "seconds": time.monotonic() - t0}
        print(json.dumps(reply), flush=True)


def _wait(pid: int, timeout: float) -> tuple[int, bool]:
    """waitpid with a timeout (pidfd + select); SIGKILL to the child's group when it runs out."""
    deadline = time.monotonic() + timeout
    fd = os.pidfd_open(pid)
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(pid, signal.SIGKILL)
                return os.waitpid(pid, 0)[1], True
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                return os.waitpid(pid, 0)[1], False
    finally:
        os.close(fd)


# ==============================================================================================================
# Seeds: real inputs of every format


def _ply_subset(src: pathlib.Path, dst: pathlib.Path, rows: int) -> None:
    from splatstream.ply import read_header

    header = read_header(src)
    vertex = header.element("vertex")
    item = vertex.dtype("<").itemsize
    data = src.read_bytes()
    head = data[:header.size].replace(f"element vertex {vertex.count}\n".encode(), f"element vertex {rows}\n".encode())
    dst.write_bytes(head + data[header.size:header.size + rows * item])


def _compressed_subset(src: pathlib.Path, dst: pathlib.Path, chunks: int) -> None:
    from splatstream.ply import read_elements

    header, elements = read_elements(src)
    n = min(chunks * 256, header.element("vertex").count)
    head = src.read_bytes()[:header.size].decode("ascii")
    parts = []
    for el in header.elements:
        count = chunks if el.name == "chunk" else n
        head = head.replace(f"element {el.name} {el.count}\n", f"element {el.name} {count}\n")
        parts.append(elements[el.name][:count].tobytes())
    dst.write_bytes(head.encode("ascii") + b"".join(parts))


def _ascii_ply(src: pathlib.Path, dst: pathlib.Path, rows: int) -> None:
    from splatstream.ply import read_elements

    header, elements = read_elements(src)
    vertex = elements["vertex"][:rows]
    lines = ["ply", "format ascii 1.0", "comment made by bench/fuzz.py", f"element vertex {len(vertex)}"]
    lines += [f"property float {name}" for name in vertex.dtype.names] + ["end_header"]
    lines += [" ".join(f"{float(v):.9g}" for v in row) for row in vertex]
    dst.write_text("\n".join(lines) + "\n")


def _gltf_from_glb(src: pathlib.Path, dst_dir: pathlib.Path) -> pathlib.Path:
    """A .gltf JSON with its buffer in a .bin beside it, from a GLB."""
    data = src.read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    bin_len = struct.unpack_from("<I", data, 20 + json_len)[0]
    binary = data[28 + json_len:28 + json_len + bin_len]
    doc["buffers"][0]["uri"] = "scene.bin"
    dst_dir.mkdir(parents=True, exist_ok=True)
    (dst_dir / "scene.bin").write_bytes(binary[:doc["buffers"][0]["byteLength"]])
    out = dst_dir / "scene.gltf"
    out.write_text(json.dumps(doc))
    return out


def build_seeds(root: pathlib.Path, use_real: bool = True) -> dict[str, list[pathlib.Path]]:
    """Seed inputs per format under `root` (fixtures, subsets of the real scenes, our writers' outputs)."""
    import warnings

    from splatstream.encode import EncodeOptions, encode_gaussians
    from splatstream.io import read_gaussians, write_gaussians

    warnings.simplefilter("ignore")
    root.mkdir(parents=True, exist_ok=True)
    real = use_real and REAL.is_dir()
    seeds: dict[str, list[pathlib.Path]] = {f: [] for f in FORMATS}
    plys = [FOREIGN / "fruit_drops_sub64.ply", FOREIGN / "fruit_drops_sub16.ply"]
    if real:
        for name, rows in (("fruit_drops_sh3.ply", 300), ("donut_sh0_no_normals.ply", 300),
                           ("lod_tile_sh3_zero_rest.ply", 200)):
            if (REAL / name).exists():
                _ply_subset(REAL / name, root / f"real_{name}", rows)
                plys.append(root / f"real_{name}")
    seeds["ply_binary"] = plys
    for i, p in enumerate(plys[:4]):
        _ascii_ply(p, root / f"ascii_{i}.ply", 80)
        seeds["ply_ascii"].append(root / f"ascii_{i}.ply")
    seeds["compressed_ply"] = [FOREIGN / "fruit_drops.compressed.ply"]
    if real:
        for name in ("guitar.compressed.ply", "biker.compressed.ply"):
            if (REAL / name).exists():
                _compressed_subset(REAL / name, root / f"real_{name}", 2)
                seeds["compressed_ply"].append(root / f"real_{name}")
    seeds["spz_v2"] = [FOREIGN / "fruit_drops_v2.spz"]
    seeds["spz_v3"] = [FOREIGN / "fruit_drops_v3.spz"]
    seeds["spz_v4"] = [FOREIGN / n for n in ("fruit_drops_v4.spz", "fruit_drops_sh0_v4.spz", "fruit_drops_sh1_v4.spz",
                                             "opaque_v4.spz")]
    for i, p in enumerate(plys[2:4]):
        g = read_gaussians(p)
        for version in (3, 4):
            out = root / f"ours_{i}_v{version}.spz"
            write_gaussians(g, out, spz_version=version)
            seeds[f"spz_v{version}"].append(out)
    sub64 = read_gaussians(FOREIGN / "fruit_drops_sub64.ply")
    write_gaussians(sub64, root / "sub64.splat")
    seeds["splat"] = [root / "sub64.splat"]
    if real and (REAL / "winter_fountain.splat").exists():
        (root / "real_winter.splat").write_bytes((REAL / "winter_fountain.splat").read_bytes()[:200 * 32])
        seeds["splat"].append(root / "real_winter.splat")
    seeds["sog_bundle"] = [FOREIGN / "fruit_drops.sog"]
    seeds["sog_dir"] = [FOREIGN / "fruit_drops_sh1_sog"]
    seeds["sog_streamed"] = [FOREIGN / "fruit_drops_lod"]
    write_gaussians(sub64, root / "sub64.glb")
    write_gaussians(sub64, root / "sub64_spz.glb", glb_compression="spz")
    seeds["glb"] = [FOREIGN / "fruit_drops_sub64_sh1.glb", root / "sub64.glb", root / "sub64_spz.glb"]
    seeds["gltf"] = [_gltf_from_glb(FOREIGN / "fruit_drops_sub64_sh1.glb", root / "gltf_a"),
                     _gltf_from_glb(root / "sub64.glb", root / "gltf_b")]
    scenes = []
    for preset in ("medium", "low", "very-high"):
        out = root / f"scene_{preset}"
        encode_gaussians(sub64, out, EncodeOptions(preset=preset))
        scenes.append(out)
    if real and (REAL / "fruit_drops_sh3.ply").exists():
        g = read_gaussians(REAL / "fruit_drops_sh3.ply")
        encode_gaussians(g.subset(slice(0, 3000)), root / "scene_lod", EncodeOptions(preset="high",
                                                                                       max_leaf_splats=512))
        scenes.append(root / "scene_lod")
    scenes += [VECTORS / "high", VECTORS / "very-low"]
    seeds["scene"] = scenes
    return seeds


# ==============================================================================================================
# Mutations. Each takes (rng, case directory, seed) and returns (input path, description).


def _copy_seed(seed: pathlib.Path, case: pathlib.Path) -> pathlib.Path:
    dst = case / seed.name
    if seed.is_dir():
        shutil.copytree(seed, dst)
    else:
        shutil.copyfile(seed, dst)
    return dst


def mutate_bytes(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """A generic byte-level mutation."""
    n = len(data)
    kind = rng.choice(["truncate", "bitflip", "bitflip", "byte", "word", "insert", "delete", "duplicate", "append",
                       "zero_span"])
    if n == 0:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))), "random bytes for an empty file"
    if kind == "truncate":
        at = rng.choice([rng.randrange(n), rng.randrange(min(n, 64)), max(0, n - 1 - rng.randrange(min(n, 64)))])
        return data[:at], f"truncated to {at} of {n} bytes"
    buf = bytearray(data)
    if kind == "bitflip":
        flips = rng.randrange(1, 9)
        for _ in range(flips):
            buf[rng.randrange(n)] ^= 1 << rng.randrange(8)
        return bytes(buf), f"{flips} bit flips"
    if kind == "byte":
        for _ in range(rng.randrange(1, 5)):
            buf[rng.randrange(n)] = rng.choice([0, 0xFF, 0x7F, 0x80, 1])
        return bytes(buf), "bytes set to 0/ff/7f/80/01"
    if kind == "word" and n >= 4:
        at = rng.randrange(n // 4) * 4
        if rng.random() < 0.5:
            word = struct.pack("<f", rng.choice(FLOAT_EXTREMES))
        else:
            word = struct.pack("<I", rng.choice(INT_EXTREMES) % 2**32)
        buf[at:at + 4] = word
        return bytes(buf), f"4-byte word at {at} set to {word.hex()}"
    if kind == "insert":
        at = rng.randrange(n + 1)
        extra = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 33)))
        return data[:at] + extra + data[at:], f"{len(extra)} bytes inserted at {at}"
    if kind == "delete":
        at = rng.randrange(n)
        k = rng.randrange(1, 65)
        return data[:at] + data[at + k:], f"{k} bytes deleted at {at}"
    if kind == "duplicate":
        at = rng.randrange(n)
        k = rng.randrange(1, min(4096, n) + 1)
        return data[:at] + data[at:at + k] + data[at:], f"{k} bytes duplicated at {at}"
    if kind == "append":
        extra = rng.choice([bytes(rng.randrange(256) for _ in range(rng.randrange(1, 100))), data[:256], b"\x00" * 32,
                            gzip.compress(b"x" * 10)])
        return data + extra, f"{len(extra)} bytes appended"
    at = rng.randrange(n)
    k = rng.randrange(1, 257)
    buf[at:at + k] = bytes(len(buf[at:at + k]))
    return bytes(buf), f"{k} bytes zeroed at {at}"


def mutate_non_regular(rng: random.Random, case: pathlib.Path, name: str) -> tuple[pathlib.Path, str]:
    """The input is not a regular file (a FIFO would hang a careless reader)."""
    path = case / name
    kind = rng.choice(["fifo", "fifo", "directory", "symlink_loop", "dev_zero", "empty", "dangling", "dev_null"])
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "symlink_loop":
        os.symlink(path.name, path)
    elif kind == "dev_zero":
        os.symlink("/dev/zero", path)
    elif kind == "dev_null":
        os.symlink("/dev/null", path)
    elif kind == "empty":
        path.write_bytes(b"")
    else:
        os.symlink(case / "missing", path)
    return path, f"non-regular input: {kind}"


# --- PLY -------------------------------------------------------------------------------------------------------


def _ply_parts(data: bytes) -> tuple[str, bytes]:
    end = data.index(b"end_header")
    nl = data.index(b"\n", end)
    return data[:nl + 1].decode("ascii"), data[nl + 1:]


def mutate_ply_header(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    head, body = _ply_parts(data)
    lines = head.split("\n")
    kinds = ["count", "count", "type", "drop_property", "rename", "duplicate_property", "list", "format",
             "duplicate_element", "extra_element", "no_end", "crlf", "comment", "keyword"]
    kind = rng.choice(kinds)
    el_lines = [i for i, line in enumerate(lines) if line.startswith("element ")]
    prop_lines = [i for i, line in enumerate(lines) if line.startswith("property ")]
    if kind == "count" and el_lines:
        i = rng.choice(el_lines)
        _, name, count = lines[i].split()
        new = rng.choice([int(count) + 1, int(count) - 1, 0, int(count) * 2, 2**31, 2**40, 10**12, 1])
        lines[i] = f"element {name} {max(new, 0)}"
        desc = f"header lies: element {name} count {count} -> {max(new, 0)}"
    elif kind == "type" and prop_lines:
        i = rng.choice(prop_lines)
        words = lines[i].split()
        new = rng.choice(["double", "uchar", "int", "short", "float64", "half", "char"])
        lines[i] = f"property {new} {words[-1]}"
        desc = f"property {words[-1]} type {words[1]} -> {new}"
    elif kind == "drop_property" and prop_lines:
        i = rng.choice(prop_lines)
        desc = f"header drops {lines[i]!r}"
        del lines[i]
    elif kind == "rename" and prop_lines:
        i = rng.choice(prop_lines)
        words = lines[i].split()
        new = words[-1][:-1] + "9" if rng.random() < 0.5 else "fil4er"
        lines[i] = " ".join(words[:-1] + [new])
        desc = f"property {words[-1]} renamed {new}"
    elif kind == "duplicate_property" and prop_lines:
        i = rng.choice(prop_lines)
        lines.insert(i, lines[i])
        desc = f"property line duplicated: {lines[i]!r}"
    elif kind == "list" and prop_lines:
        i = rng.choice(prop_lines)
        lines.insert(i, "property list uchar int vertex_indices")
        desc = "list property added"
    elif kind == "format":
        i = next(i for i, line in enumerate(lines) if line.startswith("format "))
        new = rng.choice(["ascii", "binary_big_endian", "binary_little_endian", "binary_middle_endian", ""])
        lines[i] = f"format {new} 1.0"
        desc = f"format line -> {new!r}"
    elif kind == "duplicate_element" and el_lines:
        i = rng.choice(el_lines)
        props = [line for line in lines[i + 1:] if line.startswith("property ")][:3]
        end = next(j for j, line in enumerate(lines) if line.startswith("end_header"))
        lines[end:end] = [lines[i].rsplit(" ", 1)[0] + f" {rng.choice([0, 1, 2])}"] + props
        desc = f"element declared twice: {lines[i]!r}"
    elif kind == "extra_element":
        end = next(j for j, line in enumerate(lines) if line.startswith("end_header"))
        lines[end:end] = ["element face 3", "property float a"]
        desc = "an element without data"
    elif kind == "no_end":
        head = head.replace("end_header", "end_headr")
        return head.encode("ascii") + body, "no end_header"
    elif kind == "crlf":
        return head.replace("\n", "\r\n").encode("ascii") + body, "CRLF header"
    elif kind == "comment":
        i = rng.randrange(1, len(lines) - 1)
        lines.insert(i, "comment " + "x" * rng.choice([0, 10, 5000]))
        desc = "comment inserted"
    else:
        i = rng.randrange(1, len(lines) - 1)
        lines.insert(i, rng.choice(["obj_info x", "elementvertex 3", "property", "propertyfloat x", "\x00", "é"]))
        desc = f"odd header line {lines[i]!r}"
    try:
        return "\n".join(lines).encode("ascii") + body, desc
    except UnicodeEncodeError:
        return "\n".join(lines).encode("utf-8") + body, desc


def mutate_ply_value(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """A numeric extreme in one (row, property) of a binary PLY's vertex element, or in a whole column."""
    from splatstream.ply import read_header

    header = read_header("seed", data[:1 << 20])
    vertex = header.element("vertex")
    order = "<" if header.format == "binary_little_endian" else ">"
    offset = header.size
    for el in header.elements:
        if el is vertex:
            break
        offset += el.count * el.dtype(order).itemsize
    import numpy as np

    dt = vertex.dtype(order)
    records = np.frombuffer(data[offset:offset + vertex.count * dt.itemsize], dt).copy()
    name = rng.choice(dt.names)
    value = rng.choice(FLOAT_EXTREMES)
    if rng.random() < 0.2:
        rows = slice(None)
        where = "every row"
    else:
        rows = rng.randrange(len(records))
        where = f"row {rows}"
    if records[name].dtype.kind == "f":
        with np.errstate(over="ignore", invalid="ignore"):
            records[name][rows] = value
    else:
        value = rng.choice(INT_EXTREMES)
        records[name][rows] = np.array(value).astype(records[name].dtype)
    if rng.random() < 0.15 and {"rot_0", "rot_1", "rot_2", "rot_3"} <= set(dt.names):
        for r in ("rot_0", "rot_1", "rot_2", "rot_3"):
            records[r][rows] = 0
        name, value = "rot_0..3", 0
    return data[:offset] + records.tobytes() + data[offset + records.nbytes:], f"{name} of {where} = {value!r}"


def mutate_ascii_tokens(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    head, body = _ply_parts(data)
    tokens = body.split(b" ")
    kind = rng.choice(["token", "token", "extreme", "delete", "add", "newline"])
    i = rng.randrange(len(tokens))
    if kind == "token":
        new = rng.choice(ASCII_TOKENS).encode("utf-8")
        tokens[i] = new + (b"\n" if tokens[i].endswith(b"\n") else b"")
        desc = f"ASCII value {i} -> {new!r}"
    elif kind == "extreme":
        new = repr(rng.choice(FLOAT_EXTREMES)).encode()
        tokens[i] = new + (b"\n" if tokens[i].endswith(b"\n") else b"")
        desc = f"ASCII value {i} -> {new!r}"
    elif kind == "delete":
        del tokens[i]
        desc = f"ASCII value {i} deleted"
    elif kind == "add":
        tokens.insert(i, b"0.5")
        desc = f"ASCII value inserted at {i}"
    else:
        tokens[i] = tokens[i] + b"\n"
        desc = f"line break after value {i}"
    return head.encode("ascii") + b" ".join(tokens), desc


def mutate_compressed_ply(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """Chunk bounds set to extremes (scale bounds beyond float16, NaN, inverted), or packed words randomised."""
    import numpy as np

    from splatstream.ply import read_header

    header = read_header("seed", data[:1 << 20])
    chunk = header.element("chunk")
    dt = chunk.dtype("<")
    records = np.frombuffer(data[header.size:header.size + chunk.count * dt.itemsize], dt).copy()
    name = rng.choice(dt.names)
    row = rng.randrange(len(records))
    kind = rng.choice(["extreme", "extreme", "invert"])
    if kind == "invert":
        axis = name.split("_", 1)[1]
        lo, hi = records["min_" + axis][row], records["max_" + axis][row]
        records["min_" + axis][row], records["max_" + axis][row] = hi + 1, lo - 1
        desc = f"chunk {row} bounds of {axis} inverted"
    else:
        value = rng.choice(FLOAT_EXTREMES)
        records[name][row] = value
        desc = f"chunk {row} {name} = {value!r}"
    return data[:header.size] + records.tobytes() + data[header.size + records.nbytes:], desc


# --- SPZ -------------------------------------------------------------------------------------------------------


def mutate_spz_legacy(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """Inside the gzip stream (header fields, body) or of the gzip stream itself; decompression bombs."""
    import zlib

    body = zlib.decompress(data, 31)
    kind = rng.choice(["field", "field", "body", "length", "trailing", "member", "bomb", "level"])
    if kind == "field":
        fields = {"version": (4, "<I"), "numPoints": (8, "<I"), "shDegree": (12, "<B"), "fractionalBits": (13, "<B"),
                  "flags": (14, "<B"), "reserved": (15, "<B")}
        name = rng.choice(list(fields))
        at, fmt = fields[name]
        limit = 2 ** (8 * struct.calcsize(fmt))
        value = rng.choice([v % limit for v in INT_EXTREMES] + [1, 2, 3, 4, 5, 24, 0x80])
        body = body[:at] + struct.pack(fmt, value) + body[at + struct.calcsize(fmt):]
        return gzip.compress(body, 6), f"gzip header field {name} = {value}"
    if kind == "body":
        mutated, desc = mutate_bytes(rng, body[16:])
        return gzip.compress(body[:16] + mutated, 6), f"decompressed body: {desc}"
    if kind == "length":
        cut = rng.randrange(16, len(body))
        return gzip.compress(body[:cut] if rng.random() < 0.5 else body + body[cut:], 6), "body length changed"
    if kind == "trailing":
        return data + bytes(rng.randrange(1, 64)), "bytes after the gzip stream"
    if kind == "member":
        return data + gzip.compress(body[:100]), "a second gzip member"
    if kind == "level":
        return gzip.compress(body, rng.choice([0, 1, 9])), "recompressed (another gzip level)"
    n = rng.choice([5_000_000, 50_000_000, 2**32 - 1])
    version = struct.unpack_from("<I", body, 4)[0]
    head = struct.pack("<4sIIBBBB", b"NGSP", version, n, 0, 12, 0, 0)
    return gzip.compress(head + bytes(min(n * 20, 100 << 20)), 9), f"bomb: numPoints {n}, zeros"


def mutate_spz_v4(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    import zstandard

    kind = rng.choice(["field", "field", "toc", "frame", "bomb", "extension"])
    if kind == "field":
        fields = {"version": (4, "<I"), "numPoints": (8, "<I"), "shDegree": (12, "<B"), "fractionalBits": (13, "<B"),
                  "flags": (14, "<B"), "numStreams": (15, "<B"), "tocByteOffset": (16, "<I"), "reserved": (20, "<I")}
        name = rng.choice(list(fields))
        at, fmt = fields[name]
        limit = 2 ** (8 * struct.calcsize(fmt))
        value = rng.choice([v % limit for v in INT_EXTREMES] + [3, 5, 6, 7, 24, 32, 40])
        return data[:at] + struct.pack(fmt, value) + data[at + struct.calcsize(fmt):], f"header {name} = {value}"
    streams = data[15]
    toc = struct.unpack_from("<I", data, 16)[0]
    if kind == "toc" and streams:
        i = rng.randrange(streams)
        which = rng.randrange(2)
        at = toc + 16 * i + 8 * which
        value = rng.choice(INT_EXTREMES + [struct.unpack_from("<Q", data, at)[0] + rng.choice([-1, 1])])
        return (data[:at] + struct.pack("<Q", max(0, value) % 2**64) + data[at + 8:],
                f"toc entry {i} {'uncompressed' if which else 'compressed'}Size = {value}")
    if kind == "extension":
        ext = struct.pack("<II", rng.randrange(2**32), rng.choice([0, 4, 1000])) + bytes(4)
        head = bytearray(data[:32])
        head[14] |= 2
        struct.pack_into("<I", head, 16, 32 + len(ext))
        return bytes(head) + ext + data[32:], "extension record inserted"
    if kind == "frame" and streams:
        # Replace one stream's frame by a frame of other content (a different size, or garbage), TOC updated.
        sizes = [struct.unpack_from("<QQ", data, toc + 16 * i) for i in range(streams)]
        offset = toc + 16 * streams
        frames = []
        for c, _ in sizes:
            frames.append(data[offset:offset + c])
            offset += c
        i = rng.randrange(streams)
        content = rng.choice([b"", bytes(rng.randrange(1, 5000)), os.urandom(rng.randrange(1, 300))])
        frames[i] = zstandard.ZstdCompressor(write_content_size=rng.random() < 0.7).compress(content)
        new_sizes = [(len(f), u if j != i or rng.random() < 0.5 else len(content)) for j, (f, (_, u)) in
                     enumerate(zip(frames, sizes, strict=True))]
        toc_bytes = b"".join(struct.pack("<QQ", c, u) for c, u in new_sizes)
        return data[:toc] + toc_bytes + b"".join(frames), f"stream {i} replaced by a {len(content)}-byte frame"
    n = rng.choice([5_000_000, 50_000_000, 2**32 - 1])
    sizes = [9, 1, 3, 3, 4]
    frames = [zstandard.ZstdCompressor(level=3).compress(bytes(min(n * s, 64 << 20))) for s in sizes]
    header = struct.pack("<4sIIBBBBI12s", b"NGSP", 4, n, 0, 12, 0, 5, 32, bytes(12))
    toc_bytes = b"".join(struct.pack("<QQ", len(f), n * s) for f, s in zip(frames, sizes, strict=True))
    return header + toc_bytes + b"".join(frames), f"bomb: numPoints {n}, zero streams"


# --- .splat ----------------------------------------------------------------------------------------------------


def mutate_splat(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    import numpy as np

    kind = rng.choice(["field", "field", "zeros", "random", "column"])
    if kind == "zeros":
        return bytes(len(data)), "zero-filled"
    if kind == "random":
        return os.urandom(len(data)), "random bytes"
    records = np.frombuffer(data[:len(data) // 32 * 32], np.float32).reshape(-1, 8).copy()
    column = rng.randrange(6)
    value = rng.choice(FLOAT_EXTREMES + [-1.0])
    rows = slice(None) if kind == "column" else rng.randrange(len(records))
    records[rows, column] = value
    return records.tobytes() + data[len(data) // 32 * 32:], f"record float {column} of {rows} = {value!r}"


# --- SOG -------------------------------------------------------------------------------------------------------


def mutate_json(rng: random.Random, doc, depth: int = 0):
    """A random edit somewhere in a JSON-like value: (new value, description)."""
    if isinstance(doc, dict) and doc and (depth == 0 or rng.random() < 0.75):
        key = rng.choice(list(doc))
        doc = dict(doc)
        r = rng.random()
        if r < 0.1:
            del doc[key]
            return doc, f"{key}: deleted"
        if r < 0.15:
            doc[key[:-1] + "9"] = doc.pop(key)
            return doc, f"{key}: renamed"
        doc[key], desc = mutate_json(rng, doc[key], depth + 1)
        return doc, f"{key}.{desc}"
    if isinstance(doc, list) and doc and rng.random() < 0.75:
        doc = list(doc)
        i = rng.randrange(len(doc))
        r = rng.random()
        if r < 0.1:
            del doc[i]
            return doc, f"[{i}]: deleted"
        if r < 0.15:
            doc.insert(i, copy.deepcopy(doc[i]))
            return doc, f"[{i}]: duplicated"
        doc[i], desc = mutate_json(rng, doc[i], depth + 1)
        return doc, f"[{i}].{desc}"
    if isinstance(doc, (int, float)) and not isinstance(doc, bool) and rng.random() < 0.5:
        value = rng.choice([doc + 1, doc - 1, doc * 2, -doc, doc * 1000, 0, doc + 0.5])
        return value, f"={value!r}"
    value = rng.choice(JSON_VALUES + FLOAT_EXTREMES)
    return value, f"={value!r}"


def _webp_variants(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    from PIL import Image

    kind = rng.choice(["bytes", "bytes", "lossy", "png", "resized", "huge_header", "empty", "constant_big"])
    if kind == "bytes":
        return mutate_bytes(rng, data)
    if kind == "empty":
        return b"", "empty"
    if kind == "huge_header":
        at = data.find(b"VP8L")
        if at >= 0:
            buf = bytearray(data)
            bits = struct.unpack_from("<I", buf, at + 9)[0] | 0x0FFFFFFF
            struct.pack_into("<I", buf, at + 9, bits)
            return bytes(buf), "VP8L header claims 16384x16384"
        return data, "unchanged"
    try:
        img = Image.open(io.BytesIO(data))
        img.load()
    except Exception:
        return data, "unchanged (not decodable)"
    out = io.BytesIO()
    if kind == "lossy":
        img.save(out, format="WEBP", quality=50)
        return out.getvalue(), "re-encoded as lossy WebP"
    if kind == "png":
        img.save(out, format="PNG")
        return out.getvalue(), "a PNG instead of a WebP"
    if kind == "constant_big":
        Image.new("RGBA", (2048, 2048), (1, 2, 3, 255)).save(out, format="WEBP", lossless=True)
        return out.getvalue(), "a 2048x2048 constant lossless WebP"
    w, h = img.size
    size = rng.choice([(max(1, w // 2), h), (w, max(1, h // 2)), (w * 2, h * 2), (1, 1)])
    img.resize(size).save(out, format="WEBP", lossless=True)
    return out.getvalue(), f"resized to {size[0]}x{size[1]}"


def mutate_sog_files(rng: random.Random, directory: pathlib.Path) -> str:
    """One file of an unbundled or streamed SOG directory: JSON edit, WebP replaced or corrupted, deleted,
    a FIFO, a directory, a symlink outside."""
    files = sorted(p for p in directory.rglob("*") if p.is_file())
    target = rng.choice(files)
    rel = target.relative_to(directory)
    kind = rng.choice(["content", "content", "content", "delete", "fifo", "dir", "symlink_out", "symlink_loop"])
    if kind == "content":
        if target.suffix == ".json":
            doc, desc = mutate_json(rng, json.loads(target.read_text()))
            target.write_text(json.dumps(doc))
        else:
            data, desc = _webp_variants(rng, target.read_bytes())
            target.write_bytes(data)
        return f"{rel}: {desc}"
    target.unlink()
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "dir":
        target.mkdir()
    elif kind == "symlink_out":
        os.symlink("/etc/hostname" if os.path.exists("/etc/hostname") else "/dev/null", target)
    elif kind == "symlink_loop":
        os.symlink(target.name, target)
    return f"{rel}: {kind}"


def mutate_sog_bundle(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    if rng.random() < 0.4:
        return mutate_bytes(rng, data)
    members = {}
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        for info in archive.infolist():
            members[info.filename] = archive.read(info)
    name = rng.choice(list(members))
    kind = rng.choice(["content", "content", "delete", "stored"])
    if kind == "content":
        if name.endswith(".json"):
            doc, desc = mutate_json(rng, json.loads(members[name]))
            members[name] = json.dumps(doc).encode()
        else:
            members[name], desc = _webp_variants(rng, members[name])
    elif kind == "delete":
        del members[name]
        desc = "deleted"
    else:
        desc = "stored uncompressed"
    out = io.BytesIO()
    method = zipfile.ZIP_STORED if kind == "stored" or rng.random() < 0.5 else zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(out, "w", method) as archive:
        for member, content in members.items():
            archive.writestr(member, content)
    return out.getvalue(), f"member {name}: {desc}"


# --- glTF ------------------------------------------------------------------------------------------------------


def _glb_parts(data: bytes) -> tuple[dict, bytes]:
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    binary = data[28 + json_len:] if len(data) > 28 + json_len else b""
    return doc, binary


def _glb(doc: dict, binary: bytes) -> bytes:
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary += bytes(-len(binary) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _mutate_gltf_doc(rng: random.Random, doc: dict) -> tuple[dict, str]:
    kind = rng.choice(["json", "json", "accessor", "node", "view"])
    doc = copy.deepcopy(doc)
    if kind == "accessor" and doc.get("accessors"):
        a = rng.choice(doc["accessors"])
        key = rng.choice(["count", "componentType", "normalized", "byteOffset", "type"])
        value = rng.choice({"count": [0, -1, a.get("count", 1) + 1, 2**31, 10**9], "componentType":
                            [5120, 5121, 5122, 5123, 5125, 5126, 5130, 1], "normalized": [True, False, 1],
                            "byteOffset": [1, 4, -4, 2**40], "type": ["VEC2", "MAT4", "SCALAR", 3]}[key])
        a[key] = value
        return doc, f"accessor {key} = {value!r}"
    if kind == "node" and doc.get("nodes"):
        node = rng.choice(doc["nodes"])
        key = rng.choice(["matrix", "scale", "rotation", "translation", "children", "mesh"])
        value = rng.choice({"matrix": [[float("nan")] * 16, [1e30] + [0.0] * 14 + [1.0], [2.0] * 16],
                            "scale": [[1, 2, 3], [0, 0, 0], [-1, -1, -1], [1e30] * 3], "rotation": [[0, 0, 0, 0],
                            [1, 1, 1, 1], [float("nan")] * 4], "translation": [[1e38] * 3, [float("inf")] * 3],
                            "children": [[0], [99], "x"], "mesh": [99, -1, "x"]}[key])
        node[key] = value
        return doc, f"node {key} = {value!r}"
    if kind == "view" and doc.get("bufferViews"):
        v = rng.choice(doc["bufferViews"])
        key = rng.choice(["byteOffset", "byteLength", "byteStride", "buffer"])
        value = rng.choice([0, 1, 3, -1, 2**31, 1000000, v.get(key, 0) + 4])
        v[key] = value
        return doc, f"bufferView {key} = {value!r}"
    new, desc = mutate_json(rng, doc)
    return new, desc


def mutate_glb(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    kind = rng.choice(["bytes", "doc", "doc", "binary_floats", "length"])
    if kind == "bytes":
        return mutate_bytes(rng, data)
    doc, binary = _glb_parts(data)
    if kind == "length":
        buf = bytearray(data)
        struct.pack_into("<I", buf, 8, rng.choice([0, len(data) + 4, len(data) - 4, 2**32 - 1]))
        return bytes(buf), "GLB header length lies"
    if kind == "binary_floats" and len(binary) >= 4:
        buf = bytearray(binary)
        for _ in range(rng.randrange(1, 5)):
            at = rng.randrange(len(buf) // 4) * 4
            struct.pack_into("<f", buf, at, rng.choice(FLOAT_EXTREMES))
        return _glb(doc, bytes(buf)), "float extremes in the binary chunk"
    doc, desc = _mutate_gltf_doc(rng, doc)
    return _glb(doc, binary), desc


def mutate_gltf_dir(rng: random.Random, gltf: pathlib.Path) -> str:
    doc = json.loads(gltf.read_text())
    kind = rng.choice(["doc", "doc", "bin", "uri", "bin_fifo", "bin_truncate"])
    binary = gltf.parent / "scene.bin"
    if kind == "doc":
        doc, desc = _mutate_gltf_doc(rng, doc)
        gltf.write_text(json.dumps(doc))
        return desc
    if kind == "bin":
        data, desc = mutate_bytes(rng, binary.read_bytes())
        binary.write_bytes(data)
        return f"scene.bin: {desc}"
    if kind == "uri":
        uri = rng.choice(["../outside.bin", "/etc/passwd", "missing.bin", "data:application/octet-stream;base64,AAAA",
                          "data:,abc", "http://example.com/x.bin", "scene.bin/", "%2e%2e/x", ""])
        doc["buffers"][0]["uri"] = uri
        gltf.write_text(json.dumps(doc))
        return f"buffer uri = {uri!r}"
    if kind == "bin_fifo":
        binary.unlink()
        os.mkfifo(binary)
        return "scene.bin is a FIFO"
    data = binary.read_bytes()
    binary.write_bytes(data[:rng.randrange(len(data))])
    return "scene.bin truncated"


# --- scenes ----------------------------------------------------------------------------------------------------


def _manifest_dict(scene: pathlib.Path) -> dict:
    """The manifest map; an unpaged 1.8, 1.12 or 1.15 tile table (format.md 6.2) as the same scene's 1.7 tile maps, so
    that a campaign damages one tile's map as before (the table's own damage: tests/test_manifest_table.py). A 1.15
    table's payloads, named by 16 bytes of their SHA-256, get their whole-SHA-256 names beside (hard links), which
    1.7's maps name."""
    from dataclasses import replace

    import msgpack

    from splatstream.format.manifest import manifest_from_dict
    from splatstream.format.manifest.versions import VERSION_1_7

    d = msgpack.unpackb((scene / "manifest.msgpack").read_bytes(), raw=False, strict_map_key=False)
    if not {"tile_table", "tile_table_zstd"} & d.keys() or "paged" in d:
        return d
    m = replace(manifest_from_dict(d), version=VERSION_1_7)
    if any(len(e.sha256) != 64 for t in m.tiles for e in t.groups.values()):
        tiles = []
        for t in m.tiles:
            groups = {}
            for name, e in t.groups.items():
                full = hashlib.sha256((scene / e.file).read_bytes()).hexdigest()
                if not (scene / "data" / f"{full}.bin").exists():
                    os.link(scene / e.file, scene / "data" / f"{full}.bin")
                groups[name] = replace(e, sha256=full, file=f"data/{full}.bin")
            tiles.append(replace(t, groups=groups))
        m = replace(m, tiles=tuple(tiles))
    return m.with_bytes_on_disk(m.payload_bytes()).to_dict()


def _write_manifest(scene: pathlib.Path, d: dict, reseal: bool = True, settle: bool = False) -> None:
    """Write a manifest map; `reseal`: with a valid checksum; `settle`: totals recomputed from the entries (a
    replaced payload, so that only its content can be wrong)."""
    import msgpack

    from splatstream.format.manifest import pack_manifest_dict

    if settle:
        leaves = [p for t in d["tiles"] if not t["children"] for p in t["groups"].values()]
        codebook = list((d.get("sh_codebook") or {}).get("groups", {}).values())
        d["gpu_bytes"] = sum(p["gpu_bytes"] for p in leaves + codebook)
        d["leaf_bytes_on_disk"] = sum(p["bytes"] for p in leaves + codebook)
        every = {p["file"]: p["bytes"] for t in d["tiles"] for p in t["groups"].values()}
        every.update({p["file"]: p["bytes"] for p in codebook})
        for _ in range(3):
            d["bytes_on_disk"] = sum(every.values()) + len(pack_manifest_dict(d))
    data = pack_manifest_dict(d) if reseal else msgpack.packb(d, use_bin_type=True)
    (scene / "manifest.msgpack").write_bytes(data)


def _random_leaf_edit(rng: random.Random, d, depth: int = 0):
    """A manifest edit: a random path, then a value change, a deletion, a rename or an added key."""
    if isinstance(d, dict) and d and (depth == 0 or rng.random() < 0.8):
        key = rng.choice([k for k in d if k != "checksum"] or list(d))
        d = dict(d)
        r = rng.random()
        if r < 0.07:
            del d[key]
            return d, f"{key}: deleted"
        if r < 0.12:
            new = key[:3] + "4" + key[4:] if len(key) > 3 else key + "x"
            d[new] = d.pop(key)
            return d, f"{key}: renamed {new}"
        if r < 0.15:
            d["extra_key"] = 1
            return d, f"{key}: extra key added beside it"
        d[key], desc = _random_leaf_edit(rng, d[key], depth + 1)
        return d, f"{key}.{desc}"
    if isinstance(d, list) and d and rng.random() < 0.8:
        d = list(d)
        i = rng.randrange(len(d))
        r = rng.random()
        if r < 0.08:
            del d[i]
            return d, f"[{i}]: deleted"
        if r < 0.12:
            d.insert(i, copy.deepcopy(d[i]))
            return d, f"[{i}]: duplicated"
        d[i], desc = _random_leaf_edit(rng, d[i], depth + 1)
        return d, f"[{i}].{desc}"
    if isinstance(d, (int, float)) and not isinstance(d, bool) and rng.random() < 0.6:
        value = rng.choice([d + 1, d - 1, d + 4, d - 4, d * 2, d // 2 if isinstance(d, int) else d / 2, -d, 0])
        return value, f"={value!r}"
    value = copy.deepcopy(rng.choice(MSGPACK_VALUES))
    return value, f"={value!r}"


def _payload_files(scene: pathlib.Path) -> list[pathlib.Path]:
    return sorted((scene / "data").glob("*.bin")) if (scene / "data").is_dir() else []


def _reseal_payload(rng: random.Random, scene: pathlib.Path) -> str:
    """Change values inside one payload (a range to NaN/inf/inverted/out of domain, float texels out of [0, 1],
    random texel bytes, random bytes of a fields1 content), recompress, rename and point the manifest at it
    (checksums valid): only the values can be wrong."""
    import hashlib

    import numpy as np
    import zstandard

    from splatstream.format.texformats import shuffle_bytes, unshuffle_bytes

    d = _manifest_dict(scene)
    entries = [p for t in d["tiles"] for p in t["groups"].values()]
    if d.get("sh_codebook"):
        entries += list(d["sh_codebook"]["groups"].values())
    entry = rng.choice(entries)
    raw = bytearray(zstandard.ZstdDecompressor().decompress((scene / entry["file"]).read_bytes()))
    s = rng.choice(entry["sections"])
    element = int(s["filter"][7:]) if s["filter"].startswith("shuffle") else 1
    if s["filter"] == "fields1":  # transport-coded texels (format.md 5.2): random bytes of the stored content
        dtype = np.dtype("u1")
        units = 1
    elif s["kind"] == "range":
        dtype = np.dtype("<f4") if s["dtype"] == "f32" else np.dtype("<f2")
        units = 1
    else:
        dtype = {"f32x4": np.dtype("<f4"), "f16x4": np.dtype("<f2")}.get(s["format"], np.dtype("u1"))
        units = s["layers"]
    unit = s["size"] // units
    k = rng.randrange(units)
    start = s["offset"] + k * unit
    stored = np.frombuffer(bytes(raw[start:start + unit]), np.uint8)
    values = unshuffle_bytes(stored, element).view(dtype).copy()
    if dtype.kind == "f":
        kind = rng.choice(["extreme", "extreme", "invert"]) if s["kind"] == "range" else "extreme"
        if kind == "invert":
            ranges = values.reshape(s["shape"])
            c = rng.randrange(len(ranges))
            ranges[c, 0], ranges[c, 1] = ranges[c, 1].copy() + 1, ranges[c, 0].copy() - 1
            desc = f"chunk {c}: range minimum and maximum swapped"
        else:
            with np.errstate(over="ignore", invalid="ignore"):
                at = rng.randrange(len(values))
                value = rng.choice(FLOAT_EXTREMES + [1.5, -0.5, 60000.0])
                values[at] = value
            desc = f"value {at} = {value!r}"
    else:
        at = rng.randrange(len(values))
        values[at:at + 16] = np.frombuffer(os.urandom(len(values[at:at + 16])), np.uint8)
        desc = f"16 {'fields1 content' if s['filter'] == 'fields1' else 'texel'} bytes at {at} random"
    raw[start:start + unit] = shuffle_bytes(values.view(np.uint8), element).tobytes()
    data = zstandard.ZstdCompressor().compress(bytes(raw))
    sha = hashlib.sha256(data).hexdigest()
    (scene / "data" / f"{sha}.bin").write_bytes(data)
    entry.update(file=f"data/{sha}.bin", sha256=sha, bytes=len(data))
    _write_manifest(scene, d, settle=True)
    return f"payload section {s['name']} (resealed): {desc}"


def mutate_scene(rng: random.Random, scene: pathlib.Path) -> str:
    kind = rng.choices(["field", "manifest_bytes", "payload_bytes", "payload_values", "files", "manifest_file"],
                       weights=[40, 10, 10, 20, 12, 8])[0]
    if kind == "field":
        d, desc = _random_leaf_edit(rng, _manifest_dict(scene))
        _write_manifest(scene, d, reseal=True)
        return f"manifest field (resealed): {desc}"
    if kind == "manifest_bytes":
        path = scene / "manifest.msgpack"
        data, desc = mutate_bytes(rng, path.read_bytes())
        path.write_bytes(data)
        return f"manifest bytes (not resealed): {desc}"
    payloads = _payload_files(scene)
    if kind == "payload_bytes" and payloads:
        path = rng.choice(payloads)
        data, desc = mutate_bytes(rng, path.read_bytes())
        path.write_bytes(data)
        return f"payload bytes: {desc}"
    if kind == "payload_values" and payloads:
        return _reseal_payload(rng, scene)
    if kind == "files" and payloads:
        path = rng.choice(payloads)
        how = rng.choice(["delete", "fifo", "dir", "symlink_out", "symlink_loop", "dev_zero", "other_payload",
                          "data_is_file"])
        if how == "data_is_file":
            shutil.rmtree(scene / "data")
            (scene / "data").write_bytes(b"x")
            return "data/ is a file"
        path.unlink()
        if how == "fifo":
            os.mkfifo(path)
        elif how == "dir":
            path.mkdir()
        elif how == "symlink_out":
            os.symlink("/etc/hostname" if os.path.exists("/etc/hostname") else "/dev/null", path)
        elif how == "symlink_loop":
            os.symlink(path.name, path)
        elif how == "dev_zero":
            os.symlink("/dev/zero", path)
        elif how == "other_payload" and payloads[1:]:
            shutil.copyfile(next(p for p in payloads if p != path), path)
        return f"payload {how}"
    path = scene / "manifest.msgpack"
    how = rng.choice(["delete", "fifo", "dir", "dev_zero", "symlink_loop", "empty", "garbage", "huge_claim"])
    if how == "huge_claim":
        d = _manifest_dict(scene)
        d["tiles"][0]["groups"]["base"]["raw_bytes"] = 2 << 30
        _write_manifest(scene, d)
        return "manifest (resealed): a payload claims 2 GiB"
    path.unlink()
    if how == "fifo":
        os.mkfifo(path)
    elif how == "dir":
        path.mkdir()
    elif how == "dev_zero":
        os.symlink("/dev/zero", path)
    elif how == "symlink_loop":
        os.symlink(path.name, path)
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(os.urandom(rng.randrange(1, 4096)))
    return f"manifest {how}"


# ==============================================================================================================
# Cases


@dataclasses.dataclass
class Case:
    format: str
    index: int
    description: str = ""
    outcome: str = ""
    detail: str = ""
    runs: list[Run] = dataclasses.field(default_factory=list)
    numeric_warnings: list[str] = dataclasses.field(default_factory=list)  # numpy RuntimeWarnings seen


NUMPY_WARNING = " encountered in "  # "overflow encountered in multiply", "invalid value encountered in cast", ...


FILE_MUTATORS: dict[str, list[tuple[float, Callable]]] = {
    "ply_binary": [(3, mutate_bytes), (3, mutate_ply_header), (4, mutate_ply_value)],
    "ply_ascii": [(2, mutate_bytes), (3, mutate_ply_header), (5, mutate_ascii_tokens)],
    "compressed_ply": [(3, mutate_bytes), (2, mutate_ply_header), (4, mutate_compressed_ply)],
    "spz_v2": [(3, mutate_bytes), (6, mutate_spz_legacy)],
    "spz_v3": [(3, mutate_bytes), (6, mutate_spz_legacy)],
    "spz_v4": [(4, mutate_bytes), (6, mutate_spz_v4)],
    "splat": [(4, mutate_bytes), (6, mutate_splat)],
    "sog_bundle": [(1, mutate_sog_bundle)],
    "glb": [(1, mutate_glb)],
}
INPUT_NAMES = {"ply_binary": "in.ply", "ply_ascii": "in.ply", "compressed_ply": "in.compressed.ply",
               "spz_v2": "in.spz", "spz_v3": "in.spz", "spz_v4": "in.spz", "splat": "in.splat",
               "sog_bundle": "in.sog", "glb": "in.glb"}


def make_input(rng: random.Random, fmt: str, seed: pathlib.Path, case: pathlib.Path) -> tuple[pathlib.Path, str]:
    """Mutate `seed` into an input for a case of format `fmt` inside `case`; (input path, description)."""
    if fmt in FILE_MUTATORS:
        if rng.random() < 0.04:
            return mutate_non_regular(rng, case, INPUT_NAMES[fmt])
        weights, mutators = zip(*FILE_MUTATORS[fmt], strict=True)
        mutator = rng.choices(mutators, weights=weights)[0]
        data = seed.read_bytes()
        try:
            mutated, desc = mutator(rng, data)
        except Exception as exc:  # a structured mutator that does not apply to this seed: fall back to bytes
            mutated, desc = mutate_bytes(rng, data)
            desc += f" (structured mutation skipped: {exc.__class__.__name__})"
        path = case / INPUT_NAMES[fmt]
        path.write_bytes(mutated)
        return path, f"{seed.name}: {mutator.__name__}: {desc}"
    if fmt in ("sog_dir", "sog_streamed"):
        copy_dir = _copy_seed(seed, case)
        desc = mutate_sog_files(rng, copy_dir)
        meta = "lod-meta.json" if fmt == "sog_streamed" else "meta.json"
        path = copy_dir / meta if rng.random() < 0.3 else copy_dir
        return path, f"{seed.name}: {desc}"
    if fmt == "gltf":
        copy_dir = _copy_seed(seed.parent, case)
        gltf = copy_dir / seed.name
        return gltf, f"{seed.parent.name}/{seed.name}: {mutate_gltf_dir(rng, gltf)}"
    if fmt == "scene":
        scene = case / "scene"
        shutil.copytree(seed, scene)
        return scene, f"{seed.name}: {mutate_scene(rng, scene)}"
    raise ValueError(fmt)


def _names_a_case_file(message: str, case: pathlib.Path) -> bool:
    return str(case) in message or str(case.resolve()) in message


def classify(run: Run, case_dir: pathlib.Path, outputs: list[pathlib.Path]) -> tuple[str, str]:
    """Outcome of one command (before checking what it wrote)."""
    err = run.stderr
    lines = [line for line in err.strip().splitlines() if line.strip() and "warning:" not in line]
    if run.timed_out:
        return "hang", f"still running after {run.seconds:.0f} s"
    if run.signal is not None:
        return "crash", f"killed by signal {run.signal}"
    if "Traceback" in err or "internal error" in err:
        return "traceback", (lines[-1] if lines else err)[-300:]
    if run.rc == 1 and "out of memory" in err:
        return "oom", err.strip()[-300:]
    temps = [p.name for p in case_dir.iterdir() if p.name.startswith(".")]
    temps += [str(p) for out in outputs if out.is_dir() and not out.is_symlink() for p in out.rglob(".*")]
    if temps:
        return "partial_output", f"temporary names left: {temps}"
    if run.rc != 0 and any(os.path.lexists(p) for p in outputs):
        return "partial_output", f"exit {run.rc} but {[str(p) for p in outputs if os.path.lexists(p)]} exists"
    if run.rc == 0:
        return "success", ""
    if run.rc == 2:
        if len(lines) != 1 or not lines[0].startswith(f"splatstream {run.argv[0]}: error: "):
            return "unclear_error", " | ".join(lines)[-400:]
        if not _names_a_case_file(lines[0], case_dir):
            return "unclear_error", f"names no file: {lines[0][-300:]}"
        return "clean_error", lines[0][len(f"splatstream {run.argv[0]}: error: "):][:200]
    return "failure", f"exit {run.rc}: " + " | ".join(lines)[-300:]


def ply_has_non_finite(path: pathlib.Path) -> str:
    """'' if every float of a PLY we wrote is finite, else what is not."""
    import numpy as np

    from splatstream.ply import read_elements

    _, elements = read_elements(str(path))
    for name, arr in elements.items():
        for field in arr.dtype.names:
            column = arr[field]
            if column.dtype.kind == "f" and not np.isfinite(column).all():
                return f"{name}.{field}: {int((~np.isfinite(column)).sum())} non-finite values"
    return ""


class Campaign:
    def __init__(self, workdir: pathlib.Path, seed: int = 1, jobs: int = 2, render: int = 0, spawn: bool = False,
                 use_real: bool = True, keep: pathlib.Path | None = None, timeout: float = TIMEOUT_S):
        self.workdir = workdir
        self.seed = seed
        self.jobs = jobs
        self.render_budget = render  # render cases per format at most (0: none)
        self.spawn = spawn
        self.keep = keep
        self.timeout = timeout
        self.seeds = build_seeds(workdir / "seeds", use_real)
        # Never parse a mutant in this process (its manifest may be a symlink to /dev/zero): tile ids of the seeds.
        self.tile_ids = {s: [t["id"] for t in _manifest_dict(s)["tiles"]] for s in self.seeds["scene"]}
        self.local = threading.local()
        self.runners: list = []
        self.runners_lock = threading.Lock()
        self.gl = False

    # -- running ---------------------------------------------------------------------------------------------
    def runner(self):
        r = getattr(self.local, "runner", None)
        if r is None:
            r = Spawner() if self.spawn else ForkServer()
            self.local.runner = r
            with self.runners_lock:
                self.runners.append(r)
        return r

    def cli(self, case: Case, case_dir: pathlib.Path, *argv: object) -> Run:
        run = self.runner().run([str(a) for a in argv], str(case_dir), timeout=self.timeout)
        case.runs.append(run)
        case.numeric_warnings += [line for line in run.stderr.splitlines() if NUMPY_WARNING in line]
        return run

    def close(self) -> None:
        for r in self.runners:
            r.close()

    def check_gl(self) -> bool:
        """Whether `render` works here (EGL); render cases run only then."""
        probe = self.workdir / "gl_probe"
        probe.mkdir(exist_ok=True)
        run = self.runner().run(["render", str(self.seeds["scene"][0]), "--out", str(probe / "o.png"), "--size",
                                 RENDER_SIZE, "-q"], str(probe), timeout=120)
        self.gl = run.rc == 0
        return self.gl

    # -- one case --------------------------------------------------------------------------------------------
    def run_case(self, fmt: str, index: int, render: bool) -> Case:
        rng = random.Random(f"{self.seed}:{fmt}:{index}")
        case = Case(fmt, index)
        case_dir = pathlib.Path(tempfile.mkdtemp(prefix=f"{fmt}-{index}-", dir=self.workdir / "cases"))
        try:
            seed = rng.choice(self.seeds[fmt])
            path, case.description = make_input(rng, fmt, seed, case_dir)
            if fmt == "scene":
                self._scene_commands(rng, case, case_dir, path, seed, render)
            else:
                self._file_commands(rng, case, case_dir, path, render)
        except Exception as exc:  # a bug of the campaign itself: reported, never counted as a good outcome
            import traceback

            case.outcome, case.detail = "failure", f"campaign error: {exc!r} {traceback.format_exc()[-500:]}"
        finally:
            bad = case.outcome not in GOOD
            if bad and self.keep is not None:
                dst = self.keep / f"{fmt}-{index}"
                shutil.rmtree(dst, ignore_errors=True)
                with contextlib.suppress(Exception):
                    shutil.copytree(case_dir, dst, symlinks=True, ignore_dangling_symlinks=True,
                                    copy_function=_copy_regular)
                    (dst / "case.json").write_text(json.dumps(case_record(case), indent=1))
            _rmtree(case_dir)
        return case

    def _set(self, case: Case, outcome: str, detail: str) -> None:
        if not case.outcome or SEVERITY[outcome] > SEVERITY[case.outcome]:
            case.outcome, case.detail = outcome, detail

    def _file_commands(self, rng: random.Random, case: Case, case_dir: pathlib.Path, path: pathlib.Path,
                       render: bool) -> None:
        r = rng.random()
        if render and self.gl:
            out = case_dir / "o.png"
            run = self.cli(case, case_dir, "render", path, "--out", out, "--size", RENDER_SIZE, "-q")
            self._set(case, *classify(run, case_dir, [out]))
        elif r < 0.6:
            out = case_dir / "out_scene"
            args = ["encode", "-q", path, out]
            if rng.random() < 0.3:
                args[2:2] = ["--preset", rng.choice(["high", "low", "very-high", "very-low"])]
            if rng.random() < 0.3:
                args[2:2] = ["--max-leaf-splats", "256"]
            if rng.random() < 0.2:
                args[2:2] = ["--drop-invalid"]
            run = self.cli(case, case_dir, *args)
            self._set(case, *classify(run, case_dir, [out]))
            if case.outcome == "success":
                check = case_dir / "check.ply"
                back = self.cli(case, case_dir, "decode", out, check)
                outcome, detail = classify(back, case_dir, [check])
                if outcome != "success":
                    self._set(case, "unreadable", f"decode of the encoded scene: {outcome}: {detail}")
                else:
                    self._nan_check(case, check)
        else:
            ext = rng.choice([".ply", ".ply", ".splat", ".spz", ".glb"])
            out = case_dir / f"out{ext}"
            args = ["convert", "-q", path, out]
            if ext == ".spz" and rng.random() < 0.5:
                args[2:2] = ["--spz-version", "3"]
            if ext == ".glb" and rng.random() < 0.5:
                args[2:2] = ["--glb-compression", "spz"]
            if rng.random() < 0.2:
                args[2:2] = ["--drop-invalid"]
            run = self.cli(case, case_dir, *args)
            self._set(case, *classify(run, case_dir, [out]))
            if case.outcome == "success":
                check = case_dir / "check.ply"
                back = self.cli(case, case_dir, "convert", "-q", out, check)
                outcome, detail = classify(back, case_dir, [check])
                if outcome != "success":
                    self._set(case, "unreadable", f"reading back {out.name}: {outcome}: {detail}")
                else:
                    self._nan_check(case, check)

    def _scene_commands(self, rng: random.Random, case: Case, case_dir: pathlib.Path, scene: pathlib.Path,
                        seed: pathlib.Path, render: bool) -> None:
        check = case_dir / "check.ply"
        args = ["decode", scene, check]
        if rng.random() < 0.3:  # every tile, not only the leaves (ids from the seed: the mutant may be anything)
            args += ["--tiles", ",".join(map(str, self.tile_ids[seed]))]
        if render and self.gl:
            out = case_dir / "o.png"
            run = self.cli(case, case_dir, "render", scene, "--out", out, "--size", RENDER_SIZE, "-q")
            self._set(case, *classify(run, case_dir, [out]))
            decoded = self.cli(case, case_dir, *args)
            outcome, detail = classify(decoded, case_dir, [check])
            self._set(case, outcome, detail)
            if run.rc == 0 and decoded.rc == 2:
                self._set(case, "inconsistent", f"render drew a scene decode refuses: {detail}")
        elif rng.random() < 0.25:
            run = self.cli(case, case_dir, "info", scene, *(["--json"] if rng.random() < 0.5 else []))
            self._set(case, *classify(run, case_dir, []))
        else:
            run = self.cli(case, case_dir, *args)
            self._set(case, *classify(run, case_dir, [check]))
        if case.outcome == "success" and check.exists():
            self._nan_check(case, check)

    def _nan_check(self, case: Case, ply: pathlib.Path) -> None:
        problem = ply_has_non_finite(ply)
        if problem:
            self._set(case, "silent_nan", problem)

    # -- the campaign ----------------------------------------------------------------------------------------
    def run(self, cases_per_format: int, formats: list[str] | None = None, only: tuple[str, int] | None = None,
            progress: bool = False) -> list[Case]:
        (self.workdir / "cases").mkdir(parents=True, exist_ok=True)
        formats = formats or FORMATS
        if self.render_budget:
            self.check_gl()
        plan: list[tuple[str, int, bool]] = []
        for fmt in formats:
            for i in range(cases_per_format):
                plan.append((fmt, i, i < self.render_budget))
        if only is not None:
            plan = [(only[0], only[1], only[1] < self.render_budget)]
        results: list[Case] = []
        t0 = time.monotonic()
        with ThreadPoolExecutor(max_workers=self.jobs) as pool:
            for k, case in enumerate(pool.map(lambda p: self.run_case(*p), plan)):
                results.append(case)
                if progress and (k + 1) % 100 == 0:
                    print(f"  {k + 1}/{len(plan)} cases, {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
        return results


def _copy_regular(src: str, dst: str) -> None:
    if os.path.isfile(src) and not os.path.islink(src):
        shutil.copy2(src, dst)


def _rmtree(path: pathlib.Path) -> None:
    """Remove a case directory (FIFOs and symlinks included; a directory made read-only is made writable)."""
    def onerror(func, p, exc):
        with contextlib.suppress(Exception):
            os.chmod(os.path.dirname(p), 0o755)
            func(p)

    shutil.rmtree(path, onerror=onerror)


def case_record(case: Case) -> dict:
    runs = [{"argv": r.argv, "rc": r.rc, "signal": r.signal, "timed_out": r.timed_out,
             "seconds": round(r.seconds, 3), "stderr": r.stderr[-2000:]} for r in case.runs]
    return {"format": case.format, "index": case.index, "input": case.description, "outcome": case.outcome,
            "detail": case.detail, "numeric_warnings": case.numeric_warnings, "runs": runs}


def tally(cases: list[Case]) -> dict[str, Counter]:
    counts: dict[str, Counter] = {}
    for c in cases:
        counts.setdefault(c.format, Counter())[c.outcome] += 1
    return counts


def table(cases: list[Case]) -> str:
    """The outcome counts per format as a Markdown table (every outcome column, bad ones included)."""
    counts = tally(cases)
    cols = list(OUTCOMES)
    lines = ["| format | cases | " + " | ".join(cols) + " |", "|---|---:|" + "---:|" * len(cols)]
    total = Counter()
    for fmt in [f for f in FORMATS if f in counts]:
        c = counts[fmt]
        total.update(c)
        lines.append(f"| {fmt} | {sum(c.values())} | " + " | ".join(str(c.get(k, 0)) for k in cols) + " |")
    lines.append(f"| **all** | {sum(total.values())} | " + " | ".join(str(total.get(k, 0)) for k in cols) + " |")
    return "\n".join(lines)


def mutation_family(case: Case) -> str:
    """The kind of mutation of a case, for the breakdown of a format's outcomes."""
    text = case.description.split(": ", 1)[-1] if ": " in case.description else case.description
    if case.description.startswith("non-regular"):
        return "non-regular input"
    if case.format == "scene":
        for family in ("manifest field (resealed)", "manifest bytes (not resealed)", "payload bytes",
                       "manifest (resealed)"):
            if text.startswith(family):
                return family
        if text.startswith("payload section"):
            return "payload values (resealed)"
        return "missing, FIFO, directory or symlink: " + ("payload" if text.startswith(("payload", "data/"))
                                                          else "manifest")
    return text.split(":", 1)[0]


def breakdown(cases: list[Case], fmt: str) -> str:
    """Outcomes of one format's cases per mutation family (Markdown)."""
    rows: dict[str, Counter] = {}
    for c in cases:
        if c.format == fmt:
            rows.setdefault(mutation_family(c), Counter())[c.outcome] += 1
    lines = [f"| {fmt} mutation | cases | clean_error | success | bad |", "|---|---:|---:|---:|---:|"]
    for family, c in sorted(rows.items(), key=lambda kv: -sum(kv[1].values())):
        bad = sum(v for k, v in c.items() if k not in GOOD)
        lines.append(f"| {family} | {sum(c.values())} | {c['clean_error']} | {c['success']} | {bad} |")
    return "\n".join(lines)


def run_campaign(cases_per_format: int, seed: int = 1, jobs: int = 2, formats: list[str] | None = None,
                 render: int = 0, workdir: pathlib.Path | None = None, spawn: bool = False, use_real: bool = True,
                 keep: pathlib.Path | None = None, progress: bool = False,
                 only: tuple[str, int] | None = None) -> list[Case]:
    """Run a campaign; the cases with their outcomes (tests call this with a small count and a fixed seed)."""
    with contextlib.ExitStack() as stack:
        if workdir is None:
            workdir = pathlib.Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="splatstream-fuzz-")))
        campaign = Campaign(workdir, seed, jobs, render, spawn, use_real, keep)
        stack.callback(campaign.close)
        return campaign.run(cases_per_format, formats, only, progress)


# --------------------------------------------------------------------------------------------------------------
# The network campaign (issue 37): a hostile HTTP server (tests/hostile_server.py) against `view --headless` and
# the library's fetcher. Each case ends either with the clean picture (compared with a clean run) or with a
# non-zero exit and one line naming the URL and the problem, within the timeout plus 5 s, under 1 GB; the disk
# cache holds only verified payloads afterwards.


@dataclasses.dataclass(frozen=True)
class NetCase:
    name: str
    fault: str | None            # None: the clean server
    target: str = "payload"
    times: int | None = None     # None: permanent
    scene: str = "s"             # which served scene the client asks for
    expect: str = "picture"      # "picture" (the clean one), "picture2" (the re-encoded scene's), "error" or
    #                              "either" (10 s stalls of all 44 payloads may outlast the timeout: then named)


NET_CASES = [
    NetCase("clean", None),
    NetCase("manifest drip 1 B/s", "drip", "manifest", expect="error"),
    NetCase("manifest stall", "stall", "manifest", expect="error"),
    NetCase("manifest reset (permanent)", "reset", "manifest", expect="error"),
    NetCase("manifest reset once", "reset", "manifest", 1),
    NetCase("manifest truncated once", "truncate", "manifest", 1),
    NetCase("manifest 500 permanent", "500", "manifest", expect="error"),
    NetCase("manifest 503 twice", "503", "manifest", 2),
    NetCase("manifest 404", "404", "manifest", expect="error"),
    NetCase("manifest redirect loop", "redirect_loop", "manifest", expect="error"),
    NetCase("manifest gzip", "gzip", "manifest"),
    NetCase("manifest 100 MiB", "huge_manifest", "manifest", expect="error"),
    NetCase("manifest msgpack bomb 64 MiB", "manifest_bomb", "manifest", expect="error"),
    NetCase("manifest nested 200k deep", "nested_manifest", "manifest", expect="error"),
    NetCase("payloads drip 1 B/s", "drip", "root", expect="error"),
    NetCase("payloads stall", "stall", "root", expect="error"),
    NetCase("a payload stalls once", "stall", "root", 1),
    NetCase("every payload stalls once", "stall", "payload", 1, expect="either"),
    NetCase("payloads reset once", "reset", "payload", 1),
    NetCase("payloads reset permanent", "reset", "root", expect="error"),
    NetCase("payloads truncated once", "truncate", "payload", 1),
    NetCase("payloads truncated permanent", "truncate", "root", expect="error"),
    NetCase("payloads wrong body once", "wrong", "payload", 1),
    NetCase("payloads wrong body permanent", "wrong", "root", expect="error"),
    NetCase("payloads gzip", "gzip", "payload"),
    NetCase("payloads 500 once", "500", "payload", 1),
    NetCase("payloads 500 permanent", "500", "root", expect="error"),
    NetCase("payloads 503 twice", "503", "payload", 2),
    NetCase("payloads 404 once", "404", "payload", 1),
    NetCase("payloads 404 permanent", "404", "root", expect="error"),
    NetCase("payloads redirect loop", "redirect_loop", "root", expect="error"),
    NetCase("scene re-encoded mid-stream", "reencode", times=1, expect="picture2"),
    NetCase("payload checksum-valid, undecodable", None, scene="s_bad", expect="error"),
    NetCase("1-splat tile declares 8192x8192", None, scene="s_tex", expect="error"),
]


@dataclasses.dataclass
class NetResult:
    case: str
    client: str        # "view" or "fetcher"
    outcome: str       # "picture", "named_error" or BAD: "wrong_picture", "unnamed_error", "traceback", "late",
    seconds: float     # "hang", "bad_cache", "oom"
    peak_mb: float
    exit: int | None
    message: str


def _net_scenes(workdir: pathlib.Path) -> dict[str, pathlib.Path]:
    sys.path.insert(0, str(ROOT / "tests"))
    from hostile_server import texture_bomb_scene, undecodable_scene

    from splatstream.encode import encode_file

    src = REAL / "fruit_drops_sh3.ply"
    if not src.exists():
        src = FOREIGN / "fruit_drops_sub64.ply"
    root = workdir / "root"
    encode_file(src, root / "s", max_leaf_splats=1000)
    encode_file(src, workdir / "s2", max_leaf_splats=300)  # the re-encoded version (other payloads)
    undecodable_scene(root / "s", root / "s_bad")
    texture_bomb_scene(root / "s", root / "s_tex")
    return {"root": root, "alt": workdir / "s2"}


def _view(url: str, out: pathlib.Path, cache: pathlib.Path, timeout_s: float) -> tuple[int | None, float, float, str]:
    """`view --headless` in a child: (exit status or None when killed, seconds, peak RSS in MB, stderr)."""
    cmd = [sys.executable, "-m", "cli", "view", url, "--headless", "--timeout", f"{timeout_s:g}",
           "--size", "320x240", "--gpu-mem-mb", "64", "--screenshot", str(out)]
    env = child_env({"SPLATSTREAM_CACHE_DIR": str(cache)})
    t0 = time.monotonic()
    peak_kb = 0
    with open(out.with_suffix(".err"), "wb") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, stdin=subprocess.DEVNULL, env=env)
        deadline = t0 + timeout_s + 60
        status = None
        while time.monotonic() < deadline:
            peak_kb = max(peak_kb, _vm_hwm_kb(proc.pid))
            pid, st, _ = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                status = os.waitstatus_to_exitcode(st)
                break
            time.sleep(0.02)
        else:
            proc.kill()
            os.wait4(proc.pid, 0)
        proc.returncode = status if status is not None else -9
    seconds = time.monotonic() - t0
    return status, seconds, peak_kb / 1024, out.with_suffix(".err").read_text(errors="replace")


def _vm_hwm_kb(pid: int) -> int:
    """The process's peak resident memory so far (VmHWM; ru_maxrss of a child would include its parent's peak
    from before the exec)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def _image_psnr(a: pathlib.Path, b: pathlib.Path) -> float:
    import numpy as np
    from PIL import Image

    x = np.asarray(Image.open(a), np.float64)
    y = np.asarray(Image.open(b), np.float64)
    if x.shape != y.shape:
        return 0.0
    mse = float(((x - y) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def cache_is_verified(cache: pathlib.Path) -> str:
    """'' when every payload file in the disk cache hashes to its name, else the first that does not."""
    import hashlib

    for f in (cache / "payloads").rglob("*.bin") if (cache / "payloads").is_dir() else ():
        if not hashlib.sha256(f.read_bytes()).hexdigest().startswith(f.stem) or len(f.stem) not in (32, 64):
            return str(f)
    return ""


def _classify_view(case: NetCase, status, seconds, peak_mb, err, shot, clean, clean2, url, timeout_s,
                   cache) -> tuple[str, str]:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    last = lines[-1] if lines else ""
    if "Traceback" in err or "internal error" in err:
        return "traceback", last
    if status is None:
        return "hang", last
    if peak_mb > 1024:
        return "oom", last
    if cache_is_verified(cache):
        return "bad_cache", cache_is_verified(cache)
    if seconds > timeout_s + 5:
        return "late", last
    if status == 0:
        want = clean2 if case.expect == "picture2" else clean
        psnr = _image_psnr(shot, want) if shot.exists() else 0.0
        return ("picture" if psnr >= 40 else "wrong_picture"), f"{psnr:.1f} dB against the clean run"
    errors = [ln for ln in lines if ln.startswith("splatstream view: error:") or ": not converged after" in ln
              or ln.startswith("view: http")]
    named = errors and url.split("/scenes/")[0] in errors[-1]
    return ("named_error" if named else "unnamed_error"), (errors[-1] if errors else last)


def _fetch_case(server, case: NetCase, timeout_s: float, cache: pathlib.Path) -> NetResult:
    """The library's fetcher: the manifest, then every payload; ends with every payload exact, or with a named
    failure (the manifest's FetchError, or failing() at the timeout)."""
    import resource

    from client_gl.stream.cache import DiskCache
    from client_gl.stream.fetch import Fetcher
    from client_gl.stream.sources import HttpSource
    from splatstream.errors import SplatstreamError

    url = server.url(case.scene)
    t0 = time.monotonic()
    outcome, message = "picture", ""
    f = Fetcher(HttpSource(url), cache=DiskCache(cache), manifest_timeout_s=timeout_s,
                request_deadline_s=max(1.0, timeout_s / 2)).start()
    try:
        try:
            m = f.manifest()
            wanted = {(t.id if t is not None else None, g): p for t, g, p in m.payloads()}
        except SplatstreamError as exc:
            outcome, message = "named_error", str(exc)
        else:
            f.want([(0.0, k, e) for k, e in wanted.items()])
            got = {}
            while len(got) < len(wanted) and time.monotonic() - t0 < timeout_s:
                for key, entry, body in f.done():
                    if wanted.get(key) is entry:
                        got[key] = body
                new = f.take_new_manifest()  # the scene was re-encoded (payloads answered 404): follow it
                if new is not None:
                    wanted = {(t.id if t is not None else None, g): p for t, g, p in new[1].payloads()}
                    got = {}
                    f.want([(0.0, k, e) for k, e in wanted.items()])
                time.sleep(0.01)
            if len(got) < len(wanted):
                failing = f.failing()
                message = failing[0][1] if failing else f"{len(wanted) - len(got)} payloads missing, none failing"
                outcome = "named_error" if failing and url.split("/scenes/")[0] in message else "unnamed_error"
            else:
                outcome = "exact_bytes"
    except Exception as exc:  # noqa: BLE001 - a campaign records every escape
        outcome, message = "traceback", f"{type(exc).__name__}: {exc}"
    finally:
        f.close()
    seconds = time.monotonic() - t0
    if cache_is_verified(cache):
        outcome, message = "bad_cache", cache_is_verified(cache)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # the campaign's process, server included
    return NetResult(case.name, "fetcher", outcome, seconds, peak, None, message)


NET_GOOD = ("picture", "exact_bytes", "named_error")


def run_network_campaign(workdir: pathlib.Path, timeout_s: float = 20.0, cases: list[NetCase] | None = None,
                         clients: tuple[str, ...] = ("view", "fetcher"), progress: bool = False) -> list[NetResult]:
    sys.path.insert(0, str(ROOT / "tests"))
    from hostile_server import HostileServer, Mode

    scenes = _net_scenes(workdir)
    results: list[NetResult] = []
    with HostileServer(scenes["root"]) as server:
        clean = workdir / "clean.png"
        clean2 = workdir / "clean2.png"
        if "view" in clients:
            _view(server.url("s"), clean, workdir / "cache-clean", timeout_s)
            (scenes["root"] / "s2").symlink_to(scenes["alt"])
            _view(server.url("s2"), clean2, workdir / "cache-clean2", timeout_s)
        for i, case in enumerate(cases or NET_CASES):
            expected_ok = {"picture": ("picture", "exact_bytes"), "picture2": ("picture", "exact_bytes"),
                           "error": ("named_error",), "either": NET_GOOD}[case.expect]
            for client in clients:
                mode = None
                if case.fault is not None:
                    mode = Mode(case.fault, case.target, case.times, alt=str(scenes["alt"]))
                server.set_mode(mode)
                cache = workdir / f"cache-{i}-{client}"
                if client == "view":
                    shot = workdir / f"case-{i}.png"
                    url = server.url(case.scene)
                    status, seconds, peak, err = _view(url, shot, cache, timeout_s)
                    outcome, message = _classify_view(case, status, seconds, peak, err, shot, clean, clean2, url,
                                                      timeout_s, cache)
                    r = NetResult(case.name, "view", outcome, seconds, peak, status, message)
                else:
                    r = _fetch_case(server, case, timeout_s, cache)
                if r.outcome in NET_GOOD and r.outcome not in expected_ok and not (
                        client == "fetcher" and case.scene == "s_bad"):  # the fetcher does not decode
                    r.outcome = f"unexpected_{r.outcome}"
                results.append(r)
                if progress:
                    print(f"{client:7} {case.name:40} {r.outcome:14} {r.seconds:6.1f} s {r.peak_mb:7.0f} MB  "
                          f"{r.message[:150]}", flush=True)
    return results


def network_table(results: list[NetResult]) -> str:
    out = ["| mode | client | outcome | time (s) | peak memory (MB) | exit | message |",
           "| --- | --- | --- | ---: | ---: | ---: | --- |"]
    for r in results:
        msg = r.message.replace("|", "\\|")
        if len(msg) > 160:
            msg = msg[:157] + "..."
        out.append(f"| {r.case} | {r.client} | {r.outcome} | {r.seconds:.1f} | {r.peak_mb:.0f} | "
                   f"{'' if r.exit is None else r.exit} | {msg} |")
    return "\n".join(out)


def reader_bombs(workdir: pathlib.Path) -> list[tuple[str, str, float, float]]:
    """Bombs for the SOG, glTF, SPZ and PLY readers, each read by `convert` in a child: (name, outcome, seconds,
    peak MB)."""
    bombs = workdir / "bombs"
    bombs.mkdir(parents=True, exist_ok=True)
    made = []
    # SOG: meta.json inflating to 3.5 GiB (declared), and textures with huge declared sizes
    src = zipfile.ZipFile(FOREIGN / "fruit_drops.sog")
    with zipfile.ZipFile(bombs / "meta_bomb.sog", "w", zipfile.ZIP_DEFLATED) as z:
        for name in src.namelist():
            if name == "meta.json":
                with z.open("meta.json", "w", force_zip64=True) as f:
                    f.write(b"{")
                    zeros = b" " * (1 << 24)
                    for _ in range(224):  # 3.5 GiB
                        f.write(zeros)
                    f.write(b"}")
            else:
                z.writestr(name, src.read(name))
    made.append(bombs / "meta_bomb.sog")
    # glTF: a buffer claiming 4 GiB; SPZ v2 gzip declaring 2^31 splats; PLY declaring 10^9 vertices
    data = (FOREIGN / "fruit_drops_sub64_sh1.glb").read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    doc["buffers"][0]["byteLength"] = 4 << 30
    doc["accessors"][0]["count"] = 1 << 31
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + json_len:]
    (bombs / "bomb.glb").write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    made.append(bombs / "bomb.glb")
    (bombs / "bomb.spz").write_bytes(gzip.compress(struct.pack("<4sIIBBBB", b"NGSP", 2, (1 << 31) - 1, 0, 12, 0, 0)
                                                   + bytes(1 << 24), 9))
    made.append(bombs / "bomb.spz")
    ply = (FOREIGN / "fruit_drops_sub64.ply").read_bytes().replace(b"element vertex 74\n",
                                                                     b"element vertex 1000000000\n", 1)
    (bombs / "bomb.ply").write_bytes(ply)
    made.append(bombs / "bomb.ply")
    out = []
    for path in made:
        t0 = time.monotonic()
        errfile = path.with_suffix(".err")
        with open(errfile, "wb") as errf:
            proc = subprocess.Popen([sys.executable, "-m", "cli", "convert", "-q", str(path),
                                     str(path.with_suffix(".out.ply"))], env=child_env(), stdout=subprocess.DEVNULL,
                                    stderr=errf, stdin=subprocess.DEVNULL)
            peak_kb = 0
            while True:
                peak_kb = max(peak_kb, _vm_hwm_kb(proc.pid))
                pid, st, _ = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                time.sleep(0.01)
        err = errfile.read_text(errors="replace").strip().splitlines()
        code = os.waitstatus_to_exitcode(st)
        ok = code == 2 and err and "Traceback" not in "\n".join(err) and str(path.name) in err[-1]
        out.append((path.name, ("refused: " + err[-1]) if ok else f"BAD exit {code}: {err[-1:]}",
                    time.monotonic() - t0, peak_kb / 1024))
    return out


def main() -> int:
    if "--fork-server" in sys.argv:
        fork_server_main()
        return 0
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", type=int, default=100, help="cases per format (default 100)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--formats", help=f"comma-separated subset of {','.join(FORMATS)}")
    p.add_argument("--render", type=int, default=0, help="run `render` on the first N cases of each format (EGL)")
    p.add_argument("--spawn", action="store_true", help="a new Python per command instead of the fork server")
    p.add_argument("--no-real", action="store_true", help="fixtures only (not ../shared/data/real)")
    p.add_argument("--keep", help="copy the directories of bad cases here (with case.json)")
    p.add_argument("--json", help="write every case's record here")
    p.add_argument("--only", help="FORMAT:INDEX, one case (to reproduce it)")
    p.add_argument("--network", action="store_true", help="the network campaign instead (issue 37): every mode of "
                   "tests/hostile_server.py against `view --headless` and the fetcher, and the reader bombs")
    p.add_argument("--timeout", type=float, default=20.0, help="--network: view's --timeout (default 20)")
    p.add_argument("--clients", default="view,fetcher", help="--network: view, fetcher or both")
    p.add_argument("--cases-matching", help="--network: only the cases whose name contains one of these (a,b,...)")
    args = p.parse_args()
    if args.network:
        return network_main(args)
    formats = args.formats.split(",") if args.formats else None
    only = None
    if args.only:
        fmt, index = args.only.rsplit(":", 1)
        only = (fmt, int(index))
    keep = pathlib.Path(args.keep) if args.keep else None
    if keep:
        keep.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    cases = run_campaign(args.cases, args.seed, args.jobs, formats, args.render, spawn=args.spawn,
                         use_real=not args.no_real, keep=keep, progress=True, only=only)
    seconds = time.monotonic() - t0
    print(table(cases))
    if any(c.format == "scene" for c in cases):
        print()
        print(breakdown(cases, "scene"))
    runs = sum(len(c.runs) for c in cases)
    print(f"\n{len(cases)} cases, {runs} commands, {seconds:.0f} s ({args.jobs} jobs, "
          f"{'spawn' if args.spawn else 'fork server'}, seed {args.seed})")
    warned = [c for c in cases if c.numeric_warnings]
    print(f"cases with numpy RuntimeWarnings on stderr (informational): {len(warned)}")
    for c in warned[:10]:
        print(f"  {c.format}:{c.index}: {c.description} -> {sorted(set(c.numeric_warnings))}")
    bad = [c for c in cases if c.outcome not in GOOD]
    for c in bad[:40]:
        print(f"BAD {c.format}:{c.index} {c.outcome}: {c.description} -> {c.detail}")
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps([case_record(c) for c in cases], indent=1))
    return 1 if bad else 0


def network_main(args) -> int:
    with tempfile.TemporaryDirectory(prefix="splatstream-net-") as tmp:
        work = pathlib.Path(args.keep) if args.keep else pathlib.Path(tmp)
        wanted = args.cases_matching.split(",") if args.cases_matching else None
        cases = [c for c in NET_CASES if wanted is None or any(w in c.name for w in wanted)]
        results = run_network_campaign(work, args.timeout, cases, tuple(args.clients.split(",")), progress=True)
        bombs = reader_bombs(work)
    print(network_table(results))
    print()
    print("| reader bomb | outcome | time (s) | peak memory (MB) |\n| --- | --- | ---: | ---: |")
    for name, outcome, seconds, peak in bombs:
        print(f"| {name} | {outcome.replace('|', '/')} | {seconds:.2f} | {peak:.0f} |")
    bad = [r for r in results if r.outcome not in NET_GOOD] + [b for b in bombs if b[1].startswith("BAD")]
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps([dataclasses.asdict(r) for r in results], indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
