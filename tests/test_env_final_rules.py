"""The authors' final collision rules (``Maze(collision="final")``, SPEC.md section 1)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.maze import random_rollout, state_from_vector, state_to_vector
from envs.reference import final_rules_step, reference_step

WALL = [(1.0, 1.5, -1.0, 2.0)]


@pytest.mark.parametrize(
    ("state", "action", "reference", "final"),
    [
        # Resting on the face x = 1 and pushing away: stuck under the reference rules only.
        ((1.0, 0.5, 0.0, 0.0), 0, (1.0, 0.5, 0.0, 0.0), (0.9, 0.5, -0.1, 0.0)),
        # SPEC's example: a bound clamp puts the agent inside the wall unless walls are checked.
        ((0.5, 0.0, 0.7, 0.0), 3, (1.15, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
        # Pushing into the face still stops at t = 0 under both rules.
        ((1.0, 0.5, 0.2, 0.0), 1, (1.0, 0.5, 0.0, 0.0), (1.0, 0.5, 0.0, 0.0)),
    ],
)
def test_hand_cases(state, action, reference, final):
    np.testing.assert_allclose(reference_step(state, action, 3.0, WALL), reference, atol=1e-12)
    np.testing.assert_allclose(final_rules_step(state, action, 3.0, WALL), final, atol=1e-12)
    with jax.enable_x64(True):
        for collision, expected in (("reference", reference), ("final", final)):
            env, params = envs.make("u_maze", collision=collision)
            _, nxt, *_ = env.step(jax.random.key(0), state_from_vector(jnp.asarray(state)),
                                  action, params)
            np.testing.assert_allclose(state_to_vector(nxt), expected, atol=1e-12)


def test_the_first_wall_entered_is_hit_not_the_first_listed():
    # Both walls lie on the segment x in [0.5, 1.5]; the second in the list is entered first.
    walls = [(1.3, 1.6, -1.0, 3.0), (1.0, 1.2, -1.0, 3.0)]
    state = (0.5, 1.0, 1.0, 0.0)  # RIGHT keeps vx = 1
    assert reference_step(state, 1, 3.0, walls)[0] == pytest.approx(1.3)  # through the nearer
    assert final_rules_step(state, 1, 3.0, walls)[0] == pytest.approx(1.0)


@pytest.mark.parametrize("layout", ["four_rooms", "labyrinth"])
def test_x64_steps_equal_the_plain_python_rules(layout):
    """Random states, a third of them on wall faces or bounds, every action: to 1e-12."""
    rng = np.random.default_rng(7)
    with jax.enable_x64(True):
        env, params = envs.make(layout, collision="final")
        n, walls = params.n, params.walls
        count = 3000
        states = np.c_[rng.uniform(0, n, (count, 2)), rng.uniform(-1, 1, (count, 2))]
        for axis, faces in ((0, walls[:, :2]), (1, walls[:, 2:])):
            faces = np.unique(np.r_[np.clip(faces.ravel(), 0, n), 0.0, n])
            on_face = rng.random(count) < 0.3
            states[on_face, axis] = rng.choice(faces, on_face.sum())
        states[rng.random(count) < 0.3, 2:] = 0.0
        actions = rng.integers(0, 4, count)
        step = jax.jit(jax.vmap(lambda s, a: state_to_vector(
            env.step(jax.random.key(0), state_from_vector(s), a, params)[1])))
        got = np.asarray(step(jnp.asarray(states), jnp.asarray(actions)))
    want = np.array([final_rules_step(s, int(a), n, walls.tolist())
                     for s, a in zip(states, actions, strict=True)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # The rules differ from the reference ones on some of these states.
    ref = np.array([reference_step(s, int(a), n, walls.tolist())
                    for s, a in zip(states, actions, strict=True)])
    assert (np.abs(ref - want).max(axis=1) > 1e-9).sum() > 50


def test_random_policies_reach_spec_rates():
    """SPEC.md section 1: 14.9% (uniform) and 71.2% (sticky 0.7) under the final rules."""
    env, params = envs.make("u_maze", collision="final")
    rollouts = jax.jit(jax.vmap(random_rollout, in_axes=(None, None, 0, None, None)),
                       static_argnums=(0, 3))
    keys = jax.random.split(jax.random.key(20231), 4000)
    for sticky_prob, rate in ((0.0, 0.149), (0.7, 0.712)):
        success, _ = rollouts(env, params, keys, 300, sticky_prob)
        assert abs(float(np.mean(success)) - rate) < 0.03, (sticky_prob, np.mean(success))


def test_bad_collision_name_is_refused():
    with pytest.raises(ValueError, match="collision"):
        envs.make("u_maze", collision="strict")
    assert envs.make("u_maze", collision="final")[0] != envs.make("u_maze")[0]
