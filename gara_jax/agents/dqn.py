"""Goal-conditioned DQN, the low level of every agent here.

The network sees one flat input vector (for GARA ``s ‖ goal.lo ‖ goal.hi``, for HIRO ``s ‖ g``),
so the same learner serves every algorithm. Defaults are the reference's (SPEC.md section 3).
Replay is a flashbax item buffer, a pytree, so the whole learner vmaps over seeds.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import flashbax as fbx
import jax
import jax.numpy as jnp
import optax
from flax import struct

from gara_jax.networks import MLP


@dataclasses.dataclass(frozen=True)
class DQNConfig:
    """Low-level DQN hyper-parameters (reference defaults)."""

    hidden: tuple[int, ...] = (16, 32)
    learning_rate: float = 0.01
    gamma: float = 0.95
    batch_size: int = 32
    buffer_size: int = 100_000  # the reference's final maze version (10,000 in its results one)
    learning_starts: int = 3_000  # transitions in the buffer before the first update
    target_update_every: int = 20  # environment steps between target-network copies
    td_target_clip: float = 1.0  # TD targets clipped to [-clip, clip]
    epsilon_start: float = 1.0
    epsilon_decay: float = 0.99995  # multiplied into epsilon after every step
    epsilon_min: float = 0.01
    # "taken_action": the usual DQN loss on the taken action's Q-value only. "all_actions": the
    # reference's Keras fit, MSE over all outputs towards the target network's Q-values at the
    # state with the taken action's entry replaced by the (clipped) TD target; the other
    # outputs are anchored to the target network, which steadies the greedy policy.
    loss: str = "taken_action"

    def __post_init__(self):
        if not self.hidden or any(int(h) <= 0 for h in self.hidden):
            raise ValueError(f"hidden: widths must be positive, got {self.hidden}")
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        _positive(self, "learning_rate", "batch_size", "buffer_size", "target_update_every",
                  "td_target_clip")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma: must lie in [0, 1], got {self.gamma}")
        if not self.batch_size <= self.learning_starts <= self.buffer_size:
            raise ValueError(
                "learning_starts: must lie in [batch_size, buffer_size], "
                f"got {self.learning_starts}")
        if not 0.0 <= self.epsilon_min <= self.epsilon_start <= 1.0:
            raise ValueError(
                "epsilon_start/epsilon_min: need 0 <= epsilon_min <= epsilon_start <= 1")
        if not 0.0 < self.epsilon_decay <= 1.0:
            raise ValueError(f"epsilon_decay: must lie in (0, 1], got {self.epsilon_decay}")
        if self.loss not in ("taken_action", "all_actions"):
            raise ValueError(
                f"loss: must be 'taken_action' or 'all_actions', got {self.loss!r}")


def _positive(cfg, *names):
    for name in names:
        if not getattr(cfg, name) > 0:
            raise ValueError(f"{name}: must be positive, got {getattr(cfg, name)}")


class Transition(NamedTuple):
    """One low-level transition; ``done`` cuts the bootstrap (goal reached or episode over)."""

    obs: jnp.ndarray
    action: jnp.ndarray
    reward: jnp.ndarray
    next_obs: jnp.ndarray
    done: jnp.ndarray


@struct.dataclass
class DQNState:
    params: dict
    target_params: dict
    opt_state: optax.OptState
    buffer: fbx.item_buffer.TrajectoryBufferState
    steps: jnp.ndarray  # transitions added so far
    updates: jnp.ndarray  # gradient steps taken so far
    epsilon: jnp.ndarray


class DQN(NamedTuple):
    """The learner as pure functions (optax style). Build with :func:`make_dqn`.

    ``observe`` is what a training loop calls each environment step: it stores the transition,
    takes one gradient step once ``learning_starts`` transitions are stored, copies the target
    network every ``target_update_every`` steps and decays epsilon. ``append_relabelled`` is
    hindsight relabelling of the whole replay (see :func:`append_relabelled`).
    """

    init: callable
    q_values: callable
    act: callable
    observe: callable
    update: callable
    append_relabelled: callable


def stored_in_age_order(buffer_state):
    """``(rows [N], valid [N])`` of a flashbax item buffer: slot indices oldest first.

    ``N`` is the capacity; ``valid`` marks the slots that hold a transition.

    Example:
        >>> import flashbax as fbx, jax.numpy as jnp
        >>> b = fbx.make_item_buffer(max_length=4, min_length=1, sample_batch_size=1,
        ...                          add_batches=False)
        >>> s = b.init(jnp.zeros(()))
        >>> for v in range(5):
        ...     s = b.add(s, jnp.float32(v))
        >>> rows, valid = stored_in_age_order(s)
        >>> rows.tolist(), valid.tolist()
        ([1, 2, 3, 0], [True, True, True, True])
    """
    capacity = jax.tree.leaves(buffer_state.experience)[0].shape[1]
    start = jnp.where(buffer_state.is_full, buffer_state.current_index, 0)
    n = jnp.where(buffer_state.is_full, capacity, buffer_state.current_index)
    age = jnp.arange(capacity)
    return (start + age) % capacity, age < n


def append_relabelled(buffer_state, relabel, where=True):
    """Append a relabelled copy of every stored transition (oldest first), where ``where``.

    ``relabel(transitions) -> transitions`` maps the stored batch (leading axis = capacity) to
    its copies. The buffer is a ring: once it is full the copies overwrite the oldest entries,
    so a full buffer ends up holding only copies (the reference's behaviour after a split,
    SPEC.md section 3.6). Pure and jittable; ``where`` may be traced.

    Example:
        >>> import flashbax as fbx, jax.numpy as jnp
        >>> b = fbx.make_item_buffer(max_length=4, min_length=1, sample_batch_size=1,
        ...                          add_batches=False)
        >>> s = b.add(b.init(jnp.zeros(())), jnp.float32(5))
        >>> s = append_relabelled(s, lambda t: t + 1)
        >>> s.experience[0].tolist(), int(s.current_index)
        ([5.0, 6.0, 0.0, 0.0], 2)
    """
    capacity = jax.tree.leaves(buffer_state.experience)[0].shape[1]
    rows, valid = stored_in_age_order(buffer_state)
    n = jnp.sum(valid)
    copies = relabel(jax.tree.map(lambda e: e[0, rows], buffer_state.experience))
    dest = jnp.where(valid & where, (buffer_state.current_index + jnp.arange(capacity))
                     % capacity, capacity)  # capacity: out of range, dropped
    experience = jax.tree.map(lambda e, c: e.at[0, dest].set(c.astype(e.dtype), mode="drop"),
                              buffer_state.experience, copies)
    added = jnp.where(where, n, 0)
    return buffer_state.replace(
        experience=experience,
        current_index=((buffer_state.current_index + added) % capacity).astype(
            buffer_state.current_index.dtype),
        is_full=buffer_state.is_full | (buffer_state.current_index + added >= capacity))


def make_dqn(config: DQNConfig, input_dim: int, num_actions: int) -> DQN:
    """Build a goal-conditioned DQN over ``input_dim``-vectors with ``num_actions`` actions.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> dqn = make_dqn(DQNConfig(), input_dim=12, num_actions=4)
        >>> state = dqn.init(jax.random.key(0))
        >>> a = dqn.act(state, jnp.zeros(12), jax.random.key(1), greedy=False)
        >>> t = Transition(jnp.zeros(12), a, jnp.float32(0.0), jnp.zeros(12), jnp.bool_(False))
        >>> state, info = dqn.observe(state, t, jax.random.key(2))
        >>> int(state.steps)
        1
    """
    if input_dim <= 0 or num_actions <= 0:
        raise ValueError("input_dim/num_actions: must be positive")
    net = MLP(hidden=config.hidden, out=num_actions)
    optimizer = optax.adam(config.learning_rate)
    buffer = fbx.make_item_buffer(
        max_length=config.buffer_size,
        min_length=config.learning_starts,
        sample_batch_size=config.batch_size,
        add_batches=False,
    )

    def init(key) -> DQNState:
        params = net.init(key, jnp.zeros((input_dim,)))
        dummy = Transition(jnp.zeros((input_dim,)), jnp.int32(0), jnp.float32(0.0),
                           jnp.zeros((input_dim,)), jnp.bool_(False))
        return DQNState(
            params=params,
            target_params=params,
            opt_state=optimizer.init(params),
            buffer=buffer.init(dummy),
            steps=jnp.int32(0),
            updates=jnp.int32(0),
            epsilon=jnp.float32(config.epsilon_start),
        )

    def q_values(params, obs):
        return net.apply(params, obs)

    def act(state: DQNState, obs, key, greedy: bool = False):
        """Epsilon-greedy action (greedy when ``greedy``); ``greedy`` may be a traced bool."""
        greedy_action = jnp.argmax(q_values(state.params, obs), axis=-1).astype(jnp.int32)
        k_explore, k_action = jax.random.split(key)
        explore = jax.random.uniform(k_explore) < state.epsilon
        random_action = jax.random.randint(k_action, greedy_action.shape, 0, num_actions)
        return jnp.where(jnp.logical_and(explore, jnp.logical_not(greedy)),
                         random_action, greedy_action)

    def loss_fn(params, target_params, batch: Transition):
        next_q = q_values(target_params, batch.next_obs).max(axis=-1)
        target = batch.reward + config.gamma * (1.0 - batch.done.astype(next_q.dtype)) * next_q
        target = jnp.clip(target, -config.td_target_clip, config.td_target_clip)
        if config.loss == "all_actions":
            q_all = q_values(params, batch.obs)
            taken = jax.nn.one_hot(batch.action, q_all.shape[-1], dtype=bool)
            full = jnp.where(taken, target[:, None], q_values(target_params, batch.obs))
            return jnp.mean((q_all - jax.lax.stop_gradient(full)) ** 2)
        q = jnp.take_along_axis(q_values(params, batch.obs), batch.action[:, None], axis=-1)[:, 0]
        return jnp.mean((q - jax.lax.stop_gradient(target)) ** 2)

    def update(state: DQNState, key):
        """One gradient step on a uniformly sampled batch; returns ``(state, loss)``."""
        batch = buffer.sample(state.buffer, key).experience
        loss, grads = jax.value_and_grad(loss_fn)(state.params, state.target_params, batch)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return state.replace(params=params, opt_state=opt_state, updates=state.updates + 1), loss

    def observe(state: DQNState, transition: Transition, key, live=None):
        """Store ``transition``, learn from the replay, decay epsilon: ``(state, info)``.

        ``live`` (a traced bool, or ``None``: always): where false, ``state`` comes back
        unchanged, at the cost of a live step and without a select over the replay (the row
        the add writes gets its own old value back), so that seeds that must idle inside a
        vmapped loop stay as they are.
        """
        old = state
        if live is not None:
            index = state.buffer.current_index
            stored = jax.tree.map(lambda e: e[0, index], state.buffer.experience)
            transition = jax.tree.map(lambda t, o: jnp.where(live, t, o), transition, stored)
        state = state.replace(buffer=buffer.add(state.buffer, transition), steps=state.steps + 1)
        ready = buffer.can_sample(state.buffer)
        state, loss = jax.lax.cond(
            ready, update, lambda s, k: (s, jnp.zeros((), jnp.float32)), state, key)
        copy = state.steps % config.target_update_every == 0
        target = jax.tree.map(lambda p, t: jnp.where(copy, p, t), state.params, state.target_params)
        epsilon = jnp.maximum(config.epsilon_min, state.epsilon * config.epsilon_decay)
        info = {"loss": loss, "updated": ready}
        state = state.replace(target_params=target, epsilon=epsilon)
        if live is not None:
            experience = state.buffer.experience
            keep = lambda a, b: jnp.where(live, a, b)  # noqa: E731
            state = jax.tree.map(keep, state.replace(buffer=state.buffer.replace(experience=None)),
                                 old.replace(buffer=old.buffer.replace(experience=None)))
            state = state.replace(buffer=state.buffer.replace(experience=experience))
        return state, info

    def relabel_replay(state: DQNState, relabel, where=True) -> DQNState:
        return state.replace(buffer=append_relabelled(state.buffer, relabel, where))

    return DQN(init=init, q_values=q_values, act=act, observe=observe, update=update,
               append_relabelled=relabel_replay)
