"""GARA across the mazes: every layout of SPEC.md, five methods, both success measures.

For each maze of :data:`MAZES` and each method of :data:`METHODS` (20 seeds by default, all of
a method in one process through :func:`gara_jax.train.train_many`):

- ``gara``: ``GaraConfig()``, this project's default GARA (Q-learning high level; its
  analysis splits along ``x, y`` only, ``split_dims=(0, 1)``, which this study chose);
- ``gara_no_refinement``: the same agent with the analysis never run (``min_steps=10**9``;
  the ablation's ``default-refinement``): its initial goals throughout. Not GARA; it measures
  what the learned abstraction adds;
- ``handcrafted``: ``HandcraftedConfig()`` on the authors' partition of the layout (SPEC.md 2.1);
- ``hiro``: ``HiroConfig()``, HIRO as published;
- ``hiro_paper``: ``HiroConfig.paper()``, the HIRO baseline the paper ran.

``--methods`` also takes the GARA variants of :data:`VARIANTS` (the refinement study: one
mechanism of ``GaraConfig()`` changed each).

Every method of a maze gets the same step budget, :data:`experiments.u_maze.ENV_STEPS` (set
from what Handcrafted needs on that maze; ``docs/mazes.md`` says how). Each run is summarised
as in :mod:`experiments.gara_ablation` (training success over episodes 300-399 and over the
last 30,000 steps, greedy success at the end and over the last 10 evaluations, goals,
analyses, splits, each with a 95% t-interval over seeds), and GARA is compared with its
refinement-off variant seed by seed (``paired``: the mean difference and its interval).

Writes to ``--out`` (default ``results/mazes``):

- ``mazes.json``: every run's summary, per-seed values, seed-mean curves and final partitions,
  rewritten after each run; a run already there with the same seeds, steps and config is not
  run again (``--rerun`` runs it again), so an interrupted study continues where it stopped;
- ``table.md``: the markdown table (also printed);
- ``mazes_success.png``: a row per maze: training success by steps, greedy success by steps
  (seed means with 95% bands);
- ``mazes_partitions.png``: GARA's final partition on each maze, of the seed that
  :func:`experiments.u_maze.partition_seed` picks (the successful seed with the median final
  goal count).

Usage::

    python -m experiments.mazes                           # everything, 20 seeds each
    python -m experiments.mazes --mazes u_maze,four_rooms --methods gara,gara_no_refinement
    python -m experiments.mazes --quick                   # 2 seeds, 3,000 steps: a first look
    python -m experiments.mazes --dry-run                 # the plan; nothing trained
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

MAZES = ("u_maze", "four_rooms", "u_maze_6", "big_u_maze", "labyrinth")
METHODS = ("gara", "gara_no_refinement", "handcrafted", "hiro", "hiro_paper")
# What the three no-filler variants (GARA, refinement off, Handcrafted) change.
_NO_FILLER = ("the filler box [0,6]x[3,6] (added to the authors' partition to make it a tiling; "
              "over the wall and the strip behind it) is never a target, so the high level "
              "chooses among the authors' goals (non_targets='layout'; changes big_u_maze only)",
              {"non_targets": "layout"})
# The authors' final collision rules (SPEC.md 1) for every method: under the reference rules
# big_u_maze has two absorbing corners, (4, 3) and (4.5, 3), where every action leaves the
# state unchanged until the episode times out (envs.absorbing_states); the final rules let an
# agent leave a face it only touches.
_FINAL_RULES = ("the authors' final collision rules (collision='final', SPEC.md 1), under which "
                "big_u_maze's corners (4, 3) and (4.5, 3) are no longer absorbing; the same "
                "for every method", {"collision": "final"})
# What the two k = 10 variants (GARA, refinement off) change.
_K10 = ("the high level decides every 10 steps, not 5 (k=10; SPEC.md 3.1: 5), so each option, "
        "the forward model's horizon and the analysed hop are twice as long: a lead for bounds "
        "that a goal's whole velocity range widens, since over a longer option the low level's "
        "target, not the start velocity, decides where it ends", {"k": 10})
# What the two Planning variants (GARA, refinement off) change.
_PLANNING = ("the Planning high level (planning=True, the paper's other high level): a "
             "shortest path over the goal transitions seen to succeed, towards the goal where "
             "the exit reward was obtained, so a split goal's pieces are chained by the graph "
             "rather than learned as Q-values", {"planning": True})
# What the two self-target variants (GARA, refinement off) change.
_SELF_TARGET = ("the Q-learning high level chooses the goal the agent is in as its target only "
                "where that goal holds the exit state (self_target='exit_goal'): most greedy "
                "failures on big_u_maze are loops of options towards the goal the agent is in, "
                "for GARA and refinement off alike", {"self_target": "exit_goal"})
# The authors' Handcrafted partition of the maze as a GARA agent's initial goals: with
# refinement off this agent differs from Handcrafted only in GARA's entry reward, so it says
# how much of Handcrafted's lead over refinement off is its partition.
_HAND_BOXES = ("the agent starts from the authors' Handcrafted partition of the maze (SPEC.md "
               "2.1; initial_boxes) instead of GARA's initial one: with refinement off it "
               "differs from Handcrafted only in the entry reward (GARA's "
               "entry_reward='previous_plus_one', Handcrafted's 'constant')",
               {"initial_boxes": lambda maze: _layout_boxes(maze, "handcrafted")})


def _layout_boxes(maze: str, kind: str) -> tuple:
    from gara_jax import partition

    if (maze, kind) in partition.OVERLAPPING:  # GaraConfig's boxes must tile
        raise ValueError(f"maze: {maze!r}'s {kind} boxes overlap, and a GARA agent's initial "
                         "boxes must tile the space")
    return partition.boxes_as_tuples(*partition.layout_boxes(maze, kind))


def _gara_boxes_and_holder(maze: str, point: str):
    """GARA's initial boxes ``lo, hi`` of ``maze`` and the index of the first one holding the
    layout's ``point`` (``"start"`` or ``"exit"``) in ``x, y`` (closed boxes)."""
    from envs.layouts import layout_spec
    from gara_jax import partition

    lo, hi = partition.layout_boxes(maze, "gara")
    xy = np.asarray(layout_spec(maze)[point])
    return lo, hi, int(np.argmax((lo[:, :2] <= xy).all(1) & (xy <= hi[:, :2]).all(1)))


