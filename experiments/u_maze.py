"""Reproduce the paper's U-maze study: 20-run success curves and GARA's learned partition.

By default trains ``gara`` and ``gara_planning`` (``GaraConfig()``, Q-learning and Planning
high levels), ``gara_reference`` (``GaraConfig.reference()``, the authors' version),
``handcrafted`` and ``hiro_paper`` (``HiroConfig.paper()``, the HIRO baseline the paper ran);
``--methods all`` adds ``hiro`` (HIRO as published), ``gara_reference_results``
(``GaraConfig.reference(version="results")``, the version that made the authors' result files,
SPEC.md 3.9) and ``gara_reference_results_planning`` (the same with the Planning high level,
each seed started from the same seed's final ``gara_reference_results`` partition, as the
authors ran it, SPEC.md 3.9.3; naming it alone runs ``gara_reference_results`` first). All
seeds of a method are vmapped in one process. Diagnostic methods, the paper's HIRO with one
of its mechanisms changed, can be named explicitly: ``hiro_paper_standard_target`` (its
reward-less critic target fixed),
``hiro_paper_full_range`` (its actor output scaled to the whole goal box),
``hiro_paper_unclipped_low`` (its low level's TD targets not clipped to [-1, 1], as published
HIRO's) and ``hiro_paper_full_range_unclipped_low`` (the last two together). Writes to
``--out``:

- ``metrics.csv``: method, seed, env step, eval success, training success, goals, return
  (one row per seed and epoch);
- ``episodes.csv``: method, seed, episode, end step, length, success (every training episode);
- ``summary.json``: per method the greedy success at the end (``final_success_mean`` /
  ``final_success_ci95``), the paper's training-episode success over the episodes that ended
  in the last 30,000 steps (``final_train_success_mean`` / ``final_train_success_ci95``) and
  over episodes 300-399 (``train_success_ep300_400``: mean, ci95, seeds with such episodes),
  steps to 50% / 80% greedy success, goals, wall time; for ``gara_reference_results`` and
  ``gara_reference_results_planning`` on the U-maze also ``against_authors``: our seeds
  against the authors' own runs (SPEC.md 3.9.5) in success over episodes 300-399 and final
  goals, ours minus theirs with a 95% Welch interval (:func:`against_authors`);
- ``success_curve.png``: (a) training-episode success by episode index (first 400 episodes,
  30-episode moving average), (b) the same by environment steps, (c) greedy success by
  steps; seed means with 95% confidence bands;
- ``partitions_<method>.png`` for every GARA method run: one seed's partition at 0, 10^3,
  3x10^4 steps and at the end (the seed rule: :func:`partition_seed`);
- ``config.json``: everything needed to rerun (the full config of every method).

A checkpoint is written under ``--out/checkpoints`` after an epoch when ``--checkpoint-every``
seconds (default 60; 0: every epoch, as ``--quick`` does) have passed since the last one, and
after a method's last epoch; ``--resume`` continues from it and ends with exactly the metrics
of an uninterrupted run. (A 20-seed GARA checkpoint is about 290 MB, mostly replay buffers;
one write takes seconds, too much to repeat after every 3,000-step epoch.) Result files are
written only when every method has finished, each atomically.

``--env point_u_maze`` runs the same study on the brax-simulated U-maze (envs/point_maze.py)
and writes the same files to ``results/point_u_maze`` by default.

``--dry-run`` parses and checks every argument as a run would (methods, environment, seeds
over the devices, the output directory, a ``--resume``'s arguments against the saved run),
builds every method's config, prints the plan (methods, seeds, steps, epochs, output directory
and the files a run would write) and exits with status 0, training and writing nothing; a bad
argument exits with status 2, as it would for a run.

Usage: ``gara-jax reproduce [--env u_maze] [--seeds 20] [--steps 120000] [--methods gara,hiro]
[--out DIR] [--quick] [--resume] [--dry-run]`` (or ``python -m experiments.u_maze ...``).
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

DEFAULT_METHODS = ("gara", "gara_planning", "gara_reference", "handcrafted", "hiro_paper")
#: The authors' Planning runs started from their Q-learning run's final partitions (SPEC.md
#: 3.9.3): method -> the method whose final partitions (same seeds) it starts from.
STARTS_FROM = {"gara_reference_results_planning": "gara_reference_results"}
ALL_METHODS = (*DEFAULT_METHODS, "hiro", "gara_reference_results",
               "gara_reference_results_planning")  # --methods all
DIAGNOSTIC_METHODS = ("hiro_paper_standard_target", "hiro_paper_full_range",
                      "hiro_paper_unclipped_low", "hiro_paper_full_range_unclipped_low")
METHODS = (*ALL_METHODS, *DIAGNOSTIC_METHODS)
GARA_METHODS = ("gara", "gara_planning", "gara_reference", "gara_reference_results",
                "gara_reference_results_planning")
LAST_STEPS = 30_000  # the final training success counts the episodes ending in these steps
EPISODE_WINDOW = (300, 400)  # the last quarter of the reference's 400-episode run
CURVE_EPISODES, CURVE_WINDOW = 400, 30  # the paper's curve: 400 episodes, 30-episode average
# The authors' own runs (SPEC.md 3.9.5: U-maze, 400 training episodes each, made by the results
# version): training success over episodes 300-399 and goals in the final partition, run by run.
# Their Planning run 4 is a copy of run 3 and is left out.
AUTHORS_RUNS = {
    "gara_reference_results": {"train_success_ep300_400": (0.80, 0.79, 0.75, 0.93, 0.05),
                               "final_n_goals": (10, 9, 7, 7, 30)},
    "gara_reference_results_planning": {"train_success_ep300_400": (0.99, 0.72, 0.69, 0.71),
                                        "final_n_goals": (22, 9, 7, 7)},
}
QUICK = {"seeds": 2, "steps": 3000, "steps_per_epoch": 1000, "eval_episodes": 2}
#: Environments ``--env`` takes: the paper's U-maze, its brax twin, then SPEC.md's other layouts
#: (their Handcrafted and initial GARA partitions: SPEC.md 2.1).
ENVS = ("u_maze", "point_u_maze", "four_rooms", "u_maze_6", "big_u_maze", "labyrinth")
ENV_TITLES = {"u_maze": "the U-shaped maze", "point_u_maze": "the U-shaped maze (brax ball)",
              "four_rooms": "the four-rooms maze", "u_maze_6": "the U-maze of size 6",
              "big_u_maze": "the big U-maze", "labyrinth": "the labyrinth"}
#: Default steps per seed of each environment, the same for every method: the paper's 120,000
#: on the U-mazes; on the other layouts the paper's ratio to what Handcrafted needs (120,000 is
#: 10 x the 12,000 steps after which Handcrafted's seed-mean greedy success reaches 0.8 on the
#: U-maze), so 10 x that number measured on each layout, rounded up to 30,000 steps, at most
#: 600,000 (big_u_maze: Handcrafted does not reach 0.8 within 600,000 steps).
#: docs/mazes.md has the measurements.
ENV_STEPS = {"u_maze": 120_000, "point_u_maze": 120_000, "four_rooms": 270_000,
             "u_maze_6": 330_000, "big_u_maze": 600_000, "labyrinth": 120_000}
PARTITION_STEPS = (0, 1_000, 30_000)  # the paper's panels; the run's end is added


DESCRIPTION = "Reproduce the paper's 20-run U-maze success curve and partition figure."


class UsageError(Exception):
    """A bad argument: reported as one line, exit status 2."""


def method_config(method: str, *, env: str = "u_maze", steps_per_epoch: int | None = None,
                  eval_episodes: int | None = None):
    """The default config of ``method`` (SPEC.md defaults), with optional epoch overrides."""
    from gara_jax.agents.dqn import DQNConfig
    from gara_jax.agents.td3 import DDPG_PAPER
    from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig

    unclipped = dataclasses.replace(DQNConfig(), td_target_clip=1e6)
    paper_high = lambda **kw: lambda **o: HiroConfig.paper(  # noqa: E731
        high=dataclasses.replace(DDPG_PAPER, **kw), **o)
    factories = {"gara": lambda **kw: GaraConfig(planning=False, **kw),
                 "gara_planning": lambda **kw: GaraConfig(planning=True, **kw),
                 "gara_reference": lambda **kw: GaraConfig.reference(planning=False, **kw),
                 "gara_reference_results": lambda **kw: GaraConfig.reference(
                     version="results", planning=False, **kw),
                 "gara_reference_results_planning": lambda **kw: GaraConfig.reference(
                     version="results", planning=True, **kw),
                 "handcrafted": HandcraftedConfig, "hiro_paper": HiroConfig.paper,
                 "hiro": HiroConfig,
                 "hiro_paper_standard_target": paper_high(critic_target="standard"),
                 "hiro_paper_full_range": paper_high(actor_output="box"),
                 "hiro_paper_unclipped_low": lambda **kw: HiroConfig.paper(low=unclipped, **kw),
                 "hiro_paper_full_range_unclipped_low": lambda **kw: HiroConfig.paper(
                     low=unclipped, high=dataclasses.replace(DDPG_PAPER, actor_output="box"),
                     **kw)}
    overrides = {"env": env}
    if method == "handcrafted":  # room for the layout's boxes (the labyrinth has 15)
        overrides["max_goals"] = max(HandcraftedConfig().max_goals, handcrafted_boxes(env))
    if steps_per_epoch is not None:
        overrides["steps_per_epoch"] = steps_per_epoch
    if eval_episodes is not None:
        overrides["eval_episodes"] = eval_episodes
    return factories[method](**overrides)


def handcrafted_boxes(env: str) -> int:
    """How many boxes the Handcrafted partition of ``env`` has (SPEC.md 2, 2.1).

    Example:
        >>> handcrafted_boxes("labyrinth"), handcrafted_boxes("point_u_maze")
        (15, 6)
    """
    from gara_jax import partition

    layout = "u_maze" if env == "point_u_maze" else env
    return len(partition.layout_boxes(layout, "handcrafted")[0])


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``gara-jax reproduce`` (shared with ``python -m experiments.u_maze``)."""
    p.add_argument("--seeds", type=int, default=None, help="seeds per method (default 20)")
    p.add_argument("--steps", type=int, default=None,
                   help="environment steps per seed, rounded up to epochs (default: the "
                        "environment's budget, 120000 on the U-maze)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated subset of {','.join(METHODS)}, or 'all' "
                        f"(the default, hiro and the two gara_reference_results methods; "
                        f"default: {','.join(DEFAULT_METHODS)})")
    p.add_argument("--env", default="u_maze", choices=ENVS,
                   help="u_maze (kinematic, the paper's), point_u_maze (brax rigid body) or "
                        "another maze layout of SPEC.md")
    p.add_argument("--out", default=None, help="output directory (default results/ENV)")
    p.add_argument("--quick", action="store_true",
                   help=f"a first look: {QUICK['seeds']} seeds, {QUICK['steps']} steps, "
                        f"{QUICK['steps_per_epoch']}-step epochs (explicit --seeds/--steps win)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last completed epoch")
    p.add_argument("--dry-run", action="store_true",
                   help="check the arguments, print the plan (methods, seeds, steps, output "
                        "files) and exit without training or writing anything")
    p.add_argument("--steps-per-epoch", type=int, default=None,
                   help="environment steps between evaluations / refinements (default 3000)")
    p.add_argument("--checkpoint-every", type=float, default=None, metavar="SECONDS",
                   help="seconds between checkpoints (default 60; 0: after every epoch; a "
                        "method's last epoch is always saved)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--batch-invariant", action=argparse.BooleanOptionalAction, default=None,
                   help="compile so that each seed's results do not depend on how the seeds "
                        "are spread over devices and processes (on CPU: XLA's YNNPACK dots "
                        "off, slower); default: on exactly when there is more than one device")
    p.add_argument("--distributed", action="store_true",
                   help="one of several processes (jax.distributed, from JAX_COORDINATOR_ADDRESS,"
                        " JAX_NUM_PROCESSES, JAX_PROCESS_ID): seeds over every process's "
                        "devices; process 0 writes the result files")


