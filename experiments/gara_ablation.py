"""GARA ablation on the U-maze: the reference preset, one mechanism changed at a time.

Every variant is a named config (the list :data:`VARIANTS` below); each runs all its seeds in
one process through :func:`gara_jax.train.train_many` and is summarised by

- ``train_ep300_400``: success of the training episodes 300-399 (exploration on; the last
  quarter of the reference's 400-episode run), per seed, then the mean and 95% t-interval;
- ``train_last30k``: success of the training episodes that ended in the last 30,000 steps;
- ``greedy_end``: greedy evaluation success after the last epoch (``eval_episodes`` episodes
  per seed from the start, both levels greedy);
- ``goals_end``, ``analysed``, ``splits`` (per seed, mean), and the wall time.

Results go to ``--out`` (JSON, rewritten after every variant; a variant already there with the
same seeds and steps is not run again unless ``--rerun``), and a markdown table is printed.

Usage::

    python -m experiments.gara_ablation                       # every variant, 20 x 120,000
    python -m experiments.gara_ablation --variants reference,default --seeds 5 --steps 30000
    python -m experiments.gara_ablation --list
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

LAST_STEPS = 30_000
EPISODE_WINDOW = (300, 400)


def _variants():
    """``name -> (description, config)``: the ablation, built lazily (imports JAX)."""
    from gara_jax.agents.dqn import DQNConfig
    from gara_jax.agents.high_level import HighLevelConfig
    from gara_jax.algorithms import GaraConfig, HandcraftedConfig

    ref = GaraConfig.reference()
    rep = lambda **kw: dataclasses.replace(ref, **kw)
    high = lambda **kw: dataclasses.replace(ref.high, **kw)
    low = lambda **kw: dataclasses.replace(ref.low, **kw)
    previous = GaraConfig(
        memory="options", memory_capacity=10_000, tau1=0.7, tau2=0.1, small_box_c1=None,
        low=DQNConfig(loss="all_actions", buffer_size=10_000, target_update_every=200),
        high=HighLevelConfig(epsilon_decrement=0.005))
    fixed = rep(goal_membership="partition", reached_at_start=True)
    nr = dataclasses.replace(fixed, relabel_replay=False)
    return {
        "previous_default": ("GaraConfig() before SPEC revision 2 (session 4)", previous),
        "reference": ("GaraConfig.reference(): the authors' final maze version", ref),
        # The reference with one of its mechanisms reverted.
        "ref-options_memory": ("memory of whole options (+ hindsight copies), not windows",
                               rep(memory="options")),
        "ref-per_job_model": ("a fresh forward model per analysis, fitted until stable",
                              rep(forward_model="per_job")),
        "ref-thresholds_rev1": ("tau1 0.7, tau2 0.1, small boxes never reach (revision 1)",
                                rep(tau1=0.7, tau2=0.1, small_box_c1=None)),
        "ref-no_eps_boost": ("no x1.5 epsilon boost after a split",
                             rep(split_epsilon_boost=1.0)),
        "ref-no_relabel": ("no hindsight relabelling of the low-level replay",
                           rep(relabel_replay=False)),
        "ref-eps_0.005": ("high-level epsilon decrement 0.005 (results version)",
                          rep(high=high(epsilon_decrement=0.005))),
        "ref-replay_10k_target_200": ("low-level replay 10,000, target copy every 200 steps",
                                      rep(low=low(buffer_size=10_000, target_update_every=200))),
        "ref-q_columns_copy": ("every piece gets the split goal's Q column",
                               rep(q_columns="copy")),
        "ref-skip_unreachable": ("pairs marked unreachable are not analysed again",
                                 rep(skip_unreachable=True)),
        "ref-constant_entry": ("entry reward 1, not previous + 1", rep(entry_reward="constant")),
        "ref-random_ties": ("greedy ties broken at random", rep(high=high(tie_break="random"))),
        # Changes of ours (point 4 of the GARA issue), on the reference.
        "ref+partition_membership": ("inside the target = belongs to it (first-box rule)",
                                     rep(goal_membership="partition")),
        "ref+reached_at_start": ("an option starting inside its target earns no entry reward",
                                 rep(reached_at_start=True)),
        "ref+both": ("partition membership and reached-at-start", fixed),
        "both+q_zero": ("ref+both, pieces' Q columns reset to 0 after a split",
                        dataclasses.replace(fixed, q_columns="zero")),
        "both+q_both": ("ref+both, high-level update of the reached and the targeted entry",
                        dataclasses.replace(fixed, high=dataclasses.replace(
                            fixed.high, q_target_entry="both"))),
        "both+no_relabel": ("ref+both without the replay relabelling",
                            dataclasses.replace(fixed, relabel_replay=False)),
        "both+stall_penalty": ("ref+both, intrinsic reward -1 for a step that does not move",
                               dataclasses.replace(fixed, stall_penalty=-1.0)),
        "both+per_job": ("ref+both with a fresh forward model per analysis, fitted until stable",
                         dataclasses.replace(fixed, forward_model="per_job")),
        "both+min_steps_1000": ("ref+both, a pair is analysed after 1,000 counts (not 5,000)",
                                dataclasses.replace(fixed, min_steps=1000)),
        "both+every_step": ("ref+both with the every-step intrinsic reward",
                            dataclasses.replace(fixed, intrinsic="every_step")),
        # On ref+both without the relabelling (the change that mattered most).
        "nr": ("ref+both, no replay relabelling", nr),
        "nr+stall_penalty": ("nr, intrinsic reward -1 for a step that does not move",
                             dataclasses.replace(nr, stall_penalty=-1.0)),
        "nr+min_steps_1000": ("nr, pairs analysed after 1,000 counts",
                              dataclasses.replace(nr, min_steps=1000)),
        "nr+self_target_exit": ("nr, the current goal is a target only where it holds the exit",
                                dataclasses.replace(nr, self_target="exit_goal")),
        "nr+target_200": ("nr, low-level target network copied every 200 steps",
                          dataclasses.replace(nr, low=dataclasses.replace(
                              nr.low, target_update_every=200))),
        "nr+replay_10k_target_200": ("nr, low-level replay 10,000 and target copy every 200",
                                     dataclasses.replace(nr, low=dataclasses.replace(
                                         nr.low, buffer_size=10_000, target_update_every=200))),
        "nr+eps_0.005": ("nr, high-level epsilon decrement 0.005",
                         dataclasses.replace(nr, high=dataclasses.replace(
                             nr.high, epsilon_decrement=0.005))),
        "nr+stall+penalty_0.01": ("nr, stall reward -1 and outside penalty -0.01 (not -0.1)",
                                  dataclasses.replace(nr, stall_penalty=-1.0,
                                                      outside_penalty=-0.01)),
        "nr+penalty_0.01": ("nr, outside penalty -0.01 (not -0.1)",
                            dataclasses.replace(nr, outside_penalty=-0.01)),
        "nr+stall+random_ties": ("nr, stall reward -1 and random greedy ties",
                                 dataclasses.replace(nr, stall_penalty=-1.0, high=dataclasses.replace(
                                     nr.high, tie_break="random"))),
        "nsr+target_200": ("nr+stall+random_ties, target network copied every 200 steps",
                           dataclasses.replace(nr, stall_penalty=-1.0, high=dataclasses.replace(
                               nr.high, tie_break="random"), low=dataclasses.replace(
                               nr.low, target_update_every=200))),
        "nsr+q_zero": ("nr+stall+random_ties, pieces' Q columns reset to 0",
                       dataclasses.replace(nr, stall_penalty=-1.0, q_columns="zero",
                                           high=dataclasses.replace(nr.high, tie_break="random"))),
        "nsr+per_job": ("nr+stall+random_ties, per-job forward models",
                        dataclasses.replace(nr, stall_penalty=-1.0, forward_model="per_job",
                                            high=dataclasses.replace(nr.high, tie_break="random"))),
        "nr+per_job": ("nr, a fresh forward model per analysis, fitted until stable",
                       dataclasses.replace(nr, forward_model="per_job")),
        "nr+q_zero": ("nr, pieces' Q columns reset to 0 after a split",
                      dataclasses.replace(nr, q_columns="zero")),
        "nr+random_ties": ("nr, greedy high-level ties broken at random",
                           dataclasses.replace(nr, high=dataclasses.replace(
                               nr.high, tie_break="random"))),
        "default": ("GaraConfig(): this project's default", GaraConfig()),
        "default_planning": ("GaraConfig(planning=True)", GaraConfig(planning=True)),
        "reference_planning": ("GaraConfig.reference(planning=True)",
                               GaraConfig.reference(planning=True)),
        "handcrafted": ("HandcraftedConfig()", HandcraftedConfig()),
        "handcrafted_reference": ("HandcraftedConfig.reference()", HandcraftedConfig.reference()),
        "handcrafted_previous": ("HandcraftedConfig() before SPEC revision 2 (session 4)",
                                 HandcraftedConfig(low=previous.low, high=previous.high)),
        "handcrafted+target_200": ("HandcraftedConfig(), target network copied every 200 steps",
                                   HandcraftedConfig(low=dataclasses.replace(
                                       HandcraftedConfig().low, target_update_every=200))),
    }


def summarize_run(result, total_steps: int) -> dict:
    """The ablation's numbers for one :class:`~gara_jax.train.TrainResult`."""
    from gara_jax import results as R

    m = result.metrics
    ep = result.episodes
    host = [h for h in result.host_info if h]
    per_seed = lambda key: np.sum([np.asarray(h.get(key, 0)) for h in host]) / len(result.seeds)
    n_episodes = [len(s) for s in ep["success"]]
    return {
        "train_ep300_400": R.ci_summary(R.per_seed_episode_success(ep, *EPISODE_WINDOW)),
        "train_last30k": R.ci_summary(
            R.per_seed_success_after(ep, max(0, total_steps - LAST_STEPS))),
        "greedy_end": R.ci_summary(m["eval_success"][:, -1]),
        "goals_end": float(np.mean(m["n_goals"][:, -1])),
        "analysed": float(per_seed("analysed")) if host else 0.0,
        "splits": float(per_seed("splits")) if host else 0.0,
        "reaches": float(per_seed("reaches")) if host else 0.0,
        "no_reach": float(per_seed("no_reach")) if host else 0.0,
        "episodes_min": int(min(n_episodes)),
        "wall_s": round(result.wall_time_s, 1),
        "host_s": round(result.host_time_s, 1),
    }


