"""GARA ablation on the U-maze: the reference preset, one mechanism changed at a time.

Every variant is a named config (the list :data:`VARIANTS` below); each runs all its seeds in
one process through :func:`gara_jax.train.train_many` and is summarised by

- ``train_ep300_400``: success of the training episodes 300-399 (exploration on; the last
  quarter of the reference's 400-episode run), per seed, then the mean and 95% t-interval;
- ``train_last30k``: success of the training episodes that ended in the last 30,000 steps;
- ``greedy_end``: greedy evaluation success after the last epoch (``eval_episodes`` episodes
  per seed from the start, both levels greedy);
- ``greedy_last10``: the same evaluation averaged over the last ``LAST_EVALS`` epochs per seed
  (a less noisy view of the same greedy policy: one snapshot of a DQN trained at lr 0.01
  varies from epoch to epoch);
- ``goals_end``, ``analysed``, ``splits`` (per seed, mean), and the wall time;
- ``per_seed``: the per-seed values of the three success measures (for paired comparisons).

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
LAST_EVALS = 10
EPISODE_WINDOW = (300, 400)


def _variants():
    """``name -> (description, config[, source])``: the ablation, built lazily (imports JAX).

    A third item names the variant whose final partitions (same seeds) the variant starts
    from (``initial_partitions`` of :func:`gara_jax.train.train_many`); that variant runs
    first if ``--out`` does not hold it for the same seeds and steps."""
    from gara_jax.agents.dqn import DQNConfig
    from gara_jax.agents.high_level import HighLevelConfig
    from gara_jax.algorithms import GaraConfig, HandcraftedConfig
    from gara_jax.algorithms.gara import LOW_REFERENCE

    # ``ours``: the default this U-maze study measured, GaraConfig() before the mazes study
    # (docs/mazes.md) moved the analysis to x, y (split_dims=(0, 1), "default+position_splits").
    # The rows were measured before the presets took zonotope bounds (refine_method
    # "zonotope_box") and before the default took min_volume_ratio 0.25: both are pinned to
    # what was measured, CROWN and 0.05 (the ``+zonotope_box`` rows are today's presets).
    ref = GaraConfig.reference(refine_method="crown")
    ours = GaraConfig(split_dims=None, min_volume_ratio=0.05)
    rep = lambda cfg, **kw: dataclasses.replace(cfg, **kw)
    high = lambda cfg, **kw: dataclasses.replace(cfg, high=dataclasses.replace(cfg.high, **kw))
    low = lambda cfg, **kw: dataclasses.replace(cfg, low=dataclasses.replace(cfg.low, **kw))
    fwd = lambda cfg, **kw: dataclasses.replace(
        cfg, forward=dataclasses.replace(cfg.forward, **kw))
    ours01, hc01 = rep(ours, low=LOW_REFERENCE), HandcraftedConfig(low=LOW_REFERENCE)
    previous = GaraConfig(
        split_dims=None, min_volume_ratio=0.05, memory="options", memory_capacity=10_000,
        forward_model="per_job", tau1=0.7, tau2=0.1, small_box_c1=None,
        split_epsilon_boost=1.0, relabel_replay=False, q_columns="copy", skip_unreachable=True,
        entry_reward="constant", goal_membership="box", reached_at_start=False,
        stall_penalty=None,
        low=DQNConfig(loss="all_actions", buffer_size=10_000, target_update_every=200),
        high=HighLevelConfig(epsilon_decrement=0.005, tie_break="random"))
    # The mechanism rows were measured on min_steps 1,000, the other value SPEC.md leaves
    # open; the preset takes 5,000 (`results_min_steps_5000`), which reproduces the files.
    res = GaraConfig.reference(version="results", min_steps=1000, refine_method="crown")
    return {
        # The results version (SPEC.md 3.9), with each of its 3.9 mechanisms reverted in turn.
        "results": ("GaraConfig.reference(version='results', min_steps=1000, "
                    "refine_method='crown'): the version that made the authors' result files "
                    "(SPEC.md 3.9), with min_steps 1,000 and CROWN bounds", res),
        "results-coverage_final": ("the final coverage rule: an empty intersection in any "
                                   "dimension gives c1 = c2 = 0 (3.6)",
                                   rep(res, coverage="final")),
        "results-epoch_cadence": ("trigger, forward model and analysis after every 3,000-step "
                                  "epoch, not after every episode",
                                  rep(res, cadence="epoch")),
        "results-memory_counts": ("pair counts recomputed from the memory each host step, not "
                                  "cumulative (so no relabel inflation either)",
                                  rep(res, pair_counts="memory", relabel_counts="none")),
        "results-no_count_inflation": ("the final version's relabel count move (-1 then +1), "
                                       "not +1", rep(res, relabel_counts="move")),
        "results-q_update_written_entry": ("the Q update's difference against the written "
                                           "(reached) entry, not the chosen target's",
                                           high(res, q_update="written_entry")),
        "results-q_rows_copied": ("Q rows copied at a split, not aliased",
                                  rep(res, q_rows_after_split="copied")),
        "results-300_step_episodes": ("episodes of at most 300 steps (the environment's "
                                      "limit), not 302", rep(res, max_episode_steps=None)),
        "results_min_steps_5000": ("the results version with min_steps 5,000 (SPEC.md leaves "
                                   "it open: 1,000 or 5,000) and CROWN bounds (the preset "
                                   "until it took zonotopes)", rep(res, min_steps=5000)),
        "results_min_steps_5000+merge_siblings": (
            "the same, and an analysis merges only same-verdict sibling halves, not adjacent "
            "boxes (merge='siblings'; SPEC.md 3.9.1: the files hold adjacent unmerged boxes)",
            rep(res, min_steps=5000, merge="siblings")),
        "results_min_steps_5000+ibp": (
            "the same with IBP bounds, not CROWN: looser output boxes, as the authors' Ai2 "
            "zonotopes are looser than CROWN (SPEC.md 3.6), so more boxes stay undecided and "
            "are bisected (refine_method='ibp')", rep(res, min_steps=5000, refine_method="ibp")),
        "results_min_steps_5000+ibp_planning_from_q": (
            "Planning with IBP bounds, each seed started from the same seed's final "
            "`results_min_steps_5000+ibp` partition",
            rep(res, planning=True, min_steps=5000, refine_method="ibp"),
            "results_min_steps_5000+ibp"),
        "results_min_steps_5000+zonotope": (
            "the same with zonotope bounds, not CROWN: the authors' kind of analysis (Ai2 "
            "zonotopes, SPEC.md 3.6; DeepZ's ReLU transformer, refine_method='zonotope')",
            rep(res, min_steps=5000, refine_method="zonotope")),
        "results_min_steps_5000+zonotope_planning_from_q": (
            "Planning with zonotope bounds, each seed started from the same seed's final "
            "`results_min_steps_5000+zonotope` partition",
            rep(res, planning=True, min_steps=5000, refine_method="zonotope"),
            "results_min_steps_5000+zonotope"),
        "results_min_steps_5000+zonotope_box": (
            "GaraConfig.reference(version='results'): the same with zonotopes whose unstable "
            "ReLUs are replaced by their interval [0, u] (our model of Ai2's ReLU, SPEC.md 3.6; "
            "refine_method='zonotope_box')",
            rep(res, min_steps=5000, refine_method="zonotope_box")),
        "results_min_steps_5000+zonotope_box_planning_from_q": (
            "Planning with those bounds, each seed started from the same seed's final "
            "`results_min_steps_5000+zonotope_box` partition",
            rep(res, planning=True, min_steps=5000, refine_method="zonotope_box"),
            "results_min_steps_5000+zonotope_box"),
        "results_min_steps_5000+zonotope_box+collision_final": (
            "GaraConfig.reference(version='results') in the maze with the authors' final "
            "collision rules (collision='final'; SPEC.md 1: the files were made under the "
            "reference rules, the other value of that unknown)",
            rep(res, min_steps=5000, refine_method="zonotope_box", collision="final")),
        "results_min_steps_5000+zonotope_box+collision_final_planning_from_q": (
            "Planning under the final collision rules, each seed started from the same seed's "
            "final `results_min_steps_5000+zonotope_box+collision_final` partition",
            rep(res, planning=True, min_steps=5000, refine_method="zonotope_box",
                collision="final"),
            "results_min_steps_5000+zonotope_box+collision_final"),
        "results_min_steps_5000-coverage_final": (
            "the same with the final coverage rule (an empty intersection in any dimension "
            "gives c1 = c2 = 0)", rep(res, min_steps=5000, coverage="final")),
        "results_planning_from_q": ("the results version's Planning, each seed started from "
                                    "the same seed's final `results` partition (the authors' "
                                    "runs, SPEC.md 3.9.3)", rep(res, planning=True), "results"),
        "results_min_steps_5000_planning_from_q": (
            "the results version's Planning with min_steps 5,000, each seed started from the "
            "same seed's final `results_min_steps_5000` partition",
            rep(res, planning=True, min_steps=5000), "results_min_steps_5000"),
        "results_planning": ("the results version's Planning from the two initial goals "
                             "(Planning-from-Q reverted)", rep(res, planning=True)),
        "previous_default": ("GaraConfig() before SPEC revision 2 (session 4)", previous),
        "reference": ("GaraConfig.reference(refine_method='crown'): the authors' final maze "
                      "version with CROWN bounds (the preset until it took zonotopes)", ref),
        # The reference with one of its mechanisms reverted.
        "ref-options_memory": ("memory of whole options (+ hindsight copies), not windows "
                               "(counts from the memory)",
                               rep(ref, memory="options", pair_counts="memory",
                                   relabel_counts="none")),
        "ref-per_job_model": ("a fresh forward model per analysis, fitted until stable",
                              rep(ref, forward_model="per_job")),
        "ref-thresholds_rev1": ("tau1 0.7, tau2 0.1, small boxes never reach (revision 1)",
                                rep(ref, tau1=0.7, tau2=0.1, small_box_c1=None)),
        "ref-epoch_cadence": ("trigger, forward model and analysis after every 3,000-step "
                              "epoch, not after every episode", rep(ref, cadence="epoch")),
        "ref-no_eps_boost": ("no x1.5 epsilon boost after a split",
                             rep(ref, split_epsilon_boost=1.0)),
        "ref-no_relabel": ("no hindsight relabelling of the low-level replay",
                           rep(ref, relabel_replay=False)),
        "ref-eps_0.005": ("high-level epsilon decrement 0.005 (results version)",
                          high(ref, epsilon_decrement=0.005)),
        "ref-replay_10k_target_200": ("low-level replay 10,000, target copy every 200 steps",
                                      low(ref, buffer_size=10_000, target_update_every=200)),
        "ref-q_columns_copy": ("every piece gets the split goal's Q column",
                               rep(ref, q_columns="copy")),
        "ref-skip_unreachable": ("pairs marked unreachable are not analysed again",
                                 rep(ref, skip_unreachable=True)),
        "ref-constant_entry": ("entry reward 1, not previous + 1",
                               rep(ref, entry_reward="constant")),
        "ref-random_ties": ("greedy high-level ties broken at random",
                            high(ref, tie_break="random")),
        # Changes of ours (point 4 of the GARA issue), each on the reference.
        "ref+partition_membership": ("inside the target = belongs to it (first-box rule)",
                                     rep(ref, goal_membership="partition")),
        "ref+reached_at_start": ("an option starting inside its target earns no entry reward",
                                 rep(ref, reached_at_start=True)),
        "ref+stall_penalty": ("intrinsic reward -1 for a step after which nothing moved",
                              rep(ref, stall_penalty=-1.0)),
        "ref+self_target_exit": ("the current goal is a target only where it holds the exit",
                                 rep(ref, self_target="exit_goal")),
        "ref+q_zero": ("every piece's Q column reset to 0 after a split",
                       rep(ref, q_columns="zero")),
        "ref+q_both": ("high-level update of the reached and the targeted entry",
                       high(ref, q_target_entry="both")),
        "ref+penalty_0.01": ("outside penalty -0.01, not -0.1", rep(ref, outside_penalty=-0.01)),
        "ref+min_steps_1000": ("pairs analysed after 1,000 counts, not 5,000",
                               rep(ref, min_steps=1000)),
        "ref+target_200": ("low-level target network copied every 200 steps",
                           low(ref, target_update_every=200)),
        "ref+low_lr_0.001": ("low-level Adam step size 0.001, not 0.01",
                             low(ref, learning_rate=0.001)),
        # This project's default, and each of its differences from the reference reverted.
        "default": ("GaraConfig(split_dims=None, min_volume_ratio=0.05): this project's "
                    "default of the U-maze study (every dimension split)", ours),
        "default+position_splits": ("the analysis bisects along x, y only (split_dims=(0, 1)): "
                                    "GaraConfig() from the mazes study until it took "
                                    "min_volume_ratio 0.25",
                                    rep(ours, split_dims=(0, 1))),
        "default-partition_membership": ("closed-box membership (the reference)",
                                         rep(ours, goal_membership="box")),
        "default-reached_at_start": ("entry reward also for options starting inside",
                                     rep(ours, reached_at_start=False)),
        "default-stall_penalty": ("no stall penalty", rep(ours, stall_penalty=None)),
        "default-random_ties": ("lowest-index greedy ties (the reference)",
                                high(ours, tie_break="lowest")),
        "default+relabel": ("with the reference's replay relabelling",
                            rep(ours, relabel_replay=True)),
        "default-refinement": ("diagnostic, not GARA: the default that never analyses (its "
                               "two initial goals throughout)", rep(ours, min_steps=10**9)),
        "default+piece_order_parent": ("pieces of a split take its place in the first-box "
                                       "order", rep(ours, piece_order="parent")),
        "default+initial_split_1.5": ("initial partition split at the wall's far face x = 1.5",
                                      rep(ours, initial_split_x=1.5)),
        "default+per_job_model": ("a fresh forward model per analysis, fitted until stable",
                                  rep(ours, forward_model="per_job")),
        "default_planning": ("GaraConfig(planning=True)", rep(ours, planning=True)),
        # The previous default (the reference's low-level step size 0.01) and what was tried
        # on it; its first rows are its own differences from the reference reverted.
        "default_lr0.01": ("GaraConfig() with the reference's low-level step size 0.01 (the "
                           "previous default)", ours01),
        "default_lr0.01-partition_membership": ("closed-box membership (the reference)",
                                                rep(ours01, goal_membership="box")),
        "default_lr0.01-reached_at_start": ("entry reward also for options starting inside",
                                            rep(ours01, reached_at_start=False)),
        "default_lr0.01-stall_penalty": ("no stall penalty", rep(ours01, stall_penalty=None)),
        "default_lr0.01-random_ties": ("lowest-index greedy ties (the reference)",
                                       high(ours01, tie_break="lowest")),
        "default_lr0.01+relabel": ("with the reference's replay relabelling",
                                   rep(ours01, relabel_replay=True)),
        "default_lr0.01+loop_penalty": ("the stall penalty also for returning to the option's "
                                        "start", rep(ours01, stall_includes_loops=True)),
        "default_lr0.01+per_job_model": ("a fresh forward model per analysis, fitted until "
                                         "stable", rep(ours01, forward_model="per_job")),
        "default_lr0.01+shared_steps_32": ("32 gradient steps per update of the shared forward "
                                           "model", fwd(ours01, shared_steps=32)),
        "default_lr0.01+piece_order_parent": ("pieces of a split take its place in the "
                                              "first-box order",
                                              rep(ours01, piece_order="parent")),
        "default_lr0.01+initial_split_1.5": ("initial partition split at the wall's far face "
                                             "x = 1.5", rep(ours01, initial_split_x=1.5)),
        "default_lr0.01+q_both": ("high-level update of the reached and the targeted entry",
                                  high(ours01, q_target_entry="both")),
        "default_lr0.01+high_gamma_0.9": ("high-level discount 0.9 per option, not 0.99",
                                          high(ours01, gamma=0.9)),
        "default_lr0.01+avoid_stalled": ("the low level never repeats an action that just left "
                                         "the state unchanged",
                                         rep(ours01, avoid_stalled_action=True)),
        "default_lr0.01+avoid_repeated": ("the high level never re-chooses a target at a state "
                                          "where it chose it in this episode",
                                          rep(ours01, avoid_repeated_decisions=True)),
        "default_lr0.01+target_200": ("low-level target network copied every 200 steps, not 20",
                                      low(ours01, target_update_every=200)),
        "default_lr0.01-refinement": ("diagnostic, not GARA: never analyses (its two initial "
                                      "goals throughout)", rep(ours01, min_steps=10**9)),
        "default_lr0.01_planning": ("GaraConfig(planning=True) with step size 0.01",
                                    rep(ours01, planning=True)),
        "reference_planning": ("GaraConfig.reference(planning=True)",
                               GaraConfig.reference(planning=True)),
        "handcrafted": ("HandcraftedConfig()", HandcraftedConfig()),
        "handcrafted_lr0.01": ("HandcraftedConfig() with the reference's low-level step size "
                               "0.01 (the previous default)", hc01),
        "handcrafted_lr0.01+avoid_stalled": (
            "the previous HandcraftedConfig() with the low-level stall guard",
            rep(hc01, avoid_stalled_action=True)),
        "handcrafted_reference": ("HandcraftedConfig.reference()", HandcraftedConfig.reference()),
        "handcrafted_previous": ("HandcraftedConfig() before SPEC revision 2 (session 4)",
                                 HandcraftedConfig(low=previous.low, high=previous.high,
                                                   goal_membership="box", reached_at_start=False,
                                                   stall_penalty=None)),
        "handcrafted-gara_changes": (
            "HandcraftedConfig() without the agent-level changes it shares with GARA's default "
            "(random greedy ties kept)",
            HandcraftedConfig(goal_membership="box", reached_at_start=False,
                              stall_penalty=None, low=LOW_REFERENCE)),
    }


GREEDY_OUTCOMES = ("success", "stall", "self_target_loop", "loop", "other")


def classify_episode(obs, goal, target, deciding, live, success) -> str:
    """One of :data:`GREEDY_OUTCOMES` for a greedy episode's per-step records.

    A failed episode whose state at two decision points is exactly the same is caught in a
    deterministic loop (ties aside): a ``stall`` if the state did not change at all over the
    option, a ``self_target_loop`` if every decision of the loop chose the goal the agent was
    in, else a ``loop``; ``other`` otherwise (it kept moving).

    Example:
        >>> import numpy as np
        >>> obs = np.zeros((6, 2)); on = np.ones(6, bool)
        >>> classify_episode(obs, np.zeros(6), np.ones(6), on, on, False)
        'stall'
    """
    if success:
        return "success"
    steps = np.flatnonzero(np.asarray(deciding) & np.asarray(live))
    points = np.asarray(obs)[steps]
    seen = {}
    for j, row in enumerate(map(tuple, points)):
        if row in seen:
            first = seen[row]
            if j - first == 1 and np.all(np.asarray(obs)[steps[first]: steps[j] + 1] == points[j]):
                return "stall"
            if all(goal[steps[m]] == target[steps[m]] for m in range(first, j)):
                return "self_target_loop"
            return "loop"
        seen[row] = j
    return "other"


def greedy_outcomes(result) -> dict:
    """How each seed's final greedy episode ends: counts of :data:`GREEDY_OUTCOMES`.

    One episode per seed from the final states (``Algorithm.greedy_rollout``, the policy the
    greedy evaluation runs), classified by :func:`classify_episode`.
    """
    import jax

    from gara_jax.train import compiled

    alg = compiled(result.config).alg
    if alg.greedy_rollout is None:
        return {}
    keys = jax.random.split(jax.random.key(12345), len(result.seeds))
    rec = jax.device_get(jax.jit(jax.vmap(alg.greedy_rollout))(result.final.states, keys))
    counts = dict.fromkeys(GREEDY_OUTCOMES, 0)
    for i in range(len(result.seeds)):
        counts[classify_episode(rec["obs"][i], rec["goal"][i], rec["target"][i],
                                rec["deciding"][i], rec["live"][i], rec["success"][i])] += 1
    return counts


def summarize_run(result, total_steps: int) -> dict:
    """The ablation's numbers for one :class:`~gara_jax.train.TrainResult`."""
    from gara_jax import results as R

    m = result.metrics
    ep = result.episodes
    host = [h for h in result.host_info if h]
    per_seed = lambda key: np.sum([np.asarray(h.get(key, 0)) for h in host]) / len(result.seeds)
    n_episodes = [len(s) for s in ep["success"]]
    last30k = R.per_seed_success_after(ep, max(0, total_steps - LAST_STEPS))
    greedy_last = np.mean(m["eval_success"][:, -LAST_EVALS:], axis=1)
    return {
        "train_ep300_400": R.ci_summary(R.per_seed_episode_success(ep, *EPISODE_WINDOW)),
        "train_last30k": R.ci_summary(last30k),
        "greedy_end": R.ci_summary(m["eval_success"][:, -1]),
        "greedy_last10": R.ci_summary(greedy_last),
        # Per seed, in seed order, for paired comparisons between variants.
        "per_seed": {"train_ep300_400": np.round(np.asarray(
                         R.per_seed_episode_success(ep, *EPISODE_WINDOW), float), 4).tolist(),
                     "train_last30k": np.round(np.asarray(last30k, float), 4).tolist(),
                     "goals_end": m["n_goals"][:, -1].astype(int).tolist(),
                     "greedy_end": np.round(m["eval_success"][:, -1].astype(float), 4).tolist(),
                     "greedy_last10": np.round(greedy_last.astype(float), 4).tolist()},
        "goals_end": float(np.mean(m["n_goals"][:, -1])),
        "analysed": float(per_seed("analysed")) if host else 0.0,
        "splits": float(per_seed("splits")) if host else 0.0,
        "reaches": float(per_seed("reaches")) if host else 0.0,
        "no_reach": float(per_seed("no_reach")) if host else 0.0,
        "exit_analysed": float(per_seed("exit_analysed")) if host else 0.0,
        "exit_splits": float(per_seed("exit_splits")) if host else 0.0,
        "start_skips": float(per_seed("start_skips")) if host else 0.0,
        "episodes_min": int(min(n_episodes)),
        "greedy_outcomes": greedy_outcomes(result),
        "wall_s": round(result.wall_time_s, 1),
        "host_s": round(result.host_time_s, 1),
    }


