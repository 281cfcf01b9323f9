"""experiments.gara_diagnostics: the left -> right option counts on a hand-made memory."""

from types import SimpleNamespace

import numpy as np
import pytest

from experiments import gara_diagnostics as diag

LEFT_LO, LEFT_HI = [0, 0, -1, -1], [1, 3, 1, 1]
RIGHT_LO, RIGHT_HI = [1, 0, -1, -1], [3, 3, 1, 1]


def _memory(rows, size):
    """One seed's memory: rows of (start, end, target_lo, target_hi, step); capacity 8 + 1."""
    cap = 8
    start, end = np.zeros((1, cap + 1, 4), np.float32), np.zeros((1, cap + 1, 4), np.float32)
    t_lo, t_hi = np.zeros_like(start), np.zeros_like(start)
    step = np.full((1, cap + 1), -1, np.int32)
    for i, (s, e, lo, hi, t) in enumerate(rows):
        start[0, i], end[0, i], t_lo[0, i], t_hi[0, i], step[0, i] = s, e, lo, hi, t
    return SimpleNamespace(start=start, end=end, target_lo=t_lo, target_hi=t_hi, step=step,
                           size=np.array([size]))


def test_left_right_counts_wall_face_past_face_and_hindsight_copies():
    rows = [
        ([0.5, 1, 0, 0], [1.0, 1, 0, 0], RIGHT_LO, RIGHT_HI, 5),   # stopped on the wall face
        ([0.5, 2.5, 0, 0], [1.6, 2.6, 0, 0], RIGHT_LO, RIGHT_HI, 10),  # past the face
        ([0.5, 2.5, 0, 0], [1.6, 2.6, 0, 0], RIGHT_LO, RIGHT_HI, 10),  # its hindsight copy
        ([0.2, 1, 0, 0], [0.4, 1, 0, 0], RIGHT_LO, RIGHT_HI, 15),  # missed
        ([0.2, 1, 0, 0], [0.4, 1, 0, 0], LEFT_LO, LEFT_HI, 20),    # targets the left box
        ([1.5, 2.5, 0, 0], [1.6, 2.5, 0, 0], RIGHT_LO, RIGHT_HI, 25),  # starts on the right
        ([0.5, 1, 0, 0], [1.0, 1, 0, 0], RIGHT_LO, RIGHT_HI, 30),  # beyond `size`: ignored
    ]
    counts = diag.left_right_options(_memory(rows, size=6))
    all_rows = {k: int(v[0]) for k, v in counts["all"].items()}
    original = {k: int(v[0]) for k, v in counts["original"].items()}
    assert all_rows == dict(options=4, reached=3, at_wall=1, near_wall=1, past_face=2)
    assert original == dict(options=3, reached=2, at_wall=1, near_wall=1, past_face=1)
    pooled = diag.pooled(counts)["all"]
    assert pooled["reached_frac"] == pytest.approx(0.75)
    assert pooled["at_wall_frac_of_reached"] == pytest.approx(1 / 3)


@pytest.mark.parametrize("argv", [["--seeds", "0"], ["--steps", "-5"], ["--runs", "nope"],
                                  ["--runs", "gara,gara"]])
def test_bad_arguments_exit_with_usage_error(argv):
    with pytest.raises(SystemExit) as exc:
        diag.parse_args(argv)
    assert exc.value.code == 2
