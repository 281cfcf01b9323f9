"""Reproduce the paper's U-maze study: 20-run success curves and GARA's learned partition.

Trains GARA (Q-learning and Planning high levels), Handcrafted and HIRO, all seeds of a method
vmapped in one process, and writes to ``--out``:

- ``metrics.csv``: method, seed, env step, eval success, training success, goals, return;
- ``summary.json``: per method final success (mean, 95% CI), steps to 50% / 80%, wall time;
- ``success_curve.png``: seed-mean greedy success with 95% confidence bands;
- ``partitions.png``: one GARA seed's partition at 0, 10^3, 3x10^4 steps and at the end;
- ``config.json``: everything needed to rerun (the full config of every method).

A checkpoint is written after every epoch under ``--out/checkpoints``; ``--resume`` continues
from it and ends with exactly the metrics of an uninterrupted run. Result files are written
only when every method has finished, each atomically.

``--env point_u_maze`` runs the same study on the brax-simulated U-maze (envs/point_maze.py)
and writes the same files to ``results/point_u_maze`` by default.

Usage: ``gara-jax reproduce [--env u_maze] [--seeds 20] [--steps 120000] [--methods gara,hiro]
[--out DIR] [--quick] [--resume]`` (or ``python -m experiments.u_maze ...``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

METHODS = ("gara", "gara_planning", "handcrafted", "hiro")
QUICK = {"seeds": 2, "steps": 3000, "steps_per_epoch": 1000, "eval_episodes": 2}
ENVS = ("u_maze", "point_u_maze")  # the U-maze environments the partitions are defined for
ENV_TITLES = {"u_maze": "the U-shaped maze", "point_u_maze": "the U-shaped maze (brax ball)"}
PARTITION_STEPS = (0, 1_000, 30_000)  # the paper's panels; the run's end is added


DESCRIPTION = "Reproduce the paper's 20-run U-maze success curve and partition figure."


class UsageError(Exception):
    """A bad argument: reported as one line, exit status 2."""


def method_config(method: str, *, env: str = "u_maze", steps_per_epoch: int | None = None,
                  eval_episodes: int | None = None):
    """The default config of ``method`` (SPEC.md defaults), with optional epoch overrides."""
    from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig

    factories = {"gara": lambda **kw: GaraConfig(planning=False, **kw),
                 "gara_planning": lambda **kw: GaraConfig(planning=True, **kw),
                 "handcrafted": HandcraftedConfig, "hiro": HiroConfig}
    overrides = {"env": env}
    if steps_per_epoch is not None:
        overrides["steps_per_epoch"] = steps_per_epoch
    if eval_episodes is not None:
        overrides["eval_episodes"] = eval_episodes
    return factories[method](**overrides)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``gara-jax reproduce`` (shared with ``python -m experiments.u_maze``)."""
    p.add_argument("--seeds", type=int, default=None, help="seeds per method (default 20)")
    p.add_argument("--steps", type=int, default=None,
                   help="environment steps per seed (default 120000, rounded up to epochs)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help=f"comma-separated subset of {','.join(METHODS)}")
    p.add_argument("--env", default="u_maze", choices=ENVS,
                   help="u_maze (kinematic, the paper's) or point_u_maze (brax rigid body)")
    p.add_argument("--out", default=None, help="output directory (default results/ENV)")
    p.add_argument("--quick", action="store_true",
                   help=f"a first look: {QUICK['seeds']} seeds, {QUICK['steps']} steps, "
                        f"{QUICK['steps_per_epoch']}-step epochs (explicit --seeds/--steps win)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last completed epoch")
    p.add_argument("--steps-per-epoch", type=int, default=None,
                   help="environment steps between evaluations / refinements (default 3000)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _apply_defaults(args: argparse.Namespace) -> argparse.Namespace:
    if getattr(args, "env", None) is None:
        args.env = "u_maze"
    if args.out is None:
        args.out = f"results/{args.env}"
    if args.seeds is None:
        args.seeds = QUICK["seeds"] if args.quick else 20
    if args.steps is None:
        args.steps = QUICK["steps"] if args.quick else 120_000
    if args.steps_per_epoch is None and args.quick:
        args.steps_per_epoch = QUICK["steps_per_epoch"]
    args.eval_episodes = QUICK["eval_episodes"] if args.quick else None
    return args


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="gara-jax reproduce", description=DESCRIPTION)
    add_arguments(p)
    return p.parse_args(argv)


def validate(args) -> list[str]:
    """Check arguments before any work; returns the method list. Raises :class:`UsageError`."""
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise UsageError(f"--methods: unknown method(s) {unknown or [args.methods]}; "
                         f"choose from {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise UsageError(f"--methods: repeated method in {args.methods!r}")
    if args.seeds < 1:
        raise UsageError(f"--seeds: must be >= 1, got {args.seeds}")
    if args.steps < 1:
        raise UsageError(f"--steps: must be >= 1, got {args.steps}")
    if args.steps_per_epoch is not None and args.steps_per_epoch < 1:
        raise UsageError(f"--steps-per-epoch: must be >= 1, got {args.steps_per_epoch}")
    try:
        out = Path(args.out)
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        probe = out / ".write_probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise UsageError(f"--out: cannot write to {args.out!r} ({err.strerror or err})") from err
    return methods


def run_config(args, methods) -> dict:
    """The JSON written to ``config.json``: arguments and every method's full config."""
    configs = {m: dataclasses.asdict(method_config(
        m, env=args.env, steps_per_epoch=args.steps_per_epoch, eval_episodes=args.eval_episodes))
        for m in methods}
    return {"seeds": args.seeds, "steps": args.steps, "methods": methods,
            "steps_per_epoch": args.steps_per_epoch, "quick": args.quick, "env": args.env,
            "configs": configs}


class _Progress:
    """A tqdm bar per method: epoch, agent steps/s, mean success, time left."""

    def __init__(self, method, n_seeds, n_epochs, start_epoch, steps_per_epoch, enabled):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=n_epochs, initial=start_epoch, desc=f"{method:>13}", unit="epoch",
                        disable=not enabled, file=sys.stderr, dynamic_ncols=True)
        self.agent_steps = n_seeds * steps_per_epoch

    def update(self, out):
        sps = self.agent_steps / max(out.epoch_s, 1e-9)
        self.bar.set_postfix_str(f"{sps:,.0f} agent steps/s, "
                                 f"success {float(np.mean(out.metrics['eval_success'])):.2f}")
        self.bar.update(1)

    def close(self):
        self.bar.close()


def run_method(method, args, ckpt_dir: Path) -> dict:
    """Train one method on all seeds (resuming from its checkpoint if asked); returns its record:
    ``metrics`` (name -> [n_seeds, n_epochs] lists), ``snapshots`` (seed 0), ``wall_time_s``."""
    from gara_jax import checkpoint
    from gara_jax.train import init_loop, n_epochs_for, train_epochs

    config = method_config(method, env=args.env, steps_per_epoch=args.steps_per_epoch,
                           eval_episodes=args.eval_episodes)
    n_epochs = n_epochs_for(config, args.steps)
    path = ckpt_dir / f"{method}.npz"
    loop = init_loop(config, args.seeds)
    record = {"metrics": {}, "snapshots": _seed0_snapshots(loop.states, 0), "wall_time_s": 0.0}
    if args.resume and path.exists():
        loop, record = checkpoint.load(path, loop)
    progress = _Progress(method, args.seeds, n_epochs, loop.epoch, config.steps_per_epoch,
                         enabled=not args.no_progress)
    t0, base_wall = time.perf_counter(), record["wall_time_s"]
    try:
        for out in train_epochs(config, args.seeds, args.steps, init_state=loop):
            for k, v in out.metrics.items():
                record["metrics"].setdefault(k, []).append(np.asarray(v).tolist())
            if out.snapshots and out.snapshots[0]:
                record["snapshots"].extend(_snap_json(s) for s in out.snapshots[0])
            record["wall_time_s"] = base_wall + time.perf_counter() - t0
            checkpoint.save(path, out.loop, record)
            progress.update(out)
    finally:
        progress.close()
    return record


def _snap_json(s) -> dict:
    return {"step": int(s.step), "count": int(s.count), "lo": np.asarray(s.lo).tolist(),
            "hi": np.asarray(s.hi).tolist()}


def _seed0_snapshots(states, step) -> list:
    part = getattr(states, "partition", None)
    if part is None:
        return []
    n = int(part.count[0])
    return [{"step": step, "count": n, "lo": np.asarray(part.lo[0][:n]).tolist(),
             "hi": np.asarray(part.hi[0][:n]).tolist()}]


def _as_array_metrics(record) -> dict:
    # stored as [n_epochs][n_seeds]; results use [n_seeds, n_epochs]
    return {k: np.asarray(v).T for k, v in record["metrics"].items()}


def write_outputs(out: Path, methods, records, run_cfg, seeds) -> dict:
    """Write the result files (each atomically) and return the summary."""
    import envs
    from gara_jax import plots, results

    summary, rows, curves = {}, [], {}
    for m in methods:
        metrics = _as_array_metrics(records[m])
        summary[m] = results.summarize(metrics, records[m]["wall_time_s"])
        rows.extend(results.metrics_rows(m, metrics, seeds))
        curves[m] = (metrics["env_steps"][0], metrics["eval_success"])
    results.write_metrics_csv(out / "metrics.csv", rows)
    results.write_json(out / "summary.json", summary)
    _atomic_png(out / "success_curve.png",
                lambda p: plots.plot_success_curves(
                    curves, p, title=f"Average success rate on {ENV_TITLES[run_cfg['env']]} "
                                     f"({len(seeds)} runs)"))
    gara = next((m for m in ("gara", "gara_planning") if m in methods), None)
    if gara is not None:
        snaps = records[gara]["snapshots"]
        end = int(np.asarray(records[gara]["metrics"]["env_steps"])[-1][0])
        panels = [_latest_at(snaps, s) for s in (*PARTITION_STEPS, end)]
        _, params = envs.make(run_cfg["env"])
        _atomic_png(out / "partitions.png", lambda p: plots.plot_partitions(
            [(s["step"], np.asarray(s["lo"]), np.asarray(s["hi"]), s["count"]) for s in panels],
            params, p, suptitle=f"{gara}, seed {seeds[0]}: partition at or before 0, 1e3, "
                                f"3e4 steps and at the end ({end:,})"))
    results.write_json(out / "config.json", run_cfg)
    return summary


def _latest_at(snaps, step):
    """The last snapshot taken at or before ``step`` (snapshots are taken between epochs)."""
    return [s for s in snaps if s["step"] <= step][-1]


def _atomic_png(path: Path, draw) -> None:
    tmp = path.with_name(f".{path.name}.tmp.png")
    try:
        draw(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def main(argv=None) -> int:
    """``python -m experiments.u_maze [options]``; returns the exit status."""
    return run(parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run the study for parsed arguments (see :func:`add_arguments`); returns the exit status."""
    args = _apply_defaults(args)
    try:
        methods = validate(args)
    except UsageError as err:
        print(f"gara-jax reproduce: error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out)
    run_cfg = run_config(args, methods)
    cfg_path = out / "checkpoints" / "run_config.json"
    if args.resume and cfg_path.exists():
        if json.loads(cfg_path.read_text()) != json.loads(json.dumps(run_cfg)):
            print("gara-jax reproduce: error: --resume: the arguments differ from the run in "
                  f"{args.out!r} (see {cfg_path})", file=sys.stderr)
            return 2
    from gara_jax.results import write_json

    write_json(cfg_path, run_cfg)
    from gara_jax.train import seed_list

    seeds = seed_list(args.seeds)
    records = {}
    t0 = time.perf_counter()
    try:
        for m in methods:
            records[m] = run_method(m, args, out / "checkpoints")
    except KeyboardInterrupt:
        print(f"\ninterrupted: completed epochs are saved; continue with --resume --out "
              f"{args.out}", file=sys.stderr)
        return 130
    summary = write_outputs(out, methods, records, run_cfg, seeds)
    print(f"\nwrote {out}/metrics.csv, summary.json, success_curve.png"
          f"{', partitions.png' if any(m.startswith('gara') for m in methods) else ''}, "
          f"config.json  ({time.perf_counter() - t0:.0f} s)")
    print(f"{'method':>14} {'final success':>16} {'steps to 50%':>13} {'steps to 80%':>13} "
          f"{'wall s':>8}")
    for m, s in summary.items():
        print(f"{m:>14} {s['final_success_mean']:>8.2f} ± {s['final_success_ci95']:<5.2f} "
              f"{str(s['steps_to_50']):>13} {str(s['steps_to_80']):>13} {s['wall_time_s']:>8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