def _apply_defaults(args: argparse.Namespace) -> argparse.Namespace:
    if getattr(args, "env", None) is None:
        args.env = "u_maze"
    if args.out is None:
        args.out = f"results/{args.env}"
    if args.seeds is None:
        args.seeds = QUICK["seeds"] if args.quick else 20
    if args.steps is None:
        args.steps = QUICK["steps"] if args.quick else ENV_STEPS[args.env]
    if args.steps_per_epoch is None and args.quick:
        args.steps_per_epoch = QUICK["steps_per_epoch"]
    args.eval_episodes = QUICK["eval_episodes"] if args.quick else None
    if getattr(args, "checkpoint_every", None) is None:
        args.checkpoint_every = 0.0 if args.quick else 60.0
    return args


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="gara-jax reproduce", description=DESCRIPTION)
    add_arguments(p)
    from gara_jax import compile_cache

    compile_cache.add_argument(p)
    return p.parse_args(argv)


def validate(args, *, write: bool = True) -> list[str]:
    """Check arguments before any work; returns the method list. Raises :class:`UsageError`.

    ``write=False`` (``--dry-run``) checks that ``--out`` could be created and written without
    creating anything."""
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if methods == ["all"]:
        methods = list(ALL_METHODS)
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise UsageError(f"--methods: unknown method(s) {unknown or [args.methods]}; "
                         f"choose from {', '.join(METHODS)}, or all")
    if len(set(methods)) != len(methods):
        raise UsageError(f"--methods: repeated method in {args.methods!r}")
    for method, source in STARTS_FROM.items():
        # The method runs from the source's final partitions: the source runs first.
        if method in methods:
            if source in methods:
                methods.remove(source)
            methods.insert(methods.index(method), source)
    if args.seeds < 1:
        raise UsageError(f"--seeds: must be >= 1, got {args.seeds}")
    if args.steps < 1:
        raise UsageError(f"--steps: must be >= 1, got {args.steps}")
    if not args.checkpoint_every >= 0:
        raise UsageError(f"--checkpoint-every: must be >= 0, got {args.checkpoint_every}")
    if args.steps_per_epoch is not None and args.steps_per_epoch < 1:
        raise UsageError(f"--steps-per-epoch: must be >= 1, got {args.steps_per_epoch}")
    if not write:
        _check_writable(Path(args.out))
        return methods
    try:
        out = Path(args.out)
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        probe = out / ".write_probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise UsageError(f"--out: cannot write to {args.out!r} ({err.strerror or err})") from err
    return methods


