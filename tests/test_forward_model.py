"""High-level memory and the batched forward-model fit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax.agents import forward_model as fm


def test_memory_is_a_ring_buffer_and_respects_where():
    m = fm.init_memory(3, 2)
    for i in range(5):
        m = fm.push_memory(m, jnp.full(2, i), jnp.full(2, -i), jnp.zeros(2), jnp.ones(2),
                           float(i), 5, 10 * i, where=True)
        m = fm.push_memory(m, jnp.full(2, 99), jnp.zeros(2), jnp.zeros(2), jnp.ones(2),
                           0.0, 5, 0, where=False)
    assert int(m.size) == 3 and int(m.ptr) == 2
    assert m.capacity == 3
    assert sorted(np.asarray(m.start[:3, 0]).tolist()) == [2.0, 3.0, 4.0]
    assert sorted(np.asarray(m.step[:3]).tolist()) == [20, 30, 40]


def test_match_boxes_and_pair_experience():
    boxes_lo = jnp.array([[0.0], [1.0], [2.0], [7.0]])
    boxes_hi = jnp.array([[1.0], [2.0], [3.0], [8.0]])
    m = fm.init_memory(8, 1)
    # (start state, target box, length, step)
    rows = [(0.5, (1.0, 2.0), 5, 10), (0.5, (1.0, 2.0), 3, 20), (1.5, (0.0, 1.0), 5, 30),
            (0.2, (1.0, 3.0), 5, 40),  # a target box that no longer exists: ignored
            (2.5, (7.0, 8.0), 5, 50)]  # slot 3 is padding (n_boxes = 3): ignored
    for s, (lo, hi), length, step in rows:
        m = fm.push_memory(m, jnp.array([s]), jnp.zeros(1), jnp.array([lo]), jnp.array([hi]),
                           0.0, length, step)
    target = fm.match_boxes(m.target_lo, m.target_hi, boxes_lo, boxes_hi, 3)
    assert np.asarray(target[:5]).tolist() == [1, 1, 0, -1, -1]
    start = jnp.floor(m.start[:, 0]).astype(jnp.int32)  # boxes of width 1 from 0
    steps, recent = fm.pair_experience(start, target, m, since_step=15, max_goals=4)
    expected = np.zeros((4, 4), int)
    expected[0, 1], expected[1, 0] = 8, 5
    np.testing.assert_array_equal(steps, expected)
    assert np.argwhere(np.asarray(recent)).tolist() == [[0, 1], [1, 0]]
    _, recent = fm.pair_experience(start, target, m, since_step=25, max_goals=4)
    assert np.argwhere(np.asarray(recent)).tolist() == [[1, 0]]


@pytest.fixture(scope="module")
def model():
    return fm.make_forward_model(fm.ForwardModelConfig(max_epochs=60), state_dim=4)


def _linear_job(rng, n, shift):
    s = rng.uniform(0, 3, (n, 4)).astype(np.float32)
    goal = np.tile(np.array([1, 0, -1, -1, 2, 3, 1, 1], np.float32), (n, 1))
    return np.concatenate([s, goal], 1), s * 0.5 + shift


def test_fit_learns_each_job_on_its_own_masked_data(model):
    rng = np.random.default_rng(0)
    jobs = [_linear_job(rng, 300, 0.0), _linear_job(rng, 120, 1.0)]
    x, y, mask = fm.pad_jobs(jobs, batch_size=32)
    # Garbage in the padding must not matter.
    y[~mask] = 1e3
    params = model.init(jax.random.split(jax.random.key(0), 2))
    initial = []
    for j in range(2):
        p = jax.tree.map(lambda a, j=j: a[j], params)
        initial.append(float(jnp.mean((model.apply(p, x[j][mask[j]]) - y[j][mask[j]]) ** 2)))
    out = model.fit(params, x, y, mask, jax.random.split(jax.random.key(1), 2))
    for j in range(2):
        p = jax.tree.map(lambda a, j=j: a[j], out.params)
        pred = model.apply(p, x[j][mask[j]])
        mse = float(jnp.mean((pred - y[j][mask[j]]) ** 2))
        assert mse == pytest.approx(float(out.loss[j]), rel=1e-4)
        assert mse < 0.2 * initial[j]
    assert np.all(np.asarray(out.epochs) >= 2)
    # Stable means the last epoch improved the loss by less than the threshold.
    assert np.all(np.asarray(out.stable) | (np.asarray(out.epochs) == 60))


def test_fit_respects_max_epochs_and_empty_jobs(model):
    rng = np.random.default_rng(1)
    short = fm.make_forward_model(
        fm.ForwardModelConfig(max_epochs=2, stable_decrease=0.0), state_dim=4)
    x, y, mask = fm.pad_jobs([_linear_job(rng, 64, 0.0), _linear_job(rng, 64, 0.0)], 32)
    mask[1] = False  # an empty job stops at once, untouched
    params = short.init(jax.random.split(jax.random.key(2), 2))
    out = short.fit(params, x, y, mask, jax.random.split(jax.random.key(3), 2))
    assert np.asarray(out.epochs).tolist() == [2, 0]
    assert not bool(out.stable[0])
    same = jax.tree.map(lambda a, b: bool(jnp.all(a[1] == b[1])), out.params, params)
    assert all(jax.tree.leaves(same))


def test_pad_jobs_shapes():
    x, y, m = fm.pad_jobs([(np.ones((70, 12)), np.ones((70, 4))),
                           (np.ones((5, 12)), np.ones((5, 4)))], batch_size=32)
    assert x.shape == (2, 256, 12) and y.shape == (2, 256, 4)
    assert m.sum(axis=1).tolist() == [70, 5]
    # Buckets grow by 4x, capped at max_rows (rounded up to a whole batch).
    x, _, _ = fm.pad_jobs([(np.ones((300, 12)), np.ones((300, 4)))], 32)
    assert x.shape[1] == 1024
    x, _, _ = fm.pad_jobs([(np.ones((5000, 12)), np.ones((5000, 4)))], 32, max_rows=6000)
    assert x.shape[1] == 6016


@pytest.mark.parametrize("field,value", [("hidden", ()), ("learning_rate", 0.0),
                                         ("batch_size", 0), ("max_epochs", 1),
                                         ("stable_decrease", -1.0), ("shared_steps", 0),
                                         ("shared_steps", 1.5)])
def test_config_validation_names_the_field(field, value):
    kwargs = {field: value}
    if field == "max_epochs":
        kwargs["min_epochs"] = 2
    with pytest.raises(ValueError, match=field):
        fm.ForwardModelConfig(**kwargs)
