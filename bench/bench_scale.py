"""Scaling of the encoder: wall time and peak memory of the whole process tree (client, scheduler, workers)
for scenes of growing size, in this process and on a local Dask cluster (issue 16).

    python bench/bench_scale.py --splats 1000000,6000000,30000000 --workers 2 --single 6000000 --json out.json
    python bench/bench_scale.py --splats 60000000 --workers 1,4,8,16 --json out.json      (a many-core machine)

Scenes: /work/shared/tools/make_scene.py (--seed 0) where it exists, else a built-in synthetic scene (numpy only:
clustered objects on a ground grid, SH degree 3, the same PLY layout), written once per size under --scenes and
removed after unless --keep. Memory is the sum of the proportional set sizes (PSS, shared pages split between
the processes that map them) of the encode process and all its descendants, sampled every 0.2 s; also the
largest single process. Phases: the encoder's progress lines (stderr, one per stage and 25 % step) give the
time at which each stage started (the engine reports 0 % when it submits a stage's tasks): "start" is up to the
first (imports, the local cluster's start), each stage runs until the next one starts, the last until the process
ends (the manifest). Needs only numpy and, for --workers, dask/distributed (and what splatstream needs).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import re
import shutil
import subprocess
import sys
import threading
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
MAKE_SCENE = pathlib.Path("/work/shared/tools/make_scene.py")


# ---------------------------------------------------------------------------------------------- scenes


def synthetic_scene(path: pathlib.Path, splats: int, seed: int = 0, chunk: int = 1 << 20) -> None:
    """A city-like scene in the standard 3DGS PLY layout: objects (anisotropic blobs of splats with a colour and
    SH) scattered over a ground grid, written chunk by chunk (memory stays small at any size)."""
    rng = np.random.default_rng(seed)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {splats}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    objects = max(1, splats // 20000)
    side = max(1.0, np.sqrt(objects)) * 4.0
    centres = np.column_stack([rng.uniform(0, side, objects), rng.uniform(0, side, objects),
                               rng.uniform(0, 2.0, objects)]).astype(np.float32)
    spread = rng.uniform(0.3, 1.5, (objects, 3)).astype(np.float32)
    colour = rng.normal(0, 1.0, (objects, 3)).astype(np.float32)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        for start in range(0, splats, chunk):
            n = min(chunk, splats - start)
            obj = rng.integers(0, objects, n)
            rec = np.zeros((n, len(names)), np.float32)
            rec[:, 0:3] = centres[obj] + rng.normal(0, 1, (n, 3)).astype(np.float32) * spread[obj]
            rec[:, 6:9] = colour[obj] + rng.normal(0, 0.3, (n, 3))
            rec[:, 9:54] = rng.normal(0, 0.05, (n, 45))
            rec[:, 54] = rng.normal(1.0, 2.0, n)
            rec[:, 55:58] = rng.normal(-4.0, 0.7, (n, 3))
            q = rng.normal(size=(n, 4))
            rec[:, 58:62] = q / np.linalg.norm(q, axis=1, keepdims=True)
            rec.tofile(f)
    os.replace(tmp, path)


def stream_make_scene(path: pathlib.Path, splats: int, seed: int = 0) -> None:
    """The bytes of `make_scene.py --splats N --seed S --sh-degree 3` (its loop, the same random draws), written
    object by object: make_scene.py concatenates the whole scene three times over and runs out of memory on this
    24 GB machine at 30M splats."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_scene", MAKE_SCENE)
    ms = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ms)
    rng = np.random.default_rng(seed)
    real = ms.REAL
    sources = [ms.as_arrays(ms.read_ply(real / n)) for n in
               ("fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply", "donut_sh0_no_normals.ply")]
    sources.append(ms.as_arrays(ms.read_splat(real / "winter_fountain.splat")))
    sh_bank = sources[0][2]
    n_rest = 45
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)] + \
            [f"f_rest_{i}" for i in range(n_rest)] + ["opacity"] + [f"scale_{i}" for i in range(3)] + \
            [f"rot_{i}" for i in range(4)]
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {splats}\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    side = max(1.0, np.sqrt(splats / 30000.0)) * 4.0 * 1.0
    total = 0
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        while total < splats:
            pos, dc, rest, op, scale, rot = sources[rng.integers(len(sources))]
            centre = pos.mean(0)
            size = np.percentile(np.linalg.norm(pos - centre, axis=1), 95) + 1e-9
            target = rng.uniform(0.5, 2.5)
            k = target / size
            ang = rng.uniform(0, 2 * np.pi)
            c, s = np.cos(ang / 2), np.sin(ang / 2)
            qz = np.array([[c, 0.0, 0.0, s]], np.float32)
            rz = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]], np.float32)
            off = np.array([rng.uniform(-side, side), rng.uniform(-side, side), target], np.float32)
            p = (pos - centre) * k @ rz.T + off
            r = ms.quat_mul(np.repeat(qz, len(rot), 0), rot / np.linalg.norm(rot, axis=1, keepdims=True))
            real_rest = rest if rest.shape[1] == 45 and np.abs(rest).max() > 0 else \
                sh_bank[rng.integers(len(sh_bank), size=len(pos))]
            sh = real_rest.reshape(-1, 3, 15)[:, :, :15].reshape(len(pos), n_rest)
            take = min(len(pos), splats - total)
            rows = np.concatenate([p, np.zeros_like(p), dc, sh, op, scale + np.log(k), r], 1)[:take]
            f.write(rows.astype("<f4").tobytes())
            total += len(pos)
    os.replace(tmp, path)


