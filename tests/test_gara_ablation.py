"""The GARA ablation script: variants, the greedy-episode classification, a tiny run."""

import dataclasses
import json

import numpy as np
import pytest

from experiments import gara_ablation as ab
from gara_jax.algorithms import GaraConfig


def test_every_variant_builds_and_the_default_differs_from_the_reference_as_documented():
    variants = ab._variants()
    assert {"reference", "default", "previous_default", "handcrafted"} <= set(variants)
    assert all(isinstance(v[0], str) and v[0] for v in variants.values())
    ref, ours = variants["reference"][1], variants["default"][1]
    differ = {f for f in ("goal_membership", "reached_at_start", "stall_penalty",
                          "relabel_replay") if getattr(ref, f) != getattr(ours, f)}
    assert differ == {"goal_membership", "reached_at_start", "stall_penalty", "relabel_replay"}
    assert (ref.high.tie_break, ours.high.tie_break) == ("lowest", "random")
    assert (ref.low.learning_rate, ours.low.learning_rate) == (0.01, 0.001)
    assert ref.memory == ours.memory == "windows"
    # The previous default's rows are the default with the reference's step size.
    assert variants["default_lr0.01"][1] == dataclasses.replace(ours, low=ref.low)
    assert variants["handcrafted_lr0.01"][1].low == ref.low


def test_results_rows_revert_one_mechanism_each():
    """Each ``results-...`` row differs from ``results`` in the fields its name says."""
    variants = ab._variants()
    res = variants["results"][1]
    assert variants["results_min_steps_5000+zonotope_box"][1] == GaraConfig.reference(
        version="results")
    flat = lambda c: {**dataclasses.asdict(c), **{f"high.{k}": v for k, v in  # noqa: E731
                                                  dataclasses.asdict(c.high).items()}}
    expect = {"results-coverage_final": {"coverage"}, "results-epoch_cadence": {"cadence"},
              "results-memory_counts": {"pair_counts", "relabel_counts"},
              "results-no_count_inflation": {"relabel_counts"},
              "results-q_update_written_entry": {"high", "high.q_update"},
              "results-q_rows_copied": {"q_rows_after_split"},
              "results-300_step_episodes": {"max_episode_steps"},
              "results_min_steps_5000": {"min_steps"},
              "results_planning": {"planning"}, "results_planning_from_q": {"planning"},
              "results_min_steps_5000_planning_from_q": {"planning", "min_steps"},
              "results_min_steps_5000-coverage_final": {"min_steps", "coverage"},
              "results_min_steps_5000+merge_siblings": {"min_steps", "merge"},
              "results_min_steps_5000+ibp": {"min_steps", "refine_method"},
              "results_min_steps_5000+ibp_planning_from_q": {"min_steps", "refine_method",
                                                             "planning"},
              "results_min_steps_5000+zonotope_box": {"min_steps", "refine_method"}}
    for name, fields in expect.items():
        a, b = flat(res), flat(variants[name][1])
        assert {k for k in a if a[k] != b[k]} == fields, name
    assert ab._source(variants["results_planning_from_q"]) == "results"
    assert ab._source(variants["results_planning"]) is None
    assert ab._source(variants["results_min_steps_5000_planning_from_q"]) == (
        "results_min_steps_5000")
    assert ab.with_sources(["results_planning_from_q", "default", "results"], variants) == [
        "results", "results_planning_from_q", "default"]


def _records(points, k=2):
    """Per-step records of an episode whose decision points (every k steps) visit ``points``."""
    obs = np.repeat(np.asarray(points, float), k, axis=0)
    n = len(obs)
    deciding = np.arange(n) % k == 0
    return obs, np.ones(n, bool), deciding


def test_classify_episode_by_hand():
    obs, live, deciding = _records([[0, 0], [0, 0]])
    goal, target = np.zeros(len(obs)), np.ones(len(obs))
    assert ab.classify_episode(obs, goal, target, deciding, live, False) == "stall"
    assert ab.classify_episode(obs, goal, target, deciding, live, True) == "success"
    obs, live, deciding = _records([[0, 0], [1, 0], [0, 0]])
    obs[1] = [0.5, 0]  # moving within the options
    assert ab.classify_episode(obs, goal, target, deciding, live, False) == "loop"
    assert ab.classify_episode(obs, goal, goal, deciding, live, False) == "self_target_loop"
    obs, live, deciding = _records([[0, 0], [1, 0], [2, 0]])
    assert ab.classify_episode(obs, goal, target, deciding, live, False) == "other"
    # Decision points after the episode ended do not count.
    obs, live, deciding = _records([[0, 0], [1, 0], [0, 0]])
    live[4:] = False
    assert ab.classify_episode(obs, goal, target, deciding, live, False) == "other"


def test_a_tiny_ablation_run_writes_its_json(tmp_path, capsys):
    out = tmp_path / "abl.json"
    assert ab.main(["--variants", "handcrafted", "--seeds", "2", "--steps", "3000",
                    "--out", str(out), "--no-progress"]) == 0
    row = json.loads(out.read_text())["variants"]["handcrafted"]
    s = row["summary"]
    assert row["seeds"] == 2 and row["steps"] == 3000
    assert s["train_last30k"]["n"] == 2 and 0.0 <= s["train_last30k"]["mean"] <= 1.0
    assert s["train_ep300_400"]["n"] == 0  # 3,000 steps hold fewer than 300 episodes
    assert sum(s["greedy_outcomes"].values()) == 2
    assert s["greedy_last10"]["n"] == 2 and len(s["per_seed"]["greedy_end"]) == 2
    assert np.mean(s["per_seed"]["greedy_end"]) == pytest.approx(s["greedy_end"]["mean"])
    assert "| `handcrafted` |" in capsys.readouterr().out
    # Already there with the same seeds and steps: not run again.
    assert ab.main(["--variants", "handcrafted", "--seeds", "2", "--steps", "3000",
                    "--out", str(out), "--no-progress"]) == 0


@pytest.mark.parametrize("argv", [["--variants", "nope"], ["--seeds", "0"]])
def test_bad_arguments_fail_with_exit_2(argv, tmp_path):
    argv = argv + ["--out", str(tmp_path / "x.json"), "--no-progress"]
    try:
        code = ab.main(argv)
    except SystemExit as stop:
        code = stop.code
    assert code == 2 and not (tmp_path / "x.json").exists()