def handcrafted_cuts(maze: str, where: str) -> tuple:
    """GARA's initial boxes of ``maze`` with some of them cut along the authors' Handcrafted
    boxes (each replaced by its non-empty intersections with them, in Handcrafted's order):
    ``where="exit_goal"`` cuts only the box holding the exit (the first that holds it),
    ``"other_goals"`` every other box. Both together give the intersection of the two
    partitions (on ``u_maze`` that is Handcrafted's). Velocities are never cut, so a layout
    whose Handcrafted boxes split velocities or overlap (the labyrinth) is refused.

    Example:
        >>> lo, hi = handcrafted_cuts("u_maze", "other_goals")
        >>> [(a[0], b[0], a[1], b[1]) for a, b in zip(lo, hi)]
        [(0.0, 1.0, 0.0, 2.0), (0.0, 1.0, 2.0, 3.0), (1.0, 3.0, 0.0, 3.0)]
    """
    from gara_jax import partition

    if where not in ("exit_goal", "other_goals"):
        raise ValueError(f"where: must be 'exit_goal' or 'other_goals', got {where!r}")
    hand_lo, hand_hi = partition.layout_boxes(maze, "handcrafted")
    if (maze, "handcrafted") in partition.OVERLAPPING or len(hand_lo) != len(
            partition.LAYOUT_PARTITIONS[maze]["handcrafted"]):
        raise ValueError(f"maze: {maze!r}'s Handcrafted boxes overlap or split velocities; "
                         "handcrafted_cuts needs boxes over x, y only")
    lo, hi, exit_box = _gara_boxes_and_holder(maze, "exit")
    out_lo, out_hi = [], []
    for i in range(len(lo)):
        if (i == exit_box) != (where == "exit_goal"):
            out_lo.append(lo[i]); out_hi.append(hi[i])
            continue
        for h_lo, h_hi in zip(hand_lo, hand_hi):
            a, b = np.maximum(lo[i], h_lo), np.minimum(hi[i], h_hi)
            if (b > a).all():
                out_lo.append(a); out_hi.append(b)
    return partition.boxes_as_tuples(np.array(out_lo), np.array(out_hi))


def start_goal_halves(maze: str, dim: int = 1) -> tuple:
    """GARA's initial boxes of ``maze`` with the one holding the start bisected at its
    midpoint along ``dim`` (0: ``x``, 1: ``y``), lower half first: the cut an analysis of
    the start's goal makes with one bisection.

    Example:
        >>> lo, hi = start_goal_halves("u_maze")
        >>> [(a[0], b[0], a[1], b[1]) for a, b in zip(lo, hi)]
        [(0.0, 1.0, 0.0, 1.5), (0.0, 1.0, 1.5, 3.0), (1.0, 3.0, 0.0, 3.0)]
    """
    from gara_jax import partition

    lo, hi, i = _gara_boxes_and_holder(maze, "start")
    mid = (lo[i, dim] + hi[i, dim]) / 2
    low_hi, high_lo = hi[i].copy(), lo[i].copy()
    low_hi[dim] = high_lo[dim] = mid
    new_lo = np.concatenate([lo[:i], [lo[i], high_lo], lo[i + 1:]])
    new_hi = np.concatenate([hi[:i], [low_hi, hi[i]], hi[i + 1:]])
    return partition.boxes_as_tuples(new_lo, new_hi)


