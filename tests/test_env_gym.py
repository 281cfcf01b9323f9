"""The Gymnasium adapter: registration, env_checker, errors, truncation, rendering."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium
import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs
from envs.gym_adapter import MazeEnv
from envs.maze import state_from_vector

IDS = dict(envs.GYM_IDS)


@pytest.mark.parametrize("layout", envs.LAYOUTS)
def test_check_env_passes_for_every_id(layout):
    env = gymnasium.make(IDS[layout], render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no checker warnings either
        check_env(env.unwrapped)
    env.close()


def test_check_env_on_the_wrapped_env():
    env = gymnasium.make("gara_jax/UMaze-v0", render_mode="rgb_array")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    # The only complaint allowed is gymnasium's note that the env is wrapped.
    assert all("unwrapped" in str(w.message) for w in caught), [str(w.message) for w in caught]


def test_episode_length_and_spec():
    env = gymnasium.make("gara_jax/UMaze-v0")
    assert env.spec.max_episode_steps is None  # the env truncates itself, no TimeLimit
    env.reset(seed=0)
    for t in range(1, 301):
        obs, reward, terminated, truncated, info = env.step(0)  # LEFT: stays in the corner
        assert not terminated and truncated == (t == 300)
    assert set(info) == {"hit_bound", "hit_wall"}
    short = gymnasium.make("gara_jax/UMaze-v0", max_steps=5)
    short.reset(seed=0)
    assert [short.step(0)[3] for _ in range(5)] == [False] * 4 + [True]


def test_termination_reward_and_state_option():
    env = gymnasium.make("gara_jax/UMaze-v0")
    obs, info = env.reset(seed=1, options={"state": [2.45, 0.0, 0.0, 0.0]})
    np.testing.assert_allclose(obs, [2.45, 0.0, 0.0, 0.0], rtol=1e-6)
    obs, reward, terminated, truncated, _ = env.step(1)
    assert (reward, terminated, truncated) == (10.0, True, False)
    assert obs.dtype == np.float32 and env.observation_space.contains(obs)
    with pytest.raises(ValueError, match="state"):
        env.reset(options={"state": [5.0, 0.0, 0.0, 0.0]})


@pytest.mark.parametrize("bad", [4, -1, 1.5, "1", None, np.array([0, 1])])
def test_invalid_actions_raise(bad):
    env = gymnasium.make("gara_jax/FourRooms-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.unwrapped.step(bad)


def test_numpy_integer_actions_are_accepted():
    env = MazeEnv("u_maze")
    env.reset(seed=0)
    obs = env.step(np.int64(1))[0]
    np.testing.assert_allclose(obs, [0.1, 0.0, 0.1, 0.0], rtol=1e-6)


def test_adapter_matches_the_jax_env():
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, 60)
    env = gymnasium.make("gara_jax/BigUMaze-v0")
    env.reset(seed=0)
    gym_obs = np.stack([env.step(int(a))[0] for a in actions])
    jenv, params = envs.make("big_u_maze")
    step = jax.jit(jenv.step)
    state = state_from_vector(np.zeros(4, np.float32))
    for t, a in enumerate(actions):
        obs, state, *_ = step(jax.random.key(0), state, a, params)
        np.testing.assert_array_equal(gym_obs[t], np.asarray(obs))


def test_render_and_goal_boxes():
    env = gymnasium.make("gara_jax/UMaze-v0", render_mode="rgb_array", render_size=128)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (128, 128, 3) and frame.dtype == np.uint8
    env.unwrapped.set_goal_boxes([[1.5, 2.0, -1, -1]], [[3.0, 3.0, 1, 1]])
    boxed = env.render()
    assert (boxed != frame).any()
    # Pixels change only in the upper-right region the box covers (x > 1.5, y > 2).
    changed_rows, changed_cols = np.nonzero((boxed != frame).any(-1))
    assert changed_cols.min() >= 128 * 1.5 / 3 - 3 and changed_rows.max() <= 128 / 3 + 3
    env.unwrapped.set_goal_boxes(None, None)
    np.testing.assert_array_equal(env.render(), frame)
    with pytest.raises(ValueError, match="shape"):
        env.unwrapped.set_goal_boxes([[0, 0]], [[1, 1, 1]])


def test_render_without_mode_warns_and_returns_none():
    env = MazeEnv("u_maze")
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None
    with pytest.raises(ValueError, match="render_mode"):
        MazeEnv("u_maze", render_mode="human")


def test_importing_gara_jax_registers_the_ids():
    code = (
        "import gymnasium, gara_jax; "
        "env = gymnasium.make('gara_jax/Labyrinth-v0'); "
        "print(env.reset(seed=0)[0].tolist())"
    )
    root = Path(__file__).resolve().parents[1]  # importable from here even without install
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
        cwd=root,
    )
    assert out.stdout.strip() == "[0.0, 0.0, 0.0, 0.0]"