def _fmt(s: dict) -> str:
    return "-" if s["mean"] is None else f"{s['mean']:.2f} ± {s['ci95']:.2f}"


def table(rows: dict) -> str:
    """A markdown table of the summarised variants."""
    lines = ["| variant | training, episodes 300-399 | training, last 30k steps | greedy, end "
             "| goals | analyses | splits |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, r in rows.items():
        s = r["summary"]
        lines.append(f"| `{name}` | {_fmt(s['train_ep300_400'])} | {_fmt(s['train_last30k'])} | "
                     f"{_fmt(s['greedy_end'])} | {s['goals_end']:.1f} | {s['analysed']:.1f} | "
                     f"{s['splits']:.1f} |")
    return "\n".join(lines)


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.gara_ablation",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=20, help="seeds per variant (0..n-1)")
    p.add_argument("--steps", type=int, default=120_000, help="environment steps per seed")
    p.add_argument("--variants", default="all", help="comma-separated names, or 'all'")
    p.add_argument("--out", default="results/gara_ablation.json", help="JSON file")
    p.add_argument("--rerun", action="store_true", help="run variants already in --out again")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--list", action="store_true", help="list the variants and exit")
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error("--seeds: must be >= 1")
    if args.steps < 1:
        p.error("--steps: must be >= 1")
    return args


def main(argv=None) -> int:
    import json

    args = parse_args(argv)
    variants = _variants()
    if args.list:
        for name, (desc, _) in variants.items():
            print(f"{name:28s} {desc}")
        return 0
    names = list(variants) if args.variants == "all" else [
        v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [n for n in names if n not in variants]
    if unknown:
        print(f"error: --variants: unknown {unknown}; see --list", file=sys.stderr)
        return 2

    from gara_jax.results import write_json
    from gara_jax.train import train_many

    out = Path(args.out)
    done = json.loads(out.read_text()) if out.exists() else {}
    rows = done.get("variants", {})
    for name in names:
        old = rows.get(name)
        if old and not args.rerun and old["seeds"] == args.seeds and old["steps"] == args.steps:
            continue
        desc, config = variants[name]
        bar = None
        if not args.no_progress:
            from tqdm.auto import tqdm

            bar = tqdm(desc=f"{name:>26}", unit="epoch", leave=False)

        def progress(done_epochs, n_epochs, metrics, bar=bar):
            if bar is not None:
                bar.total = n_epochs
                bar.n = done_epochs
                bar.set_postfix(goals=f"{np.mean(metrics['n_goals']):.1f}",
                                train=f"{np.mean(metrics['train_success']):.2f}",
                                greedy=f"{np.mean(metrics['eval_success']):.2f}")
                bar.refresh()

        t0 = time.perf_counter()
        result = train_many(config, args.seeds, args.steps, progress=progress)
        if bar is not None:
            bar.close()
        summary = summarize_run(result, args.steps)
        rows[name] = dict(description=desc, seeds=args.seeds, steps=args.steps,
                          config=dataclasses.asdict(config), summary=summary,
                          curves=dict(
                              env_steps=result.metrics["env_steps"][0].tolist(),
                              greedy=result.metrics["eval_success"].mean(0).tolist(),
                              train=result.metrics["train_success"].mean(0).tolist(),
                              goals=result.metrics["n_goals"].mean(0).tolist()))
        write_json(out, dict(variants=rows))
        print(f"{name}: {summary} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(table({n: rows[n] for n in names if n in rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
