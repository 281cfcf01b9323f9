"""Behaviour of the pure-functional maze: API, jit/vmap/scan, validation, hand-checked rules."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.maze import EnvParams, EnvState, Maze, state_from_vector, state_to_vector
from envs.reference import (
    NumpyReferenceMaze,
    ReferenceMaze,
    reference_step,
    reference_step_numpy,
)

KEY = jax.random.key(0)
LEFT, RIGHT, UP, DOWN = 0, 1, 2, 3
# Jitted once per module (eager op-by-op dispatch of many tiny ops is what would be slow).
STEP = jax.jit(Maze().step)
STEP_AUTORESET = jax.jit(Maze().step_autoreset)


def test_make_every_layout():
    assert envs.LAYOUTS == ("u_maze", "four_rooms", "u_maze_6", "big_u_maze", "labyrinth")
    wall_counts = {"u_maze": 1, "four_rooms": 4, "u_maze_6": 1, "big_u_maze": 3, "labyrinth": 4}
    for name in envs.LAYOUTS:
        env, params = envs.make(name)
        assert isinstance(env, Maze) and env.num_actions == 4
        assert params.walls.shape == (wall_counts[name], 4)
        obs, state = env.reset(KEY, params)
        np.testing.assert_array_equal(obs, [*params.start, 0.0, 0.0])
        assert obs.dtype == jnp.float32 and state.time.dtype == jnp.int32
    assert envs.make("u_maze_6")[1].n == 6.0
    np.testing.assert_array_equal(envs.make("big_u_maze")[1].exit, [6.0, 3.0])


def test_unknown_layout_lists_valid_names():
    with pytest.raises(ValueError, match="u_maze, four_rooms, u_maze_6, big_u_maze, labyrinth"):
        envs.make("no_such_maze")


def test_make_overrides_fields():
    _, params = envs.make("u_maze", max_steps=50, exit_reward=1.0)
    assert params.max_steps == 50 and params.exit_reward == 1.0


def test_default_params_are_the_u_maze():
    default, made = EnvParams(), envs.make("u_maze")[1]
    for field in ("n", "walls", "start", "exit", "exit_half_width", "exit_reward", "max_steps"):
        np.testing.assert_array_equal(getattr(default, field), getattr(made, field))


def test_x64_reset_is_float64():
    with jax.enable_x64(True):
        env, params = envs.make("u_maze")
        obs, state = jax.jit(env.reset)(KEY, params)
        assert obs.dtype == jnp.float64 and state.time.dtype == jnp.int32


BAD_FIELDS = [
    ("n", {"n": 0.0}),
    ("n", {"n": float("nan")}),
    ("walls", {"walls": [1.0, 1.5, -1.0, 2.0]}),
    ("walls", {"walls": [[1.0, 1.5, -1.0]]}),
    ("walls", {"walls": [[1.0, np.inf, -1.0, 2.0]]}),
    ("walls", {"walls": [[1.5, 1.0, -1.0, 2.0]]}),
    ("start", {"start": [-0.1, 0.0]}),
    ("start", {"start": [0.0, 0.0, 0.0]}),
    ("start", {"start": [1.2, 1.0]}),  # strictly inside the U-maze wall
    ("exit", {"exit": [3.5, 0.0]}),
    ("exit", {"exit": [np.nan, 0.0]}),
    ("exit_half_width", {"exit_half_width": 0.0}),
    ("exit_reward", {"exit_reward": np.inf}),
    ("max_steps", {"max_steps": 0}),
    ("max_steps", {"max_steps": 2.5}),
]


@pytest.mark.parametrize(("field", "bad"), BAD_FIELDS)
def test_invalid_params_raise_naming_the_field(field, bad):
    with pytest.raises(ValueError, match=field):
        EnvParams.create(**bad)
    direct = {k: np.asarray(v) if isinstance(v, list) else v for k, v in bad.items()}
    with pytest.raises(ValueError, match=field):
        EnvParams(**direct)  # plain construction from host values validates too
    with pytest.raises(ValueError, match=field):
        envs.make("u_maze", **bad)


def test_create_accepts_jax_arrays_and_stores_host_float64():
    params = EnvParams.create(walls=jnp.array([[1.0, 1.5, -1.0, 2.0]]), start=jnp.zeros(2))
    assert isinstance(params.walls, np.ndarray) and params.walls.dtype == np.float64
    with pytest.raises(ValueError, match="start"):
        EnvParams.create(start=jnp.array([1.2, 1.0]))


def test_params_survive_jit_vmap_and_tree_ops():
    env, params = envs.make("u_maze")
    # Tracers inside jit: no validation, no error.
    obs, _ = jax.jit(env.reset)(KEY, params)
    np.testing.assert_array_equal(obs, [0, 0, 0, 0])
    # vmap over a stack of parameter sets (host arrays with a batch axis are validated
    # elementwise), and over an axis spec made of None/0 leaves.
    other = envs.make("u_maze", start=[2.0, 2.5])[1]
    stacked = jax.tree.map(lambda a, b: np.stack([np.asarray(a), np.asarray(b)]), params, other)
    obs, _ = jax.vmap(env.reset, in_axes=(None, 0))(KEY, stacked)
    np.testing.assert_array_equal(obs[:, :2], [[0.0, 0.0], [2.0, 2.5]])
    axes = EnvParams(None, None, 0, None, None, None, None)
    obs, _ = jax.vmap(env.reset, in_axes=(None, axes))(KEY, stacked)
    np.testing.assert_array_equal(obs[:, :2], [[0.0, 0.0], [2.0, 2.5]])
    # A batch with one bad member is still caught.
    bad = jax.tree.map(lambda a: np.asarray(a).copy(), stacked)
    with pytest.raises(ValueError, match="start"):
        EnvParams(
            bad.n,
            bad.walls,
            np.array([[0.0, 0.0], [1.2, 1.0]]),
            bad.exit,
            bad.exit_half_width,
            bad.exit_reward,
            bad.max_steps,
        )


def test_state_vector_round_trip_and_batch():
    s = jnp.array([[0.5, 1.0, 0.1, -0.2], [2.0, 2.5, 0.0, 0.3]])
    state = state_from_vector(s)
    # One array per coordinate, each with the batch shape; pos/vel are [..., 2] views.
    for name in ("x", "y", "vx", "vy", "time"):
        assert getattr(state, name).shape == (2,)
    np.testing.assert_array_equal(state.x, s[:, 0])
    np.testing.assert_array_equal(state.vy, s[:, 3])
    np.testing.assert_array_equal(state.pos, s[:, :2])
    np.testing.assert_array_equal(state.vel, s[:, 2:])
    np.testing.assert_array_equal(state_to_vector(state), s)
    np.testing.assert_array_equal(state.time, 0)
    assert state.time.dtype == jnp.int32
    with pytest.raises(ValueError, match="4"):
        state_from_vector(jnp.zeros(3))


def test_state_pos_vel_are_read_only_views():
    state = state_from_vector([1.0, 2.0, 0.5, -0.25])
    assert state.pos.tolist() == [1.0, 2.0] and state.vel.tolist() == [0.5, -0.25]
    with pytest.raises(AttributeError):
        state.pos = jnp.zeros(2)
    with pytest.raises(TypeError):
        state.replace(pos=jnp.zeros(2))
    # create() builds the same state from [..., 2] arrays, broadcasting time.
    made = EnvState.create(pos=[[1.0, 2.0]], vel=[[0.5, -0.25]], time=7)
    np.testing.assert_array_equal(state_to_vector(made), [[1.0, 2.0, 0.5, -0.25]])
    assert made.time.shape == (1,) and int(made.time[0]) == 7 and made.time.dtype == jnp.int32
    with pytest.raises(ValueError, match="2"):
        EnvState.create(pos=[1.0, 2.0, 3.0], vel=[0.0, 0.0])


def _step64(s, action, name="u_maze"):
    """One x64 step from vector ``s`` -> (next vector, reward, terminated, truncated, info)."""
    with jax.enable_x64(True):
        _, params = envs.make(name)
        obs, _, reward, term, trunc, info = STEP(KEY, state_from_vector(s), action, params)
        return np.asarray(obs), float(reward), bool(term), bool(trunc), info


def test_hand_checked_rules():
    # Acceleration and damping, including the reference's asymmetry for small negatives.
    np.testing.assert_allclose(_step64([1.8, 1.0, 0.3, 0.2], RIGHT)[0], [2.2, 1.15, 0.4, 0.15])
    np.testing.assert_allclose(_step64([1.8, 1.0, -0.03, 0.2], UP)[0], [1.82, 1.3, 0.02, 0.3])
    np.testing.assert_allclose(_step64([1.8, 1.0, -0.3, 0.2], UP)[0], [1.8, 1.3, 0.0, 0.3])
    np.testing.assert_allclose(_step64([1.8, 1.0, 0.0, 0.95], UP)[0], [1.8, 2.0, 0.0, 1.0])
    # Bounds first: the offending coordinate is clamped, the other keeps p', velocity stops.
    obs, *_, info = _step64([2.95, 1.0, 0.1, 0.2], RIGHT)
    np.testing.assert_allclose(obs, [3.0, 1.15, 0.0, 0.0])
    assert bool(info["hit_bound"]) and not bool(info["hit_wall"])
    # A wall stops the agent where the segment enters it.
    obs, *_, info = _step64([0.9, 0.5, 0.2, 0.0], RIGHT)
    np.testing.assert_allclose(obs, [1.0, 0.5, 0.0, 0.0], atol=1e-12)
    assert bool(info["hit_wall"])
    # Stuck on the face: moving away gives t* = 0 again; sliding along the face works.
    np.testing.assert_allclose(_step64([1.0, 0.5, 0.0, 0.0], LEFT)[0], [1.0, 0.5, 0.0, 0.0])
    np.testing.assert_allclose(_step64([1.0, 0.5, 0.0, 0.0], UP)[0], [1.0, 0.6, 0.0, 0.1])
    # The exit box is strict and rewards 10.
    obs, reward, term, trunc, _ = _step64([2.45, 0.0, 0.0, 0.0], RIGHT)
    assert (reward, term, trunc) == (10.0, True, False)
    np.testing.assert_allclose(obs[0], 2.55)
    assert _step64([2.4, 0.0, 0.0, 0.0], RIGHT)[2] is False  # |x - 3| = 0.5 is not < 0.5
    assert _step64([2.45, 0.5, 0.0, 0.0], RIGHT)[2] is False  # |y - 0| = 0.5 is not < 0.5


def test_first_wall_in_list_order_wins():
    # Both walls meet the segment; the second is met earlier, but the first in list order that
    # meets it at all decides t* (the reference's quirk: the agent passes through the other).
    near, far = [1.2, 1.4, 0.0, 3.0], [2.0, 2.5, 0.0, 3.0]
    start = [1.1, 1.0, 0.9, 0.0]
    with jax.enable_x64(True):
        for walls, stop in (([far, near], 2.0), ([near, far], 1.2)):
            params = EnvParams.create(walls=walls)
            obs = STEP(KEY, state_from_vector(start), RIGHT, params)[0]
            np.testing.assert_allclose(obs, [stop, 1.0, 0.0, 0.0], atol=1e-12)
            np.testing.assert_allclose(reference_step(start, RIGHT, 3.0, walls), obs, atol=1e-12)


def test_out_of_range_actions_are_clipped_inside_jit():
    _, params = envs.make("u_maze")
    step = STEP
    state = state_from_vector(jnp.array([1.8, 1.0, 0.3, 0.2]))
    for bad, same in ((-1, LEFT), (-100, LEFT), (4, DOWN), (7, DOWN)):
        np.testing.assert_array_equal(
            step(KEY, state, bad, params)[0], step(KEY, state, same, params)[0]
        )
    assert not np.array_equal(step(KEY, state, 7, params)[0], step(KEY, state, UP, params)[0])


def test_step_jit_vmap_scan_agree_with_single_steps():
    env, params = envs.make("four_rooms")
    batch, steps = 8, 25
    actions = jax.random.randint(jax.random.key(1), (batch, steps), 0, 4)
    _, state0 = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(KEY, batch), params)

    def rollout(state, acts):
        def body(state, a):
            obs, state, reward, term, trunc, info = env.step_autoreset(KEY, state, a, params)
            return state, (obs, reward, term, trunc, info["final_obs"])

        return jax.lax.scan(body, state, acts)

    final, (obs, reward, term, trunc, final_obs) = jax.jit(jax.vmap(rollout))(state0, actions)
    assert obs.shape == (batch, steps, 4) and reward.shape == term.shape == (batch, steps)
    step = jax.jit(env.step_autoreset)
    for i in (0, batch - 1):
        state = jax.tree.map(lambda x, i=i: x[i], state0)
        for t in range(steps):
            o, state, r, *_ = step(KEY, state, actions[i, t], params)
            np.testing.assert_allclose(o, obs[i, t], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(state.pos, final.pos[i], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(state.vel, final.vel[i], rtol=1e-6, atol=1e-6)
        assert int(state.time) == int(final.time[i])


def test_info_has_the_same_keys_for_step_and_autoreset():
    _, params = envs.make("u_maze")
    state = state_from_vector(jnp.array([1.8, 1.0, 0.3, 0.2]))
    info_a = STEP(KEY, state, RIGHT, params)[5]
    info_b = STEP_AUTORESET(KEY, state, RIGHT, params)[5]
    assert set(info_a) == set(info_b) == {"final_obs", "discount", "hit_bound", "hit_wall"}


def test_autoreset_on_termination_keeps_final_obs():
    _, params = envs.make("u_maze")
    state = state_from_vector(jnp.array([2.45, 0.0, 0.0, 0.0])).replace(time=jnp.int32(17))
    obs, new_state, reward, term, trunc, info = STEP_AUTORESET(KEY, state, RIGHT, params)
    assert bool(term) and not bool(trunc) and float(reward) == 10.0
    np.testing.assert_array_equal(obs, [0.0, 0.0, 0.0, 0.0])
    assert int(new_state.time) == 0
    np.testing.assert_allclose(info["final_obs"], [2.55, 0.0, 0.1, 0.0], atol=1e-6)
    assert float(info["discount"]) == 0.0
    # Not done: identical to step.
    state = state_from_vector(jnp.array([1.8, 1.0, 0.3, 0.2]))
    plain, auto = STEP(KEY, state, UP, params), STEP_AUTORESET(KEY, state, UP, params)
    np.testing.assert_array_equal(plain[0], auto[0])
    np.testing.assert_array_equal(auto[5]["final_obs"], auto[0])


def test_vmapped_autoreset_with_a_mix_of_ended_and_running_envs():
    env, params = envs.make("u_maze", max_steps=3)
    vectors = jnp.array(
        [
            [2.45, 0.0, 0.0, 0.0],  # reaches the exit
            [1.8, 1.0, 0.3, 0.2],  # runs out of time (time 2 -> 3)
            [0.5, 0.5, 0.0, 0.0],  # keeps going
            [2.95, 1.0, 0.1, 0.2],  # hits the bound, keeps going
            [0.9, 0.5, 0.2, 0.0],  # hits the wall, keeps going
        ]
    )
    states = state_from_vector(vectors).replace(time=jnp.array([0, 2, 0, 1, 0], jnp.int32))
    actions = jnp.array([RIGHT, UP, UP, RIGHT, RIGHT])
    batched = jax.jit(jax.vmap(env.step_autoreset, in_axes=(None, 0, 0, None)))
    obs, new_states, reward, term, trunc, info = batched(KEY, states, actions, params)
    np.testing.assert_array_equal(term, [True, False, False, False, False])
    np.testing.assert_array_equal(trunc, [False, True, False, False, False])
    np.testing.assert_array_equal(reward, [10.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(new_states.time, [0, 0, 1, 2, 1])
    np.testing.assert_array_equal(obs[:2], np.zeros((2, 4)))  # reset where the episode ended
    np.testing.assert_array_equal(obs, state_to_vector(new_states))
    np.testing.assert_array_equal(info["hit_bound"], [False, False, False, True, False])
    np.testing.assert_array_equal(info["hit_wall"], [False, False, False, False, True])
    np.testing.assert_allclose(info["final_obs"][0], [2.55, 0.0, 0.1, 0.0], atol=1e-6)
    np.testing.assert_allclose(info["final_obs"][3], [3.0, 1.15, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(info["final_obs"][4], [1.0, 0.5, 0.0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(info["discount"], [0.0, 1.0, 1.0, 1.0, 1.0])
    # Each row is what the unbatched step gives.
    for i in range(len(vectors)):
        state_i = jax.tree.map(lambda leaf, i=i: leaf[i], states)
        single = STEP_AUTORESET(KEY, state_i, actions[i], params)
        np.testing.assert_array_equal(single[0], obs[i])
        for a, b in zip(
            jax.tree.leaves(single[1:]),
            jax.tree.leaves((new_states, reward, term, trunc, info)),
            strict=True,
        ):
            np.testing.assert_array_equal(a, b[i])


def test_truncation_at_max_steps_then_reset():
    env, params = envs.make("u_maze")
    _, state = env.reset(KEY, params)

    def body(state, _):
        obs, state, reward, term, trunc, info = env.step_autoreset(KEY, state, LEFT, params)
        return state, (term, trunc, state.time, info["final_obs"])

    _, (term, trunc, time, final_obs) = jax.jit(lambda s: jax.lax.scan(body, s, None, length=301))(
        state
    )
    assert not term.any()
    np.testing.assert_array_equal(np.flatnonzero(trunc), [299])
    assert int(time[298]) == 299 and int(time[299]) == 0 and int(time[300]) == 1
    # Without auto-reset the episode reports truncation exactly once, at step 300.
    state = state.replace(time=jnp.int32(299))
    assert bool(STEP(KEY, state, LEFT, params)[4])
    assert not bool(STEP(KEY, state.replace(time=jnp.int32(298)), LEFT, params)[4])


def test_spaces():
    env, params = envs.make("u_maze_6")
    obs_space, act_space = env.observation_space(params), env.action_space(params)
    obs, _ = env.reset(KEY, params)
    assert bool(obs_space.contains(obs))
    np.testing.assert_array_equal(obs_space.high, [6.0, 6.0, 1.0, 1.0])
    samples = jax.jit(jax.vmap(obs_space.sample))(jax.random.split(KEY, 64))
    assert bool(jax.jit(jax.vmap(obs_space.contains))(samples).all())
    assert not bool(obs_space.contains(jnp.array([6.5, 0.0, 0.0, 0.0])))
    assert not bool(obs_space.contains(jnp.zeros(3)))
    actions = jax.jit(jax.vmap(act_space.sample))(jax.random.split(KEY, 256))
    assert set(np.unique(actions).tolist()) == {0, 1, 2, 3}
    assert [bool(act_space.contains(a)) for a in (0, 3, 4, -1, 1.5)] == [
        True,
        True,
        False,
        False,
        False,
    ]
    assert bool(jax.jit(act_space.contains)(jnp.int32(2)))


def _random_free_states(rng, spec, count):
    n, walls = spec.n, np.asarray(spec.walls)
    states = []
    while len(states) < count:
        x, y = rng.uniform(0, n, 2)
        inside = (walls[:, 0] < x) & (x < walls[:, 1]) & (walls[:, 2] < y) & (y < walls[:, 3])
        if not inside.any():
            states.append([x, y, *rng.uniform(-1, 1, 2)])
    return np.asarray(states)


@pytest.mark.parametrize("name", envs.LAYOUTS)
def test_matches_the_plain_python_reference_in_x64(name):
    """Independent cross-check on every layout: random free states, 40 random actions each."""
    rng = np.random.default_rng(envs.LAYOUTS.index(name))
    _, spec = envs.make(name)
    starts = _random_free_states(rng, spec, 64)
    actions = rng.integers(0, 4, (64, 40))
    with jax.enable_x64(True):
        env, params = envs.make(name)

        def replay(s0, acts):
            def body(state, a):
                obs, state, reward, term, trunc, info = env.step(KEY, state, a, params)
                return state, (obs, reward, term, info["hit_wall"], info["hit_bound"])

            return jax.lax.scan(body, state_from_vector(s0), acts)[1]

        outputs = jax.jit(jax.vmap(replay))(starts, actions)
        obs, reward, term, hit_wall, hit_bound = map(np.asarray, outputs)
    ref = ReferenceMaze.from_layout(name)
    expected = []
    for i in range(len(starts)):
        ref.reset(starts[i])
        expected.append([ref.step(int(a))[:3] for a in actions[i]])
    ref_obs = np.array([[step[0] for step in row] for row in expected])
    ref_reward = np.array([[step[1] for step in row] for row in expected])
    ref_term = np.array([[step[2] for step in row] for row in expected])
    np.testing.assert_allclose(obs, ref_obs, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(reward, ref_reward)
    np.testing.assert_array_equal(term, ref_term)
    # The sample exercises both collision rules, not just free flight.
    assert hit_wall.any() and hit_bound.any()


def test_reference_rejects_bad_actions():
    for reference in (ReferenceMaze, NumpyReferenceMaze):
        with pytest.raises(ValueError, match="action"):
            reference().step(4)


@pytest.mark.parametrize("name", envs.LAYOUTS)
def test_numpy_reference_gives_identical_states(name):
    """The NumPy-array form of the rules (the benchmark's second baseline) is bit-identical."""
    rng = np.random.default_rng(100 + envs.LAYOUTS.index(name))
    _, spec = envs.make(name)
    states = _random_free_states(rng, spec, 64)
    # Also exact rest, velocities at the damping threshold and states on wall faces.
    states[:4, 2:] = [[0.0, 0.0], [-0.05, 0.05], [-0.03, 0.0], [1.0, -1.0]]
    states[4:8, 0] = np.asarray(spec.walls)[0, 0]
    walls = np.asarray(spec.walls)
    hits = 0
    for s0 in states:
        s_py, s_np = tuple(s0), np.array(s0)
        for a in rng.integers(0, 4, 40).tolist():
            s_py = reference_step(s_py, a, spec.n, walls.tolist())
            s_np = reference_step_numpy(s_np, a, spec.n, walls)
            assert s_np.dtype == np.float64 and s_np.shape == (4,)
            np.testing.assert_array_equal(s_np, s_py)  # exact, not approximate
            hits += s_py[2:] == (0.0, 0.0)
    assert hits > 100  # collisions (and rests) are exercised, not just free flight
    # Whole episodes with resets through the stateful classes: same transitions.
    py_env, np_env = ReferenceMaze.from_layout(name), NumpyReferenceMaze.from_layout(name)
    py_env.reset(), np_env.reset()
    for a in rng.integers(0, 4, 700).tolist():
        (obs_py, *rest_py), (obs_np, *rest_np) = py_env.step(a), np_env.step(a)
        np.testing.assert_array_equal(obs_np, obs_py)
        assert rest_np == rest_py
        if rest_py[1] or rest_py[2]:
            py_env.reset(), np_env.reset()


def test_env_state_is_a_pytree():
    state = EnvState(
        x=jnp.zeros(()), y=jnp.ones(()), vx=jnp.zeros(()), vy=jnp.zeros(()), time=jnp.int32(0)
    )
    leaves = jax.tree.leaves(state)
    assert len(leaves) == 5 and all(leaf.shape == () for leaf in leaves)
    # vmap adds the batch axis to every field; tree maps see the fields, not pos/vel.
    _, batch = jax.vmap(Maze().reset, in_axes=(0, None))(jax.random.split(KEY, 3), EnvParams())
    assert all(leaf.shape == (3,) for leaf in jax.tree.leaves(batch))
    assert batch.pos.shape == batch.vel.shape == (3, 2)


def test_absorbing_states_are_the_inner_corners_of_overlapping_walls():
    # big_u_maze: where the wall x in [4, 4.5] meets the wall y in [3, 4], on both sides.
    # No other layout has one; the final rules free both.
    for name in envs.LAYOUTS:
        found = envs.absorbing_states(*envs.make(name)).tolist()
        assert found == ([[4.0, 3.0], [4.5, 3.0]] if name == "big_u_maze" else []), name
    assert envs.absorbing_states(*envs.make("big_u_maze", collision="final")).size == 0
    # Held there, every action for 20 steps leaves the agent where it is.
    env, params = envs.make("big_u_maze")
    step = jax.jit(env.step)
    for corner in ((4.0, 3.0), (4.5, 3.0)):
        for action in (LEFT, RIGHT, UP, DOWN):
            state = state_from_vector(jnp.array([*corner, 0.0, 0.0]))
            for _ in range(20):
                obs, state, *_ = step(KEY, state, action, params)
            assert obs.tolist() == [*corner, 0.0, 0.0]
    # Two overlapping walls of one's own (a T): both inner corners, at a resolution that
    # misses them.
    params = EnvParams.create(n=3.0, walls=[[1.3, 1.7, 0.0, 2.4], [0.0, 3.0, 2.2, 2.6]],
                              start=[0, 0], exit=[3, 0])
    assert envs.absorbing_states(Maze(), params, resolution=0.5).tolist() == [
        [pytest.approx(1.3), pytest.approx(2.2)], [pytest.approx(1.7), pytest.approx(2.2)]]
    with pytest.raises(ValueError, match="resolution"):
        envs.absorbing_states(Maze(), params, resolution=0)
    with pytest.raises(ValueError, match="env"):
        envs.absorbing_states(envs.make("point_u_maze")[0], params)
