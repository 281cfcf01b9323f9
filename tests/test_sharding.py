"""Seeds sharded over devices: bitwise the one-device results, device arguments, layouts."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from gara_jax import sharding
from gara_jax import train as tr
from gara_jax.agents.dqn import DQNConfig
from gara_jax.algorithms import HandcraftedConfig

ROOT = Path(__file__).resolve().parent.parent
TINY = HandcraftedConfig(steps_per_epoch=100, eval_episodes=1,
                         low=DQNConfig(buffer_size=300, learning_starts=50))


def _env(**extra):
    env = dict(os.environ, **extra)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return env


# Handcrafted and HIRO pass too (`python tests/_sharded_run.py handcrafted gara hiro`), but each
# device compiles the epoch once, so every algorithm adds minutes; CI runs GARA, whose state
# holds Handcrafted's parts (the low-level DQN, a partition) and which has the host step.
SHARDED = ("gara",)


def test_four_devices_give_the_one_device_results_bit_for_bit():
    # 8 seeds on 1 and on 4 forced CPU devices, GARA with its host step, plus an orbax
    # checkpoint of the 4-device run resumed on 1 device (tests/_sharded_run.py).
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "_sharded_run.py"), *SHARDED], capture_output=True,
        text=True, timeout=900, cwd=ROOT,
        env=_env(XLA_FLAGS="--xla_force_host_platform_device_count=4"))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    for name in SHARDED:
        assert f"{name}: identical on 1 and 4 devices, and resumed on 1 from 4" in proc.stdout


def test_final_states_are_laid_out_over_the_seed_mesh():
    res = tr.train_many(TINY, 2, 100, devices=1)
    spec = sharding.seed_sharding(sharding.seed_mesh(1))
    for leaf in jax.tree.leaves(res.final.states) + [res.final.keys]:
        assert leaf.sharding == spec


@pytest.mark.parametrize("devices, message", [
    (0, "devices: a device count must be in"),
    (len(jax.devices()) + 1, "devices: a device count must be in"),
    (True, "devices: must be None"),
    (["cpu"], "devices: must be None"),
    ([], "devices: must be None"),
])
def test_bad_devices_are_rejected(devices, message):
    with pytest.raises(ValueError, match=message):
        tr.train_many(TINY, 2, 100, devices=devices)


def test_a_sequence_of_devices_and_a_repeated_device():
    assert sharding.resolve_devices(jax.devices()[:1]) == jax.devices()[:1]
    with pytest.raises(ValueError, match="devices: must be distinct"):
        sharding.resolve_devices(jax.devices()[:1] * 2)


def test_seeds_that_do_not_divide_over_the_devices_are_rejected():
    mesh = sharding.seed_mesh(1)
    fake = type("FakeMesh", (), {"devices": np.empty(4, object)})()
    with pytest.raises(ValueError, match=r"seeds/devices: 6 seeds do not divide over 4 "
                                         r"devices.*devices=3"):
        sharding.check_divisible(6, fake)
    sharding.check_divisible(6, mesh)  # one device: anything goes


@pytest.mark.parametrize("batch_invariant, one_seed_batch", [(False, 1), (True, 2)])
def test_seed_jit_splits_host_arguments_and_runs_one_seed_blocks_twice_when_invariant(
        batch_invariant, one_seed_batch):
    calls = []

    def f(x, c):  # seed axis first, as a seed-vmapped function's
        calls.append(x.shape)  # traced once per distinct block shape
        return 2 * x + c

    fn = sharding.SeedJit(f, batched=(0,), batch_invariant=batch_invariant)
    assert fn.batch_invariant is batch_invariant
    x = jax.device_put(np.arange(3.0), sharding.seed_sharding(sharding.seed_mesh(1)))
    np.testing.assert_array_equal(np.asarray(fn(x, 1.0)), [1.0, 3.0, 5.0])
    one = jax.device_put(np.arange(1.0), sharding.seed_sharding(sharding.seed_mesh(1)))
    out = fn(one, 0.0)
    assert out.shape == (1,) and float(out[0]) == 0.0
    assert calls == [(3,), (one_seed_batch,)]


def test_one_device_default_is_the_plain_jitted_epoch():
    # batch_invariant defaults to off on one device: train_many is bit for bit the plain
    # jit(vmap(epoch)) program, so one-device results do not change with the sharding code.
    res = tr.train_many(TINY, 2, 200, devices=1)
    alg = tr.compiled(TINY, 1).alg
    init_keys, loop_keys = tr._split_seed_keys(jax.vmap(jax.random.key)(np.arange(2)))
    states = jax.jit(jax.vmap(alg.init))(init_keys)
    run = jax.jit(jax.vmap(tr._epoch_fn(alg), in_axes=(0, 0, None)))
    for epoch in range(2):
        states, metrics = run(states, loop_keys, epoch)
        for k in ("train_success", "eval_success", "env_steps"):
            np.testing.assert_array_equal(np.asarray(metrics[k]), res.metrics[k][:, epoch])
    for a, b in zip(jax.tree.leaves(states), jax.tree.leaves(res.final.states), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_batch_invariant_must_be_a_bool():
    with pytest.raises(ValueError, match="batch_invariant: must be None, True or False"):
        tr.train_many(TINY, 2, 100, devices=1, batch_invariant="yes")


def test_seed_jit_without_a_choice_follows_the_scope():
    calls = []

    def f(x):
        calls.append(x.shape)
        return x + 1

    fn = sharding.SeedJit(f)
    one = jax.device_put(np.arange(1.0), sharding.seed_sharding(sharding.seed_mesh(1)))
    fn(one)
    with sharding.batch_invariant_scope(True):
        assert fn.invariant()
        fn(one)
    assert not fn.invariant()
    assert calls == [(1,), (2,)]


def test_reproduce_refuses_seeds_that_do_not_divide_over_the_devices(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.u_maze", "--quick", "--seeds", "2", "--methods",
         "handcrafted", "--no-progress", "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
        env=_env(XLA_FLAGS="--xla_force_host_platform_device_count=4"))
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [line for line in proc.stderr.splitlines() if "gara-jax reproduce" in line]
    assert len(lines) == 1 and "seeds/devices: 2 seeds do not divide over 4 devices" in lines[0]
    assert not (tmp_path / "out" / "metrics.csv").exists()
