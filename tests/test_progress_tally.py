"""progress.Tally: the share of a known total done, as the RAD and streamed SOG exporters report it."""
from __future__ import annotations

from splatstream.progress import Tally


def test_a_tally_reports_zero_then_the_share_done_never_above_one():
    heard: list[float] = []
    t = Tally(heard.append, 10)
    for units in (3, 3, 3, 3):  # past the total: held at 1
        t.add(units)
    assert heard == [0.0, 0.3, 0.6, 0.9, 1.0]
    t.finish()
    assert heard[-1] == 1.0


def test_an_empty_total_and_no_listener():
    heard: list[float] = []
    t = Tally(heard.append, 0)  # an empty tree: nothing to divide by
    t.finish()
    assert heard == [0.0, 1.0]
    Tally(None, 5).add(5)  # no listener: nothing heard, nothing raised
