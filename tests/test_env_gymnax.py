"""Both mazes as gymnax Environments: gymnax's own wrappers under jit(vmap(scan))."""

from __future__ import annotations

import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest

if importlib.util.find_spec("gymnax") is None:  # installed but broken must fail, not skip
    pytest.skip("gymnax is not installed (the gymnax extra)", allow_module_level=True)
from gymnax.environments import environment, spaces  # noqa: E402
from gymnax.wrappers.purerl import FlattenObservationWrapper, LogWrapper  # noqa: E402

from envs.gymnax_adapter import GymnaxMaze, make_gymnax  # noqa: E402

BATCH, STEPS, EPISODE = 4, 7, 3


def logged_rollout(env, params, key):
    """PureJaxRL's pattern: vmapped reset, then a scan of vmapped steps with random actions."""
    keys = jax.random.split(key, BATCH)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

    def body(state, key):
        k_act, k_env = jax.random.split(key)
        action = jax.random.randint(k_act, (BATCH,), 0, env.action_space(params).n)
        obs, state, reward, terminated, truncated, info = jax.vmap(
            env.step, in_axes=(0, 0, 0, None)
        )(jax.random.split(k_env, BATCH), state, action, params)
        return state, (obs, truncated, info)

    _, out = jax.lax.scan(body, state, jax.random.split(key, STEPS))
    return obs, out


@pytest.mark.parametrize("name", ["u_maze", "point_u_maze"])
def test_log_wrapper_under_jit_vmap(name):
    env, params = make_gymnax(name, max_steps=EPISODE)
    assert isinstance(env, environment.Environment)
    assert isinstance(env.action_space(params), spaces.Discrete)
    wrapped = LogWrapper(FlattenObservationWrapper(env))
    obs0, (obs, truncated, info) = jax.jit(logged_rollout, static_argnums=0)(
        wrapped, params, jax.random.key(0)
    )
    assert obs0.shape == (BATCH, 4) and obs.shape == (STEPS, BATCH, 4)
    # Nothing reaches the exit in 7 steps from the start: every third step truncates and the
    # wrapper logs an episode of length 3 and return 0.
    ended = (np.arange(STEPS) % EPISODE == EPISODE - 1)[:, None]
    np.testing.assert_array_equal(np.asarray(truncated), np.broadcast_to(ended, truncated.shape))
    np.testing.assert_array_equal(np.asarray(info["returned_episode"]), np.asarray(truncated))
    lengths = np.asarray(info["returned_episode_lengths"])
    assert np.all(lengths[EPISODE - 1 :] == EPISODE)
    assert np.all(np.asarray(info["returned_episode_returns"]) == 0.0)
    # The reset observation is the start; final_observation is the state before the reset.
    reset_rows = np.asarray(obs)[EPISODE - 1]
    np.testing.assert_allclose(reset_rows, np.zeros((BATCH, 4)), atol=1e-6)
    assert not np.allclose(np.asarray(info["final_observation"])[EPISODE - 1], 0.0)


def test_adapter_semantics_match_the_native_env():
    env, params = make_gymnax("u_maze")
    native = env.wrapped
    key = jax.random.key(0)
    obs, state = env.reset(key, params)
    state = state.replace(x=jnp.float32(2.45))
    out = env.step(key, state, 1, params)
    ref = native.step_autoreset(key, state, 1, params)
    np.testing.assert_array_equal(out[0], ref[0])
    assert bool(out[3]) and bool(out[5]["terminated"]) and float(out[2]) == 10.0
    _, _, _, terminated, info = env.step_env(key, state, 1, params)
    assert bool(terminated) and "final_obs" in info
    assert env == GymnaxMaze(native, params) and hash(env) == hash(GymnaxMaze(native, params))
    assert env != GymnaxMaze(native)  # other default parameters: not interchangeable under jit
    assert env.name == "u_maze" and env.num_actions == 4
    assert bool(env.observation_space(params).contains(obs))