def _check_writable(out: Path) -> None:
    """``out`` could be created (if missing) and written to, judged without writing."""
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"--out: {str(existing)!r} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UsageError(f"--out: cannot write to {str(existing)!r}")


def output_files(methods) -> list[str]:
    """The result files a run of ``methods`` writes to ``--out``."""
    return ["metrics.csv", "episodes.csv", "summary.json", "success_curve.png",
            *(f"partitions_{m}.png" for m in methods if m in GARA_METHODS), "config.json"]


def dry_run(args, methods) -> int:
    """``--dry-run``: build every method's config, check a ``--resume``, print the plan."""
    from gara_jax.train import n_epochs_for, seed_list

    out = Path(args.out)
    configs = {m: method_config(m, env=args.env, steps_per_epoch=args.steps_per_epoch,
                                eval_episodes=args.eval_episodes) for m in methods}
    run_cfg = run_config(args, methods)
    cfg_path = out / "checkpoints" / "run_config.json"
    resume = "no"
    if args.resume:
        if not cfg_path.exists():
            resume = f"nothing to resume in {str(out)!r}: every method starts at epoch 0"
        elif _resume_mismatch(cfg_path, run_cfg):
            return _resume_refused(args, cfg_path)
        else:
            resume = f"the arguments match the run in {str(out)!r} ({cfg_path})"
    seeds = seed_list(args.seeds)
    first = f"{seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else f"{seeds[0]}"
    lines = ["gara-jax reproduce --dry-run: the plan (nothing is trained or written)",
             f"  environment: {args.env}",
             f"  seeds: {args.seeds} per method (seeds {first}), all of a method in one process",
             f"  steps: {args.steps:,} per seed, rounded up to whole epochs",
             f"  batch-invariant: {'on' if run_cfg['batch_invariant'] else 'off'}"]
    if getattr(args, "distributed", False):
        if getattr(args, "batch_invariant", None) is None:
            lines[-1] = "  batch-invariant: on exactly when the run has more than one device"
        lines.append("  distributed: jax.distributed would start from JAX_COORDINATOR_ADDRESS="
                     f"{os.environ.get('JAX_COORDINATOR_ADDRESS', '(unset)')}, "
                     f"JAX_NUM_PROCESSES={os.environ.get('JAX_NUM_PROCESSES', '(unset)')}, "
                     f"JAX_PROCESS_ID={os.environ.get('JAX_PROCESS_ID', '(unset)')} (not "
                     "started by a dry run: the seeds are checked against every process's "
                     "devices when it starts)")
    lines.append("  methods:")
    for m, config in configs.items():
        n_epochs = n_epochs_for(config, args.steps)
        lines.append(f"    {m}: {type(config).__name__}, {n_epochs} epochs of "
                     f"{config.steps_per_epoch:,} steps ({n_epochs * config.steps_per_epoch:,} "
                     f"steps per seed), {config.eval_episodes} greedy evaluation episodes "
                     "per seed after each epoch")
    every = ("after every epoch" if args.checkpoint_every == 0
             else f"every {args.checkpoint_every:g} s")
    lines += [f"  output: {out}/ ({'exists' if out.exists() else 'would be created'})",
              f"    result files: {', '.join(output_files(methods))}",
              f"    checkpoints: {out}/checkpoints/METHOD/, {every} and after a method's last "
              "epoch",
              f"  resume: {resume}"]
    print("\n".join(lines))
    return 0


