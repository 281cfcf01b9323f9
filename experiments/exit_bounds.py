"""Why the exit analysis certifies nothing: GARA's bounds around the exit, against its data.

GARA's ``exit_analysis`` analyses the pair ``(G_e, G_e)`` (``G_e`` the goal holding the exit)
against a box around the exit. On ``big_u_maze`` it never split (docs/mazes.md). This script
trains a mazes-study method, then, per seed, takes its final shared forward model and its
memory and measures, for pieces of ``G_e`` around the exit (a quarter of ``G_e``, as the
analysis may cut with ``min_volume_ratio=0.25``, and finer: 1/16, 1/64):

- ``data``: the memory's forward-model rows that start in the piece and target ``G_e``: how
  many, the fraction whose end state lies in the exit box (what the low level really did);
- ``model``: the model's point predictions at those rows' starts, the fraction in the exit box
  (what the model learnt);
- ``bounds``: the CROWN-and-IBP bound box of the model over the piece, with ``G_e``'s whole
  velocity range and with the rows' velocity range (``input_range="data"``): its ``x, y``
  widths and ``c1``, the fraction of it inside the exit box (the analysis's verdict needs
  ``c1 >= tau1``). Every point prediction is checked to lie in its bound box (soundness).

Writes ``OUT/exit_bounds.json`` and prints a markdown table.

Usage::

    python -m experiments.exit_bounds --out results/exit_bounds
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

FRACTIONS = (4, 16, 64)  # a piece of 1/f of G_e's x-y area, around the exit
RADII = (0.25, 0.5)  # exit boxes: exit_radius values (half-widths as fractions of G_e's)


def piece_around(goal_lo, goal_hi, point, fraction: int, dims=(0, 1)):
    """The piece of ``goal`` (``1/fraction`` of its area in ``dims``) that holds ``point``,
    on the grid of equal bisections the analysis cuts along.

    Example:
        >>> lo, hi = piece_around(np.array([3., 0, -1, -1]), np.array([6., 3, 1, 1]),
        ...                       np.array([6., 3, 0, 0]), 4)
        >>> lo.tolist(), hi.tolist()
        ([4.5, 1.5, -1.0, -1.0], [6.0, 3.0, 1.0, 1.0])
    """
    cuts = int(round(np.sqrt(fraction)))
    if cuts * cuts != fraction:
        raise ValueError(f"fraction: must be a square (4, 16, ...), got {fraction}")
    lo, hi = np.array(goal_lo, float), np.array(goal_hi, float)
    for d in dims:
        width = (hi[d] - lo[d]) / cuts
        cell = min(int((point[d] - lo[d]) // width), cuts - 1)
        lo[d], hi[d] = lo[d] + cell * width, lo[d] + (cell + 1) * width
    return lo, hi


def _inside(x, lo, hi):
    return np.all((x >= lo) & (x <= hi), axis=-1)


def seed_bounds(layers, memory, goal_lo, goal_hi, exit_state, *, radius, fraction, dims):
    """The three measures above for one seed, one piece and one exit box (a dict)."""
    from gara_jax import boxes, reach
    from gara_jax.algorithms.refinement import exit_box

    p_lo, p_hi = piece_around(goal_lo, goal_hi, exit_state, fraction, dims)
    c_lo, c_hi = exit_box(goal_lo, goal_hi, exit_state, radius, dims)
    size = int(memory["size"])
    start, end = memory["start"][:size], memory["end"][:size]
    rows = (memory["data"][:size] & _inside(start, p_lo, p_hi)
            & np.all(np.isclose(memory["target_lo"][:size], goal_lo), -1)
            & np.all(np.isclose(memory["target_hi"][:size], goal_hi), -1))
    start, end = start[rows], end[rows]
    out = dict(piece_lo=p_lo.tolist(), piece_hi=p_hi.tolist(), exit_lo=c_lo.tolist(),
               exit_hi=c_hi.tolist(), rows=int(rows.sum()))
    goal_in = np.concatenate([goal_lo, goal_hi])
    inputs = {"goal_velocities": (p_lo, p_hi)}
    if len(start):
        out["data_in_exit"] = float(_inside(end, c_lo, c_hi).mean())
        pred = np.asarray(_apply(layers, np.concatenate(
            [start, np.broadcast_to(goal_in, (len(start), goal_in.size))], 1)))
        out["model_in_exit"] = float(_inside(pred, c_lo, c_hi).mean())
        narrow = np.ones(goal_lo.size, bool)
        narrow[list(dims)] = False
        d_lo = np.where(narrow, np.clip(start.min(0), p_lo, p_hi), p_lo)
        d_hi = np.where(narrow, np.clip(start.max(0), p_lo, p_hi), p_hi)
        inputs["data_velocities"] = (d_lo, d_hi)
    for name, (i_lo, i_hi) in inputs.items():
        lo, hi = np.concatenate([i_lo, goal_in]), np.concatenate([i_hi, goal_in])
        lo1, hi1 = reach.ibp(layers, lo, hi)
        lo2, hi2 = reach.crown(layers, lo, hi)
        r_lo, r_hi = (np.asarray(a) for a in boxes.intersect(lo1, hi1, lo2, hi2))
        c1, _ = boxes.coverage(r_lo, r_hi, c_lo, c_hi)
        entry = dict(width_x=float(r_hi[dims[0]] - r_lo[dims[0]]),
                     width_y=float(r_hi[dims[1]] - r_lo[dims[1]]), c1=float(c1))
        if name == "data_velocities" or (name == "goal_velocities" and len(start)):
            # Soundness: the model's prediction at every row start in the input box is inside.
            keep = _inside(start, i_lo, i_hi)
            entry["sound"] = bool(np.all(_inside(pred[keep], r_lo - 1e-5, r_hi + 1e-5)))
        out[name] = entry
    return out


def _apply(layers, x):
    for n, (kernel, bias) in enumerate(layers):
        x = x @ np.asarray(kernel) + np.asarray(bias)
        if n < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def measure(result, *, radii=RADII, fractions=FRACTIONS) -> list:
    """Per seed of ``result`` (a GARA :class:`~gara_jax.train.TrainResult`), the measures of
    :func:`seed_bounds` for every exit box and piece; ``None`` for a seed that never found the
    exit."""
    import jax

    from gara_jax import partition
    from gara_jax.networks import mlp_layers
    from gara_jax.train import fetch, final_partitions

    states = fetch(result.final.states)
    dims = tuple(result.config.split_dims or (0, 1))[:2]
    per_seed = []
    for i, part in enumerate(final_partitions(result)):
        if not bool(np.asarray(states.high.exit_known)[i]):
            per_seed.append(None)
            continue
        exit_state = np.asarray(states.high.exit_state)[i].astype(float)
        lo, hi = (np.asarray(b, float) for b in part.boxes())
        e = int(partition.locate(part, jax.numpy.asarray(exit_state)))
        layers = [(np.asarray(k)[i], np.asarray(b)[i])
                  for k, b in mlp_layers(states.forward.params)]
        memory = {f: np.asarray(getattr(states.memory, f))[i]
                  for f in ("start", "end", "target_lo", "target_hi", "data", "size")}
        per_seed.append(dict(
            exit_state=exit_state.tolist(), goal_lo=lo[e].tolist(), goal_hi=hi[e].tolist(),
            cases=[dict(radius=r, fraction=f, **seed_bounds(
                layers, memory, lo[e], hi[e], exit_state, radius=r, fraction=f, dims=dims))
                for r in radii for f in fractions]))
    return per_seed


def table(per_seed, tau1: float) -> str:
    """Markdown: per exit box and piece, over the seeds that found the exit, the means."""
    found = [s for s in per_seed if s]
    lines = [f"seeds that found the exit: {len(found)} of {len(per_seed)}", "",
             "| exit radius | piece (of G_e) | rows | data in exit box | model in exit box "
             "| bound width x, y (goal velocities) | c1 | bound width x, y (data velocities) "
             f"| c1 | seeds with c1 >= {tau1} |",
             "|---:|---:|---:|---:|---:|---|---:|---|---:|---:|"]
    if not found:
        return "\n".join(lines)

    def mean(cases, *keys, fmt=".2f"):
        vals = list(cases)
        for k in keys:
            vals = [v.get(k) if isinstance(v, dict) else None for v in vals]
        vals = [v for v in vals if v is not None]
        return (f"{np.mean(vals):{fmt}}" if vals else "-"), vals

    for j, case in enumerate(found[0]["cases"]):
        cases = [s["cases"][j] for s in found]
        wg = f"{mean(cases, 'goal_velocities', 'width_x')[0]}, " \
             f"{mean(cases, 'goal_velocities', 'width_y')[0]}"
        wd = f"{mean(cases, 'data_velocities', 'width_x')[0]}, " \
             f"{mean(cases, 'data_velocities', 'width_y')[0]}"
        c1s = [max(c["goal_velocities"]["c1"], c.get("data_velocities", {}).get("c1", 0.0))
               for c in cases]
        lines.append(
            f"| {case['radius']} | 1/{case['fraction']} | {mean(cases, 'rows', fmt='.0f')[0]} | "
            f"{mean(cases, 'data_in_exit')[0]} | {mean(cases, 'model_in_exit')[0]} | {wg} | "
            f"{mean(cases, 'goal_velocities', 'c1')[0]} | {wd} | "
            f"{mean(cases, 'data_velocities', 'c1')[0]} | "
            f"{sum(c >= tau1 for c in c1s)} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from experiments import mazes

    p = argparse.ArgumentParser(prog="python -m experiments.exit_bounds",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--maze", default="big_u_maze", help="a layout (default big_u_maze)")
    p.add_argument("--method", default="gara+exit_analysis",
                   help="a GARA method of experiments.mazes (default gara+exit_analysis)")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--steps", type=int, default=None, help="default: the maze's budget")
    p.add_argument("--out", default="results/exit_bounds")
    args = p.parse_args(argv)
    if args.method not in mazes.ALL_METHODS or not args.method.startswith("gara"):
        p.error(f"--method: {args.method!r} is not a GARA method of experiments.mazes")
    if args.seeds < 1 or (args.steps is not None and args.steps < 1):
        p.error("--seeds and --steps must be >= 1")
    from experiments.u_maze import ENV_STEPS
    from gara_jax.results import write_json
    from gara_jax.train import train_many

    steps = args.steps if args.steps is not None else ENV_STEPS[args.maze]
    config = mazes.method_config(args.method, args.maze)
    t0 = time.perf_counter()
    result = train_many(config, args.seeds, steps)
    per_seed = measure(result)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "exit_bounds.json", dict(
        maze=args.maze, method=args.method, seeds=args.seeds, steps=steps,
        commit=mazes.code_version(), config=json.loads(json.dumps(dataclasses.asdict(config))),
        wall_s=round(time.perf_counter() - t0, 1),
        greedy_end=np.asarray(result.metrics["eval_success"])[:, -1].tolist(),
        per_seed=per_seed))
    text = table(per_seed, config.tau1)
    (out / "exit_bounds.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
