"""Run by tests/test_sharding.py in a subprocess with 4 forced CPU devices: trains each
algorithm's tiny config on 8 seeds over 1 device (``batch_invariant=True``) and over 4 devices
(where that is the default) and checks, bit for bit, that
the metrics and final states agree, that the 4-device states really lie over 4 devices, and
that an orbax checkpoint written by the 4-device run after its first epoch, restored onto one
device, continues exactly (each device compiles the epoch once, so compilation dominates)."""

import sys
import tempfile

import jax
import numpy as np

from gara_jax import checkpoint
from gara_jax import train as tr
from gara_jax.agents.dqn import DQNConfig
from gara_jax.agents.forward_model import ForwardModelConfig
from gara_jax.agents.td3 import TD3Config
from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig

LOW = DQNConfig(buffer_size=600, learning_starts=100)
CONFIGS = {
    "handcrafted": HandcraftedConfig(steps_per_epoch=200, eval_episodes=1, low=LOW),
    # min_steps low enough that the host step triggers, fits the shared model and analyses.
    "gara": GaraConfig(steps_per_epoch=300, eval_episodes=1, low=LOW, min_steps=200,
                       memory_capacity=1000, max_goals=16,
                       forward=ForwardModelConfig(max_epochs=20)),
    "hiro": HiroConfig(steps_per_epoch=200, eval_episodes=1, low=LOW,
                       high=TD3Config(actor_hidden=(16,), critic_hidden=(16,), batch_size=16,
                                      buffer_size=200, learning_starts=20)),
}
SEEDS = 8
EPOCHS = {"handcrafted": 2, "gara": 4, "hiro": 2}


def host(tree):
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]


def same(a, b, what):
    a, b = host(a), host(b)
    assert len(a) == len(b), what
    bad = [i for i, (x, y) in enumerate(zip(a, b, strict=True)) if not np.array_equal(x, y)]
    assert not bad, f"{what}: {len(bad)} of {len(a)} arrays differ"


def main(names):
    assert len(jax.devices()) == 4, jax.devices()
    for name in names:
        cfg, steps = CONFIGS[name], CONFIGS[name].steps_per_epoch * EPOCHS[name]
        one = tr.train_many(cfg, SEEDS, steps, devices=1, batch_invariant=True)
        with tempfile.TemporaryDirectory() as d:
            def save_first(out, d=d):
                if out.epoch == 0:
                    checkpoint.save(f"{d}/run", out.loop, {"epoch": out.epoch})

            four = tr.train_many(cfg, SEEDS, steps, devices=4, callback=save_first)
            loop, extra = checkpoint.load(f"{d}/run", tr.init_loop(cfg, SEEDS, devices=1))
        same(one.metrics, four.metrics, f"{name} metrics")
        same(one.final.states, four.final.states, f"{name} final states")
        same(one.final.keys, four.final.keys, f"{name} loop keys")
        for leaf in jax.tree.leaves(four.final.states):
            assert len(leaf.sharding.device_set) == 4, (name, leaf.sharding)
            shards = leaf.addressable_shards
            assert len(shards) == 4 and all(s.data.shape[0] == SEEDS // 4 for s in shards)
        if name == "gara":
            assert sum(info["triggered"] for info in four.host_info) > 0, "no host step ran"
        assert loop.epoch == 1 and extra == {"epoch": 0}
        assert len(jax.tree.leaves(loop.states)[0].sharding.device_set) == 1
        rest = tr.train_many(cfg, SEEDS, steps, devices=1, batch_invariant=True, init_state=loop)
        joined = {k: np.concatenate([one.metrics[k][:, :1], rest.metrics[k]], axis=1)
                  for k in one.metrics}
        same(one.metrics, joined, f"{name} resumed metrics")
        same(one.final.states, rest.final.states, f"{name} resumed final states")
        print(f"{name}: identical on 1 and 4 devices, and resumed on 1 from 4", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or list(CONFIGS))
