"""GARA / Handcrafted agent: intrinsic reward, low-level learning, split bookkeeping,
refinement inside training."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from gara_jax.agents.dqn import DQNConfig, Transition, make_dqn
from gara_jax.algorithms import GaraConfig, HandcraftedConfig, make_algorithm
from gara_jax.algorithms.gara import intrinsic_reward
from gara_jax.algorithms.refinement import apply_split as _apply_split


def test_intrinsic_reward_once_per_option_closed_box():
    lo, hi = jnp.array([1.0, 0.0, -1.0, -1.0]), jnp.array([1.5, 2.0, 1.0, 1.0])
    on_face = jnp.array([1.0, 2.0, 0.0, 0.0])  # boxes are closed: the face counts as inside
    r, inside, first = intrinsic_reward(on_face, lo, hi, jnp.asarray(False))
    assert (float(r), bool(inside), bool(first)) == (1.0, True, True)
    r, inside, first = intrinsic_reward(on_face, lo, hi, jnp.asarray(True))
    assert (float(r), bool(inside), bool(first)) == (0.0, True, False)
    r, _, _ = intrinsic_reward(jnp.array([0.9, 1.0, 0.0, 0.0]), lo, hi, jnp.asarray(False))
    assert float(r) == pytest.approx(-0.1)
    # goal_membership="partition": a face state that belongs to another goal is not inside.
    r, inside, _ = intrinsic_reward(on_face, lo, hi, jnp.asarray(False),
                                    in_target=jnp.asarray(False))
    assert float(r) == pytest.approx(-0.1) and not bool(inside)


def test_dqn_learns_to_reach_a_nearby_box():
    """The goal-conditioned DQN with the intrinsic reward learns, in 2,500 steps, to reach a
    box up and to the right of the start (a fresh network does not)."""
    env, params = envs.make("u_maze")
    lo, hi = jnp.array([0.5, 0.5, -1.0, -1.0]), jnp.array([1.0, 1.0, 1.0, 1.0])
    goal, horizon = jnp.concatenate([lo, hi]), 15
    dqn = make_dqn(DQNConfig(buffer_size=2000, learning_starts=200, epsilon_decay=0.998,
                             target_update_every=50), 12, 4)

    def train(key):
        obs, es = env.reset(key, params)

        def step(c, key):
            ds, obs, es, t = c
            k_act, k_dqn = jax.random.split(key)
            x = jnp.concatenate([obs, goal])
            a = dqn.act(ds, x, k_act)
            nobs, nes, r, term, _, _ = env.step(key, es, a, params)
            ri, _, first = intrinsic_reward(nobs, lo, hi, False)
            ds, _ = dqn.observe(
                ds, Transition(x, a, ri + r, jnp.concatenate([nobs, goal]), first | term), k_dqn)
            end = first | term | (t + 1 >= horizon)  # short episodes from the start
            obs0, es0 = env.reset(key, params)
            obs = jnp.where(end, obs0, nobs)
            es = jax.tree.map(lambda a, b: jnp.where(end, a, b), es0, nes)
            return (ds, obs, es, jnp.where(end, 0, t + 1)), None

        c, _ = jax.lax.scan(step, (dqn.init(key), obs, es, jnp.int32(0)),
                            jax.random.split(key, 2500))
        return c[0]

    def greedy_reaches(ds):
        obs, es = env.reset(jax.random.key(0), params)

        def step(c, _):
            obs, es, hit = c
            a = jnp.argmax(dqn.q_values(ds.params, jnp.concatenate([obs, goal])))
            obs, es, *_ = env.step(jax.random.key(0), es, a, params)
            return (obs, es, hit | jnp.all((obs >= lo) & (obs <= hi))), None

        return jax.lax.scan(step, (obs, es, jnp.asarray(False)), None, horizon)[0][2]

    keys = jax.random.split(jax.random.key(0), 4)
    trained = jax.jit(jax.vmap(lambda k: greedy_reaches(train(k))))(keys)
    fresh = jax.jit(jax.vmap(lambda k: greedy_reaches(dqn.init(k))))(keys)
    assert int(trained.sum()) == 4
    assert int(fresh.sum()) <= 1


class _Verdict(NamedTuple):
    reaching_lo: np.ndarray
    reaching_hi: np.ndarray
    nonreaching_lo: np.ndarray
    nonreaching_hi: np.ndarray


def _boxes(*xy):
    lo = np.array([[x0, y0, -1.0, -1.0] for x0, x1, y0, y1 in xy], np.float32)
    hi = np.array([[x1, y1, 1.0, 1.0] for x0, x1, y0, y1 in xy], np.float32)
    return lo, hi


def _seed(max_goals):
    from gara_jax.partition import Partition

    lo, hi = _boxes((0, 1, 0, 3), (1, 3, 0, 3))
    G = max_goals
    q = np.zeros((G, G), np.float32)
    q[0, 0], q[0, 1], q[1, 0], q[1, 1] = 0.1, 0.2, 0.5, 0.3
    succ = np.zeros((G, G), bool)
    succ[1, 0] = True
    marks = lambda: np.zeros((G, G), bool)
    return dict(partition=Partition.create(lo, hi, G), q=q, succeeded=succ,
                reachable=marks(), unreachable=marks(), blocked=marks())


def test_apply_split_updates_goal_indexed_arrays():
    from gara_jax.partition import check_tiling

    seed = _seed(5)
    reach_lo, reach_hi = _boxes((0, 1, 2, 3))
    miss_lo, miss_hi = _boxes((0, 1, 0, 1), (0, 1, 1, 2))
    assert _apply_split(seed, 0, 1, _Verdict(reach_lo, reach_hi, miss_lo, miss_hi)) == "split"
    p = seed["partition"]
    assert int(p.count) == 4
    check_tiling(p, np.array([0, 0, -1, -1.0]), np.array([3, 3, 1, 1.0]))
    np.testing.assert_array_equal(np.asarray(p.lo)[[0, 2, 3]], np.concatenate([reach_lo, miss_lo]))
    q, pieces, missing = seed["q"], [0, 2, 3], [2, 3]
    for piece in pieces:
        assert q[1, piece] == pytest.approx(0.5)  # column copied from the split box
        assert bool(seed["succeeded"][1, piece])
        for other in pieces:
            assert q[piece, other] == pytest.approx(0.1)
    assert q[0, 1] == pytest.approx(0.2)  # the reaching piece keeps its value towards G_d
    assert all(q[m, 1] == 0.0 for m in missing)  # non-reaching pieces: zeroed, as the reference
    assert bool(seed["reachable"][0, 1]) and bool(seed["succeeded"][0, 1])
    assert all(seed["unreachable"][m, 1] and not seed["succeeded"][m, 1] for m in missing)
    assert np.argwhere(seed["reachable"]).tolist() == [[0, 1]]


def test_apply_split_capacity_and_plain_verdicts():
    seed = _seed(3)
    reach_lo, reach_hi = _boxes((0, 1, 2, 3))
    miss_lo, miss_hi = _boxes((0, 1, 0, 1), (0, 1, 1, 2))
    before = np.asarray(seed["partition"].lo).copy()
    assert _apply_split(seed, 0, 1, _Verdict(reach_lo, reach_hi, miss_lo, miss_hi)) == "capacity"
    assert bool(seed["blocked"][0, 1]) and int(seed["partition"].count) == 2
    np.testing.assert_array_equal(np.asarray(seed["partition"].lo), before)
    whole_lo, whole_hi = _boxes((0, 1, 0, 3))
    empty = np.zeros((0, 4), np.float32)
    assert _apply_split(seed, 0, 1, _Verdict(whole_lo, whole_hi, empty, empty)) == "reaches"
    assert bool(seed["reachable"][0, 1]) and not bool(seed["unreachable"][0, 1])
    # Nothing reaches: no mark, so the pair can be analysed again later.
    q = seed["q"].copy()
    assert _apply_split(seed, 1, 0, _Verdict(empty, empty, *_boxes((1, 3, 0, 3)))) == "no_reach"
    assert not seed["unreachable"].any() and np.array_equal(seed["q"], q)


def test_exit_split_keeps_the_way_to_the_exit_piece_open():
    """An exit analysis (s == d) splits G_s like any analysis, but its verdicts are about the
    exit box: the non-reaching piece keeps its copied Q value and marks towards the piece
    that kept index s; only (s, s) is marked. A normal split zeroes that value."""
    reach_lo, reach_hi = _boxes((2, 3, 0, 3))
    miss_lo, miss_hi = _boxes((1, 2, 0, 3))
    verdict = _Verdict(reach_lo, reach_hi, miss_lo, miss_hi)
    seed = _seed(5)
    assert _apply_split(seed, 1, 1, verdict) == "split"
    np.testing.assert_array_equal(np.asarray(seed["partition"].lo)[[1, 2]],
                                  np.concatenate([reach_lo, miss_lo]))
    assert seed["q"][2, 1] == pytest.approx(0.3)  # G_s's own value: towards the exit piece
    assert seed["q"][2, 0] == pytest.approx(0.5) and seed["q"][1, 0] == pytest.approx(0.5)
    assert bool(seed["reachable"][1, 1]) and seed["reachable"].sum() == 1
    assert not seed["unreachable"].any()
    normal = _seed(5)
    assert _apply_split(normal, 1, 0, verdict) == "split"
    assert normal["q"][2, 0] == 0.0 and bool(normal["unreachable"][2, 0])


def test_handcrafted_has_no_host_step_and_six_goals():
    alg = make_algorithm(HandcraftedConfig(steps_per_epoch=10, eval_episodes=1))
    assert alg.host_update is None and alg.name == "handcrafted"
    state = alg.init(jax.random.key(0))
    assert int(state.partition.count) == 6


@pytest.mark.parametrize("cls,field,value", [
    (GaraConfig, "tau1", 0.0), (GaraConfig, "tau2", 0.9), (GaraConfig, "refine_method", "x"),
    (GaraConfig, "min_volume_ratio", 1.0), (GaraConfig, "min_steps", -1),
    (GaraConfig, "memory_capacity", 0), (HandcraftedConfig, "env", "nowhere"),
    (HandcraftedConfig, "k", 0), (HandcraftedConfig, "steps_per_epoch", 2.5),
    (HandcraftedConfig, "planning", "yes"), (HandcraftedConfig, "low", None),
    (HandcraftedConfig, "goal_membership", "open"), (HandcraftedConfig, "eval_epsilon_low", 2.0),
    (GaraConfig, "hindsight_memory", 1), (GaraConfig, "q_columns", "rows"),
    (GaraConfig, "target_margin", 0.5), (GaraConfig, "target_margin", True),
    (GaraConfig, "split_dims", ()), (GaraConfig, "split_dims", (0, 0)),
    (GaraConfig, "split_dims", (-1,)), (GaraConfig, "exit_radius", 0.0),
    (GaraConfig, "exit_radius", 0.75), (GaraConfig, "exit_analysis", 1),
    (GaraConfig, "keep_start_goal", "yes"),
    (GaraConfig, "input_range", "box"), (GaraConfig, "model_inputs", "velocity"),
    (HandcraftedConfig, "non_targets", "filler"), (GaraConfig, "non_targets", ([0, 0], [1]))])
def test_config_validation_names_the_field(cls, field, value):
    with pytest.raises(ValueError, match=field):
        cls(**{field: value})


def test_configs_are_json_serialisable():
    import dataclasses
    import json

    for cfg in (GaraConfig(), HandcraftedConfig(planning=True)):
        text = json.dumps(dataclasses.asdict(cfg))
        assert "min_steps" in text or "max_goals" in text


def test_exit_analysis_analyses_the_goal_holding_the_exit():
    """End to end, on a U-maze whose start lies near the exit (found in the first episodes):
    with ``exit_analysis`` the pair (G_e, G_e) is analysed; without it, never (s == d is
    masked out of the trigger), and the partitions still tile the maze."""
    import dataclasses

    from gara_jax import partition
    from gara_jax.train import final_partitions, train_many

    envs.register("u_maze_exit_near", lambda **o: envs.make(
        "u_maze", **{"start": (2.5, 0.5), "max_steps": 60, **o}))
    lo, hi = partition.layout_boxes("u_maze", "gara")
    cfg = GaraConfig(env="u_maze_exit_near", initial_boxes=(lo, hi), steps_per_epoch=300,
                     eval_episodes=1, min_steps=30, shared_min_records=1, exit_analysis=True,
                     exit_radius=0.5)
    counts, runs = {}, {}
    for on in (True, False):
        runs[on] = res = train_many(dataclasses.replace(cfg, exit_analysis=on), [0, 1], 1200)
        info = [h for h in res.host_info if h]
        counts[on] = (sum(h["exit_analysed"] for h in info), sum(h["analysed"] for h in info))
        for p in final_partitions(res):
            partition.check_tiling(p, np.array([0, 0, -1, -1.0]), np.array([3, 3, 1, 1.0]))
    assert 0 < counts[True][0] <= counts[True][1]
    assert counts[False][0] == 0

    # experiments.exit_bounds on the same run: pieces and exit boxes inside G_e, the memory's
    # rows found, and the bounds sound for every prediction at a row start inside them.
    from experiments import exit_bounds

    per_seed = exit_bounds.measure(runs[True], fractions=(4, 16))
    assert len(per_seed) == 2 and all(per_seed)
    checked = 0
    for seed in per_seed:
        g_lo, g_hi = np.array(seed["goal_lo"]), np.array(seed["goal_hi"])
        assert len(seed["cases"]) == 2 * len(exit_bounds.RADII)
        for case in seed["cases"]:
            for name in ("piece", "exit"):
                lo, hi = np.array(case[f"{name}_lo"]), np.array(case[f"{name}_hi"])
                assert (g_lo <= lo).all() and (lo <= hi).all() and (hi <= g_hi + 1e-6).all()
            for inputs in ("goal_velocities", "data_velocities"):
                if inputs in case and "sound" in case[inputs]:
                    assert case[inputs]["sound"] and 0.0 <= case[inputs]["c1"] <= 1.0
                    checked += 1
            if case["rows"]:
                assert 0.0 <= case["data_in_exit"] <= 1.0 and "sound" in case["data_velocities"]
    assert checked > 0  # some piece held rows, so the soundness check ran
    assert "seeds that found the exit: 2 of 2" in exit_bounds.table(per_seed, 0.9)


def test_data_input_boxes_narrow_the_velocities_to_the_pair_data():
    """``input_range="data"``: G_s narrowed along the dimensions not in ``split_dims`` to its
    pair's data range (clipped into G_s), G_s itself for a pair without data."""
    from types import SimpleNamespace

    from gara_jax.algorithms.refinement import _data_input_boxes

    lo = np.array([[[0.0, 0, -1, -1], [1, 0, -1, -1]]])
    hi = np.array([[[1.0, 3, 1, 1], [3, 3, 1, 1]]])
    r_lo = np.full((1, 2, 2, 4), np.inf)
    r_hi = -r_lo
    r_lo[0, 0, 1], r_hi[0, 0, 1] = [0.2, 1.0, -0.5, -1.5], [0.8, 2.0, 0.25, 0.5]
    jobs = [(0, 0, 1), (0, 1, 0)]
    cfg = SimpleNamespace(split_dims=(0, 1))
    in_lo, in_hi = _data_input_boxes(cfg, (r_lo, r_hi), jobs, lo, hi)
    assert in_lo.tolist() == [[0.0, 0, -0.5, -1], [1, 0, -1, -1]]
    assert in_hi.tolist() == [[1.0, 3, 0.25, 0.5], [3, 3, 1, 1]]
    every = _data_input_boxes(SimpleNamespace(split_dims=None), (r_lo, r_hi), jobs, lo, hi)
    assert every[0].tolist() == lo[0].tolist() and every[1].tolist() == hi[0].tolist()
    only_x = _data_input_boxes(SimpleNamespace(split_dims=(0,)), (r_lo, r_hi), jobs, lo, hi)
    assert only_x[0][0].tolist() == [0.0, 1.0, -0.5, -1] and only_x[1][0, 1] == 2.0


