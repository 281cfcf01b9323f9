import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gara_jax import results


def test_mean_ci95_matches_student_t_by_hand():
    x = np.array([[0.2, 1.0], [0.4, 1.0], [0.9, 1.0]])
    mean, half = results.mean_ci95(x, axis=0)
    np.testing.assert_allclose(mean, [0.5, 1.0])
    sd = np.sqrt(((0.2 - 0.5) ** 2 + (0.4 - 0.5) ** 2 + (0.9 - 0.5) ** 2) / 2)
    np.testing.assert_allclose(half, [4.303 * sd / np.sqrt(3), 0.0])


@settings(max_examples=30, deadline=None)
@given(a=st.lists(st.integers(0, 100).map(lambda v: v / 100), min_size=2, max_size=20),
       b=st.lists(st.integers(0, 100).map(lambda v: v / 100), min_size=2, max_size=6))
def test_welch_ci95_matches_scipy_and_is_antisymmetric(a, b):
    from scipy import stats

    d = results.welch_ci95(a, b)
    assert d["mean"] == pytest.approx(np.mean(a) - np.mean(b), abs=1e-12)
    assert d["n"] == [len(a), len(b)]
    back = results.welch_ci95(b, a)
    assert back["mean"] == pytest.approx(-d["mean"], abs=1e-12)
    assert back["ci95"] == d["ci95"] and back["df"] == d["df"]
    if d["ci95"] is None:  # no spread in either sample
        assert np.var(a) + np.var(b) < 1e-20
        return
    if np.var(a) + np.var(b) < 1e-9:  # (nearly) constant samples: scipy loses precision
        return
    ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    assert d["mean"] - d["ci95"] == pytest.approx(ci.low, rel=1e-6, abs=1e-9)
    assert d["mean"] + d["ci95"] == pytest.approx(ci.high, rel=1e-6, abs=1e-9)


def test_welch_ci95_small_or_empty_samples():
    one = results.welch_ci95([0.5], [0.1, 0.3])
    assert one["mean"] == pytest.approx(0.3) and one["ci95"] is None
    assert results.welch_ci95([0.5, float("nan"), 0.7], [0.2, 0.4])["n"] == [2, 2]
    with pytest.raises(ValueError, match="welch_ci95"):
        results.welch_ci95([], [0.1, 0.2])


def test_against_authors_uses_their_runs_of_the_high_level():
    from experiments.u_maze import AUTHORS_RUNS, against_authors, authors_table

    q = against_authors("gara_reference_results", [0.66] * 20, [12] * 20)
    assert q["train_success_ep300_400"]["authors_mean"] == pytest.approx(0.664)
    assert q["final_n_goals"]["authors"] == [10, 9, 7, 7, 30]
    # Our seeds have no spread, so the interval is the authors' runs' own, t with n - 1 df.
    sd = np.std(AUTHORS_RUNS["gara_reference_results"]["train_success_ep300_400"], ddof=1)
    assert q["train_success_ep300_400"]["ci95"] == pytest.approx(2.776 * sd / np.sqrt(5),
                                                                 rel=1e-3)
    p = against_authors("gara_reference_results_planning", [0.68, 0.7], [9, 10])
    assert p["train_success_ep300_400"]["n"] == [2, 4]  # their run 4 is a copy: left out
    assert p["train_success_ep300_400"]["mean"] == pytest.approx(0.69 - 0.7775)
    # A run too short for episodes 300-399: the success is not compared, the goals are.
    short = against_authors("gara_reference_results", [float("nan")] * 2, [2, 3])
    assert short["train_success_ep300_400"]["mean"] is None
    assert short["final_n_goals"]["n"] == [2, 5]
    assert "| short | - | 0.66 (0.8, 0.79, 0.75, 0.93, 0.05) | - |" in authors_table(
        {"short": short})


def test_steps_to_uses_seed_mean_and_none_when_never():
    steps = np.array([[100, 200, 300], [100, 200, 300]])
    success = np.array([[0.0, 0.6, 1.0], [0.0, 0.2, 0.7]])
    assert results.steps_to(steps, success, 0.5) == 300
    assert results.steps_to(steps, success, 0.9) is None


def test_summary_and_csv_roundtrip(tmp_path):
    m = {"env_steps": np.array([[10, 20], [10, 20]]),
         "eval_success": np.array([[0.5, 1.0], [0.0, 0.8]]),
         "train_success": np.array([[0.1, 0.2], [0.3, 0.4]]),
         "n_goals": np.array([[2, 3], [2, 5]]),
         "episode_return": np.array([[1.0, 2.0], [0.0, 10.0]])}
    s = results.summarize(m, wall_time_s=1.5)
    assert s["final_success_mean"] == pytest.approx(0.9)
    assert s["steps_to_80"] == 20 and s["steps_to_50"] == 20
    assert s["final_n_goals_mean"] == 4.0
    path = tmp_path / "metrics.csv"
    results.write_metrics_csv(path, results.metrics_rows("gara", m, seeds=[7, 9]))
    rows = results.read_metrics_csv(path)
    assert len(rows) == 4 and rows[3]["seed"] == 9 and rows[3]["n_goals"] == 5
    assert rows[2]["eval_success"] == 0.0 and rows[1]["env_step"] == 20


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    path = tmp_path / "summary.json"
    results.write_json(path, {"a": 1})

    class Boom:
        def __bytes__(self):
            raise RuntimeError

    with pytest.raises(TypeError):
        results.write_json(path, {"a": Boom()})
    assert path.read_text().strip().startswith("{") and '"a": 1' in path.read_text()
    assert [p for p in os.listdir(tmp_path) if p.endswith(".tmp")] == []


def test_reproduce_summary_compares_the_results_methods_with_the_authors():
    from experiments.u_maze import print_table, summarize_method

    n_seeds, n_episodes = 2, 420
    success = [np.r_[np.zeros(300), np.ones(120)], np.r_[np.zeros(300), np.zeros(120)]]
    record = {"wall_time_s": 1.0,
              "metrics": {"env_steps": [[3000, 3000], [6000, 6000]],
                          "eval_success": [[0.0, 0.0], [1.0, 0.0]],
                          "n_goals": [[2, 2], [9, 5]]},
              "episodes": {"success": success,
                           "end_step": [np.arange(1, n_episodes + 1) * 14] * n_seeds}}
    s = summarize_method(record, "gara_reference_results")
    assert s["train_success_ep300_400"]["mean"] == pytest.approx(0.5)
    d = s["against_authors"]
    assert d["train_success_ep300_400"]["mean"] == pytest.approx(0.5 - 0.664)
    assert d["final_n_goals"]["ours_mean"] == 7.0 and d["final_n_goals"]["n"] == [2, 5]
    assert "against the authors' runs" in print_table({"gara_reference_results": s})
    # Other methods, or another maze, are not compared.
    assert "against_authors" not in summarize_method(record, "gara")
    assert "against_authors" not in summarize_method(record, "gara_reference_results",
                                                     "four_rooms")