#: Variants for the refinement study, each a method of :data:`METHODS` (its *base*:
#: ``GaraConfig()`` unless a third entry names another) with what its name says changed
#: (``--methods NAME``; not in the default set): name -> (what it changes, the overrides[,
#: the base]). An override may be a function of the maze's name, called for its value.
VARIANTS = {
    # Measured on the default before it took min_volume_ratio 0.25: those rows keep the 0.05
    # of their runs ("fine_cuts"), so each differs from today's ``gara`` in what its name says.
    "gara+fine_cuts": ("an analysis bisects G_s down to 0.05 of its volume, up to 32 pieces "
                       "(the authors' rule; the default before min_volume_ratio 0.25)",
                       {"min_volume_ratio": 0.05}),
    "gara+fine_cuts+all_dims": ("fine cuts along every dimension, velocities too (the "
                                "authors' rule; the default before the mazes study: "
                                "split_dims=None)",
                                {"split_dims": None, "min_volume_ratio": 0.05}),
    "gara+fine_cuts+all_dims+target_margin": (
        "fine cuts along every dimension, and the coverage measured 10% inside G_d on every "
        "side, so a prediction on a wall face of G_d does not count as entering it "
        "(target_margin=0.1)", {"split_dims": None, "target_margin": 0.1,
                                "min_volume_ratio": 0.05}),
    "gara+all_dims+one_cut": ("every dimension, and an analysis bisects G_s at most once "
                              "(min_volume_ratio=0.5: two pieces at most)",
                              {"split_dims": None, "min_volume_ratio": 0.5}),
    "gara+one_cut": ("an analysis bisects G_s at most once, along x or y "
                     "(min_volume_ratio=0.5)", {"min_volume_ratio": 0.5}),
    "gara+fine_cuts+per_job_model": ("fine cuts, and a fresh forward model per analysis, "
                                     "fitted until its loss is stable "
                                     "(forward_model='per_job')",
                                     {"forward_model": "per_job", "min_volume_ratio": 0.05}),
    "gara+zonotope_box": ("the presets' bounds: zonotopes with an unstable ReLU replaced by "
                          "its interval, our model of the authors' Ai2 (SPEC.md 3.6; "
                          "refine_method='zonotope_box'), not CROWN",
                          {"refine_method": "zonotope_box"}),
    "gara+episode_cadence": ("the trigger, forward-model step and analysis after every "
                             "episode (cadence='episode')", {"cadence": "episode"}),
    "gara+fine_cuts+cumulative_counts": (
        "fine cuts, and pair counts kept per goal index, never recomputed from the memory, so "
        "a pair's count survives a split of the other goal (pair_counts='cumulative', the "
        "authors' counts)", {"pair_counts": "cumulative", "min_volume_ratio": 0.05}),
    # The three leads above measured again on today's default (two cuts, x and y).
    "gara+target_margin": ("the coverage measured 10% inside G_d on every side, so a "
                           "prediction on a wall face of G_d does not count as entering it "
                           "(target_margin=0.1)", {"target_margin": 0.1}),
    "gara+cumulative_counts": ("pair counts kept per goal index, never recomputed from the "
                               "memory, so a pair's count survives a split of the other goal "
                               "(pair_counts='cumulative', the authors' counts)",
                               {"pair_counts": "cumulative"}),
    "gara+per_job_model": ("a fresh forward model per analysis, fitted until its loss is "
                           "stable (forward_model='per_job')", {"forward_model": "per_job"}),
    "gara+exit_analysis": ("also analyse the goal holding the exit against a box around the "
                           "exit (exit_analysis=True: the one hop the partition does not "
                           "represent)", {"exit_analysis": True}),
    "gara+data_velocities": ("bound the forward model over the velocities the pair's own data "
                             "starts from, not G_s's whole velocity range "
                             "(input_range='data')", {"input_range": "data"}),
    "gara+exit_analysis+data_velocities": (
        "the exit analysis with its bounds over the velocities its data starts from (the "
        "exit analysis alone found no piece: its bounds over G_e's whole velocity range were "
        "wider than the exit box)", {"exit_analysis": True, "input_range": "data"}),
    "gara+exit_analysis+wide_exit": (
        "the exit analysis against a box of half G_e's width on each side of the exit "
        "(exit_radius=0.5, the largest allowed, as large as the smallest piece)",
        {"exit_analysis": True, "exit_radius": 0.5}),
    "gara+exit_analysis+data_velocities+per_job_model": (
        "the exit analysis over the data's velocities, each analysis with a fresh forward "
        "model fitted until its loss is stable (forward_model='per_job'): the shared model "
        "puts fewer of its predictions in the exit box than the data has there "
        "(experiments.exit_bounds)",
        {"exit_analysis": True, "input_range": "data", "forward_model": "per_job"}),
    "gara+position_model": (
        "a forward model that sees where an option starts, not how fast (model_inputs="
        "'split_dims': the velocities are 0 in its inputs and its bounds), so its bounds do "
        "not widen with a piece's velocity range", {"model_inputs": "split_dims"}),
    "gara+exit_analysis+position_model": (
        "the exit analysis with the position-only forward model (its bounds over G_e's "
        "velocities were wider than the maze: experiments.exit_bounds)",
        {"exit_analysis": True, "model_inputs": "split_dims"}),
    "gara+keep_start_goal": (
        "the goal holding the start is never split (keep_start_goal=True): on big_u_maze the "
        "position-only model's losses were in the seeds that cut the start's region",
        {"keep_start_goal": True}),
    "gara+keep_start_goal+min_steps_1000": (
        "the start's goal never split, and a pair analysed from 1,000 steps of experience "
        "instead of 5,000 (min_steps=1000, the authors' results-version script's value): "
        "the other goals' pairs (on big_u_maze the right-hand region's splits are the ones "
        "that helped gara) are analysed sooner and more often", {"keep_start_goal": True, "min_steps": 1000}),
    "gara+data_velocities+keep_start_goal": (
        "bounds over the data's velocities (more certified splits) and the start's goal "
        "never split", {"input_range": "data", "keep_start_goal": True}),
    "gara+position_model+keep_start_goal": (
        "the position-only forward model (its splits all cut the start's region on "
        "big_u_maze) and the start's goal never split",
        {"model_inputs": "split_dims", "keep_start_goal": True}),
    "gara+no_filler_goal": _NO_FILLER,
    "gara+no_filler_goal+keep_start_goal": (
        "the filler box never a target and the start's goal never split, so on big_u_maze "
        "only the right-hand region is refined", {**_NO_FILLER[1], "keep_start_goal": True}),
    "gara+self_target_exit": _SELF_TARGET,
    "gara_no_refinement+self_target_exit": (*_SELF_TARGET, "gara_no_refinement"),
    "gara+planning": _PLANNING,
    "gara_no_refinement+planning": (*_PLANNING, "gara_no_refinement"),
    "gara_no_refinement+no_filler_goal": (*_NO_FILLER, "gara_no_refinement"),
    "handcrafted+no_filler_goal": (*_NO_FILLER, "handcrafted"),
    "gara+final_rules": _FINAL_RULES,
    "gara_no_refinement+final_rules": (*_FINAL_RULES, "gara_no_refinement"),
    "handcrafted+final_rules": (*_FINAL_RULES, "handcrafted"),
    "gara_no_refinement+handcrafted_boxes": (*_HAND_BOXES, "gara_no_refinement"),
    "gara+handcrafted_boxes": _HAND_BOXES,
    "gara_no_refinement+hand_cut_exit_goal": (
        "refinement off from GARA's initial goals with the goal holding the exit cut along "
        "the authors' Handcrafted boxes (handcrafted_cuts(maze, 'exit_goal'))",
        {"initial_boxes": lambda maze: handcrafted_cuts(maze, "exit_goal")},
        "gara_no_refinement"),
    "gara_no_refinement+start_goal_halves_y": (
        "refinement off from GARA's initial goals with the start's goal bisected along y "
        "(start_goal_halves(maze)): the cut one bisection of the start's goal gives",
        {"initial_boxes": lambda maze: start_goal_halves(maze, 1)}, "gara_no_refinement"),
    "gara_no_refinement+hand_cut_other_goals": (
        "refinement off from GARA's initial goals with every goal but the exit's cut along "
        "the authors' Handcrafted boxes (handcrafted_cuts(maze, 'other_goals'))",
        {"initial_boxes": lambda maze: handcrafted_cuts(maze, "other_goals")},
        "gara_no_refinement"),
    "gara+parent_order": (
        "a split's pieces take the split goal's place in the first-box order "
        "(piece_order='parent'), so a face shared with another goal stays with the region "
        "that held it: with the reference's 'appended' order, once the U-mazes' start goal "
        "is split the wall face x = 1 passes to the right-hand goal, and pressing against "
        "the wall enters it again", {"piece_order": "parent"}),
    # Split costs, cut rules, clipped bounds (docs/mazes.md: "Cheaper splits", "Bounds clipped").
    "gara+no_split_boost": (
        "no epsilon boost after a split (split_epsilon_boost=1, the authors' results "
        "version; the default multiplies the high level's epsilon by 1.5)",
        {"split_epsilon_boost": 1.0}),
    "gara+split_exploration": (
        "after a split the high level's epsilon is multiplied by 30 (split_epsilon_boost=30: "
        "from its floor 0.01 to 0.3, back at the floor after 580 decisions), so that the "
        "pieces get tried as targets; the default's 1.5 lifts 0.01 to 0.015",
        {"split_epsilon_boost": 30.0}),
    "gara+separation_split": (
        "an undecided box is bisected where its halves' coverage differs most "
        "(split_rule='separation'), not along the largest smear (gradient bound times "
        "width, SPEC.md 3.6)", {"split_rule": "separation"}),
    "gara+space_clip": (
        "each bounded reachable box is intersected with the state space before its "
        "coverage is measured (reach_clip='space'; sound): bounds that overshoot the "
        "velocity limits or the maze no longer lower c1", {"reach_clip": "space"}),
    "gara+space_clip+separation_split": (
        "both: the bounds clipped to the state space, and a box bisected where its halves' "
        "coverage differs most (with clipped bounds c1 is no longer near 0 everywhere)",
        {"reach_clip": "space", "split_rule": "separation"}),
    "gara+x_cuts": (
        "an analysis bisects along x only (split_dims=(0,)): a test of the cut table, where "
        "x-only cuts went with the best results on big_u_maze and four_rooms",
        {"split_dims": (0,)}),
    "gara+copy_columns": (
        "every piece of a split goal inherits its Q column as a target (q_columns='copy'; "
        "the default: only the first reaching piece keeps it, the others start at 0)",
        {"q_columns": "copy"}),
    "gara+kept_q_rows": (
        "no Q entry is zeroed at a split (q_rows_after_split='kept'): a piece found not to "
        "reach G_d within one option keeps G_s's value for targeting G_d, which the low "
        "level goes on pursuing over the next decisions",
        {"q_rows_after_split": "kept"}),
    "gara+space_clip+kept_q_rows": (
        "the bounds clipped to the state space (reach_clip='space', which makes the analysis "
        "cut the start's goal in most seeds) and no Q entry zeroed at a split "
        "(q_rows_after_split='kept', which removes what those cuts cost)",
        {"reach_clip": "space", "q_rows_after_split": "kept"}),
    "gara+k10": _K10,
    "gara_no_refinement+k10": (*_K10, "gara_no_refinement"),
    "gara+kept_q_rows+copy_columns": (
        "a split the high level does not see: every piece inherits G_s's Q row and column "
        "and nothing is zeroed (q_rows_after_split='kept', q_columns='copy')",
        {"q_rows_after_split": "kept", "q_columns": "copy"}),
}
ALL_METHODS = METHODS + tuple(VARIANTS)
QUICK = {"seeds": 2, "steps": 3000, "steps_per_epoch": 1000, "eval_episodes": 2}
CURVE_POINTS = 60  # points of the training-success-by-steps curve stored per run
TRAIN_WINDOW = 9000  # steps of the training-success window (as in the paper's figure (b))


