"""`gara-jax reproduce` in quick mode: files, resume equality, bad arguments."""

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from experiments import u_maze
from gara_jax import checkpoint, results

QUICK = ["--quick", "--seeds", "2", "--steps", "2000", "--no-progress"]
OUTPUTS = ("metrics.csv", "episodes.csv", "summary.json", "success_curve.png",
           "partitions_gara.png", "partitions_gara_reference.png", "config.json")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("quick")
    assert u_maze.main([*QUICK, "--out", str(out)]) == 0
    return out


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_quick_mode_writes_every_file_well_formed(quick_run):
    for name in OUTPUTS:
        assert (quick_run / name).stat().st_size > 0, name
    rows = _rows(quick_run / "metrics.csv")
    assert tuple(rows[0]) == ("method", "seed", "env_step", "eval_success", "train_success",
                              "n_goals", "episode_return")
    # 5 methods x 2 seeds x 2 epochs (1000-step epochs in quick mode)
    assert len(rows) == 20
    assert {r["method"] for r in rows} == set(u_maze.DEFAULT_METHODS)
    for r in rows:
        assert 0.0 <= float(r["eval_success"]) <= 1.0 and 0.0 <= float(r["train_success"]) <= 1.0
        assert math.isfinite(float(r["episode_return"]))
        assert int(r["env_step"]) in (1000, 2000)
    summary = json.loads((quick_run / "summary.json").read_text())
    assert set(summary) == set(u_maze.DEFAULT_METHODS)
    for s in summary.values():
        for key in ("final_success_mean", "final_success_ci95", "steps_to_50", "steps_to_80",
                    "wall_time_s", "final_train_success_mean", "final_train_success_ci95",
                    "train_success_ep300_400"):
            assert key in s
        assert math.isfinite(s["final_success_mean"]) and s["wall_time_s"] > 0
        assert 0.0 <= s["final_train_success_mean"] <= 1.0
        assert set(s["train_success_ep300_400"]) == {"mean", "ci95", "n"}
    config = json.loads((quick_run / "config.json").read_text())
    assert config["seeds"] == 2 and config["steps"] == 2000
    assert config["batch_invariant"] is False  # one device: XLA's defaults
    assert config["configs"]["gara"]["tau1"] == 0.9  # SPEC.md 3.6, revision 2
    assert config["configs"]["hiro_paper"]["high"]["critic_target"] == "reward_less"
    assert config["configs"]["gara_reference"]["memory"] == "windows"
    for png in ("success_curve.png", "partitions_gara.png", "partitions_gara_reference.png"):
        with Image.open(quick_run / png) as im:
            im.verify()
            assert im.size[0] > 300


def test_resume_after_kill_between_epochs_gives_identical_metrics(quick_run, tmp_path,
                                                                  monkeypatch):
    out = tmp_path / "resumed"
    args = [*QUICK, "--methods", "handcrafted,gara", "--out", str(out)]
    real_save, calls = checkpoint.save, []

    def save_then_die(*a, **kw):
        real_save(*a, **kw)
        calls.append(1)
        if len(calls) == 3:  # handcrafted done (2 epochs), gara has finished one epoch
            raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save", save_then_die)
    assert u_maze.main(args) == 130
    # nothing that looks like a finished result after the interruption
    for name in ("metrics.csv", "summary.json", "success_curve.png"):
        assert not (out / name).exists()
    monkeypatch.setattr(checkpoint, "save", real_save)
    assert u_maze.main([*args, "--resume"]) == 0
    want = [r for r in _rows(quick_run / "metrics.csv") if r["method"] in ("handcrafted", "gara")]
    got = _rows(out / "metrics.csv")
    key = lambda r: (r["method"], r["seed"], int(r["env_step"]))  # noqa: E731
    assert sorted(got, key=key) == sorted(want, key=key)


@pytest.mark.parametrize("args", [
    ["--quick", "--seeds", "3", "--steps", "2000", "--no-progress"],
    [*QUICK, "--batch-invariant"],  # compiles differently: cannot continue a run made without
])
def test_resume_with_other_arguments_is_refused(quick_run, capsys, args):
    code = u_maze.main([*args, "--out", str(quick_run), "--resume"])
    assert code == 2
    assert "differ" in capsys.readouterr().err


@pytest.mark.parametrize("bad, field", [
    (["--methods", "gara,dqn"], "--methods"),
    (["--seeds", "0"], "--seeds"),
    (["--steps", "-5"], "--steps"),
])
def test_bad_arguments_fail_with_one_line(bad, field, tmp_path, capsys):
    out = tmp_path / "o"
    assert u_maze.main(["--quick", "--no-progress", "--out", str(out), *bad]) == 2
    err = capsys.readouterr().err.strip()
    assert field in err and len(err.splitlines()) == 1
    assert not any((out / name).exists() for name in OUTPUTS)


