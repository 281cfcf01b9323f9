"""The reference's GARA mechanisms (SPEC.md section 3, revision 2) as options, and the
per-episode records.

Each test checks a mechanism against hand-counted or hand-computed values: the sliding windows
of a scripted run, the small-box rule on a translation network, replay relabelling on a small
buffer, the host step's split with the epsilon boost and the relabelled replay, the shared
forward model's incremental updates, and the per-episode records.
"""

import dataclasses

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax import reach
from gara_jax import train as tr
from gara_jax.agents import forward_model as fm
from gara_jax.agents.dqn import DQNConfig, Transition, append_relabelled, make_dqn
from gara_jax.agents.high_level import HighLevelConfig
from gara_jax.algorithms import GaraConfig, HandcraftedConfig, make_algorithm
from gara_jax.algorithms.gara import intrinsic_reward
from gara_jax.algorithms.refinement import apply_split, relabel_to_reached_goal
from gara_jax.partition import Partition, locate

LOW = DQNConfig(loss="all_actions", buffer_size=1000, learning_starts=100)


def test_reference_presets_hold_spec_revision_2():
    g = GaraConfig.reference()
    assert (g.memory, g.memory_capacity, g.forward_model, g.min_steps) == (
        "windows", 50_000, "shared", 5000)
    assert (g.tau1, g.tau2, g.small_box_c1, g.split_epsilon_boost) == (0.9, 0.01, 0.5, 1.5)
    assert g.relabel_replay and g.q_columns == "reference" and not g.skip_unreachable
    assert (g.low.buffer_size, g.low.target_update_every, g.low.loss, g.low.learning_rate) == (
        100_000, 20, "all_actions", 0.01)
    assert HandcraftedConfig.reference().low.learning_rate == 0.01
    # The defaults' one low-level difference from the reference: the step size.
    for ours, ref in ((GaraConfig(), g), (HandcraftedConfig(), HandcraftedConfig.reference())):
        assert ours.low.learning_rate == 0.001
        assert dataclasses.replace(ours.low, learning_rate=0.01) == ref.low
    assert (g.high.epsilon_decrement, g.high.tie_break) == (0.0005, "lowest")
    assert g.entry_reward == "previous_plus_one" and g.goal_membership == "box"
    # Neither variant skips unreachable pairs: the type bug hits both (SPEC 3.9.4 corrects
    # revision 2, which had the planning variant skip them).
    assert not GaraConfig.reference(planning=True).skip_unreachable
    h = HandcraftedConfig.reference()
    assert h.intrinsic == "every_step" and h.high.tie_break == "lowest"
    assert GaraConfig.reference(min_steps=7).min_steps == 7


@pytest.mark.parametrize("field,value", [
    ("memory", "episodes"), ("forward_model", "global"), ("small_box_c1", 1.5),
    ("split_epsilon_boost", 0.5), ("relabel_replay", "yes"), ("q_columns", "rows"),
    ("skip_unreachable", None), ("shared_min_records", 0), ("intrinsic", "dense"),
    ("entry_reward", "double"), ("reached_at_start", 0), ("stall_includes_loops", 1),
    ("self_target", "never"), ("stall_penalty", float("nan")), ("piece_order", "first"),
    ("initial_split_x", 3.0), ("avoid_stalled_action", 1), ("avoid_repeated_decisions", "no"),
    ("decision_memory", 0)])
def test_new_options_are_validated(field, value):
    with pytest.raises(ValueError, match=field):
        GaraConfig(**{field: value})
    with pytest.raises(ValueError, match="tie_break"):
        HighLevelConfig(tie_break="first")


def test_initial_split_x_moves_the_boundary_of_the_initial_partition():
    from gara_jax.algorithms.gara import initial_partition

    lo, hi = initial_partition(GaraConfig()).boxes()
    assert (hi[0, 0], lo[1, 0]) == (1.0, 1.0)  # the reference: the wall's near face
    lo, hi = initial_partition(GaraConfig(initial_split_x=1.5)).boxes()
    assert (hi[0, 0], lo[1, 0]) == (1.5, 1.5) and len(lo) == 2
    # The wall's left face, pressed at rest, is inside the left box only.
    face = np.array([1.0, 1.0, 0.0, 0.0])
    assert np.all((lo[0] <= face) & (face <= hi[0])) and not np.all(lo[1] <= face)


