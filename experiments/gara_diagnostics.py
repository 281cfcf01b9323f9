"""Why GARA fails on the U-maze: refinement statistics, early option outcomes and two controls.

Runs, all seeds of a run vmapped in one process through :func:`gara_jax.train_many`:

- ``gara``: ``GaraConfig()`` (SPEC.md's refinement trigger), optionally ``--refine-method
  ibp`` and ``--planning``. The host step's ``info`` of every epoch (triggered, stable,
  analysed, splits, reaches, no_reach, capacity_skips and the fit/refine/host times) is
  collected through the ``callback`` and summed.
- ``no_refine_handcrafted``: the same GARA code path with the refinement off
  (``min_steps=10**9``) started from SPEC.md's 6-box handcrafted partition. ``GaraConfig`` has
  no field choosing the initial partition, so the partition of a fresh :class:`LoopState` is
  replaced before training and the state passed as ``init_state``.
- ``no_refine_2box``: refinement off from GARA's 2-box initial partition.

After every epoch the high-level memory (states, target bounds) is read to measure the
*left -> right options*: stored options that started in goal 0 of the initial partition
(``[0,1] x [0,3]``, first-box rule), targeted a box inside goal 1 (``[1,3] x [0,3]``; before
any split exactly goal 1), the fraction of them that ended inside goal 1's closed box, and among
those the fraction that ended with ``x == 1.0`` exactly (stopped on the wall face, which the
closed box contains), and the fraction that ended past the face (``x > 1``, so the end state
belongs to goal 1 under the first-box rule). Counted over every stored row (what the forward
model is fitted on) and over original options only (without the hindsight copies, which are
stored towards the goal the option ended in). Reported at the first epoch whose host step
triggered an analysis (pooled over seeds) and at the end; every epoch's counts are in the JSON.

Writes ``OUT/gara_diagnostics.json`` (every number, the configs, seeds, steps and wall times)
and prints a markdown summary.

Usage::

    python -m experiments.gara_diagnostics --seeds 20 --steps 120000 --out results/diag
    python -m experiments.gara_diagnostics --seeds 2 --steps 12000 --out results/diag_smoke \\
        --refine-method ibp --planning --runs gara,no_refine_2box
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

RUNS = ("gara", "no_refine_handcrafted", "no_refine_2box")
NO_REFINEMENT = 10**9  # min_steps no pair ever reaches: the trigger never fires
HOST_COUNTS = ("triggered", "stable", "analysed", "splits", "reaches", "no_reach",
               "capacity_skips")
HOST_TIMES = ("fit_s", "refine_s", "host_s")
OPTION_KEYS = ("options", "reached", "at_wall", "near_wall", "past_face")
WALL_X = 1.0
NEAR_WALL_TOL = 1e-5  # float32 wall stops may land a rounding error off the face


def run_config(name: str, planning: bool, refine_method: str, goal_membership: str = "box"):
    """The ``GaraConfig`` of a run (the controls only switch the trigger off).

    The option counts below read a memory of whole options, so the runs keep
    ``memory="options"`` (the memory of the defaults before SPEC.md revision 2); for today's
    defaults and the reference see ``experiments.gara_ablation``.
    """
    from gara_jax import GaraConfig

    min_steps = GaraConfig().min_steps if name == "gara" else NO_REFINEMENT
    return GaraConfig(planning=planning, refine_method=refine_method, min_steps=min_steps,
                      goal_membership=goal_membership, memory="options")


def initial_loop(name: str, config, seeds):
    """Fresh per-seed states; the handcrafted control gets SPEC.md's 6 boxes instead of 2."""
    import jax
    import jax.numpy as jnp

    from gara_jax import partition as part
    from gara_jax.train import init_loop

    loop = init_loop(config, seeds)
    if name != "no_refine_handcrafted":
        return loop
    # Nothing in the initial state but the partition depends on it (Q-table, planner graph and
    # memory are sized by max_goals), so swapping it gives the GARA agent on those goals.
    boxes = part.handcrafted(max_goals=config.max_goals)
    batched = jax.tree.map(lambda a: jnp.repeat(a[None], len(loop.seeds), axis=0), boxes)
    return loop._replace(states=loop.states.replace(partition=batched))


