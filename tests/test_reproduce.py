"""`gara-jax reproduce` in quick mode: files, resume equality, bad arguments."""

import csv
import json
import math
import subprocess
import sys

import pytest
from PIL import Image

from experiments import u_maze
from gara_jax import checkpoint

QUICK = ["--quick", "--seeds", "2", "--steps", "2000", "--no-progress"]
OUTPUTS = ("metrics.csv", "summary.json", "success_curve.png", "partitions.png", "config.json")


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
    # 4 methods x 2 seeds x 2 epochs (1000-step epochs in quick mode)
    assert len(rows) == 16
    assert {r["method"] for r in rows} == set(u_maze.METHODS)
    for r in rows:
        assert 0.0 <= float(r["eval_success"]) <= 1.0 and 0.0 <= float(r["train_success"]) <= 1.0
        assert math.isfinite(float(r["episode_return"]))
        assert int(r["env_step"]) in (1000, 2000)
    summary = json.loads((quick_run / "summary.json").read_text())
    assert set(summary) == set(u_maze.METHODS)
    for s in summary.values():
        for key in ("final_success_mean", "final_success_ci95", "steps_to_50", "steps_to_80",
                    "wall_time_s"):
            assert key in s
        assert math.isfinite(s["final_success_mean"]) and s["wall_time_s"] > 0
    config = json.loads((quick_run / "config.json").read_text())
    assert config["seeds"] == 2 and config["steps"] == 2000
    assert config["configs"]["gara"]["tau1"] == 0.9  # SPEC.md 3.6, revision 2
    for png in ("success_curve.png", "partitions.png"):
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


def test_resume_with_other_arguments_is_refused(quick_run, capsys):
    code = u_maze.main(["--quick", "--seeds", "3", "--steps", "2000", "--no-progress",
                        "--out", str(quick_run), "--resume"])
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
        "choose from gara, gara_planning, handcrafted, hiro"]