def test_input_range_data_bounds_over_the_pairs_data(monkeypatch):
    """End to end: with ``input_range="data"`` every analysis gets an input box inside its G_s,
    equal to it in x, y, and some narrower in a velocity."""
    from gara_jax import partition, reach
    from gara_jax.train import final_partitions, train_many

    seen = []
    real = reach.refine_many

    def spy(*args, **kw):
        seen.append((np.asarray(args[1]), np.asarray(args[2]), kw.get("input_lo"),
                     kw.get("input_hi")))
        return real(*args, **kw)

    monkeypatch.setattr(reach, "refine_many", spy)
    lo, hi = partition.layout_boxes("u_maze", "gara")
    cfg = GaraConfig(initial_boxes=(lo, hi), steps_per_epoch=300, eval_episodes=1,
                     min_steps=30, shared_min_records=1, input_range="data")
    res = train_many(cfg, [0, 1], 1200)
    assert sum(h["analysed"] for h in res.host_info if h) > 0
    for p in final_partitions(res):
        partition.check_tiling(p, np.array([0, 0, -1, -1.0]), np.array([3, 3, 1, 1.0]))
    narrower = False
    for s_lo, s_hi, i_lo, i_hi in seen:
        assert (s_lo <= i_lo).all() and (i_lo <= i_hi).all() and (i_hi <= s_hi).all()
        assert (i_lo[:, :2] == s_lo[:, :2]).all() and (i_hi[:, :2] == s_hi[:, :2]).all()
        narrower |= bool(((i_hi - i_lo)[:, 2:] < (s_hi - s_lo)[:, 2:]).any())
    assert seen and narrower


