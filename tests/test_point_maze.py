"""The brax-simulated U-maze: walls hold, speed stays bounded, the functional API, Gymnasium.

Compilations are the slow part (several seconds each), so the file compiles few shapes: one
jitted scan over a batch of 64 (shared by the physics tests), one jitted single step (shared by
the single-step tests and the module's docstring examples, which run here rather than in
test_doctests.py so that they find it compiled and optimised), the Gymnasium adapter's step.
"""

from __future__ import annotations

import doctest
import warnings

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

# Optimised compiles (tests/conftest.py): brax's physics runs about 5x slower unoptimised.
pytestmark = pytest.mark.optimized

import envs
from envs.maze import state_from_vector
from envs.point_maze import (
    BALL_RADIUS,
    DAMPING,
    FORCE,
    MAX_SPEED,
    EnvParams,
    PointMaze,
    maze_mjcf,
)

BATCH, STEPS = 64, 1600  # 102,400 random steps
STICKY = 0.9  # long pushes, so the ball hits walls near its top speed
PENETRATION_TOL = 0.02  # soft contacts: the ball may sink this far into a wall or bound


def sticky_rollout(env, params, key, batch, steps):
    """A batch of sticky-random-policy trajectories with auto-reset, starting at the start.

    Returns the per-step states ``[T, B, 4]`` (before clipping), observations, actions,
    rewards, terminations and the ``hit_wall`` flags.
    """
    keys = jax.random.split(key, batch)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    step = jax.vmap(env.step_autoreset, in_axes=(0, 0, 0, None))

    def body(carry, key):
        state, prev = carry
        k_act, k_keep, k_env = jax.random.split(key, 3)
        fresh = jax.random.randint(k_act, (batch,), 0, env.num_actions)
        action = jnp.where(jax.random.uniform(k_keep, (batch,)) < STICKY, prev, fresh)
        obs, state, reward, terminated, truncated, info = step(
            jax.random.split(k_env, batch), state, action, params
        )
        # The unclipped physical state; where an episode ended (and the state was reset) only
        # the observation of the last state is left.
        raw = jnp.stack([state.x, state.y, state.vx, state.vy], -1)
        raw = jnp.where((terminated | truncated)[:, None], info["final_obs"], raw)
        return (state, action), (raw, obs, action, reward, terminated, info["hit_wall"])

    init = (state, jnp.zeros(batch, jnp.int32))
    _, out = jax.lax.scan(body, init, jax.random.split(key, steps))
    return out


@pytest.fixture(scope="module")
def maze():
    return envs.make("point_u_maze")


@pytest.fixture(scope="module")
def rollout(maze):
    env, params = maze
    run = jax.jit(sticky_rollout, static_argnums=(0, 3, 4))
    return run, run(env, params, jax.random.key(0), BATCH, STEPS)


@pytest.fixture(scope="module")
def single_step(maze):
    # The action as a Python int (weakly typed), whatever the caller passes, as the module's
    # docstring example passes it: a jnp int32 scalar is another signature, another 10-s compile.
    jitted = jax.jit(maze[0].step)
    return lambda key, state, action, params: jitted(key, state, int(action), params)


# ----------------------------------------------------------------------------------------------
# Registry, parameters, model
# ----------------------------------------------------------------------------------------------


def test_registered_everywhere(maze):
    env, params = maze
    assert "point_u_maze" in envs.ENV_NAMES and isinstance(env, PointMaze)
    assert (params.force, params.damping, params.max_steps) == (FORCE, DAMPING, 300)
    np.testing.assert_array_equal(params.walls, [[1.0, 1.5, -1.0, 2.0]])
    assert env == PointMaze() and hash(env) == hash(PointMaze())  # jit-cache friendly
    assert "gara_jax/PointUMaze-v0" in gymnasium.registry


@pytest.mark.parametrize(
    "field, value",
    [("force", 0.0), ("damping", -0.1), ("damping", np.nan), ("max_steps", 0),
     ("exit_half_width", 0.0), ("start", [4.0, 0.0]), ("exit_reward", np.inf)],
)
def test_bad_params_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        EnvParams.create(**{field: value})
    with pytest.raises(ValueError, match=field):
        envs.make("point_u_maze", **{field: value})


