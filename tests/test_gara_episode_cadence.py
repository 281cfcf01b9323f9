"""GARA's per-episode cadence and Planning started from a given partition (SPEC.md 3.9.3).

A scripted run whose episodes all truncate after 20 steps, with every pair open (``min_steps``
0, every analysis scripted to find no reaching box) and the stability test always passed:
the host step must run after every episode, trigger exactly the pairs with a memory row from
that episode, give each of them chosen in it one shared-model update and analyse a pair with
three records. Its steps must be
the per-epoch cadence's (the same keys; the host steps change only the forward model here).
A seed whose episode ends first must idle unchanged while the others finish theirs. A
Planning run started from given partitions holds them at step 0.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax import reach
from gara_jax import train as tr
from gara_jax.agents import forward_model as fm
from gara_jax.agents import high_level as hl
from gara_jax.agents.dqn import DQNConfig
from gara_jax.algorithms import GaraConfig
from gara_jax.partition import Partition, gara_initial, handcrafted, locate

# Optimised compiles (tests/conftest.py): two programs are compared bit for bit.
pytestmark = pytest.mark.optimized

EP, SPE, EPOCHS = 20, 100, 2  # episodes truncate at 20 steps: 5 per epoch, none straddles
LOW = DQNConfig(loss="all_actions", buffer_size=1000, learning_starts=100)
CFG = GaraConfig.reference(
    version="results", steps_per_epoch=SPE, eval_episodes=1, max_episode_steps=EP,
    memory_capacity=1024, max_goals=8, low=LOW, min_steps=0,
    forward=fm.ForwardModelConfig(shared_sample="without_replacement", stable_decrease=1e9),
    high=hl.HighLevelConfig(epsilon_start=1.0, epsilon_min=1.0, epsilon_decrement=0.0,
                            tie_break="lowest", q_update="authors"))


class _NoReach:
    reaching_lo = reaching_hi = np.zeros((0, 4))
    nonreaching_lo, nonreaching_hi = np.array([[0, 0, -1, -1.0]]), np.array([[1, 3, 1, 1.0]])


@pytest.fixture(scope="module")
def runs():
    """The scripted run under both cadences (seeds 0 and 1)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(reach, "refine_many", lambda *a, **k: [_NoReach] * len(a[1]))
        return {c: tr.train_many(dataclasses.replace(CFG, cadence=c), [0, 1], EPOCHS * SPE)
                for c in ("episode", "epoch")}