def test_position_model_sees_no_velocity(monkeypatch):
    """``model_inputs="split_dims"``: the forward model is fitted on start states whose
    velocities are 0 and bounded over pieces whose velocity range is the point 0, with ``x, y``
    the piece's own."""
    from gara_jax import partition, reach
    from gara_jax.algorithms import refinement
    from gara_jax.train import train_many

    seen, fitted = [], []
    real_refine, real_inputs = reach.refine_many, refinement.model_inputs

    def spy_refine(*args, **kw):
        seen.append((np.asarray(args[1]), np.asarray(args[2]), kw.get("input_lo"),
                     kw.get("input_hi")))
        return real_refine(*args, **kw)

    def spy_inputs(config, start, target_lo, target_hi, xp=np):
        x = real_inputs(config, start, target_lo, target_hi, xp)
        if xp is np:  # the per-job fits' datasets
            fitted.append(np.asarray(x))
        return x

    monkeypatch.setattr(reach, "refine_many", spy_refine)
    monkeypatch.setattr(refinement, "model_inputs", spy_inputs)
    lo, hi = partition.layout_boxes("u_maze", "gara")
    cfg = GaraConfig(initial_boxes=(lo, hi), steps_per_epoch=300, eval_episodes=1,
                     min_steps=30, shared_min_records=1, model_inputs="split_dims",
                     forward_model="per_job")  # its datasets are host arrays, unlike the shared's
    res = train_many(cfg, [0, 1], 1200)
    assert sum(h["analysed"] for h in res.host_info if h) > 0 and seen
    for s_lo, s_hi, i_lo, i_hi in seen:
        assert (i_lo[:, :2] == s_lo[:, :2]).all() and (i_hi[:, :2] == s_hi[:, :2]).all()
        assert (i_lo[:, 2:] == 0).all() and (i_hi[:, 2:] == 0).all()
    rows = np.concatenate(fitted)
    assert len(rows) and (rows[:, 2:4] == 0).all() and (rows[:, :2] != 0).any()
    assert (rows[:, 4:] != 0).any()  # the goal's bounds are still inputs