def test_geometry_is_the_models():
    with pytest.raises(ValueError, match="walls"):
        envs.make("point_u_maze", walls=[[0.0, 1.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="start"):
        envs.make("point_u_maze", start=[0.95, 1.0])  # the ball would overlap the wall
    with pytest.raises(ValueError, match="ball_radius"):
        PointMaze(ball_radius=1.0)
    with pytest.raises(ValueError, match="substeps"):
        PointMaze(substeps=0)
    with pytest.raises(ValueError, match="walls"):
        PointMaze("labyrinth")  # zero-thickness walls are not boxes
    text = maze_mjcf(3.0, [[1.0, 1.5, -1.0, 2.0]])
    assert text.count('type="box"') == 5 and 'type="plane"' in text


# ----------------------------------------------------------------------------------------------
# Physics over 100,000 random steps (one compilation)
# ----------------------------------------------------------------------------------------------


def test_walls_and_bounds_hold(rollout, maze):
    _, (raw, obs, _, _, _, hit_wall) = rollout
    env, params = maze
    raw = np.asarray(raw, np.float64)
    x, y = raw[..., 0], raw[..., 1]
    x_lo, x_hi, y_lo, y_hi = np.asarray(params.walls)[0]
    # Distance from the centre to the wall rectangle; inside it counts as negative depth.
    dx, dy = np.maximum(x_lo - x, x - x_hi), np.maximum(y_lo - y, y - y_hi)
    dist = np.where((dx < 0) & (dy < 0), np.maximum(dx, dy),
                    np.hypot(np.maximum(dx, 0), np.maximum(dy, 0)))
    assert dist.min() >= BALL_RADIUS - PENETRATION_TOL, dist.min()
    assert raw[..., :2].min() >= -PENETRATION_TOL and raw[..., :2].max() <= 3 + PENETRATION_TOL
    # Not vacuous: the ball pressed against the wall and the bounds often.
    assert np.asarray(hit_wall).mean() > 0.01
    assert (x < 0.01).mean() > 0.01
    assert dist.min() < BALL_RADIUS + 0.01
    space = env.observation_space(params)
    flat = np.asarray(obs).reshape(-1, 4)
    assert np.all(flat >= np.asarray(space.low)) and np.all(flat <= np.asarray(space.high))


def test_speed_stays_bounded(rollout):
    _, (raw, *_) = rollout
    speed = np.abs(np.asarray(raw)[..., 2:])
    # Each component is pushed by FORCE and damped at DAMPING: it stays below FORCE / DAMPING.
    assert speed.max() <= min(MAX_SPEED, FORCE / DAMPING) + 1e-3, speed.max()
    assert speed.max() > 0.5 * FORCE / DAMPING  # the sticky policy reaches near top speed


def test_episodes_end_at_the_exit(rollout):
    _, (raw, _, _, reward, terminated, _) = rollout
    terminated, reward = np.asarray(terminated), np.asarray(reward)
    assert terminated.any()
    np.testing.assert_array_equal(reward, np.where(terminated, 10.0, 0.0))
    ends = np.asarray(raw)[terminated]
    assert np.all(np.abs(ends[:, 0] - 3.0) < 0.5) and np.all(np.abs(ends[:, 1]) < 0.5)


def test_same_key_same_trajectory(rollout, maze):
    run, first = rollout
    env, params = maze
    again = run(env, params, jax.random.key(0), BATCH, STEPS)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # Different keys, different trajectories: the batch's members (each its own split key)
    # took different actions and went different ways (no second rollout needed).
    obs, actions = np.asarray(first[1]), np.asarray(first[2])
    assert not np.array_equal(actions[:, 0], actions[:, 1])
    assert not np.array_equal(obs[:, 0], obs[:, 1])


def test_scan_vmap_agree_with_single_steps(rollout, maze, single_step):
    _, (_, obs, actions, reward, terminated, _) = rollout
    env, params = maze
    # env.step, not step_autoreset: no episode ends within 25 steps of the start (asserted), so
    # the two agree here, and the single-step tests' program is reused.
    step = single_step
    key = jax.random.key(0)
    assert not np.asarray(terminated[:25, :3]).any()
    for b in range(3):
        _, state = env.reset(key, params)
        for t in range(25):
            out = step(key, state, actions[t, b], params)
            state = out[1]
            np.testing.assert_allclose(out[0], obs[t, b], atol=1e-5)
            assert float(out[2]) == float(reward[t, b]) and bool(out[3]) == bool(terminated[t, b])


# ----------------------------------------------------------------------------------------------
# Single steps (one compilation) and Gymnasium
# ----------------------------------------------------------------------------------------------


def test_push_slide_and_stop(maze, single_step):
    env, params = maze
    step = single_step
    key = jax.random.key(0)
    # RIGHT from rest: the first push gives about FORCE of velocity, damped within the step.
    obs, *_ = step(key, env.reset(key, params)[1], envs.maze.RIGHT, params)
    assert 0.7 * FORCE < float(obs[2]) < FORCE and float(obs[3]) == 0.0
    # Moving fast into the wall's left face at x = 1: stopped one radius short, at rest in x.
    state = state_from_vector(jnp.array([0.7, 1.0, 0.5, 0.0]))
    obs, state, _, _, _, info = step(key, state, envs.maze.RIGHT, params)
    obs, state, _, _, _, info = step(key, state, envs.maze.RIGHT, params)
    assert abs(float(obs[0]) - (1.0 - BALL_RADIUS)) < PENETRATION_TOL and bool(info["hit_wall"])
    assert abs(float(obs[2])) < 0.05
    # Pressed against the face, it still slides along it (frictionless contact).
    obs, *_ = step(key, state.replace(vy=jnp.float32(0.3)), envs.maze.RIGHT, params)
    assert float(obs[1]) > 1.2 and float(obs[3]) > 0.2
    # Into the exit square: terminated with reward 10.
    state = state_from_vector(jnp.array([2.4, 0.0, 0.3, 0.0]))
    obs, _, reward, terminated, truncated, _ = step(key, state, envs.maze.RIGHT, params)
    assert bool(terminated) and float(reward) == 10.0 and not bool(truncated)


def test_docstring_examples(maze, single_step):
    # envs.point_maze's examples (left out of test_doctests.py): optimised, and with the single
    # step compiled first (read back from the session's compile cache), they took 17 s here
    # against 23 s unoptimised in test_doctests.py; most of it is the vmapped autoreset step.
    env, params = maze
    key = jax.random.key(0)
    jax.block_until_ready(single_step(key, env.reset(key, params)[1], envs.maze.RIGHT, params))
    result = doctest.testmod(envs.point_maze, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0, result


def test_gymnasium_check_env_render_and_truncation():
    env = gymnasium.make("gara_jax/PointUMaze-v0", render_mode="rgb_array", max_steps=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no checker warnings either
        check_env(env.unwrapped, skip_render_check=False)
    env.reset(seed=0)
    ended = [env.step(0)[3] for _ in range(20)]
    assert ended == [False] * 19 + [True]
    env.unwrapped.set_goal_boxes([[1.5, 0.0, -1, -1]], [[3.0, 2.0, 1, 1]])
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8
    env.unwrapped.set_goal_boxes(None, None)
    assert not np.array_equal(env.render(), frame)  # the overlay was drawn