def variant_base(method: str) -> str:
    """The method of :data:`METHODS` that ``method`` changes (itself if it is one).

    Example:
        >>> variant_base("handcrafted+no_filler_goal"), variant_base("gara+one_cut")
        ('handcrafted', 'gara')
    """
    if method in VARIANTS:
        return VARIANTS[method][2] if len(VARIANTS[method]) > 2 else "gara"
    return method


def method_config(method: str, maze: str, steps_per_epoch=None, eval_episodes=None):
    """The config of ``method`` on ``maze`` (see the module docstring).

    Example:
        >>> method_config("gara_no_refinement", "four_rooms").min_steps
        1000000000
    """
    from experiments import u_maze

    if method not in ALL_METHODS:
        raise ValueError(f"method: {method!r} is not one of {', '.join(ALL_METHODS)}")
    base = variant_base(method)
    config = u_maze.method_config("gara" if base == "gara_no_refinement" else base, env=maze,
                                  steps_per_epoch=steps_per_epoch, eval_episodes=eval_episodes)
    if base == "gara_no_refinement":
        config = dataclasses.replace(config, min_steps=10**9)
    if method in VARIANTS:
        overrides = {name: value(maze) if callable(value) else value
                     for name, value in VARIANTS[method][1].items()}
        config = dataclasses.replace(config, **overrides)
    return config


