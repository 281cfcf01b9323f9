import os

import numpy as np
import pytest

from gara_jax import results


def test_mean_ci95_matches_student_t_by_hand():
    x = np.array([[0.2, 1.0], [0.4, 1.0], [0.9, 1.0]])
    mean, half = results.mean_ci95(x, axis=0)
    np.testing.assert_allclose(mean, [0.5, 1.0])
    sd = np.sqrt(((0.2 - 0.5) ** 2 + (0.4 - 0.5) ** 2 + (0.9 - 0.5) ** 2) / 2)
    np.testing.assert_allclose(half, [4.303 * sd / np.sqrt(3), 0.0])


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