def left_right_options(memory) -> dict:
    """Per-seed counts of the left -> right options held in a (host-side) ``HighMemory``.

    Returns ``{"all": {key: [S]}, "original": {key: [S]}}`` with keys ``options`` (started in
    goal 0, target inside goal 1), ``reached`` (ended in goal 1's closed box), ``at_wall``
    (reached with ``x == 1.0`` exactly), ``near_wall`` (reached with ``|x - 1| <= 1e-5``) and
    ``past_face`` (reached with ``x > 1``: the end state *belongs* to goal 1, first-box rule).
    """
    from gara_jax import partition as part

    lo, hi = (np.asarray(b, np.float32) for b in part.gara_initial().boxes())
    start, end = np.asarray(memory.start), np.asarray(memory.end)
    t_lo, t_hi = np.asarray(memory.target_lo), np.asarray(memory.target_hi)
    step, size = np.asarray(memory.step), np.asarray(memory.size)
    cap = step.shape[-1] - 1  # the last row is scratch
    valid = np.arange(cap + 1)[None, :] < size[:, None]
    inside = lambda s, g: np.all((s >= lo[g]) & (s <= hi[g]), axis=-1)
    started_left = inside(start, 0)  # goal 0 comes first: x == 1 belongs to it
    targets_right = np.all((t_lo >= lo[1]) & (t_hi <= hi[1]), axis=-1)
    options = valid & started_left & targets_right
    reached = options & inside(end, 1)
    at_wall = reached & (end[..., 0] == WALL_X)
    near_wall = reached & (np.abs(end[..., 0] - WALL_X) <= NEAR_WALL_TOL)
    past_face = reached & (end[..., 0] > WALL_X)
    # A hindsight copy is pushed right after its option in the same env step; options of one
    # seed end at distinct steps. (Once the ring wraps, the oldest row's copy may be missed.)
    prev = np.concatenate([step[:, cap - 1:cap], step[:, : cap - 1], step[:, cap:]], axis=1)
    original = ~(valid & (step == prev))
    masks = dict(options=options, reached=reached, at_wall=at_wall, near_wall=near_wall,
                 past_face=past_face)
    return {"all": {k: m.sum(axis=1) for k, m in masks.items()},
            "original": {k: (m & original).sum(axis=1) for k, m in masks.items()}}


def pooled(counts: dict) -> dict:
    """Counts summed over seeds, with the two fractions the README quotes."""
    out = {}
    for kind, per_seed in counts.items():
        c = {k: int(np.sum(per_seed[k])) for k in OPTION_KEYS}
        c["reached_frac"] = c["reached"] / c["options"] if c["options"] else None
        c["past_face_frac"] = c["past_face"] / c["options"] if c["options"] else None
        c["at_wall_frac_of_reached"] = c["at_wall"] / c["reached"] if c["reached"] else None
        c["near_wall_frac_of_reached"] = c["near_wall"] / c["reached"] if c["reached"] else None
        out[kind] = c
    return out


def per_seed(counts: dict) -> dict:
    return {kind: {k: np.asarray(v).tolist() for k, v in c.items()} for kind, c in counts.items()}


