"""Figures: success curves with confidence bands, and learned partitions over the maze.

Matplotlib with the Agg backend (no display needed). Host-side only.
"""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

# Velocity ranges narrower than the full [-1, 1] count as a split on that component.
_VEL_FULL = (-1.0, 1.0)


def plot_curve_panels(panels, path, suptitle: str = "") -> None:
    """Side-by-side panels of seed-mean curves with 95% CI bands.

    ``panels`` is a list of ``(title, xlabel, ylabel, curves)``; ``curves`` maps a label to
    ``(x [T], mean [T], ci95 [T])`` (``nan`` points are not drawn). Every panel shares the
    success axis [0, 1] and one legend.

    Example:
        >>> import tempfile, os
        >>> c = {"m": (np.arange(3), np.array([0.0, 0.5, 1.0]), np.full(3, 0.1))}
        >>> plot_curve_panels([("a", "x", "y", c)], os.path.join(tempfile.mkdtemp(), "p.png"))
    """
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 4.2), dpi=130,
                             squeeze=False)
    colors = {}
    for ax, (title, xlabel, ylabel, curves) in zip(axes[0], panels, strict=True):
        for label, (x, mean, ci) in curves.items():
            mean, ci = np.asarray(mean, np.float64), np.asarray(ci, np.float64)
            line, = ax.plot(x, mean, label=label, color=colors.get(label), linewidth=1.6)
            colors[label] = line.get_color()
            ax.fill_between(x, np.clip(mean - ci, 0, 1), np.clip(mean + ci, 0, 1),
                            color=line.get_color(), alpha=0.18, linewidth=0)
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel, ylim=(-0.02, 1.02))
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=9,
               frameon=False)
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path)
    plt.close(fig)


def _velocity_arrow(lo: float, hi: float, eps: float = 1e-6) -> str:
    """Arrow glyph for one velocity component's range: '' when unsplit, '+', '-', or '±'."""
    if lo <= _VEL_FULL[0] + eps and hi >= _VEL_FULL[1] - eps:
        return ""
    if lo >= -eps:
        return "+"
    if hi <= eps:
        return "-"
    return "±"


_GLYPH_X = {"+": "→", "-": "←", "±": "↔", "": ""}
_GLYPH_Y = {"+": "↑", "-": "↓", "±": "↕", "": ""}


def partition_labels(lo, hi, count: int, n: float, char_width: float = 0.028,
                     line_height: float = 0.05) -> list:
    """Where :func:`draw_partition` writes the goal labels: ``[(x, y, lines, fontsize), ...]``,
    one entry per distinct top left corner ``(x, y)`` of the goals' (x, y) rectangles (clipped
    to ``[0, n]^2``).

    Each goal's label is its index and arrows for the velocity components it is split on
    (→ / ← for vx, ↑ / ↓ for vy, ↔ / ↕ when the range straddles 0 without covering [-1, 1]).
    Goals whose rectangles share a top left corner (split only on velocity, or nested) share
    one entry, their labels wrapped into lines that fit the narrowest of those rectangles, so
    that no two labels are written over each other; ``char_width`` and ``line_height`` are a
    character's size at font size 7 in units of ``n`` (one panel of :func:`plot_partitions`),
    and a label too tall for the lowest of them at 7 is set at 5.

    Example:
        >>> lo = np.array([[0.0, 0.0, -1.0, -1.0], [0.0, 0.0, 0.0, -1.0], [1.0, 0.0, -1, -1]])
        >>> hi = np.array([[1.0, 1.0, 0.0, 1.0], [1.0, 1.0, 1.0, 1.0], [2.0, 1.0, 1, 1]])
        >>> partition_labels(lo, hi, 3, n=2.0)
        [(0.0, 1.0, ['0← 1→'], 7), (1.0, 1.0, ['2'], 7)]
    """
    lo, hi = np.asarray(lo)[:count], np.asarray(hi)[:count]
    groups: dict[tuple, dict] = {}  # top left corner -> labels, narrowest width, lowest height
    for g in range(count):
        x0, y0 = max(float(lo[g, 0]), 0.0), max(float(lo[g, 1]), 0.0)
        x1, y1 = min(float(hi[g, 0]), n), min(float(hi[g, 1]), n)
        label = (_GLYPH_X[_velocity_arrow(lo[g, 2], hi[g, 2])]
                 + _GLYPH_Y[_velocity_arrow(lo[g, 3], hi[g, 3])])
        group = groups.setdefault((round(x0, 6), round(y1, 6)),
                                  {"labels": [], "width": x1 - x0, "height": y1 - y0})
        group["labels"].append(f"{g}{label}")
        group["width"] = min(group["width"], x1 - x0)
        group["height"] = min(group["height"], y1 - y0)

    def wrap(labels, width_chars):
        lines = [labels[0]]
        for label in labels[1:]:
            if len(lines[-1]) + 1 + len(label) <= width_chars:
                lines[-1] += " " + label
            else:
                lines.append(label)
        return lines

    out = []
    for (x0, y1), group in groups.items():
        for fontsize in (7, 5):
            scale = n * fontsize / 7
            lines = wrap(group["labels"], max(1, int(0.9 * group["width"] / (char_width * scale))))
            if len(lines) * line_height * scale <= 0.9 * group["height"]:
                break
        out.append((x0, y1, lines, fontsize))
    return out


