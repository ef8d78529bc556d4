"""bench/encode_bound31.py (issue 31's encode bound): the table's paired ratios and the runner's exit status and
CPU accounting on a trivial command, without encoding (no timing is asserted)."""
from __future__ import annotations

import pathlib
import sys

from conftest import load_bench

ROOT = pathlib.Path(__file__).resolve().parents[1]


def load():
    return load_bench("encode_bound31")


B = load()


def _row(preset, variant, rnd, cpu, rss, ran=None):
    return {"rc": 0, "preset": preset, "ran_preset": ran or preset, "variant": variant, "round": rnd,
            "cpu_s": cpu, "rss_mb": rss, "load": 3.0}


def test_table_ratios_are_paired_by_round_and_mark_the_baseline_preset(capsys):
    rows = [_row("medium", "old", 0, 2.0, 100), _row("medium", "auto", 0, 5.0, 160),
            _row("medium", "old", 1, 4.0, 100), _row("medium", "auto", 1, 6.0, 150),
            _row("medium-12bit", "old", 0, 2.0, 100, ran="medium"), _row("medium-12bit", "auto", 0, 3.0, 120)]
    B.print_table(rows, "old")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| preset | old: CPU s, RSS MB | auto: CPU s, RSS MB | auto / old: CPU, RSS |"
    # round 0 against round 0 (2.50x), round 1 against round 1 (1.50x): not the medians' ratio
    assert lines[2] == "| medium | 2.00 / 4.00 s, 100 / 100 | 5.00 / 6.00 s, 160 / 150 | 2.50x / 1.50x, 1.60x / 1.50x |"
    assert lines[3].startswith("| medium-12bit (old: medium) | 2.00 s, 100 | 3.00 s, 120 | 1.50x, 1.20x |")


def test_run_encode_reports_exit_status_and_cpu_of_the_child():
    ok = B.run_encode([sys.executable, "-c", "sum(range(10000))"], str(ROOT), sample=False)
    assert ok["rc"] == 0 and ok["cpu_s"] > 0 and ok["rss_mb"] > 0
    failed = B.run_encode([sys.executable, "-c", "import sys; sys.stderr.write('no'); sys.exit(3)"], str(ROOT),
                          sample=True)
    assert failed["rc"] == 3 and failed["stderr_tail"] == "no"
    assert failed["cpu_s"] == max(failed["cpu_wait4_s"], failed["cpu_sampled_s"])
