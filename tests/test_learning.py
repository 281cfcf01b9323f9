"""Learning test: the Handcrafted agent solves the U-maze (SPEC.md defaults, 5 seeds)."""

import numpy as np
import pytest

from gara_jax.algorithms import HandcraftedConfig
from gara_jax.train import train_many

# Optimised compiles (tests/conftest.py): learning runs, whose run time dominates.
pytestmark = pytest.mark.optimized


@pytest.mark.slow
def test_handcrafted_reaches_the_exit_greedily_within_120k_steps():
    res = train_many(HandcraftedConfig(), seeds=5, total_steps=120_000)
    final = res.metrics["eval_success"][:, -1]
    curve = np.round(res.metrics["eval_success"].mean(axis=0), 2).tolist()
    assert res.metrics["env_steps"][0, -1] == 120_000
    assert final.mean() >= 0.7, f"final greedy success per seed {final}, mean curve {curve}"
    # Training episodes succeed too (epsilon-greedy, while still learning).
    assert res.metrics["train_success"][:, -5:].mean() >= 0.7
