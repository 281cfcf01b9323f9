"""Results of multi-seed runs: confidence intervals, summaries, CSV/JSON files written atomically.

Everything here is host-side NumPy. Metrics arrays are ``[n_seeds, n_epochs]`` as returned by
:func:`gara_jax.train_many`.
"""

from __future__ import annotations

import csv
import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

# Two-sided 95% Student-t quantiles for small seed counts (df = n - 1); normal beyond 30.
_T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
        9: 2.262, 10: 2.228, 11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131, 16: 2.120,
        17: 2.110, 18: 2.101, 19: 2.093, 20: 2.086, 21: 2.080, 22: 2.074, 23: 2.069, 24: 2.064,
        25: 2.060, 26: 2.056, 27: 2.052, 28: 2.048, 29: 2.045, 30: 2.042}

CSV_COLUMNS = ("method", "seed", "env_step", "eval_success", "train_success", "n_goals",
               "episode_return")


def mean_ci95(values, axis: int = 0):
    """Mean and the half-width of its 95% Student-t confidence interval along ``axis``.

    With one sample the half-width is 0 (no spread can be estimated).

    Example:
        >>> m, h = mean_ci95(np.array([0.0, 1.0, 1.0, 0.0]))
        >>> float(m), round(float(h), 3)
        (0.5, 0.919)
    """
    values = np.asarray(values, dtype=np.float64)
    n = values.shape[axis]
    mean = values.mean(axis=axis)
    if n < 2:
        return mean, np.zeros_like(mean)
    sem = values.std(axis=axis, ddof=1) / np.sqrt(n)
    return mean, _T95.get(n - 1, 1.960) * sem


def welch_ci95(a, b) -> dict:
    """``mean(a) - mean(b)`` and the half-width of its 95% Welch interval (unequal variances,
    Welch-Satterthwaite degrees of freedom), for two independent samples such as our seeds
    and another implementation's runs. ``nan`` values are dropped; ``ci95`` and ``df`` are
    ``None`` when either sample has fewer than two values or both have no spread.

    Example:
        >>> d = welch_ci95([0.7, 0.6, 0.8, 0.7], [0.9, 0.5, 0.4])
        >>> round(d["mean"], 3), round(d["ci95"], 2), round(d["df"], 1)
        (0.1, 0.6, 2.3)
    """
    from scipy import stats

    a, b = (np.asarray(v, dtype=np.float64) for v in (a, b))
    a, b = a[~np.isnan(a)], b[~np.isnan(b)]
    if a.size == 0 or b.size == 0:
        raise ValueError(f"welch_ci95: both samples need values (sizes {a.size}, {b.size})")
    out = {"mean": float(a.mean() - b.mean()), "ci95": None, "df": None,
           "n": [int(a.size), int(b.size)]}
    if a.size < 2 or b.size < 2:
        return out
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    if va + vb == 0:
        return out
    df = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
    out.update(ci95=float(stats.t.ppf(0.975, df) * np.sqrt(va + vb)), df=float(df))
    return out


def steps_to(env_steps, success, threshold: float):
    """First env step at which the seed-mean success reaches ``threshold``; ``None`` if never.

    Example:
        >>> steps_to(np.array([[10, 20, 30]]), np.array([[0.2, 0.6, 0.9]]), 0.5)
        20
    """
    mean = np.asarray(success, dtype=np.float64).mean(axis=0)
    hit = np.flatnonzero(mean >= threshold)
    return None if hit.size == 0 else int(np.asarray(env_steps)[0, hit[0]])


# ----------------------------------------------------------------------------------------------
# The paper's metric: success of the training episodes (SPEC.md sections 3.1 and 4)
# ----------------------------------------------------------------------------------------------


