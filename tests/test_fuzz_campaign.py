"""A short, fixed-seed run of the fuzz and fault campaign (bench/fuzz.py, issue 19): mutated inputs of every format
and corrupted scenes through the CLI under time and memory limits; every case must end in a clean error or a
legitimate success (no traceback, hang, crash, partial output, unreadable output or silent NaN).

About 260 cases (20 per format, a render of the first of each where EGL works), about a minute on 2 cores. The
long run and its counts are in BENCHMARKS.md ("Fuzz and fault campaign").
"""
from __future__ import annotations

import json
import pathlib

from conftest import load_bench

ROOT = pathlib.Path(__file__).resolve().parents[1]


def load_fuzz():
    return load_bench("fuzz")


def report(fuzz, cases) -> str:
    bad = [fuzz.case_record(c) for c in cases if c.outcome not in fuzz.GOOD]
    return fuzz.table(cases) + "\n" + "\n".join(json.dumps(b)[:1500] for b in bad[:10])


def test_short_campaign_has_only_clean_errors_and_successes(tmp_path):
    fuzz = load_fuzz()
    cases = fuzz.run_campaign(20, seed=19, jobs=2, render=1, workdir=tmp_path)
    counts = fuzz.tally(cases)
    assert set(counts) == set(fuzz.FORMATS) and all(sum(c.values()) == 20 for c in counts.values())
    assert all(c.outcome in fuzz.GOOD for c in cases), report(fuzz, cases)
    # The mutations bite: most cases are refused, and every format also has inputs that still read.
    total = sum(counts.values(), start=type(next(iter(counts.values())))())
    assert total["clean_error"] > 0.5 * len(cases) and total["success"] > 0.1 * len(cases), dict(total)


def test_spawned_commands_classify_like_forked_ones(tmp_path):
    """--spawn (a new Python per command, limits in preexec_fn) gives the same outcomes as the fork server."""
    fuzz = load_fuzz()
    kinds = ["ply_binary", "spz_v4", "scene"]
    forked = fuzz.run_campaign(3, seed=5, jobs=1, formats=kinds, workdir=tmp_path / "f")
    spawned = fuzz.run_campaign(3, seed=5, jobs=1, formats=kinds, workdir=tmp_path / "s", spawn=True)
    assert [c.outcome for c in spawned] == [c.outcome for c in forked], report(fuzz, spawned)
    assert [c.description for c in spawned] == [c.description for c in forked]


def test_a_command_past_its_time_is_a_hang_and_is_killed(tmp_path):
    """The harness itself: `serve` never ends, so at its timeout the child is killed and the case is a `hang`;
    a FIFO input is refused at once (the CLI checks before reading)."""
    import os

    fuzz = load_fuzz()
    server = fuzz.ForkServer()
    try:
        import shutil

        shutil.copytree(ROOT / "format_spec" / "vectors" / "medium", tmp_path / "root" / "s")
        run = server.run(["serve", str(tmp_path / "root"), "--port", "0"], str(tmp_path), timeout=3)
        assert run.timed_out and fuzz.classify(run, tmp_path, [])[0] == "hang"
        assert 3 <= run.seconds < 30
        os.mkfifo(tmp_path / "fifo.ply")
        run = server.run(["encode", "-q", str(tmp_path / "fifo.ply"), str(tmp_path / "s")], str(tmp_path), timeout=30)
        assert fuzz.classify(run, tmp_path, [tmp_path / "s"]) [0] == "clean_error", run.stderr
    finally:
        server.close()
