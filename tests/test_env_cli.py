"""The ``gara-jax demo`` command and the env throughput benchmark script (tiny runs)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
from pathlib import Path

import pytest

from gara_jax import cli

ROOT = Path(__file__).resolve().parents[1]


def test_demo_prints_rates_and_throughput(capsys):
    assert cli.main(["demo", "--env", "u_maze", "--episodes", "300", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    rows = {m[0]: float(m[1]) for m in re.findall(r"\| (uniform|sticky)[^|]* \| ([\d.]+)% ±", out)}
    assert set(rows) == {"uniform", "sticky"}
    assert rows["sticky"] > rows["uniform"]  # 61% vs 9% in expectation
    assert "steps/s" in out and "Reference (SPEC.md)" in out


def test_demo_takes_the_final_collision_rules(capsys):
    argv = ["demo", "--collision", "final", "--episodes", "300", "--seed", "1"]
    assert cli.main(argv) == 0
    assert "Reference (SPEC.md, final rules): uniform 14.9%" in capsys.readouterr().out


def test_demo_rejects_bad_arguments(capsys):
    for argv in (
        ["demo", "--collision", "strict"],
        ["demo", "--episodes", "0"],
        ["demo", "--env", "nope"],
        ["demo", "--sticky-prob", "1.5"],
        [],
    ):
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        assert exc.value.code == 2
    capsys.readouterr()


def test_subcommand_registry_rejects_duplicates():
    with pytest.raises(ValueError, match="demo"):
        cli.register(cli.Command("demo", "again", lambda p: None, lambda a: 0))
    assert "demo" in cli.COMMANDS


def test_benchmark_quick_run_writes_json(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location(
        "env_throughput", ROOT / "benchmarks" / "env_throughput.py"
    )
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "env_throughput.json"
    result = bench.main(
        [
            "--batches",
            "3",
            "--steps",
            "40",
            "--loop-steps",
            "300",
            "--jit-loop-steps",
            "20",
            "--repeats",
            "1",
            "--point-batches",
            "2",
            "--point-steps",
            "5",
            "--out",
            str(out),
        ]
    )
    saved = json.loads(out.read_text())
    assert saved["results"] == json.loads(json.dumps(result["results"]))
    rows = saved["results"]
    methods = [r["method"] for r in rows]
    assert methods[:3] == [
        "plain Python loop (envs.reference, Python floats)",
        "plain Python loop (envs.reference, NumPy arrays)",
        "Python loop over jit(step)",
    ]
    jax_rows = [r for r in rows if r["method"].startswith("jit(vmap(scan))")]
    pinned = [r for r in jax_rows if r["cores"] == "1 (pinned)"]
    assert [r["batch"] for r in jax_rows if r not in pinned] == [3]
    point = [r for r in rows if r["method"].startswith("point_u_maze: jit(vmap(scan))")]
    assert [(r["batch"], r["steps_per_env"], r["env"]) for r in point] == [(2, 5, "point_u_maze")]
    if hasattr(os, "sched_setaffinity") and len(os.sched_getaffinity(0)) > 1:
        assert [r["batch"] for r in pinned] == [3]
        assert all(r["xla_split_loops"] in (0, None) for r in pinned)
    # Both plain loops are timed before and after the JAX rows; the speedup column divides by
    # the best steps/s of the faster one.
    plain = rows[:2]
    assert all(len(r["times_s"]) == 2 for r in plain)
    baseline = max(r["steps_per_s_best"] for r in plain)
    assert saved["baseline"]["steps_per_s"] == baseline
    for r in rows:
        assert r["steps_per_s_best"] > 0
        assert r["speedup_vs_plain_loop"] == pytest.approx(r["steps_per_s_best"] / baseline)
    assert {"platform", "cpu_count", "jax", "backend"} <= set(saved["machine"])
    printed = capsys.readouterr().out
    assert "| method |" in printed and "x fastest plain loop" in printed
