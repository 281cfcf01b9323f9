"""Smoke test of benchmarks/bounds_throughput.py: a tiny run writes well-formed JSON."""

import importlib.util
import json
import math
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_benchmark():
    spec = importlib.util.spec_from_file_location(
        "bounds_throughput", ROOT / "benchmarks" / "bounds_throughput.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def test_quick_run_with_two_callers_writes_json(tmp_path):
    bench = load_benchmark()
    out = tmp_path / "bounds.json"
    bench.main(["--archs", "12-8-8-4", "--batches", "8", "--repeats", "1", "--callers", "2",
                "--no-refine", "--out", str(out)])
    result = json.loads(out.read_text())
    rows = result["results"]
    assert {(r["method"], r["batch"], r["callers"]) for r in rows} == {
        ("ibp", 8, 2), ("crown", 8, 2), ("zonotope", 8, 2)}
    for r in rows:
        assert math.isfinite(r["boxes_per_s_best"]) and r["boxes_per_s_best"] > 0
        assert r["context_switches_per_call"] >= 0
    assert result["machine"]["cpu_async_dispatch"] is True  # the default dispatch
    assert [f["batch"] for f in result["floor"]] == [8]
    assert "| 12-8-8-4 | ibp | 8 |" in result["table"]


def test_dispatch_cannot_change_after_the_backend_started(tmp_path):
    bench = load_benchmark()
    import jax.numpy as jnp

    jnp.zeros(1).block_until_ready()  # the backend has started in this process
    with pytest.raises(SystemExit, match="already started"):
        bench.main(["--dispatch", "sync", "--no-refine", "--out", str(tmp_path / "x.json")])


@pytest.mark.parametrize("flag", ["--callers", "--repeats"])
def test_bad_counts_are_rejected(flag, capsys):
    bench = load_benchmark()
    with pytest.raises(SystemExit):
        bench.parse_args([flag, "0"])
    assert flag in capsys.readouterr().err


def test_tightness_on_the_golden_networks(tmp_path):
    """benchmarks/bounds_tightness.py: one row per golden network; the zonotope box is narrower
    than IBP's on most outputs (it keeps the dependencies IBP forgets)."""
    spec = importlib.util.spec_from_file_location(
        "bounds_tightness", ROOT / "benchmarks" / "bounds_tightness.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "tightness.json"
    bench.main(["--out", str(out)])
    rows = json.loads(out.read_text())["results"]
    assert [r["net"] for r in rows] == ["12-8-8-4", "6-32-32-2", "4-16-4"]
    for r in rows:
        assert r["zonotope_narrower_than_ibp"] > 0.8
        assert r["median_width_crown"] < r["median_width_ibp"]