def _resume_mismatch(cfg_path: Path, run_cfg: dict) -> bool:
    """Whether the run saved in ``cfg_path`` was made with other arguments than ``run_cfg``."""
    saved = json.loads(cfg_path.read_text())
    saved.setdefault("batch_invariant", False)  # runs from before the option: XLA's defaults
    return saved != json.loads(json.dumps(run_cfg))


def _resume_refused(args, cfg_path: Path) -> int:
    print("gara-jax reproduce: error: --resume: the arguments differ from the run in "
          f"{args.out!r} (see {cfg_path})", file=sys.stderr)
    return 2


def run_config(args, methods) -> dict:
    """The JSON written to ``config.json``: arguments and every method's full config."""
    configs = {m: dataclasses.asdict(method_config(
        m, env=args.env, steps_per_epoch=args.steps_per_epoch, eval_episodes=args.eval_episodes))
        for m in methods}
    from gara_jax.sharding import seed_mesh
    from gara_jax.train import resolve_batch_invariant

    # Resolved (the default depends on the device count): a resume must compile alike.
    invariant = resolve_batch_invariant(getattr(args, "batch_invariant", None), seed_mesh(None))
    out = {"seeds": args.seeds, "steps": args.steps, "methods": methods,
           "steps_per_epoch": args.steps_per_epoch, "quick": args.quick, "env": args.env,
           "batch_invariant": invariant, "configs": configs}
    starts = {m: STARTS_FROM[m] for m in methods if m in STARTS_FROM}
    if starts:
        out["starts_from"] = starts  # each seed from the same seed's final partition
    return out


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


