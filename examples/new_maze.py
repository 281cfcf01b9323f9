"""Bring GARA to a new maze: define a layout, register it, train 20 seeds, draw the partition.

The layout ("zigzag") is a 3 x 3 maze with two walls the agent has to go round: one rising
from the bottom at x in [1, 1.5], one hanging from the top at x in [2, 2.5]. The agent starts
at (0, 0); the exit is the bottom-right corner (3, 0). GARA has no built-in partition for a
registered environment, so the example gives it one: the state space cut at x = 1 into two
boxes over (x, y, vx, vy). Its refinement then splits those boxes where the forward model
says only part of a box reaches the next one.

Run it (about 5 minutes on a 2-core CPU at the default budget)::

    python examples/new_maze.py                     # 20 seeds, 150,000 steps each
    python examples/new_maze.py --seeds 2 --steps 3000 --out /tmp/zigzag   # a quick look

It prints both success measures with 95% confidence intervals (the training episodes' success
over the run's last 30,000 steps, as the paper counts it, and the greedy evaluation at the
end), saves the final partition of the seed with the median final goal count as JSON (which
``GaraConfig(initial_boxes=partition.load_boxes(path))`` takes to start another run: the
authors' transfer experiment) and draws it next to the starting partition.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import envs
from gara_jax import partition, plots, results
from gara_jax.algorithms import GaraConfig
from gara_jax.train import train_many

NAME = "zigzag"
ZIGZAG = {"n": 3.0,
          "walls": [[1.0, 1.5, -1.0, 2.0],   # rises from below the floor to y = 2
                    [2.0, 2.5, 1.0, 4.0]],   # hangs from above the ceiling to y = 1
          "start": [0.0, 0.0], "exit": [3.0, 0.0]}
LAST_STEPS = 30_000  # the final training success counts the episodes ending in these steps


def make_zigzag(**overrides):
    """``(env, params)`` of the zigzag maze; keyword overrides replace fields (e.g.
    ``max_steps``), as ``envs.make`` does for the built-in layouts."""
    return envs.Maze(NAME), envs.EnvParams.create(**{**ZIGZAG, **overrides})


def initial_boxes():
    """Two boxes over (x, y, vx, vy) tiling the state space [0,3]^2 x [-1,1]^2, cut at x = 1."""
    lo, hi = partition.state_space(ZIGZAG["n"])
    left_hi, right_lo = hi.copy(), lo.copy()
    left_hi[0] = right_lo[0] = 1.0
    return partition.boxes_as_tuples([lo, right_lo], [left_hi, hi])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--steps", type=int, default=150_000, help="environment steps per seed")
    p.add_argument("--steps-per-epoch", type=int, default=3000)
    p.add_argument("--out", type=Path, default=Path("zigzag_results"))
    p.add_argument("--dry-run", action="store_true",
                   help="build the environment and the config, print the plan, train nothing")
    args = p.parse_args(argv)

    envs.register(NAME, make_zigzag)
    config = GaraConfig(env=NAME, initial_boxes=initial_boxes(),
                        steps_per_epoch=args.steps_per_epoch)
    if args.dry_run:
        print(f"{NAME}: GARA, {args.seeds} seeds x {args.steps:,} steps, starting from "
              f"{len(config.initial_boxes[0])} boxes; would write to {args.out}/")
        return 0
    res = train_many(config, seeds=args.seeds, total_steps=args.steps,
                     progress=lambda done, total, m: print(
                         f"\repoch {done}/{total}  greedy success "
                         f"{float(np.mean(m['eval_success'])):.2f}", end="", flush=True))
    print()

    end = int(res.metrics["env_steps"][0, -1])
    training = results.ci_summary(results.per_seed_success_after(
        res.episodes, max(end - LAST_STEPS, 0)))
    greedy = results.ci_summary(res.metrics["eval_success"][:, -1])
    goals = res.metrics["n_goals"][:, -1]
    print(f"{NAME}: {len(res.seeds)} seeds x {end:,} steps, {res.wall_time_s:.0f} s")
    print(f"  training success (last {LAST_STEPS:,} steps): "
          f"{training['mean']:.2f} ± {training['ci95']:.2f}")
    print(f"  greedy success at the end:               {greedy['mean']:.2f} ± {greedy['ci95']:.2f}")
    print(f"  goals at the end: median {np.median(goals):g} (min {goals.min()}, max {goals.max()})")

    # The seed drawn: the (lower) median of the final goal counts, the first seed that has it.
    median = sorted(goals)[(len(goals) - 1) // 2]
    seed = int(np.flatnonzero(goals == median)[0])
    args.out.mkdir(parents=True, exist_ok=True)
    final = partition.from_boxes(res.snapshots[seed][-1].lo, res.snapshots[seed][-1].hi,
                                 *partition.state_space(ZIGZAG["n"]), config.max_goals)
    partition.save_boxes(args.out / "final_partition.json", final)
    first, last = res.snapshots[seed][0], res.snapshots[seed][-1]
    plots.plot_partitions([(0, first.lo, first.hi, first.count),
                           (end, last.lo, last.hi, last.count)],
                          make_zigzag()[1], args.out / "partition.png",
                          suptitle=f"GARA on {NAME}, seed {res.seeds[seed]} "
                                   "(the median final goal count)")
    print(f"  wrote {args.out / 'final_partition.json'} and {args.out / 'partition.png'}")
    return {"training": training, "greedy": greedy, "goals": goals.tolist(),
            "seed_drawn": res.seeds[seed], "out": str(args.out)}


if __name__ == "__main__":
    main()