def test_intrinsic_reward_rules():
    lo, hi = jnp.zeros(2), jnp.ones(2)
    inside, outside = jnp.array([0.5, 0.5]), jnp.array([2.0, 0.5])
    # The reference's entry reward: previous step's value plus one.
    assert float(intrinsic_reward(inside, lo, hi, False, previous=jnp.float32(-0.1))[0]) == \
        pytest.approx(0.9)
    assert float(intrinsic_reward(inside, lo, hi, False, previous=jnp.float32(0.0))[0]) == 1.0
    # Handcrafted's: 1 on every step inside, nothing outside.
    for reached in (False, True):
        assert float(intrinsic_reward(inside, lo, hi, reached, rule="every_step")[0]) == 1.0
        assert float(intrinsic_reward(outside, lo, hi, reached, rule="every_step")[0]) == 0.0


def _scripted_windows_run(k=2, steps=24):
    """One seed, high level random among the 2 initial goals (epsilon 0.5 throughout)."""
    cfg = GaraConfig.reference(
        k=k, steps_per_epoch=steps, eval_episodes=1, memory_capacity=200, low=LOW,
        high=HighLevelConfig(epsilon_start=0.5, epsilon_min=0.5, epsilon_decrement=0.0))
    alg = make_algorithm(cfg)
    state, _ = jax.jit(alg.train_epoch)(alg.init(jax.random.key(3)), jax.random.key(4))
    return cfg, state