def code_version() -> str | None:
    """The checkout's commit (``git rev-parse --short HEAD``), with ``+changes`` when tracked
    files differ from it; ``None`` outside a git checkout. Stored with every run."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, check=True,
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+changes" if dirty.strip() else "")


def summarize(result, total_steps: int) -> dict:
    """A run's summary (:func:`experiments.gara_ablation.summarize_run`) and its curves."""
    from experiments.gara_ablation import summarize_run
    from gara_jax import results as R

    m = result.metrics
    steps = m["env_steps"][0]
    grid = np.linspace(steps[-1] / CURVE_POINTS, steps[-1], CURVE_POINTS).round().astype(int)
    greedy_mean, greedy_ci = R.mean_ci95(m["eval_success"], axis=0)
    train_mean, train_ci = R.step_success_curve(result.episodes, grid, TRAIN_WINDOW)
    out = summarize_run(result, total_steps)
    out["curves"] = {"env_steps": steps.tolist(), "greedy": greedy_mean.round(4).tolist(),
                     "greedy_ci95": greedy_ci.round(4).tolist(), "train_steps": grid.tolist(),
                     "train": np.round(train_mean, 4).tolist(),
                     "train_ci95": np.round(train_ci, 4).tolist()}
    return out


def split_log(result) -> list:
    """Per seed, every split of a GARA run in order: ``epoch`` (0-based), the split goal's
    box ``start`` and the target it was analysed against, ``target`` (each ``[lo, hi]``,
    rounded to 1e-6), from the host steps' ``verdicts``.

    Example (a run of 2 seeds, one split in seed 1 at epoch 3)::

        [[], [{"epoch": 3, "start": [[0, 0, -1, -1], [3, 3, 1, 1]], "target": [...]}]]
    """
    out = [[] for _ in result.seeds]
    for epoch, info in enumerate(result.host_info):
        for v in (info or {}).get("verdicts", []):
            if v["outcome"] == "split":
                out[v["seed"]].append(dict(
                    epoch=epoch, start=np.round(v["start_box"], 6).tolist(),
                    target=np.round(v["target_box"], 6).tolist()))
    return out


def analysis_counts(result) -> list:
    """Per seed, how often each pair was analysed with each outcome: one entry per
    ``(start, target, outcome)`` with its ``count`` and ``first_epoch``, the boxes as
    ``[x_lo, x_hi, y_lo, y_hi]`` (the goals' positions; rounded to 1e-6), in the order first
    seen. Pieces of a split goal are new boxes, so a pair's entries end at its split.

    Example (one seed, a pair analysed twice without a split)::

        [[{"start": [3, 6, 0, 3], "target": [0, 3, 0, 3], "outcome": "no_reach",
           "count": 2, "first_epoch": 12}]]
    """
    def xy(box):
        lo, hi = np.round(box, 6).tolist()
        return [lo[0], hi[0], lo[1], hi[1]]

    out = [{} for _ in result.seeds]
    for epoch, info in enumerate(result.host_info):
        for v in (info or {}).get("verdicts", []):
            start, target = xy(v["start_box"]), xy(v["target_box"])
            key = (tuple(start), tuple(target), v["outcome"])
            entry = out[v["seed"]].setdefault(key, dict(start=start, target=target,
                                                        outcome=v["outcome"], count=0,
                                                        first_epoch=epoch))
            entry["count"] += 1
    return [list(seed.values()) for seed in out]


def paired(a: dict, b: dict, measure: str) -> dict:
    """``a - b`` seed by seed for one per-seed ``measure`` of two summaries: mean and 95%
    interval (seeds without a value in either are left out).

    Example:
        >>> x = {"per_seed": {"m": [1.0, 0.5, 1.0]}}; y = {"per_seed": {"m": [0.5, 0.5, 0.5]}}
        >>> paired(x, y, "m")["mean"]
        0.3333333333333333
    """
    from gara_jax.results import ci_summary

    d = np.asarray(a["per_seed"][measure], float) - np.asarray(b["per_seed"][measure], float)
    return ci_summary(d)


def refinement_off(method: str, methods: dict) -> str | None:
    """The refinement-off agent that ``method`` is compared with: for a ``gara`` variant the
    one with the same change (``gara_no_refinement+CHANGE``) where ``methods`` holds it, else
    ``gara_no_refinement``; ``None`` for a method of another base.

    Example:
        >>> refinement_off("gara+planning", {"gara_no_refinement+planning": {}})
        'gara_no_refinement+planning'
        >>> refinement_off("gara+one_cut", {}), refinement_off("handcrafted", {})
        ('gara_no_refinement', None)
    """
    if variant_base(method) != "gara":
        return None
    same = "gara_no_refinement" + method[len("gara"):]
    return same if same in methods else "gara_no_refinement"


def goal_cuts(maze: str, lo, hi) -> str:
    """Which of GARA's initial goals of ``maze`` a partition ``lo, hi [N, D]`` cuts, and
    along what: one group per initial goal, in their order, of ``x``, ``y`` and ``v`` (a
    velocity) for the dimensions along which its pieces are cut, ``-`` for an uncut goal.

    Example:
        >>> lo = np.array([[0, 0, -1, -1], [1, 0, -1, -1], [1, 1.5, -1, -1.]])
        >>> hi = np.array([[1, 3, 1, 1], [3, 1.5, 1, 1], [3, 3, 1, 1.]])
        >>> goal_cuts("u_maze", lo, hi)
        '- y'
    """
    from gara_jax import partition

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    out = []
    for a, b in zip(*partition.layout_boxes(maze, "gara"), strict=True):
        inside = (lo >= a - 1e-9).all(1) & (hi <= b + 1e-9).all(1)
        cut = (lo[inside] > a + 1e-9) | (hi[inside] < b - 1e-9)  # [pieces, D]
        dims = cut.any(0)
        out.append("".join(n for n, c in (("x", dims[0]), ("y", dims[1]),
                                          ("v", dims[2:].any())) if c) or "-")
    return " ".join(out)