def test_keep_start_goal_never_splits_the_goal_the_episodes_start_in():
    """End to end on a short U-maze where the default splits the start's goal ``[0,1]x[0,3]``
    (seed 3): with ``keep_start_goal`` the triggered pairs from it are held back and counted,
    other pairs are still analysed, and that goal is whole in every final partition."""
    import dataclasses

    from gara_jax import partition
    from gara_jax.train import final_partitions, train_many

    envs.register("u_maze_short_start", lambda **o: envs.make(
        "u_maze", **{"max_steps": 60, **o}))
    lo, hi = partition.layout_boxes("u_maze", "gara")
    cfg = GaraConfig(env="u_maze_short_start", initial_boxes=(lo, hi), steps_per_epoch=300,
                     eval_episodes=1, min_steps=30, shared_min_records=1)
    start_box = [0.0, 0.0, 1.0, 3.0]

    def start_goal_whole(p):
        n = int(p.count)
        boxes = np.c_[np.asarray(p.lo)[:n, :2], np.asarray(p.hi)[:n, :2]]
        return any(np.allclose(b, start_box) for b in boxes)

    for keep in (False, True):
        res = train_many(dataclasses.replace(cfg, keep_start_goal=keep), [2, 3], 1500)
        info = [h for h in res.host_info if h]
        whole = [start_goal_whole(p) for p in final_partitions(res)]
        skips = sum(h["start_skips"] for h in info)
        if keep:
            assert all(whole) and skips > 0
            assert sum(h["analysed"] for h in info) > 0  # the other goal is still analysed
        else:
            assert not all(whole) and skips == 0  # the default does split it here