def draw_partition(ax, lo, hi, count: int, env_params, title: str = "") -> None:
    """Draw ``count`` goal boxes over (x, y) with the maze's walls and exit, each labelled
    with its index and velocity arrows (:func:`partition_labels`: boxes whose (x, y)
    rectangles share a top left corner share one wrapped label).
    """
    lo = np.asarray(lo)[:count]
    hi = np.asarray(hi)[:count]
    n = float(np.asarray(env_params.n))
    ax.add_patch(Rectangle((0, 0), n, n, fill=False, edgecolor="black", linewidth=1.5))
    for x0, x1, y0, y1 in np.asarray(env_params.walls, dtype=np.float64):
        x0, x1, y0, y1 = max(x0, 0), min(x1, n), max(y0, 0), min(y1, n)
        ax.add_patch(Rectangle((x0, y0), max(x1 - x0, 0.03), max(y1 - y0, 0.03),
                               facecolor="dimgray", edgecolor="black", zorder=3))
    ex, ey = np.asarray(env_params.exit, dtype=np.float64)
    w = float(np.asarray(env_params.exit_half_width))
    ax.add_patch(Rectangle((ex - w, ey - w), 2 * w, 2 * w, facecolor="red", alpha=0.6, zorder=2))
    for g in range(count):
        x0, y0 = max(lo[g, 0], 0), max(lo[g, 1], 0)
        x1, y1 = min(hi[g, 0], n), min(hi[g, 1], n)
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor="tab:green", alpha=0.12,
                               edgecolor="darkgreen", linewidth=1.0, zorder=1))
    for x0, y1, lines, fontsize in partition_labels(lo, hi, count, n):
        ax.text(x0 + 0.01 * n, y1 - 0.013 * n, "\n".join(lines), fontsize=fontsize, va="top",
                ha="left", zorder=4, linespacing=1.1)
    ax.set_xlim(-0.05, n + 0.05)
    ax.set_ylim(-0.05, n + 0.05)
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_title(title, fontsize=9)


def plot_partitions(snapshots: Sequence[tuple[int, np.ndarray, np.ndarray, int]], env_params,
                    path, suptitle: str = "") -> None:
    """One panel per ``(step, lo, hi, count)`` snapshot, side by side."""
    k = len(snapshots)
    fig, axes = plt.subplots(1, k, figsize=(3.2 * k, 3.6), dpi=120, squeeze=False)
    for ax, (step, lo, hi, count) in zip(axes[0], snapshots, strict=True):
        draw_partition(ax, lo, hi, int(count), env_params,
                       title=f"at {int(step):,} steps ({int(count)} goals)")
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