def run_method(method, args, ckpt_dir: Path, start_from: dict | None = None) -> dict:
    """Train one method on all seeds (resuming from its checkpoint if asked); returns its record:
    ``metrics`` (name -> [n_epochs][n_seeds] lists), ``episodes`` (field -> per-seed lists of
    every training episode), ``snapshots`` (per seed: the partition at step 0 and after every
    epoch that changed it) and ``wall_time_s``. ``start_from``: another method's record, whose
    final partitions (its last snapshot of each seed) the seeds start from."""
    from gara_jax import checkpoint
    from gara_jax.train import EPISODE_FIELDS, init_loop, n_epochs_for, train_epochs

    config = method_config(method, env=args.env, steps_per_epoch=args.steps_per_epoch,
                           eval_episodes=args.eval_episodes)
    n_epochs = n_epochs_for(config, args.steps)
    path, legacy = ckpt_dir / method, ckpt_dir / f"{method}.npz"  # orbax; the previous format
    invariant = getattr(args, "batch_invariant", None)
    initial = None
    if start_from is not None:
        initial = [(np.asarray(snaps[-1]["lo"]), np.asarray(snaps[-1]["hi"]))
                   for snaps in start_from["snapshots"]]
    loop = init_loop(config, args.seeds, batch_invariant=invariant, initial_partitions=initial)
    record = {"metrics": {}, "episodes": {f: [[] for _ in range(args.seeds)]
                                          for f in EPISODE_FIELDS},
              "snapshots": _initial_snapshots(loop.states, args.seeds), "wall_time_s": 0.0}
    if args.resume and checkpoint.latest_epoch(path) is not None:
        loop, record = checkpoint.load(path, loop)
    elif args.resume and legacy.exists():
        loop, record = checkpoint.load(legacy, loop)
    progress = _Progress(method, args.seeds, n_epochs, loop.epoch, config.steps_per_epoch,
                         enabled=not args.no_progress and _is_primary(args))
    t0, base_wall = time.perf_counter(), record["wall_time_s"]
    last_save = t0
    try:
        for out in train_epochs(config, args.seeds, args.steps, init_state=loop,
                                batch_invariant=invariant):
            for k, v in out.metrics.items():
                record["metrics"].setdefault(k, []).append(np.asarray(v).tolist())
            if out.episodes is not None:
                for f in EPISODE_FIELDS:
                    for i, values in enumerate(out.episodes[f]):
                        record["episodes"][f][i].extend(np.asarray(values).tolist())
            for i, snaps in enumerate(out.snapshots):
                record["snapshots"][i].extend(_snap_json(s) for s in snaps)
            record["wall_time_s"] = base_wall + time.perf_counter() - t0
            if (out.epoch + 1 == out.n_epochs
                    or time.perf_counter() - last_save >= args.checkpoint_every):
                checkpoint.save(path, out.loop, record)
                last_save = time.perf_counter()
            progress.update(out)
    finally:
        progress.close()
    return record


