"""Every command shown in the README's sh blocks runs as written, in README order, in one working directory, as a
new user would type them (issue 34). Inputs the README names but does not ship are made small here: `scene.ply`,
`city.ply` and `capture.ply` are the bundled fruit_drops scene (4,721 splats), `broken.ply` is it with a NaN,
`scene.sog` and `lod/` are the SOG fixtures, `../shared/data/real/fruit_drops_sh3.ply` and
`../shared/data/real/statues/st-peter.sog` the bundled copies; the eval's other tools' outputs are `scene.sog` and
the README's own `scene.spz`. Port 8000 (written, or `serve`'s default) becomes a free port. `serve` runs in the
background until its block ends; a `view` that opens a window runs under Xvfb and is closed with Esc once its
window is up. Not run: the install steps (`pip install`, `bash .ci/run`: CI runs them itself) and the line that
needs a running Dask scheduler and an S3 bucket."""
from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, real, xvfb_display

README = ROOT / "README.md"
VENV_BIN = Path(sys.executable).parent
FOREIGN = ROOT / "tests" / "fixtures" / "foreign"
SKIP = [  # (pattern, why): lines not run here
    (re.compile(r"^\.venv/bin/pip install"), "an install step (CI installs the package itself)"),
    (re.compile(r"^bash \.ci/run$"), "CI's own entry point"),
    (re.compile(r"--scheduler tcp://"), "needs a running Dask scheduler and an S3 bucket"),
]


def readme_blocks() -> list[list[str]]:
    """The README's sh blocks, each a list of command lines (continuations joined, comments removed)."""
    blocks, current = [], None
    for line in README.read_text().splitlines():
        if line.startswith("```"):
            if current is not None:
                blocks.append(current)
                current = None
            elif line.strip() == "```sh":
                current = []
            continue
        if current is None:
            continue
        if current and current[-1].endswith("\\"):
            current[-1] = current[-1][:-1].rstrip() + " " + line.strip()
        else:
            current.append(line.strip())
    commands = []
    for block in blocks:
        lines = [re.sub(r"\s+#.*$", "", c).strip() for c in block]
        commands.append([c for c in lines if c])
    return commands


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def display():
    if not shutil.which("Xvfb") or not shutil.which("xdotool"):
        pytest.skip("the README's window commands need Xvfb and xdotool (apt-get install xvfb xdotool)")
    with xvfb_display("2048x1280x24") as name:
        yield name


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """A directory laid out as the README assumes: the clone (samples/, .venv) with ../shared beside it."""
    from splatstream.io import read_gaussians
    from splatstream.ply import write_gaussians_ply

    top = tmp_path_factory.mktemp("readme")
    work = top / "clone"
    work.mkdir()
    (work / "samples").symlink_to(ROOT / "samples")
    (work / ".venv").symlink_to(VENV_BIN.parent)
    fruit = real("fruit_drops_sh3.ply")
    shared = top / "shared" / "data" / "real"
    shared.mkdir(parents=True)
    shutil.copy(fruit, shared / "fruit_drops_sh3.ply")
    (shared / "statues").mkdir()
    shutil.copy(real("statues/st-peter.sog"), shared / "statues" / "st-peter.sog")  # the cleaning example
    for name in ("scene.ply", "city.ply", "capture.ply"):
        shutil.copy(fruit, work / name)
    g = read_gaussians(fruit)
    g.positions[7] = np.nan
    write_gaussians_ply(g, work / "broken.ply")
    shutil.copy(FOREIGN / "fruit_drops.sog", work / "scene.sog")
    shutil.copytree(FOREIGN / "fruit_drops_lod", work / "lod")
    return work


class Block:
    """Runs one block's lines in the working directory; background servers are stopped at the end."""

    def __init__(self, work: Path, display: str | None):
        self.work, self.display = work, display
        self.port = free_port()
        self.servers: list[subprocess.Popen] = []
        self.env = {**os.environ, "PATH": f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}",
                    "SPLATSTREAM_CACHE_DIR": str(work / ".cache")}
        if display:
            self.env["DISPLAY"] = display

    def run(self, line: str) -> None:
        for pattern, _ in SKIP:
            if pattern.search(line):
                return
        line = line.replace("python3 -m venv .venv && .venv/bin/pip install -e '.[bc]' && ", "")
        line = line.replace("127.0.0.1:8000", f"127.0.0.1:{self.port}").replace("--port 8000", f"--port {self.port}")
        if line.startswith("splatstream serve"):
            line = line.rstrip("& ")
            if "--port" not in line:  # its default, 8000, may be taken on a shared machine
                line += f" --port {self.port}"
            self.serve(line)
        elif line.startswith("splatstream view") and "--headless" not in line and "--exit-when-converged" not in line:
            self.window(line)
        else:
            r = subprocess.run(["bash", "-c", line], cwd=self.work, env=self.env, capture_output=True, text=True,
                               timeout=900, stdin=subprocess.DEVNULL)
            assert r.returncode == 0, f"{line}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
            assert "Traceback" not in r.stderr and "internal error" not in r.stderr, f"{line}\n{r.stderr[-2000:]}"

    def serve(self, line: str) -> None:
        proc = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=self.work, env=self.env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
        self.servers.append(proc)
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/healthz", timeout=5):
                    return
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, f"{line}: the server did not start"
                time.sleep(0.2)

    def window(self, line: str) -> None:
        """A viewer window: up, then closed by the user's Esc; it must exit 0 without an error."""
        assert self.display, "a window command needs the display"
        proc = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=self.work, env=self.env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 120
            window = ""
            while not window:
                assert proc.poll() is None, f"{line}: exited early\n{proc.stderr.read()[-2000:]}"
                assert time.monotonic() < deadline, f"{line}: no window"
                window = subprocess.run(["xdotool", "search", "--onlyvisible", "--name", "splatstream"],
                                        env=self.env, capture_output=True, text=True).stdout.split()
                window = window[0] if window else ""
                time.sleep(0.3)
            time.sleep(3.0)  # the scene streams in
            subprocess.run(["xdotool", "windowfocus", "--sync", window], env=self.env, capture_output=True,
                           timeout=20)
            subprocess.run(["xdotool", "key", "--window", window, "Escape"], env=self.env, capture_output=True,
                           timeout=20)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode == 0, f"{line}\n{err[-2000:]}"
        assert "Traceback" not in err and "internal error" not in err, f"{line}\n{err[-2000:]}"

    def close(self) -> None:
        for proc in self.servers:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


BLOCKS = readme_blocks()


def test_the_readme_has_the_blocks_this_test_knows():
    assert len(BLOCKS) >= 10
    assert any("--exit-when-converged" in c for b in BLOCKS for c in b)


@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=[f"block{i + 1}" for i in range(len(BLOCKS))])
def test_readme_block_runs_as_written(index, workdir, request):
    block = BLOCKS[index]
    needs_window = any(c.startswith("splatstream view") and "--headless" not in c for c in block)
    display = request.getfixturevalue("display") if needs_window else None
    runner = Block(workdir, display)
    try:
        for line in block:
            runner.run(line)
    finally:
        runner.close()
