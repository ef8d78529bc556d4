"""bench/probe_error_steps.py (issue 31, gerr17): the u8 codings of the geometric error it streams with decode to the
values named in its doc, never below the true error, top-down against the parent's decoded value; the root keeps its
error and a leaf's 0 stays 0."""
from __future__ import annotations

from conftest import load_bench

P = load_bench("probe_error_steps")

# root 0 (error 1.0) -> 1 (0.5) -> 2 (0.3) -> 3 (leaf, 0); root -> 4 (1.0, its parent's error)
PARENT = {1: 0, 2: 1, 3: 2, 4: 0}
ERROR = {0: 1.0, 1: 0.5, 2: 0.3, 3: 0.0, 4: 1.0}


def test_lin255_steps_of_the_decoded_parent():
    codes: dict = {}
    e = P.stepped_errors([3, 2, 1, 0, 4], PARENT, ERROR, "lin255", codes)
    assert codes == {1: 128, 2: 153, 3: 0, 4: 255}
    assert e[0] == 1.0 and e[4] == 1.0 and e[3] == 0.0
    assert e[1] == 128 / 255  # 0.50196: ceil(0.5 * 255) = 128
    assert e[2] == (128 / 255) * 153 / 255  # against the parent's decoded 0.50196, not its 0.5: 0.30118
    assert all(e[t] >= ERROR[t] for t in ERROR)


def test_log16_largest_step_still_above():
    codes: dict = {}
    e = P.stepped_errors([0, 1, 2, 3, 4], PARENT, ERROR, "log16", codes)
    assert codes == {1: 16, 2: 11, 3: 255, 4: 0}  # 2^(-16/16) = 0.5 exactly; 0.5 * 2^(-11/16) = 0.3098 >= 0.3
    assert e[1] == 0.5 and abs(e[2] - 0.5 * 2 ** (-11 / 16)) < 1e-15 and e[3] == 0.0 and e[4] == 1.0
    assert 0.5 * 2 ** (-12 / 16) < 0.3  # one step more would fall below the true error


def test_f32_is_the_identity():
    assert P.stepped_errors(list(ERROR), PARENT, ERROR, "f32") == ERROR
