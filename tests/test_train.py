"""The training driver: determinism, resumption, input validation, short end-to-end runs."""

import jax
import numpy as np
import pytest

from gara_jax import train as tr
from gara_jax.agents.dqn import DQNConfig
from gara_jax.agents.forward_model import ForwardModelConfig
from gara_jax.algorithms import GaraConfig, HandcraftedConfig

LOW = DQNConfig(buffer_size=1000, learning_starts=100)
HANDCRAFTED = HandcraftedConfig(steps_per_epoch=300, eval_episodes=2, low=LOW)
GARA = GaraConfig(steps_per_epoch=300, eval_episodes=2, low=LOW, min_steps=200,
                  memory_capacity=1000, max_goals=16, forward=ForwardModelConfig(max_epochs=20))
# Refines within a few short epochs; a tiny capacity exercises the "split does not fit" path.
GARA_PLANNING_TINY = GaraConfig(
    steps_per_epoch=600, eval_episodes=2, max_goals=5, min_steps=300, memory_capacity=2000,
    planning=True, low=DQNConfig(buffer_size=2000, learning_starts=100),
    forward=ForwardModelConfig(max_epochs=30))
REQUIRED = ("env_steps", "train_success", "eval_success", "episode_return", "n_goals",
            "episodes_ended")


def test_same_key_gives_identical_metrics():
    a = tr.train_many(HANDCRAFTED, [3, 4], total_steps=600)
    b = tr.train_many(HANDCRAFTED, [3, 4], total_steps=600)
    assert set(a.metrics) == set(b.metrics)
    for name in a.metrics:
        np.testing.assert_array_equal(a.metrics[name], b.metrics[name], err_msg=name)
    # Different seeds really differ (the low level acts randomly early on).
    c = tr.train_many(HANDCRAFTED, [5, 6], total_steps=600)
    assert not np.array_equal(a.metrics["episode_return"], c.metrics["episode_return"]) or \
        not np.array_equal(a.metrics["option_success"], c.metrics["option_success"])


def test_resuming_from_a_loop_state_continues_the_same_run():
    full = tr.train_many(HANDCRAFTED, 2, total_steps=900)
    first = tr.train_many(HANDCRAFTED, 2, total_steps=900, callback=lambda out: out.epoch == 0)
    assert first.metrics["env_steps"].shape == (2, 1) and first.final.epoch == 1
    rest = tr.train_many(HANDCRAFTED, 2, total_steps=900, init_state=first.final)
    for name in full.metrics:
        joined = np.concatenate([first.metrics[name], rest.metrics[name]], axis=1)
        np.testing.assert_array_equal(joined, full.metrics[name], err_msg=name)


def test_handcrafted_end_to_end_and_make_train():
    calls = []
    res = tr.train_many(HANDCRAFTED, seeds=[0, 1, 2], total_steps=700,
                        progress=lambda done, total, m: calls.append((done, total)))
    assert calls == [(1, 3), (2, 3), (3, 3)]  # 700 steps round up to 3 epochs of 300
    for name in REQUIRED:
        assert res.metrics[name].shape == (3, 3), name
    np.testing.assert_array_equal(res.metrics["env_steps"][0], [300, 600, 900])
    assert np.all(res.metrics["n_goals"] == 6)
    assert np.all((res.metrics["eval_success"] >= 0) & (res.metrics["eval_success"] <= 1))
    assert np.all(res.metrics["episodes_ended"].sum(axis=1) >= 2)  # 900 steps > 3 x 300
    assert res.algorithm == "handcrafted" and res.seeds == [0, 1, 2]
    assert [len(s) for s in res.snapshots] == [1, 1, 1] and res.snapshots[0][0].count == 6
    # make_train: one seed, a pure function of the key, vmappable over keys.
    train = tr.make_train(HANDCRAFTED, total_steps=600)
    _, metrics = jax.jit(jax.vmap(train))(jax.random.split(jax.random.key(0), 2))
    assert metrics["eval_success"].shape == (2, 2)
    assert np.asarray(metrics["env_steps"])[0].tolist() == [300, 600]


def test_gara_end_to_end():
    res = tr.train_many(GARA, seeds=2, total_steps=1800)
    for name in REQUIRED:
        assert res.metrics[name].shape == (2, 6), name
    assert len(res.host_info) == 6 and all(info is not None for info in res.host_info)
    assert sum(info["triggered"] for info in res.host_info) > 0
    for seed_snaps in res.snapshots:
        assert seed_snaps[0].step == 0 and seed_snaps[0].count == 2
        steps = [s.step for s in seed_snaps]
        assert steps == sorted(steps)
        assert [s.count for s in seed_snaps] == sorted(s.count for s in seed_snaps)
    # n_goals is the partition used during each epoch; a split applies from the next one.
    final_counts = np.asarray(res.final.states.partition.count)
    assert [snaps[-1].count for snaps in res.snapshots] == final_counts.tolist()
    assert np.all(res.metrics["n_goals"][:, -1] <= final_counts)
    assert res.host_time_s > 0


def test_gara_planning_refinement_keeps_a_tiling_within_capacity():
    from gara_jax.partition import Partition, check_tiling

    cfg, n_seeds = GARA_PLANNING_TINY, 3
    seen = {"analysed": 0}

    def check(out):
        part = out.loop.states.partition
        counts = np.asarray(part.count)
        assert np.all((counts >= 2) & (counts <= cfg.max_goals))
        for i in range(n_seeds):
            check_tiling(jax.tree.map(lambda a, i=i: a[i], part))
        seen["analysed"] += out.host_info["analysed"]

    res = tr.train_many(cfg, n_seeds, total_steps=6 * 600, callback=check)
    assert res.algorithm == "gara_planning"
    for name in REQUIRED:
        assert res.metrics[name].shape == (n_seeds, 6), name
    assert np.all(res.metrics["n_goals"] <= cfg.max_goals)
    assert seen["analysed"] > 0  # the refinement really ran (otherwise this proves nothing)
    # Each snapshot is itself a valid tiling of the U-maze's state space.
    for snaps in res.snapshots:
        for snap in snaps:
            check_tiling(Partition.create(snap.lo, snap.hi, cfg.max_goals))


@pytest.mark.parametrize("seeds", [0, -1, [], [1, 1], [0, -2], [0.5], True, "3"])
def test_bad_seeds_are_rejected(seeds):
    with pytest.raises(ValueError, match="seeds"):
        tr.seed_list(seeds)


@pytest.mark.parametrize("steps", [0, -5, 2.5, True])
def test_bad_total_steps_are_rejected(steps):
    with pytest.raises(ValueError, match="total_steps"):
        tr.n_epochs_for(HANDCRAFTED, steps)


def test_init_state_must_match_seeds():
    loop = tr.init_loop(HANDCRAFTED, [0, 1])
    with pytest.raises(ValueError, match="init_state"):
        tr.train_many(HANDCRAFTED, [0, 2], total_steps=300, init_state=loop)