def _snap_json(s) -> dict:
    return {"step": int(s.step), "count": int(s.count), "lo": np.asarray(s.lo).tolist(),
            "hi": np.asarray(s.hi).tolist()}


def _initial_snapshots(states, n_seeds) -> list:
    from gara_jax.train import _snapshots

    start = _snapshots(states)  # None for an algorithm without a partition
    return [[] for _ in range(n_seeds)] if start is None else [[_snap_json(s)] for s in start]


def _is_primary(args) -> bool:
    """Process 0 of a ``--distributed`` run (the one that writes), or a single process."""
    if not getattr(args, "distributed", False):
        return True
    import jax

    return jax.process_index() == 0


def start_distributed(args) -> None:
    """``--distributed``: join the ``jax.distributed`` run the environment describes."""
    if getattr(args, "distributed", False):
        from gara_jax.distributed import initialize_from_env

        initialize_from_env()


def _as_array_metrics(record) -> dict:
    # stored as [n_epochs][n_seeds]; results use [n_seeds, n_epochs]
    return {k: np.asarray(v).T for k, v in record["metrics"].items()}


def _episodes(record) -> dict:
    return {f: [np.asarray(v, np.int64) for v in per_seed]
            for f, per_seed in record["episodes"].items()}


def summarize_method(record, method: str | None = None, env: str = "u_maze") -> dict:
    """``summary.json``'s entry for one method: the greedy fields of
    :func:`gara_jax.results.summarize`, the paper's training-episode success, and for a
    method of :data:`AUTHORS_RUNS` on the U-maze ``against_authors``."""
    from gara_jax import results

    metrics, episodes = _as_array_metrics(record), _episodes(record)
    summary = results.summarize(metrics, record["wall_time_s"])
    end = int(metrics["env_steps"][0, -1])  # the run's steps, rounded up to whole epochs
    last = results.ci_summary(results.per_seed_success_after(
        episodes, max(end - LAST_STEPS, 0)))
    window = results.ci_summary(results.per_seed_episode_success(episodes, *EPISODE_WINDOW))
    summary.update({
        "final_train_success_mean": last["mean"],
        "final_train_success_ci95": last["ci95"],
        "train_success_ep300_400": window,
        "episodes_mean": float(np.mean([len(s) for s in episodes["success"]])),
    })
    if method in AUTHORS_RUNS and env == "u_maze":
        summary["against_authors"] = against_authors(
            method, results.per_seed_episode_success(episodes, *EPISODE_WINDOW),
            metrics["n_goals"][:, -1])
    return summary


def against_authors(method: str, success_ep300_400, final_n_goals) -> dict:
    """Our seeds against the authors' own runs of ``method`` (:data:`AUTHORS_RUNS`): per
    measure the authors' values, both means and ours minus theirs with its 95% Welch
    interval (:func:`gara_jax.results.welch_ci95`; two independent samples, so the interval
    is as wide as their 4-5 runs make it).

    Example:
        >>> d = against_authors("gara_reference_results", [0.6, 0.7, 0.65], [7, 9, 8])
        >>> round(d["train_success_ep300_400"]["mean"], 3), d["final_n_goals"]["authors_mean"]
        (-0.014, 12.6)
    """
    from gara_jax.results import welch_ci95

    ours = {"train_success_ep300_400": success_ep300_400, "final_n_goals": final_n_goals}
    out = {"source": "SPEC.md 3.9.5"}
    for measure, theirs in AUTHORS_RUNS[method].items():
        mine = np.asarray(ours[measure], dtype=np.float64)
        mine = mine[~np.isnan(mine)]  # seeds without episodes 300-399 (a short run)
        diff = (welch_ci95(mine, theirs) if mine.size else
                {"mean": None, "ci95": None, "df": None, "n": [0, len(theirs)]})
        out[measure] = {"authors": list(theirs), "authors_mean": float(np.mean(theirs)),
                        "ours_mean": float(mine.mean()) if mine.size else None, **diff}
    return out