def run_one(name: str, config, seeds: int, steps: int) -> dict:
    """Train one run, collecting host-step info and left -> right option statistics per epoch."""
    import jax

    from gara_jax import results, train_many

    epochs, snaps, diag_s = [], {}, [0.0]

    def callback(out):
        t0 = time.perf_counter()
        info = out.host_info or {}
        counts = left_right_options(jax.device_get(out.loop.states.memory))
        epochs.append({
            "epoch": out.epoch, "env_steps": int(out.metrics["env_steps"][0]),
            "eval_success_mean": float(np.mean(out.metrics["eval_success"])),
            "n_goals_mean": float(np.mean(out.metrics["n_goals"])),
            "epoch_s": out.epoch_s,
            **{k: int(info.get(k, 0)) for k in HOST_COUNTS},
            **{k: float(info.get(k, 0.0)) for k in HOST_TIMES},
            "left_right": pooled(counts)})
        if info.get("triggered", 0) and "first_trigger" not in snaps:
            snaps["first_trigger"] = dict(epoch=out.epoch, per_seed=per_seed(counts),
                                          **pooled(counts))
        snaps["final"] = dict(epoch=out.epoch, per_seed=per_seed(counts), **pooled(counts))
        diag_s[0] += time.perf_counter() - t0

    loop = initial_loop(name, config, seeds)
    res = train_many(config, list(loop.seeds), steps, callback=callback, init_state=loop)
    part = jax.device_get(res.final.states.partition)
    totals = {k: sum(e[k] for e in epochs) for k in HOST_COUNTS + HOST_TIMES}
    return {
        "config": dataclasses.asdict(config), "seeds": res.seeds, "steps": steps,
        "summary": results.summarize(res.metrics, res.wall_time_s),
        "final_eval_success": res.metrics["eval_success"][:, -1].tolist(),
        "final_n_goals": res.metrics["n_goals"][:, -1].tolist(),
        "wall_time_s": res.wall_time_s, "first_epoch_s": res.first_epoch_s,
        "host_time_s": res.host_time_s, "diagnostics_s": diag_s[0],
        "host_totals": totals,
        "left_right_first_trigger": snaps.get("first_trigger"),
        "left_right_final": snaps["final"],
        "final_partitions": [
            {"lo": part.lo[i][: part.count[i]].tolist(), "hi": part.hi[i][: part.count[i]].tolist()}
            for i in range(len(res.seeds))],
        "epochs": epochs,
    }


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def markdown(records: dict) -> str:
    """Two tables: outcome and refinement verdicts per run; left -> right options."""
    lines = ["| run | final greedy success (95% CI) | goals at end | analyses | no reaching part"
             " | split | whole box reaches | capacity skips | wall (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in records.items():
        s, t = r["summary"], r["host_totals"]
        lines.append(f"| {name} | {s['final_success_mean']:.2f} ± {s['final_success_ci95']:.2f}"
                     f" | {s['final_n_goals_mean']:.2f} | {t['analysed']} | {t['no_reach']}"
                     f" | {t['splits']} | {t['reaches']} | {t['capacity_skips']}"
                     f" | {r['wall_time_s']:.0f} |")
    lines += ["", "Left -> right options in the high-level memory (start in [0,1]x[0,3], target "
              "inside [1,3]x[0,3]); all stored rows / originals without hindsight copies:", "",
              "| run | when (epoch) | options | ended in right box (closed) | of those at x = 1"
              " | ended past the face (x > 1) |",
              "|---|---|---:|---:|---:|---:|"]
    for name, r in records.items():
        for when in ("first_trigger", "final"):
            snap = r[f"left_right_{when}"]
            if snap is None:
                continue
            a, o = snap["all"], snap["original"]
            lines.append(
                f"| {name} | {when} ({snap['epoch']}) | {a['options']} / {o['options']}"
                f" | {_pct(a['reached_frac'])} / {_pct(o['reached_frac'])}"
                f" | {_pct(a['at_wall_frac_of_reached'])} / {_pct(o['at_wall_frac_of_reached'])}"
                f" | {_pct(a['past_face_frac'])} / {_pct(o['past_face_frac'])} |")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m experiments.gara_diagnostics",
                                description=__doc__.split("\n", 1)[0])
    p.add_argument("--seeds", type=int, default=20, help="seeds per run (0..n-1)")
    p.add_argument("--steps", type=int, default=120_000, help="environment steps per seed")
    p.add_argument("--out", default="results/gara_diagnostics", help="output directory")
    p.add_argument("--refine-method", choices=("crown", "ibp", "zonotope", "zonotope_box"),
                   default="crown")
    p.add_argument("--planning", action="store_true", help="planner high level in every run")
    p.add_argument("--goal-membership", choices=("box", "partition"), default="box",
                   help="when the low level counts as inside its target (see HandcraftedConfig)")
    p.add_argument("--runs", default=",".join(RUNS), help=f"subset of {','.join(RUNS)}")
    from gara_jax import compile_cache

    compile_cache.add_argument(p)
    args = p.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    args.runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    if not args.runs or set(args.runs) - set(RUNS) or len(set(args.runs)) != len(args.runs):
        p.error(f"--runs: choose distinct names from {', '.join(RUNS)}, got {args.runs}")
    if args.seeds < 1 or args.steps < 1:
        p.error("--seeds and --steps must be >= 1")
    return args


def main(argv=None) -> int:
    from gara_jax import results

    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    records = {}
    for name in args.runs:  # one at a time: each run already vmaps all seeds
        print(f"[gara_diagnostics] {name}: {args.seeds} seeds x {args.steps} steps",
              file=sys.stderr, flush=True)
        records[name] = run_one(name, run_config(name, args.planning, args.refine_method,
                                           args.goal_membership),
                                args.seeds, args.steps)
    report = {"seeds": args.seeds, "steps": args.steps, "refine_method": args.refine_method,
              "planning": args.planning, "goal_membership": args.goal_membership,
              "runs": records,
              "total_wall_time_s": time.perf_counter() - t0}
    results.write_json(out / "gara_diagnostics.json", report)
    print(markdown(records))
    print(f"\nwrote {out / 'gara_diagnostics.json'} ({report['total_wall_time_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
