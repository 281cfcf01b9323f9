"""Partition figure labels: every goal labelled once, stacked goals wrapped to their box."""

import numpy as np

from envs.maze import make_params
from gara_jax import plots


def _stacked_partition():
    # Three (x, y) boxes; the lower right one split into 8 velocity pieces (goals 2..9).
    lo = [[0, 0, -1, -1], [1, 0, -1, -1]]
    hi = [[1, 1, 1, 1], [2, 1, 1, 1]]
    for vx in ((-1, 0), (0, 1)):
        for vy in ((-1, -0.5), (-0.5, 0), (0, 0.5), (0.5, 1)):
            lo.append([2, 0, vx[0], vy[0]])
            hi.append([3, 1, vx[1], vy[1]])
    return np.asarray(lo, float), np.asarray(hi, float)


def test_goals_sharing_a_rectangle_share_one_wrapped_label():
    lo, hi = _stacked_partition()
    n = 3.0
    entries = plots.partition_labels(lo, hi, len(lo), n)
    assert [(x, y) for x, y, _, _ in entries] == [(0.0, 1.0), (1.0, 1.0), (2.0, 1.0)]
    words = [w for _, _, lines, _ in entries for line in lines for w in line.split()]
    assert sorted(int(w.rstrip("←→↑↓↔↕")) for w in words) == list(range(len(lo)))
    x, y, lines, fontsize = entries[2]
    assert len(lines) > 1  # eight labels do not fit on one line of a unit-wide box
    width_chars = int(0.9 * 1.0 / (0.028 * n * fontsize / 7))
    assert all(len(line) <= width_chars for line in lines)
    assert "2←↓" in lines[0] and "9→↑" in lines[-1]


def test_nested_rectangles_with_one_top_left_corner_share_a_label():
    lo = np.array([[0.0, 1.5, -1, -1], [0.0, 2.0, -1, -1], [0.0, 0.0, -1, -1]])
    hi = np.array([[1.0, 3.0, 1, 1], [1.0, 3.0, 0, 1], [1.0, 1.5, 1, 1]])
    entries = plots.partition_labels(lo, hi, 3, n=3.0)
    assert [(x, y, lines) for x, y, lines, _ in entries] == [(0.0, 3.0, ["0 1←"]),
                                                             (0.0, 1.5, ["2"])]


def test_draw_partition_writes_one_text_per_corner(tmp_path):
    import matplotlib.pyplot as plt

    lo, hi = _stacked_partition()
    fig, ax = plt.subplots()
    plots.draw_partition(ax, lo, hi, len(lo), make_params())
    assert len(ax.texts) == 3
    plt.close(fig)