def test_host_step_after_every_episode_on_that_episode_alone(runs):
    res = runs["episode"]
    assert CFG.cadence == "episode" and GaraConfig.reference().cadence == "episode"
    calls = [c for info in res.host_info for c in info["calls"]]
    assert [info["host_calls"] for info in res.host_info] == [SPE // EP] * EPOCHS
    assert all(c["seeds"].tolist() == [True, True] for c in calls)  # both seeds, every episode
    assert [len(e) for e in res.episodes["length"]] == [EPOCHS * SPE // EP] * 2
    # Hand count from the memory: the pairs (s != d) with a row in each episode.
    states = jax.device_get(res.final.states)
    records = np.zeros((2, CFG.max_goals, CFG.max_goals), int)
    for j, call in enumerate(calls):
        triggered = updates = analysed = 0
        for i in range(2):
            mem, part = (jax.tree.map(lambda a, i=i: a[i], x) for x in (states.memory,
                                                                         states.partition))
            rows = (np.arange(mem.capacity + 1) < mem.size) & (mem.episode == j)
            start = np.asarray(locate(part, jnp.asarray(mem.start)))[rows]
            target = np.asarray(fm.match_boxes(mem.target_lo, mem.target_hi, part.lo, part.hi,
                                               part.count))[rows]
            rows_of = lambda chosen_only: {  # noqa: E731
                (int(s), int(d)) for s, d, data in zip(start, target, mem.data[rows],
                                                        strict=True)
                if s != d and not (chosen_only and data)}
            # Triggered: a row of the pair in the episode; updated: chosen in it (a decision's
            # count-only row), one update each.
            pairs, chosen = rows_of(False), rows_of(True)
            for s, d in chosen:
                records[i, s, d] += 1
            triggered += len(pairs)
            updates += len(chosen)
            # Two goals: at most one job per seed; a pair is ready from its third record.
            analysed += any(records[i, s, d] >= CFG.shared_min_records for s, d in pairs)
        assert (call["triggered"], call["fit_updates"]) == (triggered, updates), j
        assert call["analysed"] == call["no_reach"] == analysed, j
    assert sum(c["analysed"] for c in calls) > 0
    np.testing.assert_array_equal(states.forward.records, records)


def test_steps_are_the_epoch_cadences(runs):
    """Nothing but the forward model changes in these host steps, so both cadences take the
    same steps: metrics, episodes and every other part of the state are equal."""
    ep, epoch = runs["episode"], runs["epoch"]
    assert set(ep.metrics) == set(epoch.metrics)
    for k, v in epoch.metrics.items():
        assert ep.metrics[k].dtype == v.dtype, k
        # Means are summed on the host over the segments: equal up to rounding.
        np.testing.assert_allclose(ep.metrics[k], v, rtol=1e-5, err_msg=k)
    for f in tr.EPISODE_FIELDS:
        for a, b in zip(ep.episodes[f], epoch.episodes[f], strict=True):
            np.testing.assert_array_equal(a, b)
    a, b = (jax.device_get(r.final.states.replace(forward=None)) for r in (ep, epoch))
    jax.tree.map(np.testing.assert_array_equal, a, b)


def test_a_seed_whose_episode_ended_idles_unchanged(runs):
    """Seed 0, three steps before its episode's end, beside seed 1 at an episode's start: one
    segment takes 3 steps of seed 0 and 20 of seed 1, and each seed ends as it does beside a
    copy of itself (where no seed idles)."""
    comp = tr.compiled(CFG)
    loop = tr.init_loop(CFG, [0, 1])
    states = loop.states
    states = states.replace(
        env_state=states.env_state.replace(time=states.env_state.time.at[0].set(EP - 3)),
        episode=states.episode.replace(length=states.episode.length.at[0].set(EP - 3)))
    host = jax.device_get(states)
    # Laid out as the run's states are (so the segment compiled for the runs is reused).
    pick = lambda rows: jax.tree.map(  # noqa: E731
        lambda a: jax.device_put(a[np.asarray(rows)], loop.keys.sharding), host)
    keys = loop.keys
    mixed, seg = comp.segment(pick([0, 1]), keys, 0)
    assert np.asarray(seg["steps"]).tolist() == [3, EP]
    assert np.asarray(seg["ended"]).tolist() == [True, True]
    for i in (0, 1):
        alone, _ = comp.segment(pick([i, i]), jax.device_put(
            np.asarray(keys)[[i, i]], loop.keys.sharding), 0)
        row = lambda t, i=i: jax.tree.map(lambda a: np.asarray(a[i]), jax.device_get(t))
        jax.tree.map(np.testing.assert_array_equal, row(mixed), row(alone))
    assert np.asarray(mixed.env_steps).tolist() == [3, EP]
    assert np.asarray(mixed.dqn.buffer.current_index).tolist() == [3, EP]


def test_planning_starts_from_the_given_partitions():
    """Seed 5 from the 6-box handcrafted partition, seed 7 from GARA's initial one split
    again at y = 1.5: both at step 0 (and, nothing being refined, at the end)."""
    cfg = GaraConfig.reference(version="results", planning=True, steps_per_epoch=10,
                               eval_episodes=1, max_episode_steps=EP, max_goals=8, low=LOW,
                               memory_capacity=256)
    lo, hi = (np.asarray(a) for a in gara_initial(8).boxes())
    lo3 = np.concatenate([lo, lo[1:]])
    hi3 = np.concatenate([hi, hi[1:]])
    hi3[1, 1], lo3[2, 1] = 1.5, 1.5
    given = [handcrafted(8), (lo3, hi3)]
    res = tr.train_many(cfg, [5, 7], 10, initial_partitions=given)
    for i, (want_lo, want_hi) in enumerate([handcrafted(8).boxes(), (lo3, hi3)]):
        snap = res.snapshots[i][0]
        assert snap.step == 0 and snap.count == len(want_lo)
        np.testing.assert_array_equal(snap.lo, want_lo)
        np.testing.assert_array_equal(snap.hi, want_hi)
        end = tr.final_partitions(res)[i]
        np.testing.assert_array_equal(np.asarray(end.boxes()[0]), want_lo)
    assert res.metrics["n_goals"][:, -1].tolist() == [6, 3]
    # Only the partition is taken: the rest is a fresh agent's.
    assert not np.asarray(res.final.states.reachable).any()


def test_initial_partitions_are_validated():
    cfg = GaraConfig(max_goals=8)
    lo, hi = (np.asarray(a) for a in gara_initial(8).boxes())
    with pytest.raises(ValueError, match=r"initial_partitions\[0\]: partition: boxes do not "
                                         "cover"):
        tr.starting_partitions(cfg, [(lo[:1], hi[:1])], 1)
    overlap = (np.concatenate([lo, lo[:1]]), np.concatenate([hi, hi[:1]]))
    with pytest.raises(ValueError, match=r"initial_partitions\[1\]: .*overlap"):
        tr.starting_partitions(cfg, [(lo, hi), overlap], 2)
    with pytest.raises(ValueError, match="initial_partitions: one partition per seed"):
        tr.starting_partitions(cfg, [(lo, hi)], 2)
    with pytest.raises(ValueError, match=r"initial_partitions\[0\]: max_goals"):
        tr.starting_partitions(GaraConfig(max_goals=4), [handcrafted(6)], 1)
    with pytest.raises(ValueError, match="initial_partitions: only GARA"):
        from gara_jax.algorithms import HandcraftedConfig

        tr.starting_partitions(HandcraftedConfig(), [handcrafted(6)], 1)
    ranked = Partition.create(lo, hi, 8, rank=True)
    with pytest.raises(ValueError, match="piece_order"):
        tr.starting_partitions(cfg, [ranked], 1)
    p = tr.starting_partitions(dataclasses.replace(cfg, piece_order="parent"), [ranked], 1)
    assert p.rank.shape == (1, 8)


@pytest.mark.parametrize("field,value", [("cadence", "step"), ("max_episode_steps", 0)])
def test_new_fields_are_validated(field, value):
    with pytest.raises(ValueError, match=field):
        GaraConfig(**{field: value})