def test_unwritable_out_dir_fails_with_one_line(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert u_maze.main(["--quick", "--no-progress", "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--out" in err and len(err.splitlines()) == 1


def test_console_command_reports_bad_method(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "gara_jax.cli", "reproduce", "--methods", "ppo",
                           "--out", str(tmp_path / "o")], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "gara-jax reproduce: error: --methods: unknown method(s) ['ppo']; "
        "choose from gara, gara_planning, gara_reference, handcrafted, hiro_paper, hiro, "
        "gara_reference_results, gara_reference_results_planning, hiro_paper_standard_target, "
        "hiro_paper_full_range, hiro_paper_unclipped_low, hiro_paper_full_range_unclipped_low, "
        "or all"]


def test_episodes_csv_is_every_training_episode_and_matches_the_metrics(quick_run):
    episodes = _rows(quick_run / "episodes.csv")
    assert tuple(episodes[0]) == results.EPISODE_CSV_COLUMNS
    metrics = _rows(quick_run / "metrics.csv")
    summary = json.loads((quick_run / "summary.json").read_text())
    for method in u_maze.DEFAULT_METHODS:
        for seed in ("0", "1"):
            eps = [r for r in episodes if r["method"] == method and r["seed"] == seed]
            end = np.array([int(r["end_step"]) for r in eps])
            length = np.array([int(r["length"]) for r in eps])
            success = np.array([int(r["success"]) for r in eps])
            assert [int(r["episode"]) for r in eps] == list(range(len(eps)))
            # Episodes are back to back: each starts where the previous one ended.
            np.testing.assert_array_equal(np.diff(end, prepend=0), length)
            # The reference presets truncate at 302 steps (SPEC.md 3.1, 3.9.3), the rest at
            # the environment's 300; a successful episode may be shorter.
            limit = getattr(u_maze.method_config(method), "max_episode_steps", None) or 300
            assert limit == (302 if method == "gara_reference" else 300), method
            assert np.all((length >= 1) & (length <= limit)) and set(success) <= {0, 1}
            assert np.all(success[length < limit] == 1)
            # Each epoch's training success is the success rate of the episodes ending in it.
            for row in (r for r in metrics if r["method"] == method and r["seed"] == seed):
                step = int(row["env_step"])
                inside = (end > step - 1000) & (end <= step)
                want = success[inside].mean() if inside.any() else 0.0
                assert float(row["train_success"]) == pytest.approx(want, abs=1e-6)
        n_window = sum(1 for seed in ("0", "1") if sum(
            1 for r in episodes if r["method"] == method and r["seed"] == seed) > 300)
        assert summary[method]["train_success_ep300_400"]["n"] == n_window


def test_episode_index_curve_by_hand_on_the_quick_run(quick_run):
    rows = [r for r in _rows(quick_run / "episodes.csv") if r["method"] == "handcrafted"]
    per_seed = [[int(r["success"]) for r in rows if r["seed"] == s] for s in ("0", "1")]
    n, window = min(len(p) for p in per_seed), 30
    by_hand = []
    for e in range(n):  # trailing mean over the last <= 30 episodes, then over seeds
        by_hand.append(sum(sum(p[max(0, e - window + 1): e + 1]) / (e + 1 - max(0, e - window
                                                                             + 1))
                           for p in per_seed) / 2)
    episodes = {"success": [np.array(p) for p in per_seed]}
    mean, _ = results.episode_success_curve(episodes, 400, window)
    np.testing.assert_allclose(mean, by_hand[:400], atol=1e-12)
    # And on numbers small enough to read: seeds [1,0,1,1] and [0,0,1,1], window 2.
    mean, ci = results.episode_success_curve(
        {"success": [np.array([1, 0, 1, 1]), np.array([0, 0, 1, 1])]}, 400, 2)
    np.testing.assert_allclose(mean, [0.5, 0.25, 0.5, 1.0])
    assert ci[-1] == 0.0 and ci[0] > 0


def test_partition_figure_seed_rule_and_panels_at_the_paper_steps():
    record = {"metrics": {"eval_success": [[0.0, 1.0, 1.0, 1.0, 0.0]],
                          "n_goals": [[2, 7, 4, 9, 4]]}}
    row, rule = u_maze.partition_seed(record)
    assert row == 1 and "successful" in rule  # successful seeds 1, 2, 3: goals 7, 4, 9
    record["metrics"]["eval_success"] = [[0.0] * 5]
    assert u_maze.partition_seed(record) == (2, "no seed succeeds: the median final goal count")
    snaps = [{"step": 0, "n": 2}, {"step": 3000, "n": 3}, {"step": 30000, "n": 5},
             {"step": 36000, "n": 6}]
    assert [u_maze.partition_at(snaps, t)["n"] for t in (0, 1000, 29999, 30000, 120000)] == [
        2, 2, 3, 5, 6]


def test_methods_all_is_the_default_published_hiro_and_the_results_version(tmp_path):
    args = u_maze._apply_defaults(u_maze.parse_args(
        ["--methods", "all", "--out", str(tmp_path / "o")]))
    assert u_maze.validate(args) == [*u_maze.DEFAULT_METHODS, "hiro", "gara_reference_results",
                                     "gara_reference_results_planning"]
    # The Planning-from-Q method alone runs its source first; named after it, it moves after.
    for names in ("gara_reference_results_planning",
                  "gara_reference_results_planning,gara_reference_results"):
        args = u_maze._apply_defaults(u_maze.parse_args(
            ["--methods", names, "--out", str(tmp_path / "o")]))
        assert u_maze.validate(args) == ["gara_reference_results",
                                         "gara_reference_results_planning"]
    args = u_maze._apply_defaults(u_maze.parse_args(["--out", str(tmp_path / "o")]))
    assert u_maze.validate(args) == list(u_maze.DEFAULT_METHODS)


def test_checkpoint_interval_saves_a_methods_last_epoch_and_keeps_the_metrics(quick_run, tmp_path,
                                                                              monkeypatch):
    real_save, saved = checkpoint.save, []
    monkeypatch.setattr(checkpoint, "save",
                        lambda path, loop, extra: (saved.append(loop.epoch),
                                                   real_save(path, loop, extra)))
    out = tmp_path / "sparse"
    assert u_maze.main([*QUICK, "--methods", "handcrafted", "--checkpoint-every", "1e9",
                        "--out", str(out)]) == 0
    assert saved == [2]  # only after the last of the two epochs
    want = [r for r in _rows(quick_run / "metrics.csv") if r["method"] == "handcrafted"]
    assert _rows(out / "metrics.csv") == want
    assert u_maze.main([*QUICK, "--checkpoint-every", "-1", "--out", str(out)]) == 2