def moving_average(values, window: int = 30):
    """Trailing moving average along the last axis: entry ``i`` averages ``values[i-w+1 .. i]``
    (fewer at the start), as a plotted learning curve does.

    Example:
        >>> moving_average(np.array([0.0, 1.0, 1.0, 0.0]), window=2).tolist()
        [0.0, 0.5, 1.0, 0.5]
    """
    values = np.asarray(values, dtype=np.float64)
    if window < 1:
        raise ValueError(f"window: must be >= 1, got {window}")
    csum = np.cumsum(values, axis=-1)
    shifted = np.concatenate([np.zeros(values.shape[:-1] + (window,)), csum], axis=-1)
    n = np.minimum(np.arange(1, values.shape[-1] + 1), window)
    return (csum - shifted[..., : values.shape[-1]]) / n


def episode_success_curve(episodes, n_episodes: int = 400, window: int = 30):
    """The paper's curve by episode index: ``(mean [E], ci95 [E])`` over seeds.

    Each seed's per-episode success (its first ``n_episodes`` training episodes; the
    reference's run is 400 episodes) is smoothed by a ``window``-episode moving average, then
    averaged over seeds with a 95% t-interval. ``E`` is ``n_episodes`` capped at the fewest
    episodes any seed has. ``episodes`` is :attr:`gara_jax.train.TrainResult.episodes`.

    Example:
        >>> eps = {"success": [np.array([0, 1, 1]), np.array([0, 0, 1, 1])]}
        >>> mean, ci = episode_success_curve(eps, n_episodes=400, window=2)
        >>> mean.tolist()
        [0.0, 0.25, 0.75]
    """
    success = episodes["success"]
    n = min([n_episodes] + [len(s) for s in success])
    per_seed = np.stack([moving_average(np.asarray(s[:n], np.float64), window)
                         for s in success])
    return mean_ci95(per_seed, axis=0)


def step_success_curve(episodes, grid, window_steps: int = 9000):
    """Training-episode success against environment steps: ``(mean [T], ci95 [T])`` over seeds.

    At each step ``g`` of ``grid`` a seed's value is the success rate of its episodes that
    ended in ``(g - window_steps, g]`` (``nan`` where none did; such seeds are left out of the
    mean at that point).

    Example:
        >>> eps = {"success": [np.array([0, 1])], "end_step": [np.array([100, 250])]}
        >>> step_success_curve(eps, [100, 300], window_steps=250)[0].tolist()
        [0.0, 0.5]
    """
    grid = np.asarray(grid)
    rows = []
    for success, end in zip(episodes["success"], episodes["end_step"], strict=True):
        inside = (end[None, :] > grid[:, None] - window_steps) & (end[None, :] <= grid[:, None])
        count = inside.sum(axis=1)
        hits = (inside & (np.asarray(success)[None, :] > 0)).sum(axis=1)
        rows.append(np.where(count > 0, hits / np.maximum(count, 1), np.nan))
    rows = np.stack(rows)
    mean = np.full(len(grid), np.nan)
    ci = np.full(len(grid), np.nan)
    for t in range(len(grid)):
        ok = ~np.isnan(rows[:, t])
        if ok.any():
            mean[t], ci[t] = mean_ci95(rows[ok, t])
    return mean, ci


def per_seed_episode_success(episodes, first: int, last: int):
    """Each seed's success rate over its episodes ``first .. last - 1`` (``nan`` if it has
    none there).

    Example:
        >>> per_seed_episode_success({"success": [np.array([0, 1, 1, 1])]}, 1, 3).tolist()
        [1.0]
    """
    return np.array([np.mean(s[first:last]) if len(s) > first else np.nan
                     for s in episodes["success"]], dtype=np.float64)


def per_seed_success_after(episodes, step: int):
    """Each seed's success rate over the training episodes that ended after ``step``
    environment steps (``nan`` if none did).

    Example:
        >>> eps = {"success": [np.array([0, 1, 1])], "end_step": [np.array([10, 20, 30])]}
        >>> per_seed_success_after(eps, 15).tolist()
        [1.0]
    """
    out = []
    for success, end in zip(episodes["success"], episodes["end_step"], strict=True):
        late = np.asarray(end) > step
        out.append(np.mean(np.asarray(success)[late]) if late.any() else np.nan)
    return np.array(out, dtype=np.float64)


