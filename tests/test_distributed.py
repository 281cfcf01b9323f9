"""`gara-jax reproduce --distributed`: two local processes write the one-process results."""

import csv
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from gara_jax.distributed import settings_from_env

ROOT = Path(__file__).resolve().parent.parent
ARGS = ["-m", "experiments.u_maze", "--quick", "--seeds", "2", "--steps", "2000",
        "--methods", "gara", "--no-progress"]  # GARA: the host step runs on each process's seeds


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_") and k != "XLA_FLAGS"}
    env.update(extra)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_two_processes_give_the_one_process_files(tmp_path):
    # Two processes of one device each: batch-invariant by default; the one-process run asks.
    single = subprocess.run([sys.executable, *ARGS, "--batch-invariant", "--out",
                             str(tmp_path / "one")],
                            capture_output=True, text=True, timeout=600, cwd=ROOT, env=_env())
    assert single.returncode == 0, single.stderr[-3000:]
    coordinator = f"127.0.0.1:{_free_port()}"
    procs = [subprocess.Popen(
        [sys.executable, *ARGS, "--distributed", "--out", str(tmp_path / "two")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
        env=_env(JAX_COORDINATOR_ADDRESS=coordinator, JAX_NUM_PROCESSES="2",
                 JAX_PROCESS_ID=str(i))) for i in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
    # Each process trained its one seed; process 0 gathered and wrote everything.
    assert _rows(tmp_path / "two" / "metrics.csv") == _rows(tmp_path / "one" / "metrics.csv")
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    two = json.loads((tmp_path / "two" / "summary.json").read_text())
    config = json.loads((tmp_path / "two" / "config.json").read_text())
    assert config["batch_invariant"] is True
    for method in one:
        one[method].pop("wall_time_s"), two[method].pop("wall_time_s")
    assert one == two
    assert "wrote" in outs[0][0] and "wrote" not in outs[1][0]


def test_distributed_without_a_coordinator_fails_with_one_line(tmp_path):
    proc = subprocess.run([sys.executable, *ARGS, "--distributed", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT, env=_env())
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if "gara-jax reproduce" in line]
    assert len(lines) == 1 and "JAX_COORDINATOR_ADDRESS" in lines[0], proc.stderr[-2000:]


@pytest.mark.parametrize("env, message", [
    ({"JAX_PROCESS_ID": "x"}, "JAX_PROCESS_ID: must be an integer"),
    ({"JAX_NUM_PROCESSES": "0"}, "JAX_NUM_PROCESSES: must be >= 1"),
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"}, r"JAX_PROCESS_ID: must be in \[0, 2\)"),
])
def test_bad_environment_values_name_the_variable(env, message):
    with pytest.raises(ValueError, match=message):
        settings_from_env(env)
