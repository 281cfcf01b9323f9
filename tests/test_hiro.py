"""HIRO: config validation, TD3, replay, goal transition, relabelling, a tiny end-to-end run."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax.agents.dqn import DQNConfig
from gara_jax.agents.td3 import (
    Batch,
    TD3Config,
    make_td3,
    replay_add,
    replay_init,
    replay_sample,
)
from gara_jax.algorithms.hiro import (
    HiroConfig,
    candidate_log_likelihood,
    goal_transition,
    intrinsic_reward,
    make_hiro,
    relabel_goal,
)

CONTRACT_KEYS = {"env_steps", "train_success", "episodes_ended", "episode_return", "n_goals"}


# ------------------------------------------------------------------------------------------------
# Config
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, field", [
    ({"env": "no_such_maze"}, "env"),
    ({"k": 0}, "k"),
    ({"steps_per_epoch": 3001}, "steps_per_epoch"),
    ({"eval_episodes": 0}, "eval_episodes"),
    ({"low": {"gamma": 0.9}}, "low"),
    ({"high": DQNConfig()}, "high"),
    ({"goal_position_range": -1.0}, "goal_position_range"),
    ({"goal_velocity_range": 0.0}, "goal_velocity_range"),
    ({"goal_noise": -0.1}, "goal_noise"),
    ({"relabel_candidates": 1}, "relabel_candidates"),
    ({"relabel_sigma": -1.0}, "relabel_sigma"),
    ({"relabel_temperature": 0.0}, "relabel_temperature"),
    ({"high_reward_scale": float("nan")}, "high_reward_scale"),
])
def test_hiro_config_rejects_bad_fields(kwargs, field):
    with pytest.raises(ValueError, match=field):
        HiroConfig(**kwargs)


@pytest.mark.parametrize("kwargs, field", [
    ({"actor_hidden": ()}, "actor_hidden"),
    ({"critic_hidden": (0, 3)}, "critic_hidden"),
    ({"tau": 0.0}, "tau"),
    ({"gamma": 1.5}, "gamma"),
    ({"policy_delay": 0}, "policy_delay"),
    ({"noise_clip": -1.0}, "noise_clip"),
    ({"batch_size": 100, "learning_starts": 50}, "learning_starts"),
])
def test_td3_config_rejects_bad_fields(kwargs, field):
    with pytest.raises(ValueError, match=field):
        TD3Config(**kwargs)


def test_hiro_config_defaults_follow_the_paper_and_serialise():
    cfg = HiroConfig()
    assert (cfg.env, cfg.k, cfg.steps_per_epoch, cfg.eval_episodes) == ("u_maze", 5, 3000, 10)
    h = cfg.high
    assert (h.actor_hidden, h.critic_hidden, h.actor_lr, h.critic_lr) == (
        (300, 300), (300, 300), 1e-4, 1e-3)
    assert (h.gamma, h.tau, h.policy_delay, h.batch_size) == (0.99, 0.005, 2, 100)
    assert cfg.relabel_candidates == 10
    json.dumps(dataclasses.asdict(cfg))


# ------------------------------------------------------------------------------------------------
# TD3 and replay
# ------------------------------------------------------------------------------------------------


def _train_td3(td3, state, make_batch, steps, key):
    def body(state, key):
        k_batch, k_update = jax.random.split(key)
        state, info = td3.update(state, make_batch(k_batch), k_update)
        return state, info["critic_loss"]

    return jax.jit(lambda s, k: jax.lax.scan(body, s, jax.random.split(k, steps)))(state, key)


def test_td3_critic_learns_terminal_reward_and_actor_finds_the_best_action():
    # One-step problem: reward -|a - 0.5| summed over both action dims, then the episode ends.
    # The critics should fit it and the actor should move to a = (0.5, 0.5).
    cfg = TD3Config(actor_hidden=(16,), critic_hidden=(32, 32), actor_lr=3e-3, critic_lr=3e-3,
                    batch_size=64, learning_starts=64, buffer_size=128)
    td3 = make_td3(cfg, obs_dim=2, act_dim=2, act_low=-1.0, act_high=1.0)
    state = td3.init(jax.random.key(0))
    obs = jnp.ones((64, 2))
    reward_of = lambda a: -jnp.sum(jnp.abs(a - 0.5), axis=-1)

    def make_batch(key):
        actions = jax.random.uniform(key, (64, 2), minval=-1.0, maxval=1.0)
        return Batch(obs, actions, reward_of(actions), obs, jnp.ones(64, bool))

    test = make_batch(jax.random.key(1))
    err_before = float(jnp.mean(jnp.abs(
        td3.q_values(state.critic_params, obs, test.action)[0] - test.reward)))
    state, losses = _train_td3(td3, state, make_batch, 800, jax.random.key(2))
    for q in td3.q_values(state.critic_params, obs, test.action):
        assert float(jnp.mean(jnp.abs(q - test.reward))) < 0.1 * err_before
    assert losses[-1] < 0.01 * losses[0]
    np.testing.assert_allclose(td3.policy(state.actor_params, obs[0]), [0.5, 0.5], atol=0.1)
    assert int(state.updates) == 800


def test_td3_critic_bootstraps_through_non_terminal_transitions():
    # A self-loop with reward 1 and gamma 0.5 has Q = 1 / (1 - 0.5) = 2.
    cfg = TD3Config(actor_hidden=(8,), critic_hidden=(32,), critic_lr=1e-2, gamma=0.5, tau=0.1,
                    policy_delay=1, batch_size=16, learning_starts=16, buffer_size=32)
    td3 = make_td3(cfg, obs_dim=1, act_dim=1, act_low=-1.0, act_high=1.0)
    state = td3.init(jax.random.key(0))
    obs = jnp.zeros((16, 1))
    batch = Batch(obs, jnp.zeros((16, 1)), jnp.ones(16), obs, jnp.zeros(16, bool))
    state, _ = _train_td3(td3, state, lambda _: batch, 800, jax.random.key(1))
    a = td3.policy(state.actor_params, obs)
    q1, q2 = td3.q_values(state.critic_params, obs, a)
    np.testing.assert_allclose(q1, 2.0, atol=0.15)
    np.testing.assert_allclose(q2, 2.0, atol=0.15)


def test_td3_act_respects_the_action_box():
    td3 = make_td3(TD3Config(actor_hidden=(8,), critic_hidden=(8,)), 3, 2, [-1.0, 0.0], [1.0, 5.0])
    state = td3.init(jax.random.key(0))
    keys = jax.random.split(jax.random.key(1), 500)
    a = jax.jit(jax.vmap(lambda kk: td3.act(state, jnp.ones(3), kk, 10.0)))(keys)
    assert bool(jnp.all(a[:, 0] >= -1) & jnp.all(a[:, 0] <= 1))
    assert bool(jnp.all(a[:, 1] >= 0) & jnp.all(a[:, 1] <= 5))
    greedy = td3.act(state, jnp.ones(3), keys[0], 0.0)
    np.testing.assert_allclose(greedy, td3.policy(state.actor_params, jnp.ones(3)))


def test_replay_masked_add_never_samples_invalid_items_and_wraps():
    buf = replay_init(jnp.zeros((), jnp.int32), capacity=4)
    for i in range(10):  # valid items are the even numbers; odd ones are invalid writes
        buf = replay_add(buf, i, valid=i % 2 == 0)
    # Capacity 4 keeps the 3 most recent valid items: 4, 6, 8.
    assert int(buf.size) == 3
    sample = replay_sample(buf, jax.random.key(0), 300)
    assert set(np.asarray(sample).tolist()) == {4, 6, 8}


# ------------------------------------------------------------------------------------------------
# Goals
# ------------------------------------------------------------------------------------------------


def test_goal_transition_keeps_the_absolute_target_and_telescopes():
    key_s, key_g = jax.random.split(jax.random.key(0))
    states = jax.random.normal(key_s, (6, 4))
    goal = jax.random.normal(key_g, (4,))
    # The absolute target s + g is invariant under h.
    for i in range(5):
        g_next = goal_transition(states[i], goal, states[i + 1])
        np.testing.assert_allclose(states[i + 1] + g_next, states[i] + goal, rtol=1e-6, atol=1e-6)
        goal = g_next
    # Applying h along a trajectory gives s_0 + g_0 - s_i (what the relabelling uses).
    g0 = jax.random.normal(key_g, (4,))

    def step(g, pair):
        return goal_transition(pair[0], g, pair[1]), g

    _, seq = jax.lax.scan(step, g0, (states[:-1], states[1:]))
    np.testing.assert_allclose(seq, states[0] + g0 - states[:-1], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(
        intrinsic_reward(states[0], g0, states[1]),
        -jnp.linalg.norm(states[0] + g0 - states[1]), rtol=1e-6)


def _directional_q(x):
    """Hand-set low-level Q: with goal g = x[4:], prefers LEFT/RIGHT/UP/DOWN as g points."""
    g = x[..., 4:6]
    return 5.0 * jnp.stack([-g[..., 0], g[..., 0], g[..., 1], -g[..., 1]], axis=-1)


RIGHT, LEFT = 1, 0
_relabel = jax.jit(relabel_goal, static_argnums=(0,))  # eager dispatch would dominate the tests
GOAL_LOW = jnp.array([-3.0, -3.0, -2.0, -2.0])
GOAL_HIGH = -GOAL_LOW


def _option_moving_right(k=5):
    # The agent moved right by 0.5 a step, pushing RIGHT every step.
    states = jnp.zeros((k, 4)).at[:, 0].set(0.5 * jnp.arange(k))
    next_obs = jnp.array([0.5 * k, 0.0, 0.0, 0.0])
    return states, jnp.full(k, RIGHT), next_obs


def test_relabelling_replaces_a_goal_that_does_not_explain_the_actions():
    states, actions, next_obs = _option_moving_right()
    proposed = jnp.array([-2.0, 0.0, 0.0, 0.0])  # "go left": RIGHT is then very unlikely
    goal, index = _relabel(_directional_q, states, actions, 5, proposed, next_obs,
                               jax.random.key(0), GOAL_LOW, GOAL_HIGH)
    assert int(index) != 0
    assert float(goal[0]) > 0.0
    # It is the candidate of highest likelihood (recomputed by hand from the same samples).
    achieved = next_obs - states[0]
    noise = jax.random.normal(jax.random.key(0), (8, 4))
    cands = jnp.clip(jnp.concatenate([proposed[None], achieved[None],
                                      achieved + 0.5 * GOAL_HIGH * noise]), GOAL_LOW, GOAL_HIGH)
    cands, states = np.asarray(cands, np.float64), np.asarray(states, np.float64)
    ll = []
    for c in cands:
        total = 0.0
        for s in states:
            g = states[0] + c - s
            q = 5.0 * np.array([-g[0], g[0], g[1], -g[1]])
            total += q[RIGHT] - np.log(np.sum(np.exp(q)))
        ll.append(total)
    assert int(index) == int(np.argmax(ll))
    np.testing.assert_allclose(goal, cands[int(index)], rtol=1e-6)


def test_relabelling_keeps_the_original_goal_when_it_explains_the_actions_best():
    states, _, next_obs = _option_moving_right()
    actions = jnp.full(5, LEFT)  # logged LEFT pushes although the agent drifted right
    proposed = jnp.array([-3.0, 0.0, 0.0, 0.0])  # the most "left" goal in the box
    goal, index = _relabel(_directional_q, states, actions, 5, proposed, next_obs,
                               jax.random.key(1), GOAL_LOW, GOAL_HIGH)
    assert int(index) == 0
    np.testing.assert_allclose(goal, proposed)


def test_relabelling_ignores_steps_after_the_option_was_cut():
    # Two valid LEFT steps, then padding that says RIGHT: only the valid steps may count.
    states, _, next_obs = _option_moving_right()
    actions = jnp.array([LEFT, LEFT, RIGHT, RIGHT, RIGHT])
    proposed = jnp.array([-3.0, 0.0, 0.0, 0.0])
    ll_cut = candidate_log_likelihood(_directional_q, states, actions, 2,
                                      jnp.stack([proposed, -proposed]))
    assert float(ll_cut[0]) > float(ll_cut[1])
    _, index = _relabel(_directional_q, states, actions, 2, proposed, next_obs,
                            jax.random.key(2), GOAL_LOW, GOAL_HIGH)
    assert int(index) == 0


def test_relabelling_is_batched():
    states, actions, next_obs = _option_moving_right()
    proposed = jnp.array([[-2.0, 0.0, 0.0, 0.0], [2.5, 0.0, 0.0, 0.0]])
    goals, index = _relabel(_directional_q, jnp.stack([states] * 2),
                                jnp.stack([actions] * 2), jnp.array([5, 5]), proposed,
                                jnp.stack([next_obs] * 2), jax.random.key(0), GOAL_LOW, GOAL_HIGH)
    assert goals.shape == (2, 4) and index.shape == (2,)
    assert int(index[0]) != 0 and float(goals[0, 0]) > 0


# ------------------------------------------------------------------------------------------------
# End to end
# ------------------------------------------------------------------------------------------------

TINY = HiroConfig(
    steps_per_epoch=100, eval_episodes=2,
    low=DQNConfig(batch_size=8, learning_starts=32, buffer_size=256),
    high=TD3Config(actor_hidden=(16,), critic_hidden=(16,), batch_size=8, learning_starts=8,
                   buffer_size=128),
)


@pytest.fixture(scope="module")
def tiny():
    algo = make_hiro(TINY)
    init = jax.jit(jax.vmap(algo.init))
    train = jax.jit(jax.vmap(algo.train_epoch))
    evaluate = jax.jit(jax.vmap(algo.evaluate))

    def run(seed):
        keys = jax.random.split(jax.random.key(seed), 2)
        states = init(keys)
        history = []
        for epoch in range(2):
            states, metrics = train(states, jax.random.split(jax.random.fold_in(keys[0], epoch), 2))
            history.append(metrics)
        return states, history, evaluate(states, keys)

    return algo, run


def test_end_to_end_two_seeds_two_epochs(tiny):
    algo, run = tiny
    assert algo.name == "hiro" and algo.host_update is None and algo.config is TINY
    states, history, evaluation = run(0)
    for epoch, metrics in enumerate(history):
        assert CONTRACT_KEYS <= set(metrics)
        metrics = dict(metrics)
        log = metrics.pop("episode_log")  # per step, as GARA's (base.epoch_metrics)
        for name, value in log.items():
            assert value.shape == (2, 100), name
        np.testing.assert_array_equal(log["ended"].sum(axis=1), metrics["episodes_ended"])
        for name, value in metrics.items():
            assert value.shape == (2,), name
            assert bool(jnp.all(jnp.isfinite(value))), name
        np.testing.assert_array_equal(metrics["env_steps"], [(epoch + 1) * 100] * 2)
        assert metrics["env_steps"].dtype == jnp.int32
        np.testing.assert_array_equal(metrics["n_goals"], [0, 0])
    # Both levels learned in the second epoch.
    assert bool(jnp.all(history[1]["low_loss"] > 0))
    assert bool(jnp.all(history[1]["critic_loss"] > 0))
    assert set(evaluation) == {"eval_success", "eval_return"}
    for value in evaluation.values():
        assert value.shape == (2,) and bool(jnp.all(jnp.isfinite(value)))
    assert bool(jnp.all((evaluation["eval_success"] >= 0) & (evaluation["eval_success"] <= 1)))


def test_stored_options_are_consecutive_k_step_pieces_of_the_trajectory(tiny):
    # 200 steps, no episode can end (300-step limit, the exit is far): 40 options of k = 5
    # steps each, chained: each option starts where the previous one ended.
    _, run = tiny
    states, _, _ = run(0)
    replay = jax.tree.map(lambda x: np.asarray(x[0]), states.replay)
    assert int(replay.size) == 40
    data = replay.data
    np.testing.assert_array_equal(data.length[:40], 5)
    assert not data.done[:40].any()
    np.testing.assert_allclose(data.states[0, 0], [0, 0, 0, 0])  # the start state
    np.testing.assert_allclose(data.obs[:40], data.states[:40, 0])
    np.testing.assert_allclose(data.next_obs[:39], data.obs[1:40])
    # Goals proposed during warm-up lie in the goal box.
    high = np.array([3.0, 3.0, 2.0, 2.0])
    assert np.all(np.abs(data.goal[:40]) <= high + 1e-6)


def test_same_key_same_metrics_and_different_key_differs(tiny):
    _, run = tiny
    _, h1, e1 = run(0)
    _, h2, e2 = run(0)
    _, h3, _ = run(1)
    for a, b in zip(h1, h2, strict=True):
        jax.tree.map(np.testing.assert_array_equal, a, b)
    for name in e1:
        np.testing.assert_array_equal(e1[name], e2[name])
    assert not np.array_equal(h1[1]["intrinsic_reward"], h3[1]["intrinsic_reward"])


@pytest.mark.parametrize("delay", [2, 64])
def test_delayed_actor_steps_follow_the_block_schedule(delay):
    # 100 steps = 20 blocks of k = 5, one option stored per block; the critic steps on every
    # block from the one that stores the 8th option (learning_starts); the actor (and the soft
    # target update) on the odd blocks among those with delay 2, never with a delay longer
    # than the epoch.
    cfg = dataclasses.replace(TINY, high=dataclasses.replace(TINY.high, policy_delay=delay))
    algo = make_hiro(cfg)
    state = algo.init(jax.random.key(0))
    new, _ = jax.jit(jax.vmap(algo.train_epoch))(
        jax.tree.map(lambda x: x[None], state), jax.random.key(1)[None])
    new = jax.tree.map(lambda x: x[0], new)
    critic_steps = int(new.high.updates)
    assert critic_steps > 0
    changed = lambda a, b: any(bool(jnp.any(x != y)) for x, y in zip(  # noqa: E731
        jax.tree.leaves(a), jax.tree.leaves(b), strict=True))
    assert changed(new.high.critic_params, state.high.critic_params)
    assert critic_steps == 20 - (TINY.high.learning_starts - 1)
    first = 20 - critic_steps
    actor_steps = sum(b % delay == delay - 1 for b in range(first, 20))
    assert changed(new.high.actor_params, state.high.actor_params) == (actor_steps > 0)
    assert changed(new.high.critic_target, state.high.critic_target) == (actor_steps > 0)
    # Adam's step count is the number of actor steps taken.
    assert int(jax.tree.leaves(new.high.actor_opt)[0]) == actor_steps


# ------------------------------------------------------------------------------------------------
# The GARA authors' HIRO baseline (SPEC.md 3.7): HiroConfig.paper()
# ------------------------------------------------------------------------------------------------


def test_paper_preset_is_spec_3_7():
    cfg = HiroConfig.paper()
    h = cfg.high
    assert (cfg.goal_space, cfg.relabel, cfg.goal_noise, cfg.high_reward_scale, cfg.k) == (
        "absolute", False, 0.1, 1.0, 5)
    assert (h.actor_hidden, h.critic_hidden, h.actor_lr, h.critic_lr, h.gamma, h.batch_size,
            h.tau, h.buffer_size) == ((16, 32), (16, 32), 5e-4, 1e-3, 0.99, 32, 0.05, 20_000)
    assert (h.twin_critics, h.policy_delay, h.policy_noise, h.critic_target, h.actor_output) == (
        False, 1, 0.0, "reward_less", "tanh_clipped")
    assert cfg.low == DQNConfig() and cfg.low.td_target_clip == 1.0
    json.dumps(dataclasses.asdict(cfg))
    with pytest.raises(ValueError, match="^relabel:"):
        HiroConfig(goal_space="absolute")
    with pytest.raises(ValueError, match="^goal_space:"):
        HiroConfig(goal_space="polar")
    for field, value in (("critic_target", "no_reward"), ("actor_output", "sigmoid")):
        with pytest.raises(ValueError, match=f"^{field}:"):
            TD3Config(**{field: value})


@pytest.mark.parametrize("critic_target", ["reward_less", "standard"])
def test_ddpg_critic_step_regresses_on_the_hand_computed_target(critic_target):
    # One critic, no target smoothing: the loss of a critic step is mean (Q(s,a) - y)^2 with
    # y = r + g Q'(s', mu'(s')) (standard) or g Q'(s', mu'(s')) (reward-less) where not done,
    # y = r where done. A non-terminal reward makes the two differ.
    cfg = TD3Config(actor_hidden=(8,), critic_hidden=(8,), policy_noise=0.0, noise_clip=0.0,
                    policy_delay=1, batch_size=4, learning_starts=4, buffer_size=8,
                    twin_critics=False, critic_target=critic_target, gamma=0.9,
                    actor_output="tanh_clipped")
    td3 = make_td3(cfg, obs_dim=2, act_dim=2, act_low=jnp.array([0.0, -1.0]),
                   act_high=jnp.array([3.0, 1.0]))
    state = td3.init(jax.random.key(0))
    obs = jnp.array([[0.0, 0.0], [1.0, 2.0], [3.0, 0.5], [2.0, 2.0]])
    next_obs = obs[::-1] + 0.25
    batch = Batch(obs, jnp.array([[0.5, 0.0], [1.0, 0.2], [0.0, -0.5], [0.9, 0.9]]),
                  jnp.array([2.0, 0.0, 10.0, -1.0]), next_obs,
                  jnp.array([False, False, True, False]))
    (q_next,) = td3.q_values(state.critic_target, next_obs,
                             td3.policy(state.actor_target, next_obs))
    q_next = np.asarray(q_next, np.float64)
    r, done = np.asarray(batch.reward, np.float64), np.asarray(batch.done)
    targets = {"standard": np.where(done, r, r + 0.9 * q_next),
               "reward_less": np.where(done, r, 0.9 * q_next)}
    assert targets["standard"][0] != targets["reward_less"][0]
    want = targets[critic_target]
    (q,) = td3.q_values(state.critic_params, obs, batch.action)
    _, loss = td3.critic_update(state, batch, jax.random.key(1))
    np.testing.assert_allclose(float(loss), np.mean((np.asarray(q, np.float64) - want) ** 2),
                               rtol=1e-5)
    # The tanh-clipped actor never proposes outside [0, 1] x [-1, 1] (the box is [0,3]x[-1,1]).
    a = td3.policy(state.actor_params, jax.random.normal(jax.random.key(2), (256, 2)) * 50)
    assert bool(jnp.all((a[:, 0] >= 0) & (a[:, 0] <= 1) & (jnp.abs(a[:, 1]) <= 1)))


TINY_PAPER = HiroConfig.paper(
    steps_per_epoch=100, eval_episodes=2,
    low=DQNConfig(batch_size=8, learning_starts=32, buffer_size=256),
    high=dataclasses.replace(HiroConfig.paper().high, batch_size=8, learning_starts=8,
                             buffer_size=128))


def test_paper_hiro_trains_end_to_end_with_fixed_absolute_goals():
    from gara_jax.agents.dqn import stored_in_age_order

    algo = make_hiro(TINY_PAPER)
    keys = jax.random.split(jax.random.key(0), 2)
    states = jax.jit(jax.vmap(algo.init))(keys)
    train = jax.jit(jax.vmap(algo.train_epoch))
    for epoch in range(2):
        states, metrics = train(states, jax.random.split(jax.random.fold_in(keys[0], epoch), 2))
    assert bool(jnp.all(metrics["critic_loss"] > 0)) and bool(jnp.all(metrics["low_loss"] > 0))
    evaluation = jax.jit(jax.vmap(algo.evaluate))(states, keys)
    assert bool(jnp.all((evaluation["eval_success"] >= 0) & (evaluation["eval_success"] <= 1)))
    # Seed 0's high-level replay: 40 options, goals inside the observation bounds with
    # positions in [0, 1] up to the 0.1 exploration noise.
    replay = jax.tree.map(lambda x: np.asarray(x[0]), states.replay)
    goals = replay.data.goal[: int(replay.size)]
    assert int(replay.size) == 40
    assert np.all(goals[:, :2] >= 0) and np.all(goals[:, :2] <= 1.0 + 5 * 0.1)
    assert np.all(np.abs(goals[:, 2:]) <= 1.0)
    # Seed 0's low-level replay: the goal half of the input stays fixed through a transition
    # and the reward is -||g - s'||.
    buffer = jax.tree.map(lambda x: x[0], states.low.buffer)
    rows, valid = stored_in_age_order(buffer)
    exp = jax.tree.map(lambda x: np.asarray(x[0][np.asarray(rows)[np.asarray(valid)]]),
                       buffer.experience)
    assert len(exp.reward) == 200
    np.testing.assert_array_equal(exp.obs[:, 4:], exp.next_obs[:, 4:])
    np.testing.assert_allclose(
        exp.reward, -np.linalg.norm(exp.obs[:, 4:] - exp.next_obs[:, :4], axis=-1), rtol=1e-5)
    # Goals change only at option boundaries (every k = 5 steps; no episode ended).
    changes = np.flatnonzero(np.any(np.diff(exp.obs[:, 4:], axis=0) != 0, axis=1)) + 1
    assert set(changes) <= set(range(0, 200, 5)) and len(changes) >= 30


def test_sequential_and_vmapped_seed_schedules_run_the_same_algorithm():
    # "sequential" runs the seeds' TD3 steps one after another under vmap: the same updates,
    # only the floating-point kernels differ, so a short run agrees to rounding.
    outs = []
    for schedule in ("sequential", "vmap"):
        algo = make_hiro(dataclasses.replace(TINY, seed_schedule=schedule))
        keys = jax.random.split(jax.random.key(3), 2)
        states = jax.jit(jax.vmap(algo.init))(keys)
        states, metrics = jax.jit(jax.vmap(algo.train_epoch))(states, keys)
        outs.append((states, metrics))
    (s1, m1), (s2, m2) = outs
    assert float(jnp.min(m1["critic_loss"])) > 0  # the high level did learn
    for name in ("critic_loss", "low_loss", "train_success", "goal_distance"):
        np.testing.assert_allclose(m1[name], m2[name], rtol=1e-4, atol=1e-6, err_msg=name)
    np.testing.assert_array_equal(s1.high.updates, s2.high.updates)
    np.testing.assert_array_equal(s1.replay.data.actions, s2.replay.data.actions)
    with pytest.raises(ValueError, match="^seed_schedule:"):
        HiroConfig(seed_schedule="pmap")