def with_sources(names, variants) -> list:
    """``names`` with each variant's source (the variant whose final partitions it starts
    from) placed before it, once.

    Example:
        >>> with_sources(["b", "a"], {"a": ("", None), "b": ("", None, "a")})
        ['a', 'b']
    """
    ordered = []
    for name in names:
        source = _source(variants[name])
        if source is not None and source not in ordered:
            ordered.append(source)
        if name not in ordered:
            ordered.append(name)
    return ordered


def _source(variant) -> str | None:
    """The variant whose final partitions ``variant`` starts from, or ``None``."""
    return variant[2] if len(variant) > 2 else None


def _final_boxes(result) -> list | None:
    """Each seed's final partition as ``[lo, hi]`` lists (GARA), what a variant started from
    it takes; ``None`` for an algorithm without a partition to refine."""
    from gara_jax.algorithms import GaraConfig
    from gara_jax.train import final_partitions

    if not isinstance(result.config, GaraConfig):
        return None
    return [[np.asarray(b).tolist() for b in p.boxes()] for p in final_partitions(result)]


def _fmt(s: dict) -> str:
    return "-" if s["mean"] is None else f"{s['mean']:.2f} ± {s['ci95']:.2f}"


def _last_evals(row: dict) -> str:
    """``greedy_last10`` with its interval; for rows stored before it existed, the mean alone
    from the seed-mean greedy curve (the same number, without the per-seed spread)."""
    if "greedy_last10" in row["summary"]:
        return _fmt(row["summary"]["greedy_last10"])
    return f"{np.mean(row['curves']['greedy'][-LAST_EVALS:]):.2f}"