def make_scene(splats: int, directory: pathlib.Path, generator: str) -> pathlib.Path:
    path = directory / f"scene_{splats}.ply"
    if path.exists():
        return path
    if generator == "make_scene" or (generator == "auto" and MAKE_SCENE.exists()):
        stream_make_scene(path, splats)
    else:
        synthetic_scene(path, splats)
    return path


# ---------------------------------------------------------------------------------------------- memory


def _children_map() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        kids.setdefault(ppid, []).append(int(entry))
    return kids


def _pss(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class TreeMemory(threading.Thread):
    """Samples the summed PSS of a process and its descendants; keeps the peak (and the largest process)."""

    def __init__(self, pid: int, interval: float = 0.2):
        super().__init__(daemon=True)
        self.pid, self.interval = pid, interval
        self.peak = self.peak_one = self.peak_procs = 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            kids = _children_map()
            tree, todo = [], [self.pid]
            while todo:
                p = todo.pop()
                tree.append(p)
                todo += kids.get(p, [])
            sizes = [_pss(p) for p in tree]
            self.peak = max(self.peak, sum(sizes))
            self.peak_one = max(self.peak_one, max(sizes))
            self.peak_procs = max(self.peak_procs, len(tree))
            self.stop.wait(self.interval)


PROGRESS_LINE = re.compile(r"^encode: (\S+) \d+% \(([\d.]+)s\)$")
DONE_LINE = re.compile(r"^wrote .*, ([\d.]+)s$")


def phases(stderr: str, wall: float) -> dict[str, float]:
    """Seconds per stage from the encoder's progress lines (a stage seen again later adds to its first entry).
    The lines count from the encode's start; the imports before it go to "start"."""
    lines = stderr.splitlines()
    marks = [(m[1], float(m[2])) for m in map(PROGRESS_LINE.match, lines) if m]
    done = [float(m[1]) for m in map(DONE_LINE.match, lines) if m]
    end = done[-1] if done else wall
    out: dict[str, float] = {"start": wall - end}
    previous, since = "start", 0.0
    for stage, t in marks:
        if stage != previous:
            out[previous] = out.get(previous, 0.0) + t - since
            previous, since = stage, t
    out[previous] = out.get(previous, 0.0) + max(0.0, end - since)
    return {k: round(v, 1) for k, v in out.items()}


def run_encode(scene: pathlib.Path, out: pathlib.Path, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "cli", "encode", str(scene), str(out), *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    mem = TreeMemory(proc.pid)
    mem.start()
    _, err = proc.communicate()
    wall = time.perf_counter() - t0
    mem.stop.set()
    mem.join()
    if proc.returncode:
        raise SystemExit(f"encode failed ({' '.join(cmd)}):\n{err}")
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    return {"wall_s": round(wall, 2), "peak_tree_mb": round(mem.peak / 2**20), "peak_process_mb":
            round(mem.peak_one / 2**20), "processes": mem.peak_procs, "output_mb": round(size / 1e6, 1),
            "phases_s": phases(err, wall)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", default="1000000,6000000,30000000", help="comma-separated scene sizes")
    ap.add_argument("--workers", default="2", help="comma-separated local Dask cluster sizes")
    ap.add_argument("--single", default="", help="sizes also encoded by the single-process encoder (comma-separated)")
    ap.add_argument("--memory-per-worker", default="1GB", help="partition size budget of each worker")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--lod-merge", default="", help="comma-separated LOD merges to run each engine with (e.g. "
                    "auto,grid); empty: the encoder's default only")
    ap.add_argument("--scenes", default="/tmp/bench_scale", help="where scenes and outputs are written")
    ap.add_argument("--generator", choices=["auto", "make_scene", "synthetic"], default="auto")
    ap.add_argument("--keep", action="store_true", help="keep the scenes")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args()
    directory = pathlib.Path(a.scenes)
    directory.mkdir(parents=True, exist_ok=True)
    sizes = [int(float(s)) for s in a.splats.split(",") if s]
    workers = [int(w) for w in a.workers.split(",") if w]
    single = {int(float(s)) for s in a.single.split(",") if s}
    results = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "host": platform.node()},
               "preset": a.preset, "memory_per_worker": a.memory_per_worker, "runs": []}
    for n in sizes:
        t = time.perf_counter()
        scene = make_scene(n, directory, a.generator)
        input_mb = scene.stat().st_size / 2**20
        print(f"{n} splats: scene {input_mb:.0f} MiB ({time.perf_counter() - t:.0f}s)", flush=True)
        runs = [("single", [])] if n in single else []
        runs += [(f"dask-{w}", ["--workers", str(w), "--memory-per-worker", a.memory_per_worker]) for w in workers]
        merges = [m for m in a.lod_merge.split(",") if m]
        if merges:
            runs = [(f"{name}-{m}", [*extra, "--lod-merge", m]) for name, extra in runs for m in merges]
        for name, extra in runs:
            out = directory / f"out_{n}_{name}"
            load = os.getloadavg()[0]
            r = run_encode(scene, out, ["--preset", a.preset, *extra])
            r["load_before"], r["load_after"] = round(load, 1), round(os.getloadavg()[0], 1)
            shutil.rmtree(out, ignore_errors=True)
            r.update({"splats": n, "engine": name, "input_mb": round(input_mb),
                      "us_per_splat": round(r["wall_s"] / n * 1e6, 3)})
            results["runs"].append(r)
            print(json.dumps(r), flush=True)
            if a.json:
                pathlib.Path(a.json).write_text(json.dumps(results, indent=1))
        if not a.keep:
            scene.unlink()


if __name__ == "__main__":
    main()