def ci_summary(values) -> dict:
    """``{"mean", "ci95", "n"}`` of per-seed values, ignoring ``nan`` (seeds without data).

    Example:
        >>> ci_summary([1.0, 0.0, float("nan")])["n"]
        2
    """
    values = np.asarray(values, dtype=np.float64)
    values = values[~np.isnan(values)]
    if values.size == 0:
        return {"mean": None, "ci95": None, "n": 0}
    mean, half = mean_ci95(values)
    return {"mean": float(mean), "ci95": float(half), "n": int(values.size)}


def summarize(metrics: Mapping[str, np.ndarray], wall_time_s: float) -> dict:
    """The per-method summary written to ``summary.json``.

    ``final_success_mean`` / ``final_success_ci95`` are over seeds of the last epoch's greedy
    evaluation success; ``steps_to_50`` / ``steps_to_80`` use the seed-mean curve.
    """
    success = np.asarray(metrics["eval_success"], dtype=np.float64)
    steps = np.asarray(metrics["env_steps"])
    mean, half = mean_ci95(success[:, -1])
    return {
        "final_success_mean": float(mean),
        "final_success_ci95": float(half),
        "steps_to_50": steps_to(steps, success, 0.5),
        "steps_to_80": steps_to(steps, success, 0.8),
        "wall_time_s": float(wall_time_s),
        "n_seeds": int(success.shape[0]),
        "env_steps": int(steps[0, -1]),
        "final_n_goals_mean": float(np.mean(metrics["n_goals"][:, -1])),
    }


def metrics_rows(method: str, metrics: Mapping[str, np.ndarray], seeds):
    """One CSV row per (seed, epoch), in :data:`CSV_COLUMNS` order."""
    n_seeds, n_epochs = np.asarray(metrics["env_steps"]).shape
    for i in range(n_seeds):
        for e in range(n_epochs):
            yield (method, int(seeds[i]), int(metrics["env_steps"][i, e]),
                   float(metrics["eval_success"][i, e]), float(metrics["train_success"][i, e]),
                   int(metrics["n_goals"][i, e]), float(metrics["episode_return"][i, e]))


EPISODE_CSV_COLUMNS = ("method", "seed", "episode", "end_step", "length", "success")


def episode_rows(method: str, episodes, seeds):
    """One ``episodes.csv`` row per training episode (:data:`EPISODE_CSV_COLUMNS` order;
    episodes numbered from 0 per seed).

    Example:
        >>> eps = {"success": [np.array([0, 1])], "length": [np.array([300, 40])],
        ...        "end_step": [np.array([300, 340])]}
        >>> list(episode_rows("m", eps, [7]))
        [('m', 7, 0, 300, 300, 0), ('m', 7, 1, 340, 40, 1)]
    """
    for i, seed in enumerate(seeds):
        for e, (end, length, success) in enumerate(zip(
                episodes["end_step"][i], episodes["length"][i], episodes["success"][i],
                strict=True)):
            yield (method, int(seed), e, int(end), int(length), int(success))


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: readers see the old
    file or the complete new one, never a half-written one."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode())


def write_csv(path, columns, rows) -> None:
    """Write ``rows`` (tuples in ``columns`` order) with a header line, atomically."""
    import io

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def write_metrics_csv(path, rows) -> None:
    """Write ``rows`` (tuples in :data:`CSV_COLUMNS` order) with a header, atomically."""
    write_csv(path, CSV_COLUMNS, rows)


def write_episodes_csv(path, rows) -> None:
    """Write ``rows`` (tuples in :data:`EPISODE_CSV_COLUMNS` order), atomically."""
    write_csv(path, EPISODE_CSV_COLUMNS, rows)


def read_metrics_csv(path) -> list[dict]:
    """Rows of a ``metrics.csv`` as dicts with typed values."""
    types = {"method": str, "seed": int, "env_step": int, "eval_success": float,
             "train_success": float, "n_goals": int, "episode_return": float}
    with open(path, newline="") as f:
        return [{k: types[k](v) for k, v in row.items()} for row in csv.DictReader(f)]