def test_sliding_windows_of_a_scripted_run_match_a_hand_count():
    k, steps = 2, 24
    cfg, state = _scripted_windows_run(k, steps)
    mem = jax.device_get(state.memory)
    n = int(mem.size)
    data, start, end = mem.data[:n], mem.start[:n], mem.end[:n]
    t_lo, step = mem.target_lo[:n], mem.step[:n]
    markers = np.flatnonzero(~data)
    # No episode ends in 24 steps from the start, so options start at t = 0, k, 2k, ...
    assert step[markers].tolist() == list(range(1, steps + 1, k))
    targets = t_lo[markers]
    same = [bool(np.array_equal(targets[i], targets[i - 1])) for i in range(1, len(targets))]
    assert 0 < sum(same) < len(same)  # the script switches targets sometimes, not always
    windows = np.flatnonzero(data)
    # Hand count: every step of an option whose target equals the previous option's.
    assert len(windows) == k * sum(same)
    # Window stored at step t (stored after env step t + 1) runs s_{t-k} -> s_{t+1}; its target
    # is its option's; the marker of the option starting at t = 2k holds s_{2k}.
    by_step = {int(step[w]): w for w in windows}
    marker_obs = {int(step[m]) - 1: start[m] for m in markers}
    for t_plus_1, w in by_step.items():
        t = t_plus_1 - 1
        option_start = t - t % k
        np.testing.assert_array_equal(t_lo[w], t_lo[markers[option_start // k]])
        if (t - k) in marker_obs:
            np.testing.assert_array_equal(start[w], marker_obs[t - k])
        # s_{t+1} ends window t and starts window t + k + 1 (if stored).
        if t_plus_1 + k + 1 in by_step:
            np.testing.assert_array_equal(end[w], start[by_step[t_plus_1 + k + 1]])
    # The trigger's count: one per window plus one per option start.
    target_goal = fm.match_boxes(state.memory.target_lo, state.memory.target_hi,
                                 state.partition.lo, state.partition.hi, state.partition.count)
    counts, _ = fm.pair_experience(locate(state.partition, state.memory.start), target_goal,
                                   state.memory, 0, cfg.max_goals)
    assert int(np.asarray(counts).sum()) == len(windows) + len(markers)


def test_small_box_rule_on_a_translation_network():
    # F(s, G) = s + (1, 0, 0, 0); G_s = [0, 2] x [0, 1]^3, G_d = [1.5, 4] x [0, 1]^3.
    d = 4
    eye = np.eye(d, 3 * d)
    layers = [(np.concatenate([eye, -eye], 0).T, np.zeros(2 * d)),
              (np.concatenate([np.eye(d), -np.eye(d)]), np.array([1.0, 0, 0, 0]))]
    s_lo, s_hi = [0.0, 0, 0, 0], [2.0, 1, 1, 1]
    t_lo, t_hi = [1.5, 0, 0, 0], [4.0, 1, 1, 1]
    # The root (c1 = 0.75) is bisected on x; the halves are too small to split again
    # (min_volume_ratio 0.9): [1, 2] reaches (c1 = 1), [0, 1] has c1 = 0.5 exactly.
    common = dict(tau1=0.9, tau2=0.01, min_volume_ratio=0.9, method="ibp")
    never = reach.refine(layers, s_lo, s_hi, t_lo, t_hi, small_box_c1=None, **common)
    assert never.reaching_lo.tolist() == [[1.0, 0, 0, 0]]
    assert never.nonreaching_hi.tolist() == [[1.0, 1, 1, 1]]
    lenient = reach.refine(layers, s_lo, s_hi, t_lo, t_hi, small_box_c1=0.45, **common)
    assert lenient.reaching_lo.tolist() == [s_lo] and lenient.reaching_hi.tolist() == [s_hi]
    assert len(lenient.nonreaching_lo) == 0
    strict = reach.refine(layers, s_lo, s_hi, t_lo, t_hi, small_box_c1=0.55, **common)
    assert strict.reaching_lo.tolist() == never.reaching_lo.tolist()
    with pytest.raises(ValueError, match="small_box_c1"):
        reach.refine(layers, s_lo, s_hi, t_lo, t_hi, small_box_c1=2.0)


def _small_buffer(capacity, values):
    b = fbx.make_item_buffer(max_length=capacity, min_length=1, sample_batch_size=1,
                             add_batches=False)
    s = b.init(jnp.zeros(()))
    for v in values:
        s = b.add(s, jnp.float32(v))
    return s


def test_replay_relabelling_appends_copies_oldest_first():
    s = _small_buffer(5, [1, 2, 3])
    out = append_relabelled(s, lambda t: t + 10)
    assert out.experience[0].tolist() == [13, 2, 3, 11, 12]
    assert int(out.current_index) == 1 and bool(out.is_full)  # 13 wrapped onto slot 0
    out = append_relabelled(s, lambda t: t + 10, where=False)
    assert out.experience[0].tolist() == [1, 2, 3, 0, 0] and int(out.current_index) == 3
    # Full ring (oldest is slot 2): every entry is replaced by its own copy.
    full = _small_buffer(4, [1, 2, 3, 4, 5, 6])
    out = append_relabelled(full, lambda t: -t)
    assert out.experience[0].tolist() == [-5, -6, -3, -4] and int(out.current_index) == 2


def test_goal_relabelling_of_a_low_level_replay():
    p = Partition.create([[0, 0, -1, -1], [1, 0, -1, -1.0]], [[1, 3, 1, 1], [3, 3, 1, 1.0]], 4)
    dqn = make_dqn(DQNConfig(buffer_size=8, learning_starts=2, batch_size=2), 12, 4)
    state = dqn.init(jax.random.key(0))
    goal = jnp.concatenate([p.lo[0], p.hi[0]])
    for x in (0.5, 2.0):
        nxt = jnp.array([x, 1.0, 0.0, 0.0])
        t = Transition(jnp.concatenate([jnp.zeros(4), goal]), jnp.int32(1), jnp.float32(-0.1),
                       jnp.concatenate([nxt, goal]), jnp.bool_(False))
        state, _ = dqn.observe(state, t, jax.random.key(1))
    state = dqn.append_relabelled(state, lambda t: relabel_to_reached_goal(t, p))
    exp = jax.device_get(state.buffer.experience)
    assert int(state.buffer.current_index) == 4
    np.testing.assert_allclose(exp.reward[0, :4], [-0.1, -0.1, 1.0, 1.0])
    np.testing.assert_array_equal(exp.next_obs[0, 2, 4:], np.concatenate([p.lo[0], p.hi[0]]))
    np.testing.assert_array_equal(exp.next_obs[0, 3, 4:], np.concatenate([p.lo[1], p.hi[1]]))
    np.testing.assert_array_equal(exp.obs[0, 3, 4:], exp.next_obs[0, 3, 4:])


def test_apply_split_copies_only_rows_like_the_reference():
    G = 5
    lo, hi = np.array([[0, 0, -1, -1], [1, 0, -1, -1.0]]), np.array([[1, 3, 1, 1], [3, 3, 1, 1.0]])
    q = np.zeros((G, G), np.float32)
    q[0, 0], q[0, 1], q[1, 0] = 0.1, 0.2, 0.5
    marks = lambda: np.zeros((G, G), bool)
    seed = dict(partition=Partition.create(lo, hi, G), q=q, succeeded=marks(),
                reachable=marks(), unreachable=marks(), blocked=marks(),
                records=np.ones((G, G), np.int32))

    class Verdict:
        reaching_lo, reaching_hi = np.array([[0, 2, -1, -1.0]]), np.array([[1, 3, 1, 1.0]])
        nonreaching_lo, nonreaching_hi = np.array([[0, 0, -1, -1.0]]), np.array([[1, 2, 1, 1.0]])

    assert apply_split(seed, 0, 1, Verdict, q_columns="reference") == "split"
    q = seed["q"]
    # Row copied, then Q[miss, d] = 0 and the new column 2 left at 0.
    np.testing.assert_allclose(q[2], [0.1, 0, 0, 0, 0])
    assert q[1, 0] == pytest.approx(0.5) and q[1, 2] == 0.0  # new column left at 0
    assert q[0, 1] == pytest.approx(0.2)
    assert seed["records"][0].sum() == 0 and seed["records"][:, 2].sum() == 0
    assert seed["records"][1, 1] == 1


def _crafted_host_state(cfg, rows=600):
    """One seed whose memory holds left -> right windows: from y > 1.5 they end in the right
    box (x = 2), from below they stay at x = 0.5. The pair (0, 1) passes the trigger."""
    loop = tr.init_loop(cfg, [0])
    rng = np.random.default_rng(0)
    mem = jax.device_get(loop.states.memory)
    start = np.zeros((1, rows, 4), np.float32)
    start[0, :, 0] = rng.uniform(0, 1, rows)
    start[0, :, 1] = rng.uniform(0, 3, rows)
    start[0, :, 2:] = rng.uniform(-1, 1, (rows, 2))
    end = start.copy()
    high_up = start[0, :, 1] > 1.5
    end[0, :, 0] = np.where(high_up, 2.0, 0.5)
    end[0, :, 2:] = 0.0
    t_lo = np.broadcast_to(np.asarray(loop.states.partition.lo[0, 1]), (1, rows, 4))
    t_hi = np.broadcast_to(np.asarray(loop.states.partition.hi[0, 1]), (1, rows, 4))
    put = lambda a, v: jnp.asarray(np.concatenate([v, a[:, rows:]], axis=1), a.dtype)
    memory = loop.states.memory.replace(
        start=put(mem.start, start), end=put(mem.end, end), target_lo=put(mem.target_lo, t_lo),
        target_hi=put(mem.target_hi, t_hi), length=put(mem.length, np.ones((1, rows))),
        step=put(mem.step, np.full((1, rows), 10)), episode=put(mem.episode, np.zeros((1, rows))),
        data=put(mem.data, np.ones((1, rows), bool)), size=jnp.asarray([rows], jnp.int32))
    # Two transitions in the low-level replay, so the relabelling has something to copy.
    dqn = make_dqn(cfg.low, 12, 4)
    one = jax.tree.map(lambda a: a[0], loop.states.dqn)
    for x in (0.5, 2.0):
        g = jnp.concatenate([loop.states.partition.lo[0, 1], loop.states.partition.hi[0, 1]])
        t = Transition(jnp.concatenate([jnp.zeros(4), g]), jnp.int32(0), jnp.float32(-0.1),
                       jnp.concatenate([jnp.array([x, 1.0, 0, 0]), g]), jnp.bool_(False))
        one, _ = dqn.observe(one, t, jax.random.key(0))
    states = loop.states.replace(
        memory=memory, env_steps=jnp.asarray([20], jnp.int32),
        dqn=jax.tree.map(lambda a: a[None], one),
        high=loop.states.high.replace(epsilon=jnp.asarray([0.4], jnp.float32),
                                      q=loop.states.high.q.at[0, 0, 1].set(0.3)))
    return states


HOST_CFG = dict(steps_per_epoch=100, eval_episodes=1, min_steps=100, memory_capacity=1024,
                max_goals=16, low=LOW, refine_method="ibp", tau1=0.9, tau2=0.01,
                min_volume_ratio=0.05,
                small_box_c1=0.5, forward=fm.ForwardModelConfig(max_epochs=200),
                memory="options", forward_model="per_job", split_dims=None)


def test_host_step_splits_boosts_epsilon_and_relabels_the_replay():
    cfg = GaraConfig(**HOST_CFG, split_epsilon_boost=1.5, relabel_replay=True,
                     q_columns="reference")
    alg = make_algorithm(cfg)
    states = _crafted_host_state(cfg)
    new, info = alg.host_update(states, epoch=0)
    assert info["triggered"] == 1 and info["analysed"] == 1 and info["splits"] == 1
    assert bool(info["changed"][0])
    # The verdict names the pair and its boxes as they were before the split.
    (v,) = info["verdicts"]
    old_lo, old_hi = np.asarray(states.partition.lo[0]), np.asarray(states.partition.hi[0])
    assert (v["seed"], v["start"], v["target"], v["outcome"]) == (0, 0, 1, "split")
    np.testing.assert_array_equal(v["start_box"], [old_lo[0], old_hi[0]])
    np.testing.assert_array_equal(v["target_box"], [old_lo[1], old_hi[1]])
    count = int(new.partition.count[0])
    assert count >= 3
    lo, hi = np.asarray(new.partition.lo[0, :count]), np.asarray(new.partition.hi[0, :count])
    # The reaching piece (index 0) is the upper part of the left box.
    assert lo[0, 1] >= 1.0 and hi[0, 0] <= 1.0
    assert float(new.high.epsilon[0]) == pytest.approx(0.6)  # 0.4 x 1.5, one split
    assert bool(new.reachable[0, 0, 1]) and bool(new.unreachable[0, 2, 1])
    assert float(new.high.q[0, 0, 1]) == pytest.approx(0.3)
    assert float(new.high.q[0, 2, 1]) == 0.0
    # Relabelled replay: the 2 stored transitions got a copy each, reward 1, goal = the box
    # holding their next state under the new partition.
    buf = jax.device_get(new.dqn.buffer)
    assert int(buf.current_index[0]) == 4
    np.testing.assert_allclose(buf.experience.reward[0, 0, 2:4], [1.0, 1.0])
    right = np.concatenate([lo[1], hi[1]])
    np.testing.assert_array_equal(buf.experience.next_obs[0, 0, 3, 4:], right)
    # Without the boost and relabelling the same split leaves epsilon and the replay alone.
    plain = GaraConfig(**HOST_CFG, split_epsilon_boost=1.0, relabel_replay=False)
    new2, info2 = make_algorithm(plain).host_update(_crafted_host_state(plain), epoch=0)
    assert info2["splits"] == 1 and float(new2.high.epsilon[0]) == pytest.approx(0.4)
    assert int(new2.dqn.buffer.current_index[0]) == 2


def test_piece_order_parent_keeps_the_wall_face_in_the_left_region_after_a_split():
    face = jnp.array([1.0, 0.5, 0.0, 0.0])  # pressed against the wall, at rest

    def face_goal(order):
        cfg = GaraConfig(**HOST_CFG, piece_order=order)
        new, info = make_algorithm(cfg).host_update(_crafted_host_state(cfg), epoch=0)
        assert info["splits"] == 1
        partition = jax.tree.map(lambda a: a[0], new.partition)
        count = int(partition.count)
        # The lower part of the left box (below y = 1.5) went to appended pieces.
        goal = int(locate(partition, face))
        return goal, partition, count

    goal, partition, count = face_goal("appended")
    assert goal == 1 and partition.rank is None  # the right box [1, 3] x [0, 3]
    goal, partition, count = face_goal("parent")
    assert goal >= 2 and float(partition.hi[goal, 0]) == 1.0  # a piece of the left box
    assert sorted(np.asarray(partition.rank[:count]).tolist()) == list(range(count))
    assert int(partition.rank[1]) == count - 1  # the right box comes after every piece


def test_shared_forward_model_needs_records_before_an_analysis():
    cfg = GaraConfig(**dict(HOST_CFG, forward_model="shared"), shared_min_records=3)
    alg = make_algorithm(cfg)
    states = _crafted_host_state(cfg)
    before = jax.device_get(states.forward.params)
    # The crafted rows are all of episode 0: one update per host step for the pair (0, 1).
    for epoch in range(2):
        states, info = alg.host_update(states, epoch=epoch)
        assert info["fit_updates"] == 1 and info["analysed"] == 0
        assert int(states.forward.records[0, 0, 1]) == epoch + 1
    after = jax.device_get(states.forward.params)
    assert any(not np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(before), jax.tree.leaves(after), strict=True))
    last, prev = float(states.forward.mse_last[0, 0, 1]), float(states.forward.mse_prev[0, 0, 1])
    states, info = alg.host_update(states, epoch=2)
    expect_ready = float(states.forward.mse_last[0, 0, 1]) - last < cfg.forward.stable_decrease
    assert info["analysed"] == int(expect_ready)
    assert np.isfinite(prev)


def test_shared_updates_skip_empty_segments_and_dead_slots():
    f = fm.make_forward_model(fm.ForwardModelConfig(), state_dim=4)
    params = jax.tree.map(lambda p: p[0], f.init(jax.random.split(jax.random.key(0), 1)))
    x, y = jnp.ones((10, 12)), jnp.zeros((10, 4))
    rows, seg_start, seg_len = fm.pair_segments(np.zeros(10), np.ones(10, bool), np.array([1, 0]))
    assert seg_len.tolist() == [0, 10]
    keys = jax.random.split(jax.random.key(1), 2)
    opt = f.init_optimizer(params)
    same, _, mse = f.shared_updates(params, opt, x, y, jnp.asarray(rows), jnp.asarray(seg_start),
                                    jnp.asarray(seg_len), jnp.array([True, False]), keys)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(same), strict=True):
        np.testing.assert_array_equal(a, b)  # pair 1 has no rows, pair 0's slot is not live
    assert float(mse[0]) == 0.0 and float(mse[1]) > 0.0
    moved, _, _ = f.shared_updates(params, opt, x, y, jnp.asarray(rows), jnp.asarray(seg_start),
                                   jnp.asarray(seg_len), jnp.array([False, True]), keys)
    assert any(not np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(params), jax.tree.leaves(moved), strict=True))


