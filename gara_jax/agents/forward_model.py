"""GARA's forward model ``F_k(s, G) -> s'`` and the high-level memory it learns from.

**High-level memory.** A fixed-capacity ring buffer (a pytree, so it vmaps over seeds) of
experience rows: a start state, an end state, the *bounds* of the goal box targeted, the
environment reward, a length (the environment steps the row counts towards the trigger), the
environment step at which it was stored, the episode it belongs to, and whether it is forward-
model data (``data``) or only counts. What a row holds depends on GARA's ``memory`` option:
whole options (start and end of each option, length ``k``), or the reference's sliding windows
(one row per environment step, ``s_{t-k} -> s_{t+1}``, length 1, plus a count-only row per
option start; SPEC.md section 3.4). It stores states and boxes, never goal indices: a split
changes what an index means, so goals are derived from the stored states (``locate``) and the
stored target bounds whenever they are needed (DESIGN.md), and nothing has to be rewritten
after a refinement.

**Forward model.** ``MLP(hidden=(8, 8), out=D)`` on ``s ‖ G.lo ‖ G.hi``, Adam (lr 0.005), mean
squared error, minibatches of 32 (SPEC.md section 3.5). Two ways to train it:

- :func:`make_forward_model` ``fit``: one fresh model per analysis job, J models at once
  (``vmap`` over jobs, each on its own zero-padded, masked dataset) until each one's loss has
  stabilised: after every epoch (one shuffled pass over the job's data) the full-data MSE is
  measured, and a job stops once it fell by less than ``stable_decrease`` over the last epoch,
  after at least ``min_epochs``. A job that has not stabilised after ``max_epochs`` is reported
  as not stable. One jitted ``lax.while_loop``; jobs that stopped are frozen.
- :func:`make_forward_model` ``shared_updates``: the reference's way, one network per seed that
  is never re-initialised; each update is one gradient step (``shared_steps``) on a random
  sample of at most ``batch_size`` of a pair's data rows, followed by the MSE on a fresh
  sample (the record the reference's stability rule reads).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from gara_jax.networks import MLP

#: How the shared forward model samples a pair's rows (``ForwardModelConfig.shared_sample``).
SHARED_SAMPLES = ("with_replacement", "without_replacement")


@dataclasses.dataclass(frozen=True)
class ForwardModelConfig:
    """Forward-model hyper-parameters (SPEC.md section 3 defaults).

    Attributes:
        hidden: hidden layer widths of the ReLU MLP.
        learning_rate: Adam step size.
        batch_size: minibatch size of one gradient step.
        stable_decrease: a model has stabilised when its full-data MSE fell by less than this
            over one epoch.
        min_epochs: epochs before the stability test applies.
        max_epochs: epochs after which an unstable model is given up on (for this round).
        shared_steps: gradient steps of one update of the shared model (GARA's
            ``forward_model="shared"``), each on a fresh sample of ``batch_size`` of the pair's
            rows, before the update's MSE record. 1 in the reference, so that its model has
            taken about one step per episode in which the pair was chosen when it is first
            analysed; more steps analyse a model that has actually fitted the pair's data.
        shared_sample: how one update of the shared model draws its ``batch_size`` rows (and
            the rows of its MSE record) from a pair's rows. ``"with_replacement"``: uniformly
            with replacement (this project's first implementation). ``"without_replacement"``:
            a uniformly random subset of ``min(batch_size, rows)`` distinct rows, so a pair
            with fewer rows than that trains on all of them once: the reference's "random
            sample of at most 32" (SPEC.md section 3.5).
    """

    hidden: tuple[int, ...] = (8, 8)
    learning_rate: float = 0.005
    batch_size: int = 32
    stable_decrease: float = 0.01
    min_epochs: int = 2
    max_epochs: int = 100
    shared_steps: int = 1
    shared_sample: str = "with_replacement"

    def __post_init__(self):
        if not self.hidden or any(int(h) <= 0 for h in self.hidden):
            raise ValueError(f"hidden: widths must be positive, got {self.hidden}")
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate: must be positive, got {self.learning_rate}")
        if int(self.batch_size) != self.batch_size or self.batch_size < 1:
            raise ValueError(f"batch_size: must be an integer >= 1, got {self.batch_size}")
        if not self.stable_decrease >= 0:
            raise ValueError(f"stable_decrease: must be >= 0, got {self.stable_decrease}")
        if int(self.min_epochs) != self.min_epochs or self.min_epochs < 1:
            raise ValueError(f"min_epochs: must be an integer >= 1, got {self.min_epochs}")
        if int(self.max_epochs) != self.max_epochs or self.max_epochs < self.min_epochs:
            raise ValueError(
                f"max_epochs: must be an integer >= min_epochs, got {self.max_epochs}")
        if (isinstance(self.shared_steps, bool) or int(self.shared_steps) != self.shared_steps
                or self.shared_steps < 1):
            raise ValueError(f"shared_steps: must be an integer >= 1, got {self.shared_steps}")
        if self.shared_sample not in SHARED_SAMPLES:
            raise ValueError(
                f"shared_sample: must be one of {SHARED_SAMPLES}, got {self.shared_sample!r}")


# ----------------------------------------------------------------------------------------------
# High-level memory
# ----------------------------------------------------------------------------------------------


@struct.dataclass
class HighMemory:
    """Ring buffer of experience rows, capacity ``C``; rows ``[0, size)`` are filled.

    Every array has ``C + 1`` rows: the last one is scratch, written when nothing is to be
    stored, so a push never has to read the row it replaces (a conditional write inside a
    vmapped scan is otherwise a read-modify-write of the whole row on every step).

    Attributes:
        start, end: ``[C + 1, D]`` start and end states.
        target_lo, target_hi: ``[C + 1, D]`` bounds of the goal box targeted.
        reward: ``[C + 1]`` environment reward collected.
        length: ``[C + 1]`` environment steps the row counts for the trigger.
        step: ``[C + 1]`` the agent's environment-step counter when the row was stored.
        episode: ``[C + 1]`` the agent's episode counter when the row was stored.
        data: ``[C + 1]`` the row is forward-model data (else it only counts).
        ptr: next row to write; size: rows filled.
    """

    start: jax.Array
    end: jax.Array
    target_lo: jax.Array
    target_hi: jax.Array
    reward: jax.Array
    length: jax.Array
    step: jax.Array
    episode: jax.Array
    data: jax.Array
    ptr: jax.Array
    size: jax.Array

    @property
    def capacity(self) -> int:
        return self.reward.shape[-1] - 1


def init_memory(capacity: int, state_dim: int) -> HighMemory:
    """An empty memory.

    Example:
        >>> init_memory(10_000, 4).capacity
        10000
    """
    rows = lambda *shape: jnp.zeros((capacity + 1, *shape), jnp.float32)
    return HighMemory(start=rows(state_dim), end=rows(state_dim), target_lo=rows(state_dim),
                      target_hi=rows(state_dim), reward=rows(),
                      length=jnp.zeros((capacity + 1,), jnp.int32),
                      step=jnp.zeros((capacity + 1,), jnp.int32),
                      episode=jnp.zeros((capacity + 1,), jnp.int32),
                      data=jnp.zeros((capacity + 1,), bool),
                      ptr=jnp.int32(0), size=jnp.int32(0))


def push_memory(memory: HighMemory, start, end, target_lo, target_hi, reward, length, step,
                where=True, episode=0, data=True, live=None) -> HighMemory:
    """Store one row, only ``where`` it is true (else the scratch row is written, so it
    costs the same either way inside a vmapped scan); the oldest row is overwritten once full.
    ``live`` (``None``: always): where false, nothing changes, not even the scratch row (the
    written row gets its own old value back), for seeds idling inside a vmapped loop.

    Example:
        >>> import jax.numpy as jnp
        >>> m = init_memory(2, 1)
        >>> for i in range(3):
        ...     m = push_memory(m, jnp.full(1, i), jnp.zeros(1), jnp.zeros(1), jnp.ones(1),
        ...                     0.0, 5, i)
        >>> m.start[:2, 0].tolist(), int(m.size), int(m.ptr)
        ([2.0, 1.0], 2, 1)
    """
    capacity = memory.capacity
    if live is not None:
        where = where & live
    i = jnp.where(where, memory.ptr, capacity)
    put = lambda rows, value: rows.at[i].set(jnp.asarray(value, rows.dtype))
    if live is not None:
        put = lambda rows, value: rows.at[i].set(  # noqa: E731
            jnp.where(live, jnp.asarray(value, rows.dtype), rows[i]))
    return memory.replace(
        start=put(memory.start, start),
        end=put(memory.end, end),
        target_lo=put(memory.target_lo, target_lo),
        target_hi=put(memory.target_hi, target_hi),
        reward=put(memory.reward, reward),
        length=put(memory.length, length),
        step=put(memory.step, step),
        episode=put(memory.episode, episode),
        data=put(memory.data, data),
        ptr=jnp.where(where, (memory.ptr + 1) % capacity, memory.ptr).astype(jnp.int32),
        size=jnp.where(where, jnp.minimum(memory.size + 1, capacity), memory.size).astype(
            jnp.int32),
    )


def match_boxes(lo, hi, boxes_lo, boxes_hi, n_boxes) -> jax.Array:
    """Index of the (first) valid box with exactly the bounds ``lo, hi``, else -1.

    Used to find which current goal a stored target box is; a box that has since been split
    matches none. ``lo, hi`` may have leading batch axes.

    Example:
        >>> import jax.numpy as jnp
        >>> blo, bhi = jnp.array([[0.0], [1.0]]), jnp.array([[1.0], [2.0]])
        >>> match_boxes(jnp.array([[1.0], [0.0]]), jnp.array([[2.0], [2.0]]), blo, bhi, 2).tolist()
        [1, -1]
    """
    same = jnp.all((lo[..., None, :] == boxes_lo) & (hi[..., None, :] == boxes_hi), axis=-1)
    same = same & (jnp.arange(boxes_lo.shape[0]) < n_boxes)
    return jnp.where(jnp.any(same, axis=-1), jnp.argmax(same, axis=-1), -1).astype(jnp.int32)


def pair_experience(start_goal, target_goal, memory: HighMemory, since_step, max_goals: int):
    """Per goal pair: experience held in memory (summed ``length``), and whether it was explored
    lately (a row stored after ``since_step``).

    Args:
        start_goal, target_goal: ``[C + 1]`` goal indices of each stored option (from ``locate`` on
            ``memory.start`` and :func:`match_boxes` on the target bounds; -1 for none).
        since_step: rows stored after this env step count as recently explored.

    Returns:
        ``(steps [G, G] int32, recent [G, G] bool)``.
    """
    rows = jnp.arange(memory.capacity + 1) < memory.size
    ok = rows & (start_goal >= 0) & (target_goal >= 0)
    flat = jnp.where(ok, start_goal * max_goals + target_goal, 0)
    steps = jnp.zeros(max_goals * max_goals, jnp.int32).at[flat].add(
        jnp.where(ok, memory.length, 0))
    recent = jnp.zeros(max_goals * max_goals, bool).at[flat].max(ok & (memory.step > since_step))
    return steps.reshape(max_goals, max_goals), recent.reshape(max_goals, max_goals)


def pair_start_ranges(start_goal, target_goal, memory: HighMemory, max_goals: int):
    """Per goal pair: the range of the start states of its forward-model data rows (the
    model's training inputs), ``+inf/-inf`` for a pair with none (GARA's ``input_range``).

    Args:
        start_goal, target_goal: ``[C + 1]`` goal indices of each row, as for
            :func:`pair_experience`.

    Returns:
        ``(lo [G, G, D], hi [G, G, D])``.

    Example:
        >>> import jax.numpy as jnp
        >>> m = init_memory(4, 1)
        >>> for x in (0.5, -0.25):
        ...     m = push_memory(m, jnp.full(1, x), jnp.zeros(1), jnp.zeros(1), jnp.ones(1),
        ...                     0.0, 5, 0)
        >>> lo, hi = pair_start_ranges(jnp.zeros(5, int), jnp.ones(5, int), m, 2)
        >>> lo[0, 1, 0].item(), hi[0, 1, 0].item(), bool(jnp.isinf(lo[1, 0, 0]))
        (-0.25, 0.5, True)
    """
    rows = (jnp.arange(memory.capacity + 1) < memory.size) & memory.data
    ok = rows & (start_goal >= 0) & (target_goal >= 0)
    flat = jnp.where(ok, start_goal * max_goals + target_goal, 0)
    dim = memory.start.shape[-1]
    pick = lambda fill: jnp.where(ok[:, None], memory.start, fill)  # noqa: E731
    lo = jnp.full((max_goals * max_goals, dim), jnp.inf).at[flat].min(pick(jnp.inf))
    hi = jnp.full((max_goals * max_goals, dim), -jnp.inf).at[flat].max(pick(-jnp.inf))
    return lo.reshape(max_goals, max_goals, dim), hi.reshape(max_goals, max_goals, dim)


# ----------------------------------------------------------------------------------------------
# Forward model
# ----------------------------------------------------------------------------------------------


class FitResult(NamedTuple):
    """Output of :attr:`ForwardModel.fit` (leading job axis J on every field)."""

    params: dict  # trained parameters
    loss: jax.Array  # final full-data MSE
    epochs: jax.Array  # epochs trained
    stable: jax.Array  # the loss stabilised before max_epochs


class ForwardModel(NamedTuple):
    """The forward model as pure functions. Build with :func:`make_forward_model`.

    - ``init(keys [J]) -> params`` (stacked over jobs),
    - ``apply(params, inputs) -> predicted s_{t+k}`` (one job's parameters),
    - ``fit(params, inputs [J, N, 3D], targets [J, N, D], mask [J, N], keys [J]) -> FitResult``,
      jitted; ``N`` must be a multiple of the batch size (pad with :func:`pad_jobs`).
    - ``init_optimizer(params) -> opt_state`` (one model's Adam state),
    - ``shared_updates(params, opt_state, inputs [N, 3D], targets [N, D], rows [M],
      seg_start [U], seg_len [U], live [U], keys [U]) -> (params, opt_state, mse [U])``: ``U``
      incremental updates of one shared model; update ``u`` trains on rows drawn from
      ``rows[seg_start[u] : seg_start[u] + seg_len[u]]`` (row indices grouped by goal pair,
      see :func:`pair_segments`); not jitted (callers ``vmap``/``jit`` it over seeds).
    """

    init: callable
    apply: callable
    fit: callable
    init_optimizer: callable
    shared_updates: callable


def pair_segments(pair_of_row, valid, pairs):
    """Row indices grouped by pair, and each pair's segment in them (host side, NumPy).

    ``pair_of_row [N]`` is each row's pair id, ``valid [N]`` which rows count, ``pairs [U]`` the
    pair ids asked for. Returns ``(rows [N], seg_start [U], seg_len [U])``: ``rows`` lists the
    valid rows sorted by pair (padded with 0), and pair ``pairs[u]``'s rows are
    ``rows[seg_start[u] : seg_start[u] + seg_len[u]]``.

    Example:
        >>> import numpy as np
        >>> rows, start, length = pair_segments(np.array([3, 1, 3, 2]),
        ...                                     np.array([True, True, True, False]),
        ...                                     np.array([3, 2]))
        >>> rows[start[0]: start[0] + length[0]].tolist(), length.tolist()
        ([0, 2], [2, 0])
    """
    idx = np.flatnonzero(valid)
    keys = np.asarray(pair_of_row)[idx]
    order = np.argsort(keys, kind="stable")
    sorted_keys, idx = keys[order], idx[order]
    start = np.searchsorted(sorted_keys, pairs, side="left")
    end = np.searchsorted(sorted_keys, pairs, side="right")
    rows = np.zeros(len(valid), np.int32)
    rows[: len(idx)] = idx
    return rows, start.astype(np.int32), (end - start).astype(np.int32)


def make_forward_model(config: ForwardModelConfig, state_dim: int) -> ForwardModel:
    """Build the forward model for ``state_dim``-dimensional states (inputs ``3 * state_dim``).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> fm = make_forward_model(ForwardModelConfig(max_epochs=3), state_dim=4)
        >>> params = fm.init(jax.random.split(jax.random.key(0), 2))
        >>> x = jnp.ones((2, 32, 12)); y = jnp.zeros((2, 32, 4)); m = jnp.ones((2, 32), bool)
        >>> out = fm.fit(params, x, y, m, jax.random.split(jax.random.key(1), 2))
        >>> out.loss.shape, out.epochs.shape
        ((2,), (2,))
    """
    if state_dim <= 0:
        raise ValueError(f"state_dim: must be positive, got {state_dim}")
    net = MLP(hidden=config.hidden, out=state_dim)
    optimizer = optax.adam(config.learning_rate)
    batch = config.batch_size

    def init(keys):
        return jax.vmap(lambda k: net.init(k, jnp.zeros((3 * state_dim,))))(keys)

    def apply(params, inputs):
        return net.apply(params, inputs)

    def masked_mse(params, x, y, m):
        se = jnp.mean((apply(params, x) - y) ** 2, axis=-1)
        return jnp.sum(jnp.where(m, se, 0.0)) / jnp.maximum(jnp.sum(m), 1)

    def fit_one(params, x, y, m, key):
        n = x.shape[0]
        n_batches = n // batch

        def epoch(params, opt_state, key):
            # Valid rows first, in a random order; batches past the data are no-ops.
            order = jnp.argsort(jnp.where(m, jax.random.uniform(key, (n,)), 2.0))

            def step(carry, b):
                params, opt_state = carry
                idx = jax.lax.dynamic_slice(order, (b * batch,), (batch,))
                bm = m[idx]
                grads = jax.grad(masked_mse)(params, x[idx], y[idx], bm)
                updates, new_opt = optimizer.update(grads, opt_state, params)
                new_params = optax.apply_updates(params, updates)
                live = jnp.any(bm)
                keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(live, a, b), new, old)
                return (keep(new_params, params), keep(new_opt, opt_state)), None

            (params, opt_state), _ = jax.lax.scan(step, (params, opt_state),
                                                  jnp.arange(n_batches))
            return params, opt_state

        def cond(c):
            return ~c["done"]

        def body(c):
            key, k_epoch = jax.random.split(c["key"])
            params, opt_state = epoch(c["params"], c["opt"], k_epoch)
            loss = masked_mse(params, x, y, m)
            n_epochs = c["epochs"] + 1
            stable = (n_epochs >= config.min_epochs) & (c["loss"] - loss < config.stable_decrease)
            done = stable | (n_epochs >= config.max_epochs)
            return dict(params=params, opt=opt_state, loss=loss, epochs=n_epochs, key=key,
                        stable=stable, done=done)

        init_c = dict(params=params, opt=optimizer.init(params), loss=masked_mse(params, x, y, m),
                      epochs=jnp.int32(0), key=key, stable=jnp.asarray(False),
                      done=~jnp.any(m))
        # vmap turns this into one loop that runs until every job is done, applying the body
        # only to the jobs still running.
        out = jax.lax.while_loop(cond, body, init_c)
        return FitResult(out["params"], out["loss"], out["epochs"], out["stable"])

    fit = jax.jit(jax.vmap(fit_one))

    def shared_updates(params, opt_state, x, y, rows, seg_start, seg_len, live, keys):
        """The reference's incremental training of one shared model (SPEC.md section 3.5)."""

        def draw(key, start, length):
            if config.shared_sample == "without_replacement":
                offset, ok = distinct_sample(key, length, batch)
                idx = rows[jnp.clip(start + offset, 0, rows.shape[0] - 1)]
                return idx, ok
            # ``batch`` rows of the segment, uniformly with replacement (masked if empty).
            pick = start + jnp.floor(jax.random.uniform(key, (batch,)) * length).astype(jnp.int32)
            idx = rows[jnp.clip(pick, 0, rows.shape[0] - 1)]
            return idx, jnp.broadcast_to(length > 0, (batch,))

        def one(carry, inp):
            params, opt_state = carry
            start, length, live_u, key = inp
            k_fit, k_eval = jax.random.split(key)
            go = live_u & (length > 0)

            def gradient_step(carry, k):
                params, opt_state = carry
                idx, ok = draw(k, start, length)
                grads = jax.grad(masked_mse)(params, x[idx], y[idx], ok)
                updates, new_opt = optimizer.update(grads, opt_state, params)
                new_params = optax.apply_updates(params, updates)
                return jax.tree.map(lambda a, b: jnp.where(go, a, b),
                                    (new_params, new_opt), (params, opt_state)), None

            # One step keeps the reference's key use (the step draws with ``k_fit`` itself).
            fit_keys = (k_fit[None] if config.shared_steps == 1
                        else jax.random.split(k_fit, config.shared_steps))
            (params, opt_state), _ = jax.lax.scan(gradient_step, (params, opt_state), fit_keys)
            idx, ok = draw(k_eval, start, length)
            return (params, opt_state), masked_mse(params, x[idx], y[idx], ok)

        (params, opt_state), mse = jax.lax.scan(one, (params, opt_state),
                                                (seg_start, seg_len, live, keys))
        return params, opt_state, mse

    return ForwardModel(init=init, apply=apply, fit=fit, init_optimizer=optimizer.init,
                        shared_updates=shared_updates)


def distinct_sample(key, n, size: int):
    """``min(size, n)`` distinct indices drawn uniformly from ``[0, n)`` (``n`` may be traced).

    Returns ``(idx [size] int32, ok [size] bool)``: the first ``min(size, n)`` slots hold the
    sample (``ok``), the rest are 0 and masked. With ``n <= size`` the sample is every index;
    otherwise Floyd's algorithm (a uniformly random subset, in no particular order).

    Example:
        >>> import jax
        >>> idx, ok = distinct_sample(jax.random.key(0), 100, 8)
        >>> len(set(idx.tolist())), bool(ok.all()), bool((idx < 100).all())
        (8, True, True)
        >>> idx, ok = distinct_sample(jax.random.key(0), 3, 8)
        >>> sorted(idx[ok].tolist()), int(ok.sum())
        ([0, 1, 2], 3)
    """
    n = jnp.asarray(n, jnp.int32)
    u = jax.random.uniform(key, (size,))

    def floyd(i, chosen):
        j = n - size + i
        t = jnp.minimum(jnp.floor(u[i] * (j + 1).astype(jnp.float32)).astype(jnp.int32), j)
        taken = jnp.any((chosen == t) & (jnp.arange(size) < i))
        return chosen.at[i].set(jnp.where(taken, j, t))

    chosen = jax.lax.fori_loop(0, size, floyd, jnp.zeros((size,), jnp.int32))
    every = jnp.arange(size, dtype=jnp.int32)
    small = n <= size
    ok = every < jnp.minimum(n, size)
    idx = jnp.where(small, jnp.where(ok, every, 0), chosen)
    return idx.astype(jnp.int32), ok


def pad_jobs(datasets, batch_size: int, min_rows: int = 256, max_rows: int | None = None):
    """Stack per-job ``(inputs [n_j, 3D], targets [n_j, D])`` numpy datasets into padded arrays.

    Rows are padded to ``min_rows * 4**i`` (capped at ``max_rows``, e.g. the memory capacity)
    and rounded up to a multiple of ``batch_size``, so that only a handful of shapes is ever
    compiled. Returns ``(inputs [J, N, 3D], targets [J, N, D], mask [J, N])`` (numpy).

    Example:
        >>> import numpy as np
        >>> x, y, m = pad_jobs([(np.ones((300, 12)), np.ones((300, 4)))], batch_size=32)
        >>> x.shape, int(m.sum())
        ((1, 1024, 12), 300)
    """
    longest = max(len(x) for x, _ in datasets)
    rows = min_rows
    while rows < longest and (max_rows is None or rows < max_rows):
        rows *= 4
    if max_rows is not None:
        rows = min(rows, max(max_rows, longest))
    rows = int(np.ceil(rows / batch_size) * batch_size)
    in_dim = datasets[0][0].shape[1]
    out_dim = datasets[0][1].shape[1]
    inputs = np.zeros((len(datasets), rows, in_dim), np.float32)
    targets = np.zeros((len(datasets), rows, out_dim), np.float32)
    mask = np.zeros((len(datasets), rows), bool)
    for j, (x, y) in enumerate(datasets):
        inputs[j, : len(x)] = x
        targets[j, : len(y)] = y
        mask[j, : len(x)] = True
    return inputs, targets, mask
