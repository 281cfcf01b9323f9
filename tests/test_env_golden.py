"""Parity with the authors' reference: golden trajectories (x64) and sanity statistics (float32)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.maze import random_rollout, state_from_vector
from envs.reference import NumpyReferenceMaze, ReferenceMaze


# The golden trajectories ship with the tests (tests/data/README.md says where they came from).
GOLDEN = Path(__file__).resolve().parent / "data" / "u_maze_reference_trajectories.npz"


@pytest.fixture(scope="module")
def golden():
    path = GOLDEN
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def test_golden_layout_is_the_u_maze(golden):
    _, params = envs.make("u_maze")
    assert float(golden["maze"][0]) == params.n
    np.testing.assert_array_equal(golden["walls"], params.walls)
    np.testing.assert_array_equal(golden["start"], params.start)
    np.testing.assert_array_equal(golden["exit"], params.exit)


def test_golden_trajectories_x64(golden):
    states, actions = golden["states"], golden["actions"]
    lengths, rewards, dones = golden["lengths"], golden["rewards"], golden["dones"]
    valid = np.arange(actions.shape[1])[None, :] < lengths[:, None]
    with jax.enable_x64(True):
        env, params = envs.make("u_maze")

        def replay(s0, acts):
            def body(state, a):
                obs, state, reward, term, trunc, _ = env.step(jax.random.key(0), state, a, params)
                return state, (obs, reward, term, trunc)

            return jax.lax.scan(body, state_from_vector(s0), acts)[1]

        obs, reward, term, trunc = jax.jit(jax.vmap(replay))(
            jnp.asarray(states[:, 0]), jnp.asarray(actions)
        )
        assert obs.dtype == jnp.float64
        obs, reward, term, trunc = map(np.asarray, (obs, reward, term, trunc))
    assert valid.sum() > 20_000  # the whole file is checked, not a sample
    np.testing.assert_allclose(obs[valid], states[:, 1:][valid], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(reward[valid], rewards[valid])
    np.testing.assert_array_equal(term[valid], dones[valid])
    # "done" in the golden file means the exit was reached; 300-step rows end by truncation,
    # which our env reports on their last step (time starts at 0 for every row).
    last = lengths - 1
    rows = np.arange(len(lengths))
    full = lengths == actions.shape[1]
    assert full.any() and (~full).any()
    np.testing.assert_array_equal(trunc[rows, last], full & ~dones[rows, last])
    assert not trunc[valid & (np.arange(actions.shape[1])[None, :] < last[:, None])].any()


# The NumPy form is about 15x slower per step; every 8th trajectory is plenty for it (it is
# also checked for bit-identical states against the Python-floats form on every layout).
@pytest.mark.parametrize(("reference", "every"), [(ReferenceMaze, 1), (NumpyReferenceMaze, 8)])
def test_golden_trajectories_plain_python_reference(golden, reference, every):
    env = reference.from_layout("u_maze")
    for i in range(0, len(golden["lengths"]), every):
        env.reset(golden["states"][i, 0])
        steps = [env.step(int(a)) for a in golden["actions"][i, : golden["lengths"][i]]]
        obs, reward, terminated, _ = map(np.asarray, zip(*steps, strict=True))
        valid = slice(0, len(steps))
        np.testing.assert_allclose(obs, golden["states"][i, 1:][valid], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(reward, golden["rewards"][i, valid])
        np.testing.assert_array_equal(terminated, golden["dones"][i, valid])


# SPEC.md section 1: success rates and mean successful lengths from the start, 300 steps.
SANITY = {0.0: (0.089, 206.0), 0.7: (0.610, 152.0)}
EPISODES = 4000
# One jitted function for both policies (the repeat probability is traced), compiled once.
ROLLOUTS = jax.jit(
    jax.vmap(random_rollout, in_axes=(None, None, 0, None, None)), static_argnums=(0, 3)
)


@pytest.mark.parametrize("sticky_prob", sorted(SANITY))
def test_float32_random_policies_match_reference_rates(sticky_prob):
    env, params = envs.make("u_maze")
    keys = jax.random.split(jax.random.key(20231), EPISODES)
    success, length = ROLLOUTS(env, params, keys, 300, sticky_prob)
    assert success.shape == (EPISODES,)
    success, length = np.asarray(success), np.asarray(length)
    rate, mean_length = SANITY[sticky_prob]
    assert abs(success.mean() - rate) < 0.04, success.mean()
    # Standard error of the mean length is about 3 steps here; 15 is a loose, robust bound.
    assert abs(length[success].mean() - mean_length) < 15, length[success].mean()
    assert (length[~success] == 300).all() and (length[success] <= 300).all()
