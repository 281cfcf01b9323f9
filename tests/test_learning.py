"""Learning test: the Handcrafted agent solves the U-maze (SPEC.md defaults, 5 seeds)."""

import numpy as np
import pytest

from gara_jax.algorithms import HandcraftedConfig
from gara_jax.train import train_many

# Optimised compiles (tests/conftest.py): learning runs, whose run time dominates.
pytestmark = pytest.mark.optimized


@pytest.mark.slow
def test_handcrafted_reaches_the_exit_greedily_within_45k_steps():
    # A bit under 4x the 12,000 steps at which Handcrafted's 20-seed greedy success reaches
    # 0.8 (docs/mazes.md, "Step budgets"); the paper's 120,000 would only add steps at 1.0.
    res = train_many(HandcraftedConfig(), seeds=5, total_steps=45_000)
    final = res.metrics["eval_success"][:, -1]
    curve = np.round(res.metrics["eval_success"].mean(axis=0), 2).tolist()
    assert res.metrics["env_steps"][0, -1] == 45_000
    assert final.mean() >= 0.7, f"final greedy success per seed {final}, mean curve {curve}"
    # Training episodes succeed too (epsilon-greedy, while still learning).
    assert res.metrics["train_success"][:, -5:].mean() >= 0.7