def cut_table(runs: dict, maze: str) -> str:
    """Every seed of every stored GARA run on ``maze`` that starts from GARA's initial goals
    (seeds 0-19, ``initial_boxes`` unset), grouped by :func:`goal_cuts` of its final
    partition: seeds, greedy success over the last 10 evaluations and training success over
    the last 30k steps, each beside the same seeds' refinement-off agent
    (:func:`refinement_off`). An observation, not an ablation: a seed's final partition is
    itself an outcome of its run."""
    methods = runs.get(maze, {})
    groups: dict = {}
    used = 0
    for key, run in methods.items():
        off = refinement_off(key, methods)
        if ("@" in key or key.startswith("gara_no_refinement") or off not in methods
                or not run.get("final_partitions") or run["config"].get("initial_boxes")):
            continue
        used += 1
        mine, theirs = run["summary"]["per_seed"], methods[off]["summary"]["per_seed"]
        values = zip(mine["greedy_last10"], theirs["greedy_last10"], mine["train_last30k"],
                     theirs["train_last30k"], strict=True)
        for (lo, hi), v in zip(run["final_partitions"], values, strict=True):
            groups.setdefault(goal_cuts(maze, lo, hi), []).append(v)
    lines = [f"{maze}: the final partitions of {used} GARA runs' seeds, by the initial goals "
             "they cut (in GARA's initial order)", "",
             "| cuts | seeds | greedy, last 10 evals: GARA / refinement off / difference "
             "| training, last 30k steps: GARA / refinement off / difference |",
             "|---|---:|---:|---:|"]
    for sig, v in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        m = np.asarray(v, float).mean(0)
        lines.append(f"| `{sig}` | {len(v)} | {m[0]:.2f} / {m[1]:.2f} / {m[0] - m[1]:+.2f} | "
                     f"{m[2]:.2f} / {m[3]:.2f} / {m[2] - m[3]:+.2f} |")
    return "\n".join(lines)


def run_key(method: str, seeds) -> str:
    """Where a run of ``method`` on ``seeds`` is stored: ``method`` for seeds ``0..n-1``,
    ``method@seedsA-B`` for another block (``--first-seed``).

    Example:
        >>> run_key("gara", range(20)), run_key("gara", range(20, 40))
        ('gara', 'gara@seeds20-39')
    """
    seeds = list(seeds)
    return method if seeds[0] == 0 else f"{method}@seeds{seeds[0]}-{seeds[-1]}"


def pooled(methods: dict, method: str, measure: str = "greedy_last10"):
    """``method``'s per-seed ``measure`` over all its stored seed blocks (the 0-based run and
    every ``method@seedsA-B``), in seed order: ``(seeds, values)``, or ``None`` if it has no
    run. Blocks must not overlap (``ValueError``).

    Example:
        >>> runs = {"gara": {"seeds": 2, "summary": {"per_seed": {"m": [1.0, 0.0]}}},
        ...         "gara@seeds2-2": {"seeds": 1, "first_seed": 2,
        ...                           "summary": {"per_seed": {"m": [0.5]}}}}
        >>> pooled(runs, "gara", "m")
        ([0, 1, 2], [1.0, 0.0, 0.5])
    """
    seeds, values = [], []
    for key, run in methods.items():
        if key.split("@")[0] != method:
            continue
        first = run.get("first_seed", 0)
        seeds += range(first, first + run["seeds"])
        values += list(run["summary"]["per_seed"][measure])
    if not seeds:
        return None
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"pooled: the seed blocks of {method!r} overlap")
    order = np.argsort(seeds)
    return [seeds[i] for i in order], [values[i] for i in order]


def pooled_table(runs: dict) -> str:
    """For each method with more than one seed block (``--first-seed``), its training success
    over the last 30,000 steps and greedy success over the last 10 evaluations pooled over all
    its seeds, and the greedy success paired against the refinement-off agent (as in
    :func:`variant_table`) over the seeds both have run (``""`` when no method has a second
    block)."""
    from gara_jax.results import ci_summary

    lines = []
    for maze, methods in runs.items():
        names = sorted({k.split("@")[0] for k in methods if "@" in k})
        for name in names:
            seeds, values = pooled(methods, name)
            train = pooled(methods, name, "train_last30k")[1]
            off = refinement_off(name, methods)
            cell, n_pair = "-", 0
            other = pooled(methods, off) if off else None
            if other is not None:
                theirs = dict(zip(*other))
                both = [(v, theirs[s]) for s, v in zip(seeds, values) if s in theirs]
                n_pair = len(both)
                if both:
                    cell = _fmt(ci_summary(np.subtract(*np.asarray(both, float).T)))
            lines.append(f"| {maze} | `{name}` | {len(seeds)} | "
                         f"{_fmt(ci_summary(np.asarray(train, float)))} | "
                         f"{_fmt(ci_summary(np.asarray(values, float)))} | "
                         f"{'`' + off + '`' if off else '-'} | {n_pair} | {cell} |")
    if not lines:
        return ""
    head = ["| maze | method | seeds | training, last 30k steps | greedy, last 10 evals "
            "| refinement off | paired seeds | − refinement off (paired) |",
            "|---|---|---:|---:|---:|---|---:|---:|"]
    return "\n".join(head + lines)


def _fmt(s) -> str:
    return "-" if not s or s.get("mean") is None else f"{s['mean']:.2f} ± {s['ci95']:.2f}"


