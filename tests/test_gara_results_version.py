"""The authors' results version and the mechanisms both their versions share (SPEC.md 3.9).

Each test checks one mechanism against hand-computed values: the results coverage rule on the
SPEC's hand case, the authors' Q update and the aliased Q rows on small tables, the cumulative
pair counts of a scripted run and across a scripted split, the relabels after an update, the
forward model's sample without replacement, the presets field by field, and the validation.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax import boxes, reach
from gara_jax import train as tr
from gara_jax.agents import forward_model as fm
from gara_jax.agents import high_level as hl
from gara_jax.agents.dqn import DQNConfig, Transition, make_dqn
from gara_jax.algorithms import GaraConfig, HandcraftedConfig, make_algorithm, refinement
from gara_jax.algorithms.gara import RESULTS_MIN_STEPS
from gara_jax.algorithms.refinement import apply_split
from gara_jax.partition import Partition, locate

LOW = DQNConfig(loss="all_actions", buffer_size=1000, learning_starts=100)
# GARA's initial right-hand goal [1, 3] x [0, 3], full velocities.
RIGHT_LO, RIGHT_HI = np.array([1.0, 0, -1, -1]), np.array([3.0, 3, 1, 1])


# -- the coverage rule (SPEC.md 3.6, 3.9.2) ---------------------------------------------------


def test_results_coverage_rule_skips_a_dimension_without_intersection():
    cov = lambda lo, hi, rule: [float(c) for c in boxes.coverage(
        jnp.array(lo), jnp.array(hi), jnp.array(RIGHT_LO), jnp.array(RIGHT_HI), rule=rule)]
    # R lies left of x = 1 and inside [0, 3] x [-1, 1]^2 in y, vx, vy.
    r_lo, r_hi = [0.2, 1.0, -0.5, 0.0], [0.6, 2.0, 0.5, 0.5]
    assert cov(r_lo, r_hi, "final") == [0.0, 0.0]
    # Results: x is left out of all three volumes; over (y, vx, vy) R lies inside G_d:
    # c1 = (1 * 1 * 0.5) / (1 * 1 * 0.5) = 1, c2 = 0.5 / (3 * 2 * 2).
    c1, c2 = cov(r_lo, r_hi, "results")
    assert c1 == pytest.approx(1.0) and c2 == pytest.approx(0.5 / 12)
    # Half of R above y = 3: c1 = (1 * 1 * 0.5) / (2 * 1 * 0.5) = 0.5 under "results".
    c1, c2 = cov([0.2, 2.0, -0.5, 0.0], [0.6, 4.0, 0.5, 0.5], "results")
    assert c1 == pytest.approx(0.5) and c2 == pytest.approx(0.5 / 12)
    # Where every dimension intersects the two rules agree (here c1 = 0.5 on x).
    both = [cov([0.0, 1.0, -0.5, 0.0], [2.0, 2.0, 0.5, 0.5], rule) for rule in ("final", "results")]
    assert both[0] == pytest.approx(both[1]) and both[0][0] == pytest.approx(0.5)
    # A face touching x = 1 intersects in a point: not skipped, so c1 = 0 under both rules.
    assert cov([0.5, 1.0, -0.5, 0.0], [1.0, 2.0, 0.5, 0.5], "results") == [0.0, 0.0]
    with pytest.raises(ValueError, match="rule"):
        boxes.coverage(jnp.zeros(1), jnp.ones(1), jnp.zeros(1), jnp.ones(1), rule="draft")


def test_results_coverage_rule_makes_the_left_region_reach_the_right_one():
    """F(s, G) = s - (0.5, 0, 0, 0) on the left box [0, 1] x [0, 3]: every prediction stops
    short of x = 1, inside [1, 3] x [0, 3] in y, vx, vy."""
    d = 4
    eye = np.eye(d, 3 * d)
    layers = [(np.concatenate([eye, -eye], 0).T, np.zeros(2 * d)),
              (np.concatenate([np.eye(d), -np.eye(d)]), np.array([-0.5, 0, 0, 0]))]
    s_lo, s_hi = [0.0, 0, -1, -1], [1.0, 3, 1, 1]
    common = dict(tau1=0.9, tau2=0.01, min_volume_ratio=0.05, method="ibp", small_box_c1=0.5)
    final = reach.refine(layers, s_lo, s_hi, RIGHT_LO, RIGHT_HI, coverage="final", **common)
    assert len(final.reaching_lo) == 0 and final.nonreaching_lo.tolist() == [s_lo]
    results = reach.refine(layers, s_lo, s_hi, RIGHT_LO, RIGHT_HI, coverage="results", **common)
    assert results.reaching_lo.tolist() == [s_lo] and len(results.nonreaching_lo) == 0
    with pytest.raises(ValueError, match="coverage"):
        reach.refine(layers, s_lo, s_hi, RIGHT_LO, RIGHT_HI, coverage="draft")


# -- the Q update and the aliased rows (SPEC.md 3.3, 3.9.3) ---------------------------------


def _option(start, target, next_goal, reward=1.0):
    return hl.OptionOutcome(start=jnp.int32(start), target=jnp.int32(target),
                            next_goal=jnp.int32(next_goal), reward=jnp.float32(reward),
                            terminated=jnp.bool_(False), reached=jnp.bool_(target == next_goal),
                            exit_state=jnp.zeros(2), blocked=jnp.bool_(False))


def test_authors_q_update_takes_the_difference_against_the_chosen_target():
    q = np.zeros((3, 3), np.float32)
    q[0] = [0.2, 0.5, 0.1]
    q[2] = [0.3, 0.0, 0.6]

    def learn(q_update, outcome, **kw):
        cfg = hl.HighLevelConfig(alpha=0.1, gamma=0.9, q_update=q_update, **kw)
        hs = hl.init_high_state(cfg, 3, 2).replace(q=jnp.asarray(q))
        return np.asarray(hl.learn_from_option(cfg, hs, outcome, 3, jnp.bool_(True)).q)

    # Option 0 -> 1 that ended in goal 2: TD target 1 + 0.9 * max Q[2] = 1.54.
    missed = _option(0, 1, 2)
    written = learn("written_entry", missed)
    authors = learn("authors", missed)
    assert written[0, 2] == pytest.approx(0.1 + 0.1 * (1.54 - 0.1))  # 0.244
    assert authors[0, 2] == pytest.approx(0.1 + 0.1 * (1.54 - 0.5))  # 0.204, against Q[0][1]
    for out in (written, authors):
        changed = np.argwhere(out != q).tolist()
        assert changed == [[0, 2]]
    # An option that ended in its target, and the textbook entry: the same update either way.
    for outcome, kw in ((_option(0, 2, 2), {}), (missed, dict(q_target_entry="target"))):
        np.testing.assert_allclose(learn("authors", outcome, **kw),
                                   learn("written_entry", outcome, **kw))


def _split_seed(G=5, aliased=False):
    lo = np.array([[0, 0, -1, -1], RIGHT_LO])
    hi = np.array([[1, 3, 1, 1], RIGHT_HI])
    q = np.zeros((G, G), np.float32)
    q[0, 0], q[0, 1], q[1, 0] = 0.1, 0.2, 0.5
    marks = lambda: np.zeros((G, G), bool)
    seed = dict(partition=Partition.create(lo, hi, G), q=q, succeeded=marks(),
                reachable=marks(), unreachable=marks(), blocked=marks(),
                records=np.full((G, G), 3, np.int32), pair_count=np.full((G, G), 7, np.int32))
    if aliased:
        seed["alias"] = np.arange(G, dtype=np.int32)
    return seed


class _UpperReaches:
    """The left box split in y: [2, 3] reaches the right box, [0, 1] and [1, 2] do not."""

    reaching_lo, reaching_hi = np.array([[0, 2, -1, -1.0]]), np.array([[1, 3, 1, 1.0]])
    nonreaching_lo = np.array([[0, 0, -1, -1.0], [0, 1, -1, -1.0]])
    nonreaching_hi = np.array([[1, 1, 1, 1.0], [1, 2, 1, 1.0]])


def test_aliased_q_rows_share_the_zero_and_later_updates():
    results = {}
    for mode in ("copied", "aliased_at_split", "aliased", "kept"):
        seed = _split_seed(aliased=mode == "aliased")
        assert apply_split(seed, 0, 1, _UpperReaches, "reference", mode) == "split"
        results[mode] = seed
    # Pieces: index 0 (the reaching [2, 3]), then 2 and 3 appended (not reaching).
    copied = results["copied"]["q"]
    np.testing.assert_allclose(copied[[0, 2, 3], 0], 0.1)
    np.testing.assert_allclose(copied[[0, 2, 3], 1], [0.2, 0.0, 0.0])
    # "kept": no piece loses G_s's value towards the target, though the marks still say
    # which pieces were found not to reach it.
    kept = results["kept"]
    np.testing.assert_allclose(kept["q"][[0, 2, 3], 1], 0.2)
    np.testing.assert_allclose(kept["q"][[0, 2, 3], 0], 0.1)
    assert kept["unreachable"][[2, 3], 1].all() and kept["reachable"][0, 1]
    for mode in ("aliased_at_split", "aliased"):
        q = results[mode]["q"]
        # Q[non-reaching piece][1] = 0 on one shared row: G_s's index and every piece lose it.
        np.testing.assert_allclose(q[[0, 2, 3], 1], 0.0)
        np.testing.assert_allclose(q[[0, 2, 3], 0], 0.1)
        assert q[1, 0] == pytest.approx(0.5)  # the right box's row is not in the group
    assert results["aliased"]["alias"].tolist() == [0, 1, 0, 0, 4]

    # A later update from piece 2 (option 2 -> 1 that entered goal 1): TD target
    # 1 + 0.9 * max Q[1] = 1.45, so Q[2][1] = 0.1 * 1.45; under "aliased" rows 0 and 3 get it
    # too, under "aliased_at_split" the rows are independent by then.
    cfg = hl.HighLevelConfig(alpha=0.1, gamma=0.9, q_update="authors")
    for mode, rows in (("aliased_at_split", [2]), ("aliased", [0, 2, 3])):
        seed = results[mode]
        hs = hl.init_high_state(cfg, 5, 2).replace(
            q=jnp.asarray(seed["q"]), alias=None if mode != "aliased" else jnp.asarray(
                seed["alias"]))
        q = np.asarray(hl.learn_from_option(cfg, hs, _option(2, 1, 1), 4, jnp.bool_(True)).q)
        others = [g for g in range(5) if g not in rows]
        np.testing.assert_allclose(q[rows, 1], 0.145, rtol=1e-6)
        np.testing.assert_allclose(q[others], seed["q"][others])
        np.testing.assert_allclose(q[rows, 0], 0.1)


def test_split_keeps_index_keyed_counts_and_records():
    for records, kept in (("cleared", False), ("kept", True)):
        seed = _split_seed()
        apply_split(seed, 0, 1, _UpperReaches, "reference", "copied", records)
        # Index 0 (the piece that kept it): counts kept as a start and as a target.
        assert seed["pair_count"][0, 1] == 7 and seed["pair_count"][1, 0] == 7
        assert seed["pair_count"][[2, 3]].sum() == 0 and seed["pair_count"][:, [2, 3]].sum() == 0
        assert (seed["records"][1, 0] == 3) == kept and (seed["records"][0, 1] == 3) == kept
        assert seed["records"][[2, 3]].sum() == 0 and seed["records"][:, [2, 3]].sum() == 0
        assert seed["records"][1, 1] == 3


# -- cumulative counts in the jitted steps (SPEC.md 3.9.3) -----------------------------------


def test_cumulative_counts_of_a_scripted_run_match_a_hand_count():
    """24 steps, k = 2, one seed choosing at random among the 2 initial goals: the counter
    is +1 per window and +1 per decision for a pair that already has a count."""
    cfg = GaraConfig.reference(
        version="results", k=2, steps_per_epoch=24, eval_episodes=1, memory_capacity=200,
        low=LOW, high=hl.HighLevelConfig(epsilon_start=0.5, epsilon_min=0.5,
                                         epsilon_decrement=0.0))
    alg = make_algorithm(cfg)
    state, _ = jax.jit(alg.train_epoch)(alg.init(jax.random.key(3)), jax.random.key(4))
    mem = jax.device_get(state.memory)
    n = int(mem.size)
    start = np.asarray(locate(state.partition, state.memory.start))[:n]
    target = np.asarray(fm.match_boxes(state.memory.target_lo, state.memory.target_hi,
                                       state.partition.lo, state.partition.hi,
                                       state.partition.count))[:n]
    step, data = mem.step[:n], mem.data[:n]
    hand = np.zeros((cfg.max_goals, cfg.max_goals), int)
    for t in np.unique(step):
        # At a step, the decision (the count-only row) comes before that step's window.
        for r in np.flatnonzero((step == t) & ~data):
            hand[start[r], target[r]] += hand[start[r], target[r]] > 0
        for r in np.flatnonzero((step == t) & data):
            hand[start[r], target[r]] += 1
    np.testing.assert_array_equal(np.asarray(state.pair_count), hand)
    # The memory's count (every window and every decision) is larger: the first decisions of
    # a pair come before it exists.
    assert 0 < hand.sum() < n and hand.sum() >= data.sum()


# -- host steps: counts across a split, relabels after an update ---------------------------
# The analyses are scripted (the fit reports every job stable, ``refine_many`` returns a given
# verdict): the real analysis of this crafted memory is tested in test_gara_reference.py.


HOST_CFG = dict(steps_per_epoch=100, eval_episodes=1, min_steps=100, memory_capacity=1024,
                max_goals=16, low=LOW, refine_method="ibp", tau1=0.9, tau2=0.01,
                small_box_c1=0.5, memory="windows", forward_model="per_job",
                pair_counts="cumulative", relabel_replay=True)
ROWS = 600


@pytest.fixture(scope="module")
def crafted():
    """One seed whose memory holds 600 left -> right windows from random starts in the left
    box, whose pair (0, 1) has the count 700 (the trigger's), (1, 0) a count of 9 and two MSE
    records, and whose low-level replay holds 2 transitions (for the relabelling to copy)."""
    cfg = GaraConfig(**HOST_CFG)
    loop = tr.init_loop(cfg, [0])
    rng = np.random.default_rng(0)
    mem = jax.device_get(loop.states.memory)
    start = np.zeros((1, ROWS, 4), np.float32)
    start[0, :, 0] = rng.uniform(0, 1, ROWS)
    start[0, :, 1] = rng.uniform(0, 3, ROWS)
    start[0, :, 2:] = rng.uniform(-1, 1, (ROWS, 2))
    t_lo = np.broadcast_to(RIGHT_LO.astype(np.float32), (1, ROWS, 4))
    t_hi = np.broadcast_to(RIGHT_HI.astype(np.float32), (1, ROWS, 4))
    put = lambda a, v: jnp.asarray(np.concatenate([v, a[:, ROWS:]], axis=1), a.dtype)
    memory = loop.states.memory.replace(
        start=put(mem.start, start), end=put(mem.end, start), target_lo=put(mem.target_lo, t_lo),
        target_hi=put(mem.target_hi, t_hi), length=put(mem.length, np.ones((1, ROWS))),
        step=put(mem.step, np.full((1, ROWS), 10)), episode=put(mem.episode, np.zeros((1, ROWS))),
        data=put(mem.data, np.ones((1, ROWS), bool)), size=jnp.asarray([ROWS], jnp.int32))
    count = np.zeros((1, 16, 16), np.int32)
    count[0, 0, 1], count[0, 1, 0] = 700, 9
    records = np.zeros((1, 16, 16), np.int32)
    records[0, 1, 0] = 2
    dqn = make_dqn(cfg.low, 12, 4)
    one = jax.tree.map(lambda a: a[0], loop.states.dqn)
    g = jnp.concatenate([jnp.asarray(RIGHT_LO), jnp.asarray(RIGHT_HI)]).astype(jnp.float32)
    for x in (0.5, 2.0):
        t = Transition(jnp.concatenate([jnp.zeros(4), g]), jnp.int32(0), jnp.float32(-0.1),
                       jnp.concatenate([jnp.array([x, 1.0, 0, 0]), g]), jnp.bool_(False))
        one, _ = dqn.observe(one, t, jax.random.key(0))
    params = fm.make_forward_model(cfg.forward, 4).init(jax.random.split(jax.random.key(0), 1))
    states = loop.states.replace(
        memory=memory, env_steps=jnp.asarray([20], jnp.int32), pair_count=jnp.asarray(count),
        forward=loop.states.forward.replace(records=jnp.asarray(records)),
        dqn=jax.tree.map(lambda a: a[None], one))
    return states, params


def _scripted_host_step(monkeypatch, crafted, verdict, **options):
    states, params = crafted
    monkeypatch.setattr(refinement, "_fit_per_job",
                        lambda config, forward, st, jobs, *a: (np.ones(len(jobs), bool), params))
    monkeypatch.setattr(reach, "refine_many", lambda *a, **k: [verdict])
    cfg = GaraConfig(**HOST_CFG, **options)
    new, info = make_algorithm(cfg).host_update(states, epoch=0)
    assert info["triggered"] == 1 and info["analysed"] == 1 and bool(info["updated"][0])
    return states, new, info


def test_cumulative_counts_survive_a_split_and_the_relabel_moves_or_inflates_them(
        monkeypatch, crafted):
    out = {}
    for relabel in ("none", "move", "add"):
        states, new, info = _scripted_host_step(monkeypatch, crafted, _UpperReaches,
                                                relabel_counts=relabel,
                                                records_after_split="kept")
        assert info["splits"] == 1
        out[relabel] = np.asarray(new.pair_count[0])
        assert int(new.forward.records[0, 1, 0]) == 2  # towards index 0: records kept
    partition = jax.tree.map(lambda a: a[0], new.partition)
    left_start = np.asarray(locate(partition, states.memory.start[0, :ROWS]))
    rows_in = {p: int(np.sum(left_start == p)) for p in (0, 2, 3)}
    assert sum(rows_in.values()) == ROWS and min(rows_in.values()) > 0
    none = out["none"]
    # Keyed by goal index: index 0 keeps its counts; the appended pieces 2, 3 start from 0.
    assert none[0, 1] == 700 and none[1, 0] == 9
    assert none[[2, 3]].sum() == 0 and none[:, [2, 3]].sum() == 0
    # "move" (final version): -1 on (0, 1), +1 on (piece, 1) for every window whose start moved.
    move = out["move"]
    assert move[0, 1] == 700 - rows_in[2] - rows_in[3]
    assert (move[2, 1], move[3, 1]) == (rows_in[2], rows_in[3])
    assert move[:, 1].sum() == 700 and move[1, 0] == 9
    # "add" (results version): +1 on (new start, 1) for every window: 600 counts more.
    add = out["add"]
    assert add[0, 1] == 700 + rows_in[0]
    assert (add[2, 1], add[3, 1]) == (rows_in[2], rows_in[3])
    assert add[:, 1].sum() == 700 + ROWS


def test_host_step_writes_the_alias_groups_of_a_split(monkeypatch, crafted):
    states, params = crafted
    q = states.high.q.at[0, 0, 0].set(0.1).at[0, 0, 1].set(0.2)
    high = states.high.replace(q=q, alias=jnp.arange(16, dtype=jnp.int32)[None])
    _, new, info = _scripted_host_step(monkeypatch, (states.replace(high=high), params),
                                       _UpperReaches, q_rows_after_split="aliased")
    assert info["splits"] == 1
    assert np.asarray(new.high.alias[0, :5]).tolist() == [0, 1, 0, 0, 4]
    np.testing.assert_allclose(np.asarray(new.high.q[0, [0, 2, 3], 1]), 0.0)
    np.testing.assert_allclose(np.asarray(new.high.q[0, [0, 2, 3], 0]), 0.1)


class _WholeBoxReaches:
    reaching_lo, reaching_hi = np.array([[0, 0, -1, -1.0]]), np.array([[1, 3, 1, 1.0]])
    nonreaching_lo = nonreaching_hi = np.zeros((0, 4))


def test_relabels_after_an_analysis_whose_whole_box_reaches(monkeypatch, crafted):
    """With ``relabel_after="update"`` the replay gets its hindsight copies and the counts
    their inflation after a whole-box "reaches"; with ``"split"`` only after a split."""
    seen = {}
    for after in ("split", "update"):
        _, new, info = _scripted_host_step(monkeypatch, crafted, _WholeBoxReaches,
                                           relabel_counts="add", relabel_after=after)
        assert info["reaches"] == 1 and info["splits"] == 0 and not bool(info["changed"][0])
        assert bool(new.reachable[0, 0, 1]) and int(new.partition.count[0]) == 2
        seen[after] = (int(new.dqn.buffer.current_index[0]), int(new.pair_count[0, 0, 1]))
    assert seen["split"] == (2, 700)
    assert seen["update"] == (4, 700 + ROWS)  # every window's start is still in goal 0


# -- the forward model's sample (SPEC.md 3.5) ------------------------------------------------


def test_shared_sample_without_replacement_uses_every_row_of_a_small_pair():
    idx, ok = fm.distinct_sample(jax.random.key(0), 1000, 32)
    assert len(set(np.asarray(idx).tolist())) == 32 and bool(ok.all())
    assert int(np.max(np.asarray(idx))) < 1000
    # Three rows: one update trains on each once, and its MSE record is over exactly them.
    f = fm.make_forward_model(fm.ForwardModelConfig(shared_sample="without_replacement"), 4)
    params = jax.tree.map(lambda p: p[0], f.init(jax.random.split(jax.random.key(0), 1)))
    x = jnp.arange(10 * 12, dtype=jnp.float32).reshape(10, 12) / 100
    y = jnp.arange(10 * 4, dtype=jnp.float32).reshape(10, 4) / 40
    pair = np.array([0, 1, 0, 1, 1, 0, 1, 1, 0, 1])
    rows, seg_start, seg_len = fm.pair_segments(pair, np.ones(10, bool), np.array([0]))
    take = rows[seg_start[0]: seg_start[0] + seg_len[0]]
    assert sorted(take.tolist()) == [0, 2, 5, 8]
    new, _, mse = f.shared_updates(params, f.init_optimizer(params), x, y, jnp.asarray(rows),
                                   jnp.asarray(seg_start), jnp.asarray(seg_len),
                                   jnp.array([True]), jax.random.split(jax.random.key(1), 1))
    full = jnp.mean((f.apply(new, x[take]) - y[take]) ** 2)
    assert float(mse[0]) == pytest.approx(float(full), rel=1e-5)


# -- the presets (SPEC.md 3.9.2) and validation ----------------------------------------------


def test_results_preset_field_by_field():
    final, res = GaraConfig.reference(), GaraConfig.reference(version="results")
    expected = dict(
        # 3.9.2, the results version's own.
        coverage="results", split_epsilon_boost=1.0, memory_capacity=10_000, min_steps=5000,
        relabel_counts="add",
        # 3.9.3, what both versions do.
        pair_counts="cumulative", records_after_split="kept", relabel_after="update",
        q_rows_after_split="aliased_at_split", skip_unreachable=False, cadence="episode",
        max_episode_steps=302)
    assert {name: getattr(res, name) for name in expected} == expected
    assert (res.high.epsilon_decrement, res.high.q_update) == (0.005, "authors")
    assert res.low.buffer_size == 10_000
    assert res.forward.shared_sample == "without_replacement"
    # 3.9.2, unchanged from the final version.
    assert dataclasses.replace(res.low, buffer_size=100_000) == final.low
    assert (res.low.target_update_every, res.low.learning_rate, res.low.gamma,
            res.low.batch_size, res.low.learning_starts) == (20, 0.01, 0.95, 32, 3000)
    assert dataclasses.replace(res.forward, shared_sample=final.forward.shared_sample) == \
        final.forward
    assert (res.forward.hidden, res.forward.learning_rate, res.forward.batch_size,
            res.forward.shared_steps) == ((8, 8), 0.005, 32, 1)
    same = ("memory", "forward_model", "shared_min_records", "tau1", "tau2", "min_volume_ratio",
            "small_box_c1", "intrinsic", "entry_reward", "goal_membership", "reached_at_start",
            "stall_penalty", "relabel_replay", "q_columns", "k", "steps_per_epoch")
    assert {n: getattr(res, n) for n in same} == {n: getattr(final, n) for n in same}
    assert (res.tau1, res.tau2, res.min_volume_ratio, res.small_box_c1) == (0.9, 0.01, 0.05, 0.5)
    # Both values of the open min_steps; the planning variant skips nothing either (3.9.3).
    assert RESULTS_MIN_STEPS == (1000, 5000)
    assert GaraConfig.reference(version="results", min_steps=1000).min_steps == 1000
    planning = GaraConfig.reference(version="results", planning=True)
    assert planning.planning and not planning.skip_unreachable
    hc = HandcraftedConfig.reference(version="results")
    assert (hc.high.epsilon_decrement, hc.low.buffer_size, hc.high.q_update) == (
        0.005, 10_000, "authors")
    assert hc.intrinsic == "every_step"
    assert hc.max_episode_steps == HandcraftedConfig.reference().max_episode_steps == 302


def test_final_preset_has_what_both_versions_do():
    """SPEC.md 3.9.3-3.9.4 on the final version; its own values stay (revision 2's 3.3-3.6)."""
    for planning in (False, True):
        f = GaraConfig.reference(planning=planning)
        assert (f.pair_counts, f.records_after_split, f.relabel_after, f.q_rows_after_split,
                f.relabel_counts, f.skip_unreachable) == (
            "cumulative", "kept", "update", "aliased_at_split", "move", False)
        assert (f.cadence, f.max_episode_steps) == ("episode", 302)
        assert (f.high.q_update, f.forward.shared_sample) == ("authors", "without_replacement")
        assert (f.coverage, f.split_epsilon_boost, f.memory_capacity, f.min_steps) == (
            "final", 1.5, 50_000, 5000)
        assert (f.high.epsilon_decrement, f.low.buffer_size) == (0.0005, 100_000)
    assert HandcraftedConfig.reference().high.q_update == "authors"
    # The project's defaults keep the first readings (nothing there changed numerically).
    ours = GaraConfig()
    assert (ours.pair_counts, ours.records_after_split, ours.relabel_after,
            ours.q_rows_after_split, ours.relabel_counts, ours.coverage) == (
        "memory", "cleared", "split", "copied", "none", "final")
    assert (ours.cadence, ours.max_episode_steps) == ("epoch", None)
    assert (ours.high.q_update, ours.forward.shared_sample) == ("written_entry",
                                                                "with_replacement")


@pytest.mark.parametrize("field,value", [
    ("coverage", "draft"), ("q_rows_after_split", "shared"), ("pair_counts", "ring"),
    ("records_after_split", "reset"), ("relabel_counts", "double"), ("relabel_after", "never"),
    ("merge", "one_pass")])
def test_new_options_are_validated(field, value):
    with pytest.raises(ValueError, match=field):
        GaraConfig(**{field: value})


def test_option_combinations_and_nested_options_are_validated():
    with pytest.raises(ValueError, match="pair_counts"):
        GaraConfig(pair_counts="cumulative", memory="options")
    with pytest.raises(ValueError, match="relabel_counts"):
        GaraConfig(relabel_counts="add")
    with pytest.raises(ValueError, match="q_update"):
        hl.HighLevelConfig(q_update="target")
    with pytest.raises(ValueError, match="shared_sample"):
        fm.ForwardModelConfig(shared_sample="stratified")
    for make in (GaraConfig.reference, HandcraftedConfig.reference):
        with pytest.raises(ValueError, match="version"):
            make(version="first_commit")