def test_non_targets_are_never_chosen_end_to_end():
    """``non_targets``: no training option aims at a goal inside a region (the memory's rows
    hold every option's target box); the regions are checked, ``"layout"`` gives the layout's
    filler boxes (none without a layout), and the presets take it."""
    import envs
    from gara_jax import partition
    from gara_jax.algorithms.gara import non_target_regions
    from gara_jax.train import train_many

    lo, hi = partition.layout_boxes("u_maze", "gara")  # [0,1]x[0,3] and [1,3]x[0,3]
    right = ([[1.0, 0.0, -1.0, -1.0]], [[3.0, 3.0, 1.0, 1.0]])
    cfg = GaraConfig(steps_per_epoch=300, eval_episodes=1, min_steps=10**9, non_targets=right)
    res = train_many(cfg, [0, 1], 600)
    mem = res.final.states.memory
    for i in range(2):
        rows = np.asarray(mem.target_lo[i])[: int(mem.size[i])]
        assert len(rows) and (rows[:, 0] == 0.0).all()  # every option aimed at [0,1]x[0,3]
    assert non_target_regions(cfg, 4)[0].tolist() == right[0]
    assert non_target_regions(GaraConfig(env="big_u_maze", non_targets="layout"), 4)[1].tolist() \
        == [[6.0, 6.0, 1.0, 1.0]]
    with pytest.raises(ValueError, match="non_targets: regions of dimension 2"):
        non_target_regions(GaraConfig(non_targets=([[0.0, 0.0]], [[1.0, 1.0]])), 4)
    envs.register("u_maze_no_layout", lambda **o: envs.make("u_maze", **o))
    assert non_target_regions(GaraConfig.reference(env="u_maze_no_layout",
                                                   initial_boxes=(lo, hi)), 4) is None
    assert GaraConfig.reference().non_targets == HandcraftedConfig.reference().non_targets \
        == "layout"
