"""TD3 (Fujimoto et al., 2018) for bounded continuous actions, as pure functions; HIRO's high level.

The learner holds the actor, the twin critics, their target copies and the two Adam states; it
does not own a replay buffer, because HIRO rewrites the sampled actions (goal relabelling) between
sampling and learning. :class:`Replay` is a small ring buffer with a *masked* add, which HIRO
needs: options end at data-dependent steps, and under ``vmap`` a conditional add would otherwise
turn into a select over the whole buffer. Everything here is a pytree and vmaps over seeds.

Defaults are HIRO's (Nachum et al., 2018) higher-level TD3 settings: 300-300 ReLU actor and
critics, Adam 1e-4 (actor) / 1e-3 (critics), gamma 0.99, soft target updates tau = 0.005, target
policy smoothing noise 0.2 clipped at 0.5, actor and targets updated every 2nd critic update,
batch 100, replay 200,000.

Three options turn the same learner into the DDPG high level of the GARA authors' HIRO baseline
(SPEC.md 3.7; :data:`DDPG_PAPER` sets all of them with that baseline's sizes and rates):
``twin_critics=False`` (one critic, no clipped double Q), ``critic_target="reward_less"`` (their
TD target) and ``actor_output="tanh_clipped"`` (their actor output range); with
``policy_noise=0`` and ``policy_delay=1`` the update is plain DDPG.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from gara_jax.agents.dqn import Transition
from gara_jax.networks import MLP


@dataclasses.dataclass(frozen=True)
class TD3Config:
    """TD3 hyper-parameters (HIRO's higher-level values).

    Noises are in units of the action half-range ``(act_high - act_low) / 2``, as TD3 scales
    them by ``max_action``. ``learning_starts`` counts stored transitions.
    """

    actor_hidden: tuple[int, ...] = (300, 300)
    critic_hidden: tuple[int, ...] = (300, 300)
    actor_lr: float = 1e-4
    critic_lr: float = 1e-3
    gamma: float = 0.99
    tau: float = 0.005  # soft target update rate
    policy_noise: float = 0.2  # target policy smoothing noise (fraction of the half-range)
    noise_clip: float = 0.5  # ... clipped to this (fraction of the half-range)
    policy_delay: int = 2  # actor and target updates every `policy_delay` critic updates
    batch_size: int = 100
    buffer_size: int = 200_000
    learning_starts: int = 300  # transitions stored before the first update
    twin_critics: bool = True  # False: one critic (DDPG), no clipped double Q
    # "standard": r + gamma (1 - done) Q'(s', mu'(s')). "reward_less": the GARA authors' DDPG,
    # gamma Q'(s', mu'(s')) on non-terminal transitions (the reward is left out) and r on
    # terminal ones; identical wherever only terminal transitions carry a reward.
    critic_target: str = "standard"
    # "box": mid + half * tanh(net), the whole action box. "tanh_clipped": the GARA authors'
    # DDPG, tanh(net) in [-1, 1] clipped to the box, so the policy only reaches box ∩ [-1, 1].
    actor_output: str = "box"

    def __post_init__(self):
        for name in ("actor_hidden", "critic_hidden"):
            widths = getattr(self, name)
            if not widths or any(int(h) <= 0 for h in widths):
                raise ValueError(f"{name}: widths must be positive, got {widths}")
            object.__setattr__(self, name, tuple(int(h) for h in widths))
        for name in ("actor_lr", "critic_lr", "batch_size", "buffer_size", "policy_delay"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma: must lie in [0, 1], got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau: must lie in (0, 1], got {self.tau}")
        for name in ("policy_noise", "noise_clip"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if self.critic_target not in ("standard", "reward_less"):
            raise ValueError("critic_target: must be 'standard' or 'reward_less', "
                             f"got {self.critic_target!r}")
        if self.actor_output not in ("box", "tanh_clipped"):
            raise ValueError("actor_output: must be 'box' or 'tanh_clipped', "
                             f"got {self.actor_output!r}")
        if not self.batch_size <= self.learning_starts < self.buffer_size:
            raise ValueError(
                "learning_starts: must lie in [batch_size, buffer_size), "
                f"got {self.learning_starts}")


# The DDPG high level of the GARA authors' HIRO baseline (SPEC.md 3.7): 16-32 ReLU actor and
# critic, tanh actor output clipped to the goal box, Adam 5e-4 / 1e-3, gamma 0.99, soft target
# rate 0.05, batch 32, replay 20,000, their reward-less critic target. SPEC.md gives no warm-up;
# updates start once a batch is stored.
DDPG_PAPER = TD3Config(
    actor_hidden=(16, 32), critic_hidden=(16, 32), actor_lr=5e-4, critic_lr=1e-3, gamma=0.99,
    tau=0.05, policy_noise=0.0, noise_clip=0.0, policy_delay=1, batch_size=32,
    buffer_size=20_000, learning_starts=32, twin_critics=False, critic_target="reward_less",
    actor_output="tanh_clipped")

# A batch (or one) of transitions for :func:`TD3.update`: the same fields as the DQN's.
Batch = Transition


def td_target(config: TD3Config, reward, done, next_q):
    """The critic's TD target from ``next_q = Q'(s', mu'(s'))`` (the minimum over the twin
    critics where there are two), as ``config.critic_target`` defines it.

    Example:
        >>> import jax.numpy as jnp
        >>> r, d, q = jnp.array([1.0, 10.0]), jnp.array([False, True]), jnp.array([5.0, 5.0])
        >>> td_target(TD3Config(gamma=0.5), r, d, q).tolist()
        [3.5, 10.0]
        >>> td_target(TD3Config(gamma=0.5, critic_target="reward_less"), r, d, q).tolist()
        [2.5, 10.0]
    """
    done = jnp.asarray(done, bool)
    bootstrap = config.gamma * next_q
    if config.critic_target == "reward_less":
        return jnp.where(done, reward, bootstrap)
    return reward + jnp.where(done, 0.0, bootstrap)


@struct.dataclass
class TD3State:
    actor_params: Any
    critic_params: Any
    actor_target: Any
    critic_target: Any
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    updates: jnp.ndarray  # critic updates taken so far


class Critics(nn.Module):
    """``n`` independent Q networks on ``obs ‖ action``; returns a tuple of ``n`` values."""

    hidden: tuple[int, ...]
    n: int = 2

    @nn.compact
    def __call__(self, obs, action):
        x = jnp.concatenate([obs, action], axis=-1)
        return tuple(MLP(self.hidden, 1)(x)[..., 0] for _ in range(self.n))


class TD3(NamedTuple):
    """TD3 as pure functions. Build with :func:`make_td3`.

    - ``init(key) -> TD3State``
    - ``act(state, obs, key, noise_std) -> action``: the actor's action plus Gaussian noise of
      standard deviation ``noise_std`` (absolute units; scalar or per dimension; 0 is greedy),
      clipped to the action box.
    - ``update(state, batch, key) -> (state, info)``: one critic step on ``batch``; every
      ``policy_delay``-th call also an actor step and a soft target update.
    - ``critic_update(state, batch, key) -> (state, critic_loss)`` and
      ``actor_update(state, obs) -> (state, actor_loss)`` (actor step plus soft target
      update): the two halves of ``update``, for callers that schedule the delayed actor step
      themselves (under ``vmap`` the ``cond`` in ``update`` has a per-seed predicate, so it
      becomes a select that computes the actor step on every call).
    - ``q_values(critic_params, obs, action) -> (q1, q2)`` (``(q,)`` with one critic),
      ``policy(actor_params, obs)``.
    """

    init: Any
    act: Any
    update: Any
    critic_update: Any
    actor_update: Any
    q_values: Any
    policy: Any


def make_td3(config: TD3Config, obs_dim: int, act_dim: int, act_low, act_high) -> TD3:
    """Build a TD3 learner for observations of ``obs_dim`` and actions in ``[act_low, act_high]``.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> td3 = make_td3(TD3Config(actor_hidden=(8,), critic_hidden=(8,)), 3, 2, -1.0, 1.0)
        >>> state = td3.init(jax.random.key(0))
        >>> a = td3.act(state, jnp.zeros(3), jax.random.key(1), noise_std=0.1)
        >>> a.shape, bool(jnp.all(jnp.abs(a) <= 1.0))
        ((2,), True)
        >>> batch = Batch(jnp.zeros((4, 3)), jnp.zeros((4, 2)), jnp.ones(4), jnp.zeros((4, 3)),
        ...               jnp.ones(4, bool))
        >>> state, info = td3.update(state, batch, jax.random.key(2))
        >>> int(state.updates)
        1
    """
    if obs_dim <= 0 or act_dim <= 0:
        raise ValueError("obs_dim/act_dim: must be positive")
    low = jnp.broadcast_to(jnp.asarray(act_low, jnp.float32), (act_dim,))
    high = jnp.broadcast_to(jnp.asarray(act_high, jnp.float32), (act_dim,))
    if not np.all(np.asarray(low) < np.asarray(high)):
        raise ValueError("act_low/act_high: need act_low < act_high in every dimension")
    mid, half = (high + low) / 2.0, (high - low) / 2.0

    actor_net = MLP(config.actor_hidden, act_dim)
    critic_net = Critics(config.critic_hidden, 2 if config.twin_critics else 1)
    actor_opt = optax.adam(config.actor_lr)
    critic_opt = optax.adam(config.critic_lr)

    def policy(actor_params, obs):
        out = jnp.tanh(actor_net.apply(actor_params, obs))
        if config.actor_output == "tanh_clipped":
            return jnp.clip(out, low, high)
        # tanh squashing keeps the deterministic policy inside the box without clipping.
        return mid + half * out

    def q_values(critic_params, obs, action):
        return critic_net.apply(critic_params, obs, action)

    def init(key) -> TD3State:
        k_actor, k_critic = jax.random.split(key)
        actor_params = actor_net.init(k_actor, jnp.zeros((obs_dim,)))
        critic_params = critic_net.init(k_critic, jnp.zeros((obs_dim,)), jnp.zeros((act_dim,)))
        return TD3State(
            actor_params=actor_params,
            critic_params=critic_params,
            actor_target=actor_params,
            critic_target=critic_params,
            actor_opt=actor_opt.init(actor_params),
            critic_opt=critic_opt.init(critic_params),
            updates=jnp.int32(0),
        )

    def act(state: TD3State, obs, key, noise_std=0.0):
        action = policy(state.actor_params, obs)
        noise = jnp.asarray(noise_std, action.dtype) * jax.random.normal(key, action.shape)
        return jnp.clip(action + noise, low, high)

    def critic_loss(critic_params, state: TD3State, batch: Batch, key):
        # Target policy smoothing: noisy target actions make the critic smooth in the action.
        noise = jnp.clip(config.policy_noise * jax.random.normal(key, batch.action.shape),
                         -config.noise_clip, config.noise_clip) * half
        next_action = jnp.clip(policy(state.actor_target, batch.next_obs) + noise, low, high)
        # Clipped double Q: the minimum of the twin targets counters overestimation.
        next_q = functools.reduce(
            jnp.minimum, q_values(state.critic_target, batch.next_obs, next_action))
        target = jax.lax.stop_gradient(td_target(config, batch.reward, batch.done, next_q))
        return sum(jnp.mean((q - target) ** 2)
                   for q in q_values(critic_params, batch.obs, batch.action))

    def actor_loss(actor_params, critic_params, obs):
        q1 = q_values(critic_params, obs, policy(actor_params, obs))[0]
        return -jnp.mean(q1)

    def actor_step(state: TD3State, obs):
        loss, grads = jax.value_and_grad(actor_loss)(state.actor_params, state.critic_params, obs)
        updates, opt = actor_opt.update(grads, state.actor_opt, state.actor_params)
        actor_params = optax.apply_updates(state.actor_params, updates)
        soft = lambda online, target: jax.tree.map(
            lambda p, t: config.tau * p + (1.0 - config.tau) * t, online, target)
        state = state.replace(
            actor_params=actor_params,
            actor_opt=opt,
            actor_target=soft(actor_params, state.actor_target),
            critic_target=soft(state.critic_params, state.critic_target),
        )
        return state, loss

    def critic_step(state: TD3State, batch: Batch, key):
        loss, grads = jax.value_and_grad(critic_loss)(state.critic_params, state, batch, key)
        updates, opt = critic_opt.update(grads, state.critic_opt, state.critic_params)
        state = state.replace(critic_params=optax.apply_updates(state.critic_params, updates),
                              critic_opt=opt, updates=state.updates + 1)
        return state, loss

    def update(state: TD3State, batch: Batch, key):
        state, loss = critic_step(state, batch, key)
        delayed = state.updates % config.policy_delay == 0
        state, a_loss = jax.lax.cond(
            delayed, actor_step, lambda s, o: (s, jnp.zeros((), jnp.float32)), state, batch.obs)
        return state, {"critic_loss": loss, "actor_loss": a_loss}

    return TD3(init=init, act=act, update=update, critic_update=critic_step,
               actor_update=actor_step, q_values=q_values, policy=policy)


# ------------------------------------------------------------------------------------------------
# Replay with a masked add
# ------------------------------------------------------------------------------------------------


@struct.dataclass
class Replay:
    """Ring buffer over a pytree of items; ``data`` leaves have a leading ``capacity`` axis.

    Every :func:`replay_add` writes at ``ptr``; only a valid add advances ``ptr``, so an invalid
    write is simply overwritten by the next one. The slot at ``ptr`` is therefore never sampled,
    and at most ``capacity - 1`` items are kept.
    """

    data: Any
    ptr: jnp.ndarray
    size: jnp.ndarray


def replay_init(example, capacity: int) -> Replay:
    """An empty buffer for items shaped like ``example`` (one item, no batch axis).

    Example:
        >>> import jax.numpy as jnp
        >>> buf = replay_init({"x": jnp.zeros(3)}, capacity=5)
        >>> buf.data["x"].shape, int(buf.size)
        ((5, 3), 0)
    """
    if capacity < 2:
        raise ValueError(f"capacity: must be at least 2, got {capacity}")
    data = jax.tree.map(lambda x: jnp.zeros((capacity,) + jnp.shape(x), jnp.asarray(x).dtype),
                        example)
    return Replay(data=data, ptr=jnp.int32(0), size=jnp.int32(0))


def replay_add(buffer: Replay, item, valid=True) -> Replay:
    """Store ``item`` where ``valid`` (a traced bool is fine); cost independent of ``valid``.

    Example:
        >>> import jax.numpy as jnp
        >>> buf = replay_init(jnp.zeros(()), capacity=4)
        >>> buf = replay_add(buf, 1.0, valid=False)
        >>> buf = replay_add(buf, 2.0, valid=True)
        >>> int(buf.size), buf.data.tolist()
        (1, [2.0, 0.0, 0.0, 0.0])
    """
    capacity = jax.tree.leaves(buffer.data)[0].shape[0]
    data = jax.tree.map(lambda d, x: d.at[buffer.ptr].set(jnp.asarray(x, d.dtype)),
                        buffer.data, item)
    valid = jnp.asarray(valid, jnp.int32)
    return Replay(data=data, ptr=(buffer.ptr + valid) % capacity,
                  size=jnp.minimum(buffer.size + valid, capacity - 1))


def replay_sample(buffer: Replay, key, batch_size: int):
    """``batch_size`` items drawn uniformly (with replacement) among the stored ones.

    The buffer must hold at least one item; the caller gates on ``buffer.size``.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> buf = replay_add(replay_init(jnp.zeros(()), capacity=4), 7.0)
        >>> replay_sample(buf, jax.random.key(0), 3).tolist()
        [7.0, 7.0, 7.0]
    """
    capacity = jax.tree.leaves(buffer.data)[0].shape[0]
    # The `size` most recent items sit just before `ptr`.
    back = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    index = (buffer.ptr - 1 - back) % capacity
    return jax.tree.map(lambda d: d[index], buffer.data)
