"""Orbax checkpoints: exact resume, atomic replacement, mismatch errors, the old .npz format."""

import jax
import numpy as np
import pytest

from gara_jax import checkpoint
from gara_jax import train as tr
from gara_jax.agents.dqn import DQNConfig
from gara_jax.algorithms import HandcraftedConfig

CFG = HandcraftedConfig(steps_per_epoch=100, eval_episodes=1,
                        low=DQNConfig(buffer_size=300, learning_starts=50))


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))]


def _saving_run(tmp_path, stop_after=None):
    def save(out):
        checkpoint.save(tmp_path / "run", out.loop, {"epoch": out.epoch, "m": [1.5]})
        return stop_after is not None and out.epoch == stop_after

    return tr.train_many(CFG, 2, 300, callback=save)


def test_resume_from_an_orbax_checkpoint_is_exact(tmp_path):
    full = tr.train_many(CFG, 2, 300)
    first = _saving_run(tmp_path, stop_after=0)
    assert checkpoint.latest_epoch(tmp_path / "run") == 1
    loop, extra = checkpoint.load(tmp_path / "run", tr.init_loop(CFG, 2))
    assert loop.epoch == 1 and extra == {"epoch": 0, "m": [1.5]}
    for a, b in zip(_leaves(first.final.states), _leaves(loop.states), strict=True):
        np.testing.assert_array_equal(a, b)
    rest = tr.train_many(CFG, 2, 300, init_state=loop)
    for name in full.metrics:
        joined = np.concatenate([first.metrics[name], rest.metrics[name]], axis=1)
        np.testing.assert_array_equal(joined, full.metrics[name], err_msg=name)
    for a, b in zip(_leaves(full.final.states), _leaves(rest.final.states), strict=True):
        np.testing.assert_array_equal(a, b)


def test_only_the_newest_epoch_is_kept_and_a_failed_write_keeps_it(tmp_path, monkeypatch):
    _saving_run(tmp_path)
    assert checkpoint.latest_epoch(tmp_path / "run") == 3
    assert sorted(p.name for p in (tmp_path / "run").iterdir() if p.name.isdigit()) == ["3"]
    loop, _ = checkpoint.load(tmp_path / "run", tr.init_loop(CFG, 2))
    # A write that dies half-way (here: while the arrays are written) leaves epoch 3 intact.
    import orbax.checkpoint as ocp

    def die(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ocp.PyTreeCheckpointHandler, "async_save", die)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save(tmp_path / "run", loop._replace(epoch=4), {"epoch": 9})
    monkeypatch.undo()
    # So does a temporary directory left by a killed process.
    (tmp_path / "run" / "5.orbax-checkpoint-tmp-1").mkdir()
    assert checkpoint.latest_epoch(tmp_path / "run") == 3
    back, extra = checkpoint.load(tmp_path / "run", tr.init_loop(CFG, 2))
    assert back.epoch == 3 and extra["epoch"] == 2
    for a, b in zip(_leaves(loop.states), _leaves(back.states), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_mismatched_run_is_refused_by_name(tmp_path):
    _saving_run(tmp_path, stop_after=0)
    with pytest.raises(ValueError, match=r"seeds \[0, 1\] differ from this run's \[0, 1, 2\]"):
        checkpoint.load(tmp_path / "run", tr.init_loop(CFG, 3))
    bigger = HandcraftedConfig(steps_per_epoch=100, eval_episodes=1,
                               low=DQNConfig(buffer_size=400, learning_starts=50))
    with pytest.raises(ValueError, match=r"array .*buffer.* is float32\(2, 1, 300, 12\), this "
                                         r"run's .* is float32\(2, 1, 400, 12\)"):
        checkpoint.load(tmp_path / "run", tr.init_loop(bigger, 2))
    with pytest.raises(ValueError, match="no complete checkpoint"):
        checkpoint.load(tmp_path / "nothing", tr.init_loop(CFG, 2))


def test_the_previous_npz_format_is_read_and_converted(tmp_path):
    first = tr.train_many(CFG, 2, 300, callback=lambda out: out.epoch == 0)
    checkpoint.save_npz(tmp_path / "old.npz", first.final, {"epoch": 0})
    template = tr.init_loop(CFG, 2)
    old, extra = checkpoint.load(tmp_path / "old.npz", template)
    assert old.epoch == 1 and extra == {"epoch": 0}
    converted = checkpoint.convert(tmp_path / "old.npz", tmp_path / "new", tr.init_loop(CFG, 2))
    new, _ = checkpoint.load(tmp_path / "new", tr.init_loop(CFG, 2))
    for a, b, c in zip(_leaves(old.states), _leaves(new.states), _leaves(converted.states),
                       strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