def test_shared_steps_take_that_many_gradient_steps_per_update():
    """``shared_steps=n`` is n single-step updates on fresh samples: the same fit as n calls of
    the reference's update (here with all rows alike, so every sample is the same batch)."""
    x, y = jnp.ones((8, 12)), jnp.full((8, 4), 0.5)
    rows, seg_start, seg_len = fm.pair_segments(np.zeros(8), np.ones(8, bool), np.array([0]))
    seg = tuple(map(jnp.asarray, (rows, seg_start, seg_len)))
    key = jax.random.key(3)

    def run(steps, calls):
        f = fm.make_forward_model(fm.ForwardModelConfig(shared_steps=steps), state_dim=4)
        params = jax.tree.map(lambda p: p[0], f.init(jax.random.split(jax.random.key(0), 1)))
        opt = f.init_optimizer(params)
        update = jax.jit(f.shared_updates)
        for _ in range(calls):
            params, opt, mse = update(params, opt, x, y, *seg, jnp.array([True]), key[None])
        return params, float(mse[0])

    one, mse_one = run(1, 1)
    many, mse_many = run(20, 1)
    repeated, mse_repeated = run(1, 20)
    assert mse_many < 0.5 * mse_one  # twenty steps fit a constant target much better
    for a, b in zip(jax.tree.leaves(many), jax.tree.leaves(repeated), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert mse_many == pytest.approx(mse_repeated, rel=1e-4)


def test_episode_records_match_the_epoch_counts():
    cfg = dataclasses.replace(HandcraftedConfig(steps_per_epoch=400, eval_episodes=1, low=LOW))
    res = tr.train_many(cfg, [0, 1], total_steps=1200)
    ep = res.episodes
    for i in range(2):
        success, length, end = ep["success"][i], ep["length"][i], ep["end_step"][i]
        assert len(success) == int(res.metrics["episodes_ended"][i].sum())
        assert int(success.sum()) == int(round(float(
            (res.metrics["train_success"][i] * res.metrics["episodes_ended"][i]).sum())))
        # Episodes tile the run: each ends `length` steps after the previous one.
        np.testing.assert_array_equal(np.diff(np.concatenate([[0], end])), length)
        assert np.all(length <= 300) and np.all((length < 300) | (success == 0))
        assert np.all(success[length < 300] == 1)  # ended early only by reaching the exit
        assert end[-1] <= 1200


def _replay_after_one_epoch(**overrides):
    cfg = GaraConfig(steps_per_epoch=200, eval_episodes=1, low=LOW, memory_capacity=500,
                     high=HighLevelConfig(epsilon_start=1.0, epsilon_min=1.0), **overrides)
    alg = make_algorithm(cfg)
    state, _ = jax.jit(alg.train_epoch)(alg.init(jax.random.key(5)), jax.random.key(6))
    exp = jax.device_get(state.dqn.buffer.experience)
    n = int(state.dqn.buffer.current_index)
    return {name: np.asarray(getattr(exp, name))[0, :n] for name in exp._fields}


def test_stall_penalty_replaces_the_reward_of_steps_that_do_not_move():
    t = _replay_after_one_epoch(stall_penalty=-1.0)
    stalled = np.all(t["obs"][:, :4] == t["next_obs"][:, :4], axis=1)
    assert 0 < stalled.sum() < len(stalled)  # random actions from rest press on bounds
    np.testing.assert_allclose(t["reward"][stalled], -1.0)
    assert np.all(t["reward"][~stalled] > -1.0)
    plain = _replay_after_one_epoch(stall_penalty=None)
    stalled = np.all(plain["obs"][:, :4] == plain["next_obs"][:, :4], axis=1)
    assert np.all(plain["reward"][stalled] > -1.0)


def test_avoid_stalled_action_never_repeats_a_step_that_did_not_move():
    def repeats_after_a_stall(t):
        same_state = np.all(t["obs"][:, :4] == t["next_obs"][:, :4], axis=1)[:-1]
        repeated = t["action"][1:] == t["action"][:-1]
        # One epoch of 200 steps: no truncation, so consecutive rows are consecutive steps
        # unless the exit was reached.
        return int(np.sum(same_state & repeated & ~t["done"][:-1])), int(same_state.sum())

    guarded, stalls = repeats_after_a_stall(_replay_after_one_epoch(avoid_stalled_action=True))
    assert guarded == 0 and stalls > 0
    plain, _ = repeats_after_a_stall(_replay_after_one_epoch(avoid_stalled_action=False))
    assert plain > 0  # random actions repeat a stalled press about a quarter of the time


def _constant_low_level(q_values, **overrides):
    """Handcrafted with a low level whose Q-values are ``q_values`` in every state."""
    alg = make_algorithm(HandcraftedConfig(steps_per_epoch=10, eval_episodes=1, low=LOW,
                                           **overrides))
    state = alg.init(jax.random.key(0))
    layers = state.dqn.params["params"]
    last = sorted(layers)[-1]
    layers[last]["kernel"] = jnp.zeros_like(layers[last]["kernel"])
    layers[last]["bias"] = jnp.asarray(q_values, jnp.float32)
    return alg, state


def test_avoid_stalled_action_in_the_greedy_rollout_slides_along_a_bound():
    """A low level whose Q-values prefer DOWN, then RIGHT, everywhere: from the start corner
    DOWN never moves; with the guard, every stalled DOWN is followed by a RIGHT, up to the
    wall face x = 1, where RIGHT stalls too (a one-step memory cannot leave a corner of two
    stalled actions)."""

    def rollout(avoid):
        # Q-values of LEFT, RIGHT, UP, DOWN.
        alg, state = _constant_low_level([0.0, 1.0, 0.0, 2.0], avoid_stalled_action=avoid)
        return jax.device_get(alg.greedy_rollout(state, jax.random.key(1)))

    plain = rollout(False)
    assert np.all(plain["obs"][:, :2] == 0.0) and not plain["success"]
    guarded = rollout(True)
    x = guarded["obs"][:, 0]
    assert np.all(guarded["obs"][:, 1] == 0.0)  # DOWN keeps y on the bound
    assert x[2] > 0.0 and np.all(np.diff(x) >= 0.0)
    assert x[-1] == pytest.approx(1.0) and np.all(x <= 1.0 + 1e-6)


def test_avoid_repeated_decisions_tries_every_target_at_a_state_before_repeating_one():
    """A low level that never moves (DOWN at the start corner): every decision is at the same
    state. Greedy, the high level then repeats its best target; with the memory it takes the
    targets in the order of their Q-values, then (all of them tried) the best again."""

    def decisions(avoid):
        alg, state = _constant_low_level([0.0, 0.0, 0.0, 1.0],  # always DOWN
                                         avoid_repeated_decisions=avoid)
        q = state.high.q.at[0].set(jnp.array([0.1, 0.6, 0.5, 0.4, 0.3, 0.2]))
        state = state.replace(high=state.high.replace(q=q))
        rec = jax.device_get(alg.greedy_rollout(state, jax.random.key(1)))
        assert np.all(rec["obs"] == rec["obs"][0])
        steps = np.flatnonzero(rec["deciding"])
        # Within an option the target in force is the one chosen at its start.
        assert np.all(rec["target"][steps[0]: steps[1]] == rec["target"][steps[0]])
        return rec["target"][steps].tolist()

    assert decisions(False)[:8] == [1] * 8
    assert decisions(True)[:8] == [1, 2, 3, 4, 5, 0, 1, 1]
    with pytest.raises(ValueError, match="avoid_repeated_decisions"):
        HandcraftedConfig(avoid_repeated_decisions=True, planning=True)


def test_avoid_repeated_decisions_trains():
    cfg = GaraConfig(steps_per_epoch=400, eval_episodes=1, low=LOW, memory_capacity=500,
                     avoid_repeated_decisions=True, decision_memory=8)
    res = tr.train_many(cfg, [0], total_steps=400)
    assert res.metrics["env_steps"][0, -1] == 400
    memory = jax.device_get(res.final.states.episode)
    assert memory.decided_obs.shape == (1, 8, 4) and memory.decided_target.shape == (1, 8)
    assert np.all(memory.decided_target[0] >= 0)  # 80 decisions filled the 8 slots


def test_reached_at_start_pays_no_entry_reward_to_options_starting_inside():
    left_lo, left_hi = np.array([0, 0, -1, -1.0]), np.array([1, 3, 1, 1.0])

    def entries_inside_left(t):
        goal_left = np.all(t["obs"][:, 4:8] == left_lo, axis=1) & np.all(
            t["obs"][:, 8:] == left_hi, axis=1)
        inside = lambda s: np.all((s >= left_lo) & (s <= left_hi), axis=1)
        stay = goal_left & inside(t["obs"][:, :4]) & inside(t["next_obs"][:, :4])
        return int(np.sum(stay & (t["reward"] >= 0.9))), int(stay.sum())

    with_flag, n = entries_inside_left(_replay_after_one_epoch(reached_at_start=True,
                                                              goal_membership="box"))
    assert with_flag == 0 and n > 0
    without, _ = entries_inside_left(_replay_after_one_epoch(reached_at_start=False,
                                                            goal_membership="box"))
    assert without > 0  # the first step of every such option earns the entry reward