def table(rows: dict) -> str:
    """A markdown table of the summarised variants."""
    lines = ["| variant | training, episodes 300-399 | training, last 30k steps | greedy, end "
             f"| greedy, last {LAST_EVALS} evals "
             "| greedy fails: stall / self-target loop / loop / other | goals | analyses "
             "| splits |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in rows.items():
        s = r["summary"]
        o = s.get("greedy_outcomes") or {}
        fails = " / ".join(str(o.get(k, "-")) for k in GREEDY_OUTCOMES[1:])
        lines.append(f"| `{name}` | {_fmt(s['train_ep300_400'])} | {_fmt(s['train_last30k'])} | "
                     f"{_fmt(s['greedy_end'])} | {_last_evals(r)} | {fails} | "
                     f"{s['goals_end']:.1f} | {s['analysed']:.1f} | {s['splits']:.1f} |")
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
    from gara_jax import compile_cache

    compile_cache.add_argument(p)
    args = p.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
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
        for name, (desc, *_) in variants.items():
            print(f"{name:30s} {desc}")
        return 0
    names = list(variants) if args.variants == "all" else [
        v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [n for n in names if n not in variants]
    if unknown:
        print(f"error: --variants: unknown {unknown}; see --list", file=sys.stderr)
        return 2
    names = with_sources(names, variants)

    from gara_jax.results import write_json
    from gara_jax.train import train_many

    out = Path(args.out)
    done = json.loads(out.read_text()) if out.exists() else {}
    rows = done.get("variants", {})
    for name in names:
        old = rows.get(name)
        sources = {_source(variants[n]) for n in names}
        if (old and not args.rerun and old["seeds"] == args.seeds and old["steps"] == args.steps
                and (name not in sources or old.get("final_partitions"))):
            continue
        desc, config = variants[name][:2]
        source = _source(variants[name])
        initial = None
        if source is not None:
            initial = [(np.asarray(lo), np.asarray(hi))
                       for lo, hi in rows[source]["final_partitions"]]
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
        result = train_many(config, args.seeds, args.steps, progress=progress,
                            initial_partitions=initial)
        if bar is not None:
            bar.close()
        summary = summarize_run(result, args.steps)
        rows[name] = dict(description=desc, seeds=args.seeds, steps=args.steps,
                          config=dataclasses.asdict(config), summary=summary,
                          starts_from=source, final_partitions=_final_boxes(result),
                          curves=dict(
                              env_steps=result.metrics["env_steps"][0].tolist(),
                              greedy=result.metrics["eval_success"].mean(0).tolist(),
                              train=result.metrics["train_success"].mean(0).tolist(),
                              goals=result.metrics["n_goals"].mean(0).tolist()))
        # Re-read before writing, so that several processes can share one --out file.
        on_disk = json.loads(out.read_text())["variants"] if out.exists() else {}
        on_disk[name] = rows[name]
        rows.update(on_disk)
        write_json(out, dict(variants=on_disk))
        print(f"{name}: {summary} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(table({n: rows[n] for n in names if n in rows}))
    against = authors_rows({n: rows[n] for n in names if n in rows})
    if against:
        from experiments.u_maze import authors_table

        print("\n" + authors_table(against))
    return 0


def authors_rows(rows: dict) -> dict:
    """The results preset's variants (``results...`` rows on the U-maze) against the authors'
    own runs of the same high level (``experiments.u_maze.against_authors``)."""
    from experiments.u_maze import against_authors

    out = {}
    for name, r in rows.items():
        if not name.startswith("results") or r["config"].get("env") != "u_maze":
            continue
        method = ("gara_reference_results_planning" if r["config"].get("planning")
                  else "gara_reference_results")
        ps = r["summary"]["per_seed"]
        out[name] = against_authors(method, ps["train_ep300_400"], ps["goals_end"])
    return out


if __name__ == "__main__":
    sys.exit(main())
