"""High-level learner: Q update by hand, goal choice, the planner's shortest paths."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax.agents import high_level as hl


def test_q_update_matches_hand_computation():
    q = np.zeros((5, 5), np.float32)
    q[3] = [0.2, 0.7, -0.4, 0.1, 9.0]  # slot 4 is padding (n_goals = 4): must be ignored
    q[1, 3] = 0.5
    alpha, gamma, reward = 0.01, 0.99, 10.0
    out = hl.q_update(jnp.asarray(q), 1, 3, reward, 3, False, 4, alpha, gamma)
    expected = q.copy()
    expected[1, 3] = 0.5 + alpha * (reward + gamma * 0.7 - 0.5)
    np.testing.assert_allclose(np.asarray(out), expected, rtol=1e-6)
    # A terminal option does not bootstrap.
    out = hl.q_update(jnp.asarray(q), 1, 3, reward, 3, True, 4, alpha, gamma)
    assert float(out[1, 3]) == pytest.approx(0.5 + alpha * (reward - 0.5))


def test_q_goal_greedy_ignores_padding_and_breaks_ties_randomly():
    q = jnp.zeros((6, 6)).at[2].set(jnp.array([0.0, 1.0, 1.0, 0.0, 0.5, 99.0]))
    keys = jax.random.split(jax.random.key(0), 200)
    picks = np.asarray(jax.vmap(lambda k: hl.q_goal(k, q, 2, 5, 0.0))(keys))
    assert set(picks.tolist()) == {1, 2}  # both maxima, never the padded slot 5


def test_q_goal_explores_uniformly_over_valid_goals():
    q = jnp.zeros((8, 8)).at[0, 3].set(1.0)
    keys = jax.random.split(jax.random.key(1), 4000)
    picks = np.asarray(jax.vmap(lambda k: hl.q_goal(k, q, 0, 5, 1.0))(keys))
    counts = np.bincount(picks, minlength=8)
    assert counts[5:].sum() == 0
    assert np.all(np.abs(counts[:5] / 4000 - 0.2) < 0.03)


def test_epsilon_decays_linearly_per_decision_to_floor():
    cfg = hl.HighLevelConfig()
    eps = jnp.float32(1.0)
    eps = hl.decay_epsilon(cfg, eps, False)
    assert float(eps) == 1.0
    for _ in range(100):
        eps = hl.decay_epsilon(cfg, eps, True)
    assert float(eps) == pytest.approx(0.95, abs=1e-5)  # 0.0005 per decision (SPEC 3.3)
    for _ in range(2000):
        eps = hl.decay_epsilon(cfg, eps, True)
    assert float(eps) == pytest.approx(0.01)


def test_q_target_entry_both_updates_the_failed_target_too():
    q = jnp.zeros((3, 3)).at[1].set(jnp.array([0.0, 0.0, 4.0])).at[0, 2].set(2.0)
    out = hl.OptionOutcome(start=jnp.int32(0), target=jnp.int32(2), next_goal=jnp.int32(1),
                           reward=jnp.float32(0.0), terminated=jnp.bool_(False),
                           reached=jnp.bool_(False), exit_state=jnp.zeros(2),
                           blocked=jnp.bool_(False))
    hs = hl.init_high_state(hl.HighLevelConfig(), 3, 2).replace(q=q)
    # TD target 0 + 0.99 * max Q[1] = 3.96; alpha 0.5: Q[0, 1] 0 -> 1.98, Q[0, 2] 2 -> 2.98.
    for entry, expect in (("reached", (1.98, 2.0)), ("target", (0.0, 2.98)),
                          ("both", (1.98, 2.98))):
        cfg = hl.HighLevelConfig(alpha=0.5, q_target_entry=entry)
        new = hl.learn_from_option(cfg, hs, out, 3, jnp.bool_(True)).q
        assert (float(new[0, 1]), float(new[0, 2])) == pytest.approx(expect)


def test_lowest_index_ties_like_the_reference():
    q = jnp.zeros((4, 4)).at[0, 2].set(1.0).at[0, 3].set(1.0)
    picks = {int(hl.q_goal(jax.random.key(i), q, 0, 4, 0.0, "lowest")) for i in range(20)}
    assert picks == {2}
    picks = {int(hl.q_goal(jax.random.key(i), q, 0, 4, 0.0, "random")) for i in range(40)}
    assert picks == {2, 3}


def _hand_graph():
    # 0 -> 1 -> 2 -> 4 (exit), 0 -> 3 -> 4, 5 -> 5 only, 6 unreachable, 2 <-> 1 cycle.
    # Slot 7 is padding, with a (stale) edge 0 -> 7 that must be ignored.
    succ = np.zeros((8, 8), bool)
    for i, j in [(0, 1), (1, 2), (2, 1), (2, 4), (0, 3), (3, 4), (5, 5), (0, 7), (7, 4)]:
        succ[i, j] = True
    exit_goals = np.zeros(8, bool)
    exit_goals[4] = True
    return jnp.asarray(succ), jnp.asarray(exit_goals)


def test_shortest_distances_on_hand_graph():
    succ, exit_goals = _hand_graph()
    dist = hl.shortest_distances(succ, exit_goals, 7)
    inf = float("inf")
    assert np.asarray(dist).tolist() == [2.0, 2.0, 1.0, 1.0, 0.0, inf, inf, inf]


def test_incremental_relaxation_converges_and_forgets_removed_edges():
    raw, exit_goals = _hand_graph()
    succ = hl.clean_graph(raw, 7)
    assert not bool(succ[5, 5]) and not bool(succ[0, 7]) and bool(succ[0, 1])
    dist = jnp.full(8, jnp.inf)
    for _ in range(8):
        dist = hl.relax_distances(dist, succ, exit_goals)
    np.testing.assert_array_equal(dist, hl.shortest_distances(raw, exit_goals, 7))
    # Removing 3 -> 4 must lengthen 3's path away (3 has no other route: inf), 0 goes via 1.
    succ = succ.at[3, 4].set(False)
    for _ in range(8):
        dist = hl.relax_distances(dist, succ, exit_goals)
    assert float(dist[3]) == float("inf") and float(dist[0]) == 3.0


def test_plan_goal_follows_next_hop_and_falls_back_to_random():
    succ, exit_goals = _hand_graph()
    dist = hl.shortest_distances(succ, exit_goals, 7)
    key = jax.random.key(0)
    assert int(hl.plan_goal(key, dist, succ, 2, 7, 0.0)) == 4
    # From 0 both 1 (dist 2) and 3 (dist 1) are successors: the shortest path goes via 3.
    assert int(hl.plan_goal(key, dist, succ, 0, 7, 0.0)) == 3
    # In the exit goal it targets the exit goal itself.
    assert int(hl.plan_goal(key, dist, succ, 4, 7, 0.0)) == 4
    # No known path (goal 6): uniform over the valid goals.
    keys = jax.random.split(key, 2000)
    picks = np.asarray(jax.vmap(lambda k: hl.plan_goal(k, dist, succ, 6, 7, 0.0))(keys))
    assert set(picks.tolist()) == set(range(7))


def test_learn_from_option_adds_edges_only_for_successful_allowed_options():
    cfg = hl.HighLevelConfig()
    hs = hl.init_high_state(cfg, max_goals=4, state_dim=2)

    def outcome(start, target, reached, blocked=False, reward=0.0, terminated=False):
        return hl.OptionOutcome(
            start=jnp.int32(start), target=jnp.int32(target), next_goal=jnp.int32(target),
            reward=jnp.float32(reward), terminated=jnp.asarray(terminated),
            reached=jnp.asarray(reached), exit_state=jnp.array([2.5, 0.5]),
            blocked=jnp.asarray(blocked))

    hs1 = hl.learn_from_option(cfg, hs, outcome(0, 1, True), 3, True)
    assert bool(hs1.succeeded[0, 1])
    for o in (outcome(0, 1, False), outcome(0, 1, True, blocked=True), outcome(1, 1, True)):
        assert not bool(hl.learn_from_option(cfg, hs, o, 3, True).succeeded.any())
    # Nothing happens when the option did not end.
    same = hl.learn_from_option(cfg, hs, outcome(0, 1, True, reward=10.0, terminated=True), 3,
                                False)
    assert not bool(same.succeeded.any()) and not bool(same.exit_known)
    assert float(jnp.abs(same.q).sum()) == 0.0
    done = hl.learn_from_option(cfg, hs, outcome(0, 2, True, reward=10.0, terminated=True), 3,
                                True)
    assert bool(done.exit_known) and np.asarray(done.exit_state).tolist() == [2.5, 0.5]
    assert float(done.q[0, 2]) == pytest.approx(0.1)


@pytest.mark.parametrize("field,value", [("alpha", 0.0), ("gamma", 1.5), ("epsilon_min", 2.0),
                                         ("epsilon_decrement", -1.0), ("planner_sweeps", 0)])
def test_config_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        hl.HighLevelConfig(**{field: value})


def test_targets_mask_restricts_choice_bootstrap_and_planner():
    """``targets`` (``non_targets``): a masked goal is never chosen, greedy or random, nor the
    bootstrap's best; an all-false mask falls back to every valid goal."""
    q = jnp.zeros((5, 5)).at[0].set(jnp.array([0.0, 0.2, 9.0, 0.1, 0.0]))
    targets = jnp.array([True, True, False, True, True])
    keys = jax.random.split(jax.random.key(2), 600)
    choose = jax.jit(jax.vmap(lambda k, eps, t: hl.q_goal(k, q, 0, 4, eps, targets=t),
                              in_axes=(0, None, None)))  # one compile for the three calls
    assert set(np.asarray(choose(keys, 0.0, targets)).tolist()) == {1}  # 9.0 masked, 4 padding
    assert set(np.asarray(choose(keys, 1.0, targets)).tolist()) == {0, 1, 3}
    assert set(np.asarray(choose(keys, 1.0, jnp.zeros(5, bool))).tolist()) == {0, 1, 2, 3}
    # Bootstrap from row 0: max over goals 0, 1, 3 is 0.2, not the masked 9.0.
    out = hl.q_update(q, 3, 1, 1.0, 0, False, 4, 0.5, 0.5, targets=targets)
    assert float(out[3, 1]) == pytest.approx(0.5 * (1.0 + 0.5 * 0.2))
    # Planner: the shortest way 0 -> 2 -> 3 (exit) is masked at 2, so the hop is 1 (-> 4 -> 3).
    succ = jnp.zeros((5, 5), bool).at[0, 2].set(True).at[2, 3].set(True)
    succ = succ.at[0, 1].set(True).at[1, 4].set(True).at[4, 3].set(True)
    dist = hl.shortest_distances(succ, jnp.array([False, False, False, True, False]), 5)
    plan = jax.jit(jax.vmap(lambda k, eps, t: hl.plan_goal(k, dist, succ, 0, 5, eps, t),
                            in_axes=(0, None, None)))
    assert set(np.asarray(plan(keys, 0.0, jnp.ones(5, bool))).tolist()) == {2}
    assert set(np.asarray(plan(keys, 0.0, targets)).tolist()) == {1}
    assert set(np.asarray(plan(keys, 1.0, targets)).tolist()) == {0, 1, 3, 4}