def partition_seed(record) -> tuple[int, str]:
    """The seed (row index) drawn in the partition figure, and the rule, in words.

    The rule: among the seeds whose greedy evaluation succeeds at the end (success >= 0.5),
    the one whose final goal count is their median (the lower median; of several seeds with
    that count, the first); if none succeeds, the same over all seeds.

    Example:
        >>> rec = {"metrics": {"eval_success": [[1.0, 0.0, 1.0, 1.0]],
        ...                    "n_goals": [[5, 9, 3, 4]]}}
        >>> partition_seed(rec)[0]
        3
    """
    metrics = _as_array_metrics(record)
    success, goals = metrics["eval_success"][:, -1], metrics["n_goals"][:, -1]
    pool = np.flatnonzero(success >= 0.5)
    rule = "the successful seed with the median final goal count"
    if pool.size == 0:
        pool, rule = np.arange(len(success)), "no seed succeeds: the median final goal count"
    median = sorted(goals[pool])[(len(pool) - 1) // 2]
    return int(min(i for i in pool if goals[i] == median)), rule


def partition_at(snaps, step):
    """The partition in effect at ``step``: the last snapshot taken at or before it.

    The partition changes only in a host step (a snapshot, stamped with the seed's step
    count, is taken after each one that changed it: between epochs, or with
    ``cadence="episode"`` after an episode), so between snapshots it is the last one's: the
    panel at 1,000 steps is exact.
    """
    return [s for s in snaps if s["step"] <= step][-1]


def write_outputs(out: Path, methods, records, run_cfg, seeds) -> dict:
    """Write the result files (each atomically) and return the summary."""
    import envs
    from gara_jax import plots, results

    summary, rows, episode_rows = {}, [], []
    by_episode, by_step, greedy = {}, {}, {}
    for m in methods:
        metrics, episodes = _as_array_metrics(records[m]), _episodes(records[m])
        summary[m] = summarize_method(records[m], m, run_cfg["env"])
        rows.extend(results.metrics_rows(m, metrics, seeds))
        episode_rows.extend(results.episode_rows(m, episodes, seeds))
        steps = metrics["env_steps"][0]
        label = f"{m} ({len(seeds)} seeds)"
        mean, ci = results.episode_success_curve(episodes, CURVE_EPISODES, CURVE_WINDOW)
        by_episode[label] = (np.arange(1, len(mean) + 1), mean, ci)
        by_step[label] = (steps, *results.step_success_curve(
            episodes, steps, window_steps=int(steps[0])))
        greedy[label] = (steps, *results.mean_ci95(metrics["eval_success"], axis=0))
    results.write_metrics_csv(out / "metrics.csv", rows)
    results.write_episodes_csv(out / "episodes.csv", episode_rows)
    results.write_json(out / "summary.json", summary)
    env_title = ENV_TITLES[run_cfg["env"]]
    epoch = int(by_step[next(iter(by_step))][0][0])
    panels = [
        (f"(a) training episodes ({CURVE_WINDOW}-episode moving average)", "training episode",
         "success rate", by_episode),
        (f"(b) training episodes (ended in the last {epoch:,} steps)", "environment steps",
         "success rate", by_step),
        ("(c) greedy evaluation (both levels greedy)", "environment steps", "success rate",
         greedy),
    ]
    _atomic_png(out / "success_curve.png", lambda p: plots.plot_curve_panels(
        panels, p, suptitle=f"Average success rate on {env_title} ({len(seeds)} runs, "
                            "mean and 95% CI over seeds)"))
    _, params = envs.make(run_cfg["env"])
    for m in (m for m in methods if m in GARA_METHODS):
        row, rule = partition_seed(records[m])
        snaps = records[m]["snapshots"][row]
        end = int(np.asarray(records[m]["metrics"]["env_steps"])[-1][row])
        shown = [(t, partition_at(snaps, t)) for t in (*PARTITION_STEPS, end) if t <= end]
        _atomic_png(out / f"partitions_{m}.png", lambda p, m=m, row=row, rule=rule, shown=shown:
                    plots.plot_partitions(
                        [(t, np.asarray(s["lo"]), np.asarray(s["hi"]), s["count"])
                         for t, s in shown], params, p,
                        suptitle=f"{m}, seed {seeds[row]} ({rule})"))
    results.write_json(out / "config.json", run_cfg)
    return summary


def _atomic_png(path: Path, draw) -> None:
    tmp = path.with_name(f".{path.name}.tmp.png")
    try:
        draw(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def main(argv=None) -> int:
    """``python -m experiments.u_maze [options]``; returns the exit status."""
    from gara_jax import compile_cache

    args = parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    return run(args)


def run(args: argparse.Namespace) -> int:
    """Run the study for parsed arguments (see :func:`add_arguments`); returns the exit status."""
    args = _apply_defaults(args)
    dry = getattr(args, "dry_run", False)
    try:
        methods = validate(args, write=not dry)
        if not dry:
            start_distributed(args)
        if not (dry and getattr(args, "distributed", False)):
            from gara_jax.sharding import check_divisible, seed_mesh

            check_divisible(args.seeds, seed_mesh(None))  # the seeds are sharded over every device
    except (UsageError, ValueError) as err:
        print(f"gara-jax reproduce: error: {err}", file=sys.stderr)
        return 2
    if dry:
        return dry_run(args, methods)
    out = Path(args.out)
    run_cfg = run_config(args, methods)
    cfg_path = out / "checkpoints" / "run_config.json"
    if args.resume and cfg_path.exists():
        if _resume_mismatch(cfg_path, run_cfg):
            return _resume_refused(args, cfg_path)
    from gara_jax.results import write_json

    if _is_primary(args):
        write_json(cfg_path, run_cfg)
    from gara_jax.train import seed_list

    seeds = seed_list(args.seeds)
    records = {}
    t0 = time.perf_counter()
    try:
        for m in methods:
            records[m] = run_method(m, args, out / "checkpoints",
                                    start_from=records.get(STARTS_FROM.get(m)))
    except KeyboardInterrupt:
        print(f"\ninterrupted: completed epochs are saved; continue with --resume --out "
              f"{args.out}", file=sys.stderr)
        return 130
    if not _is_primary(args):
        return 0
    summary = write_outputs(out, methods, records, run_cfg, seeds)
    figures = [f"partitions_{m}.png" for m in methods if m in GARA_METHODS]
    print(f"\nwrote {out}/: metrics.csv, episodes.csv, summary.json, success_curve.png, "
          f"{''.join(f + ', ' for f in figures)}config.json  "
          f"({time.perf_counter() - t0:.0f} s)")
    print(print_table(summary))
    return 0


def print_table(summary) -> str:
    """The summary as a markdown table (training and greedy success with 95% CIs)."""
    fmt = lambda mean, ci: "-" if mean is None else f"{mean:.2f} ± {ci:.2f}"  # noqa: E731
    lines = ["| method | training, last 30k steps | training, episodes 300-399 | "
             "greedy, end | goals | wall s |", "|---|---:|---:|---:|---:|---:|"]
    for m, s in summary.items():
        w = s["train_success_ep300_400"]
        lines.append(f"| {m} | {fmt(s['final_train_success_mean'], s['final_train_success_ci95'])}"
                     f" | {fmt(w['mean'], w['ci95'])} | "
                     f"{fmt(s['final_success_mean'], s['final_success_ci95'])} | "
                     f"{s['final_n_goals_mean']:.1f} | {s['wall_time_s']:.0f} |")
    rows = {m: s["against_authors"] for m, s in summary.items() if "against_authors" in s}
    if rows:
        lines += ["", authors_table(rows)]
    return "\n".join(lines)


def authors_table(rows) -> str:
    """``{name: against_authors(...)}`` as a markdown table: ours, the authors' runs, and
    ours minus theirs with its 95% Welch interval, for the success and the goals."""
    def cell(d):
        theirs = f"{d['authors_mean']:.2f} ({', '.join(f'{v:g}' for v in d['authors'])})"
        if d["mean"] is None:
            return f"- | {theirs} | -"
        ci = "-" if d["ci95"] is None else f"{d['ci95']:.2f}"
        return f"{d['ours_mean']:.2f} | {theirs} | {d['mean']:+.2f} ± {ci}"

    lines = ["| against the authors' runs (SPEC.md 3.9.5) | training, ep. 300-399: ours "
             "| authors | ours − authors (Welch) | goals at the end: ours | authors "
             "| ours − authors (Welch) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, d in rows.items():
        lines.append(f"| {name} | {cell(d['train_success_ep300_400'])} | "
                     f"{cell(d['final_n_goals'])} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