def table(runs: dict) -> str:
    """The markdown table of ``runs`` (``maze -> method -> run``), with the paired rows:
    ``gara`` and ``handcrafted`` each minus ``gara_no_refinement``, seed by seed."""
    lines = ["| maze | method | steps | training, ep. 300-399 | training, last 30k steps "
             "| greedy, end | greedy, last 10 evals | goals | analyses | splits |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for maze, methods in runs.items():
        for method, run in methods.items():
            s = run["summary"]
            lines.append(
                f"| {maze} | `{method}` | {run['steps']:,} | {_fmt(s['train_ep300_400'])} | "
                f"{_fmt(s['train_last30k'])} | {_fmt(s['greedy_end'])} | "
                f"{_fmt(s['greedy_last10'])} | {s['goals_end']:.1f} | {s['analysed']:.1f} | "
                f"{s['splits']:.1f} |")
        # GARA's gain from refinement, and the authors' partition's: what a partition can
        # add over the initial goals on this maze.
        for method in ("gara", "handcrafted"):
            if method in methods and "gara_no_refinement" in methods:
                a, b = methods[method]["summary"], methods["gara_no_refinement"]["summary"]
                cells = " | ".join(_fmt(paired(a, b, k)) for k in (
                    "train_ep300_400", "train_last30k", "greedy_end", "greedy_last10"))
                lines.append(f"| {maze} | {method} − no refinement (paired) | | {cells} | | | |")
    return "\n".join(lines)


def variant_table(runs: dict) -> str:
    """The refinement study's table: each variant of :data:`VARIANTS` in ``runs`` against
    the refinement-off agent and against its base (:func:`variant_base`), seed by seed over the
    greedy success of the last 10 evaluations (``""`` when ``runs`` holds no variant). A
    ``gara`` variant is compared with the refinement-off agent that has the same change
    (``gara_no_refinement+CHANGE``) where that has run, else with ``gara_no_refinement``; a
    variant of another base has no refinement-off comparison."""
    lines = []
    for maze, methods in runs.items():
        for name in (v for v in methods if v in VARIANTS):
            s = methods[name]["summary"]
            base = variant_base(name)
            off = refinement_off(name, methods)
            vs = [_fmt(paired(s, methods[other]["summary"], "greedy_last10"))
                  if other in methods else "-" for other in (off, base)]
            lines.append(f"| {maze} | `{name}` | {_fmt(s['train_last30k'])} | "
                         f"{_fmt(s['greedy_last10'])} | {vs[0]} | {vs[1]} | "
                         f"{s['goals_end']:.1f} | {s['splits']:.1f} |")
    if not lines:
        return ""
    head = ["| maze | variant | training, last 30k steps | greedy, last 10 evals "
            "| − refinement off (paired) | − its base (paired) | goals | splits |",
            "|---|---|---:|---:|---:|---:|---:|---:|"]
    return "\n".join(head + lines)


def plot(runs: dict, out: Path) -> None:
    """``mazes_success.png`` and, where GARA ran, ``mazes_partitions.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import envs
    from experiments.u_maze import partition_seed
    from gara_jax import plots

    mazes = list(runs)
    # One colour per method across every maze, and a legend of them all: a maze may lack a
    # method (the U-maze's HIRO lives in the U-maze study).
    methods = sorted({k for m in mazes for k in runs[m]},
                     key=lambda k: (ALL_METHODS + (k,)).index(k))
    colour = {k: f"C{i % 10}" for i, k in enumerate(methods)}
    legend = {}
    fig, axes = plt.subplots(len(mazes), 2, figsize=(10, 3.0 * len(mazes)), dpi=110,
                             squeeze=False)
    for row, maze in zip(axes, mazes, strict=True):
        for method, run in runs[maze].items():
            c = run["summary"]["curves"]
            for ax, (x, y, ci) in zip(row, ((c["train_steps"], c["train"], c["train_ci95"]),
                                            (c["env_steps"], c["greedy"], c["greedy_ci95"])),
                                      strict=True):
                y, ci = np.asarray(y, float), np.asarray(ci, float)
                line, = ax.plot(x, y, label=method, linewidth=1.4, color=colour[method])
                legend.setdefault(method, line)
                ax.fill_between(x, np.clip(y - ci, 0, 1), np.clip(y + ci, 0, 1),
                                color=line.get_color(), alpha=0.15, linewidth=0)
        row[0].set(title=f"{maze}: training success ({TRAIN_WINDOW:,}-step window)",
                   ylim=(-0.02, 1.02), xlabel="environment steps")
        row[1].set(title=f"{maze}: greedy success", ylim=(-0.02, 1.02),
                   xlabel="environment steps")
        for ax in row:
            ax.grid(alpha=0.3)
            ax.title.set_fontsize(9)
    fig.legend([legend[k] for k in methods], methods, loc="lower center", ncol=len(methods),
               fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(out / "mazes_success.png")
    plt.close(fig)

    with_gara = [m for m in mazes if "gara" in runs[m] and runs[m]["gara"]["final_partitions"]]
    if not with_gara:
        return
    fig, axes = plt.subplots(1, len(with_gara), figsize=(3.4 * len(with_gara), 3.8), dpi=110,
                             squeeze=False)
    for ax, maze in zip(axes[0], with_gara, strict=True):
        run = runs[maze]["gara"]
        per_seed = run["summary"]["per_seed"]
        record = {"metrics": {"eval_success": [per_seed["greedy_end"]],
                              "n_goals": [per_seed["goals_end"]]}}
        seed, _ = partition_seed(record)
        lo, hi = (np.asarray(b) for b in run["final_partitions"][seed])
        plots.draw_partition(ax, lo, hi, len(lo), envs.make(maze)[1],
                             title=f"{maze}: seed {seed}, {len(lo)} goals")
    fig.suptitle("GARA's final partitions (the successful seed with the median goal count)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "mazes_partitions.png")
    plt.close(fig)


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m experiments.mazes",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--mazes", default=",".join(MAZES), help="comma-separated subset of "
                   f"{','.join(MAZES)}")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of "
                   f"{','.join(ALL_METHODS)} (default: {','.join(METHODS)}; the gara+ variants "
                   "change one mechanism of GaraConfig(), see VARIANTS)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per run (default 20)")
    p.add_argument("--first-seed", type=int, default=0,
                   help="train seeds FIRST..FIRST+SEEDS-1 (default 0); a run from another "
                        "first seed is stored as METHOD@seedsA-B beside the 0-based run, and "
                        "the pooled table puts the blocks of a method together")
    p.add_argument("--steps", type=int, default=None,
                   help="steps per seed for every maze (default: each maze's budget)")
    p.add_argument("--out", default="results/mazes", help="output directory")
    p.add_argument("--quick", action="store_true", help=f"a first look: {QUICK['seeds']} "
                   f"seeds, {QUICK['steps']:,} steps, {QUICK['steps_per_epoch']}-step epochs")
    p.add_argument("--rerun", action="store_true", help="run again what --out already holds")
    p.add_argument("--dry-run", action="store_true", help="print the plan; train nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--cut-table", metavar="JSON", default=None,
                   help="print, for each of --mazes, the final partitions of every GARA run "
                        "stored in JSON (a mazes.json) grouped by the goals they cut "
                        "(cut_table); train nothing")
    from gara_jax import compile_cache

    compile_cache.add_argument(p)
    args = p.parse_args(argv)
    for name, valid in (("mazes", MAZES), ("methods", ALL_METHODS)):
        chosen = [v.strip() for v in getattr(args, name).split(",") if v.strip()]
        bad = [v for v in chosen if v not in valid]
        if not chosen or bad or len(set(chosen)) != len(chosen):
            p.error(f"--{name}: {bad or getattr(args, name)!r} invalid or repeated; choose "
                    f"from {', '.join(valid)}")
        setattr(args, name, chosen)
    args.seeds = args.seeds if args.seeds is not None else (QUICK["seeds"] if args.quick else 20)
    if args.seeds < 1 or (args.steps is not None and args.steps < 1):
        p.error("--seeds and --steps must be >= 1")
    if args.first_seed < 0:
        p.error(f"--first-seed: must be >= 0, got {args.first_seed}")
    for maze in args.mazes:  # a variant undefined on a maze fails here, before any training
        for method in args.methods:
            try:
                method_config(method, maze)
            except ValueError as err:
                p.error(f"--methods {method} on --mazes {maze}: {err}")
    return args


def steps_for(args, maze: str) -> int:
    from experiments.u_maze import ENV_STEPS

    if args.steps is not None:
        return args.steps
    return QUICK["steps"] if args.quick else ENV_STEPS[maze]


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.cut_table is not None:
        runs = json.loads(Path(args.cut_table).read_text())["runs"]
        print("\n\n".join(cut_table(runs, maze) for maze in args.mazes))
        return 0
    spe = QUICK["steps_per_epoch"] if args.quick else None
    evals = QUICK["eval_episodes"] if args.quick else None
    out = Path(args.out)
    plan = [(maze, method, steps_for(args, maze)) for maze in args.mazes
            for method in args.methods]
    if args.dry_run:
        print(f"python -m experiments.mazes --dry-run: {len(plan)} runs of {args.seeds} seeds "
              f"(nothing is trained or written), to {out}/")
        for maze, method, steps in plan:
            config = method_config(method, maze, spe, evals)
            print(f"  {maze:11s} {method:19s} {type(config).__name__}, {steps:,} steps per seed")
        return 0

    from gara_jax import compile_cache

    compile_cache.setup(args.no_compile_cache)
    from gara_jax.results import write_json
    from gara_jax.train import final_partitions, train_many

    out.mkdir(parents=True, exist_ok=True)
    path = out / "mazes.json"
    runs = json.loads(path.read_text())["runs"] if path.exists() else {}
    version = code_version()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    for maze, method, steps in plan:
        key = run_key(method, seeds)
        old = runs.get(maze, {}).get(key)
        config = method_config(method, maze, spe, evals)
        same = json.loads(json.dumps(dataclasses.asdict(config)))  # as stored (tuples: lists)
        if (old and not args.rerun and old["seeds"] == args.seeds and old["steps"] == steps
                and old["config"] == same):
            continue
        bar = None
        if not args.no_progress:
            from tqdm.auto import tqdm

            bar = tqdm(desc=f"{maze}/{key}", unit="epoch", leave=False, file=sys.stderr)

        def progress(done, total, metrics, bar=bar):
            if bar is not None:
                bar.total, bar.n = total, done
                bar.set_postfix(goals=f"{np.mean(metrics['n_goals']):.1f}",
                                greedy=f"{np.mean(metrics['eval_success']):.2f}")
                bar.refresh()

        t0 = time.perf_counter()
        result = train_many(config, seeds, steps, progress=progress)
        if bar is not None:
            bar.close()
        summary = summarize(result, steps)
        partitions = splits = None
        if result.algorithm.startswith("gara"):
            partitions = [[np.asarray(b).round(6).tolist() for b in p.boxes()]
                          for p in final_partitions(result)]
            splits = split_log(result)
        record = dict(seeds=args.seeds, steps=steps, commit=version,
                      config=dataclasses.asdict(config), summary=summary,
                      final_partitions=partitions, split_log=splits)
        if splits is not None:
            record["analyses"] = analysis_counts(result)
        if args.first_seed:
            record["first_seed"] = args.first_seed
        runs.setdefault(maze, {})[key] = record
        write_json(path, {"runs": runs})
        s = summary
        print(f"{maze}/{key}: training (last 30k) {_fmt(s['train_last30k'])}, greedy "
              f"(last 10) {_fmt(s['greedy_last10'])}, goals {s['goals_end']:.1f} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    chosen = {m: {k: runs[m][k] for k in args.methods if k in runs.get(m, {})}
              for m in args.mazes if m in runs}
    blocks = {m: {k: r for k, r in runs[m].items() if k.split("@")[0] in args.methods}
              for m in args.mazes if m in runs}
    text = "\n\n".join(t for t in (table(chosen), variant_table(chosen), pooled_table(blocks))
                        if t)
    (out / "table.md").write_text(text + "\n")
    plot(chosen, out)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
