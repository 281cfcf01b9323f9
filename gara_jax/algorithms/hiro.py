"""HIRO (Nachum et al., 2018): raw states as goals, a TD3 high level with off-policy relabelling.

Two versions behind one config: ``HiroConfig()`` is HIRO as published (relative goals, goal
transition, TD3, off-policy correction); ``HiroConfig.paper()`` is the baseline the GARA
authors ran (SPEC.md 3.7: absolute goals, a small DDPG high level, no goal transition, no
correction), each of its differences a named option.

Read top to bottom: config, the goal helpers (transition, intrinsic reward, relabelling), then
``make_hiro`` with ``init`` / ``train_epoch`` / ``evaluate`` (the contract of ``base.py``).

Every ``k`` steps the high level (TD3 over ``s``) proposes a *relative* goal ``g``: the desired
change of state. The low level (the project's goal-conditioned DQN over ``s ‖ g``) is rewarded
``-||s + g - s'||`` and its goal moves with it, ``g' = s + g - s'``, so the absolute target
``s + g`` stays fixed during an option. An option ends after ``k`` steps or when the episode
ends; its high-level transition ``(s_t, g_t, R, s_{t+k}, done)`` is stored together with the
logged low-level states and actions. When the high level learns, each sampled goal is replaced by
the candidate under which the *current* low level most likely produced the logged actions
(candidates: the original goal, ``s_{t+k} - s_t``, and samples around the latter).

One epoch is one ``lax.scan`` over blocks of ``k`` environment steps (an inner scan); the high
level takes one TD3 step per block, i.e. per ``k`` environment steps, as HIRO trains its higher
level once per ``c`` steps. Doing it once per block rather than "when an option ends" keeps it
out of the per-step loop, where ``vmap`` would turn a ``cond`` into computing it every step.
TD3's delayed actor step (every ``policy_delay``-th critic step) runs on every
``policy_delay``-th block of an epoch, a schedule shared by all seeds so that it stays a real
branch under ``vmap`` (a per-seed counter would make it a select computed on every block).

Example:
    >>> import jax
    >>> from gara_jax.agents.dqn import DQNConfig
    >>> from gara_jax.agents.td3 import TD3Config
    >>> cfg = HiroConfig(steps_per_epoch=50, eval_episodes=2,
    ...                  low=DQNConfig(batch_size=8, learning_starts=16, buffer_size=64),
    ...                  high=TD3Config(actor_hidden=(16,), critic_hidden=(16,), batch_size=4,
    ...                                 learning_starts=4, buffer_size=64))
    >>> algo = make_hiro(cfg)
    >>> state = algo.init(jax.random.key(0))
    >>> state, metrics = jax.jit(algo.train_epoch)(state, jax.random.key(1))
    >>> int(metrics["env_steps"]), int(metrics["n_goals"])
    (50, 0)
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

import envs
from gara_jax.agents.dqn import DQNConfig, DQNState, Transition, make_dqn
from gara_jax.agents.td3 import (
    DDPG_PAPER,
    Batch,
    Replay,
    TD3Config,
    TD3State,
    make_td3,
    replay_add,
    replay_init,
    replay_sample,
)
from gara_jax.algorithms.base import Algorithm, epoch_metrics

# ------------------------------------------------------------------------------------------------
# Config
# ------------------------------------------------------------------------------------------------

# HIRO's low level has no TD-target clipping. The reference DQN clips to [-1, 1], which suits
# GARA's +1 / -0.1 rewards but would flatten every -||s + g - s'|| return (a distance of 0.05
# kept for 20 steps already sums to -1) to -1, so HIRO uses a bound that never binds.
# HIRO's low level keeps the replay and target period it was measured with (SPEC.md revision 1
# defaults); the unclipped TD targets are HIRO's own convention.
HIRO_LOW = DQNConfig(td_target_clip=1e6, buffer_size=10_000, target_update_every=200)


@dataclasses.dataclass(frozen=True)
class HiroConfig:
    """HIRO on a maze. The TD3 settings (``high``) and the relabelling are the HIRO paper's.

    ``goal_space="relative"`` (HIRO): a goal is a desired change of state, in the box
    ``[-goal_high, goal_high]`` with ``goal_high = (P, P, V, V)``: ``P``
    (``goal_position_range``, default the maze size ``n``) bounds position changes, since no
    move inside ``[0, n]`` is longer; ``V = goal_velocity_range`` = 2 bounds velocity changes,
    since velocities lie in ``[-1, 1]``. The goal follows the state (``g' = s + g - s'``) and the
    low level is rewarded ``-||s + g - s'||``.
    ``goal_space="absolute"`` (the GARA authors' baseline): a goal is a state, in the
    observation bounds ``[0, n]^2 x [-1, 1]^2``; it stays fixed for the ``k`` steps of an option
    and the low level is rewarded ``-||g - s'||``. HIRO's off-policy correction is defined for
    relative goals only, so it needs ``relabel=False``.

    :meth:`paper` returns the GARA authors' version (SPEC.md 3.7).

    Example:
        >>> HiroConfig().k, HiroConfig().high.batch_size
        (5, 100)
        >>> HiroConfig(relabel_candidates=1)
        Traceback (most recent call last):
        ...
        ValueError: relabel_candidates: must be >= 2 (the original goal and s_{t+k} - s_t), got 1
    """

    env: str = "u_maze"
    collision: str = "reference"  # the maze's wall rules (see GaraConfig.collision)
    k: int = 5  # environment steps per high-level decision (HIRO's c)
    steps_per_epoch: int = 3000  # a multiple of k
    eval_episodes: int = 10
    low: DQNConfig = HIRO_LOW
    high: TD3Config = TD3Config()
    goal_position_range: float | None = None  # None: the maze size n
    goal_velocity_range: float = 2.0
    goal_noise: float = 1.0  # std of the Gaussian exploration noise on proposed goals (absolute)
    high_reward_scale: float = 0.1  # HIRO scales the higher level's reward by 0.1
    low_reward_scale: float = 1.0  # ... and the lower level's by 1
    relabel: bool = True  # off-policy goal correction on/off
    relabel_candidates: int = 10  # original goal, s_{t+k} - s_t and 8 samples around the latter
    relabel_sigma: float = 0.5  # std of those samples, as a fraction of the goal half-range
    relabel_temperature: float = 1.0  # Boltzmann temperature of the low level's Q-values
    goal_space: str = "relative"  # or "absolute" (see above)
    # How the seeds' high-level updates run when train_epoch is vmapped over seeds:
    # "sequential" one seed after another (lax.map; on CPU the per-seed matrix products are
    # much faster than XLA's batched ones), "vmap" as batched operations. Same algorithm;
    # floating-point results differ in the last bits. No effect on one unbatched seed.
    seed_schedule: str = "sequential"

    @classmethod
    def paper(cls, **overrides) -> HiroConfig:
        """The HIRO baseline as the GARA authors ran it (SPEC.md 3.7), ``overrides`` on top.

        Absolute goals, clipped to the observation bounds; the DDPG high level
        :data:`~gara_jax.agents.td3.DDPG_PAPER` (16-32 networks, their reward-less critic
        target: ``high=dataclasses.replace(DDPG_PAPER, critic_target="standard")`` turns that
        bug off; their actor's tanh output is clipped to the goal box, so proposed goal
        positions lie in ``[0, 1]^2`` plus the exploration noise, while the exit is at
        ``(3, 0)``; ``actor_output="box"`` scales it to the whole box instead); exploration
        noise 0.1; the environment reward unscaled; the low level is the GARA agents' DQN
        (``DQNConfig()``: the [-1, 1] TD-target clip, replay 100,000, target copy every 20
        steps); no goal transition, no off-policy correction.

        Example:
            >>> cfg = HiroConfig.paper()
            >>> cfg.goal_space, cfg.high.critic_target, cfg.high.actor_hidden, cfg.relabel
            ('absolute', 'reward_less', (16, 32), False)
        """
        base = dict(goal_space="absolute", relabel=False, high=DDPG_PAPER, low=DQNConfig(),
                    goal_noise=0.1, high_reward_scale=1.0)
        return cls(**(base | overrides))

    def __post_init__(self):
        if self.env not in envs.ENV_NAMES:
            raise ValueError(f"env: unknown environment {self.env!r}; valid: {envs.ENV_NAMES}")
        envs.validate_collision(self.env, self.collision)
        for name in ("k", "steps_per_epoch", "eval_episodes"):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0:
                raise ValueError(f"{name}: must be a positive integer, got {value!r}")
        if self.steps_per_epoch % self.k:
            raise ValueError(
                f"steps_per_epoch: must be a multiple of k={self.k}, got {self.steps_per_epoch}")
        if not isinstance(self.low, DQNConfig):
            raise ValueError(f"low: must be a DQNConfig, got {type(self.low).__name__}")
        if not isinstance(self.high, TD3Config):
            raise ValueError(f"high: must be a TD3Config, got {type(self.high).__name__}")
        if self.goal_position_range is not None and not self.goal_position_range > 0:
            raise ValueError(
                f"goal_position_range: must be positive or None, got {self.goal_position_range}")
        for name in ("goal_velocity_range", "relabel_temperature"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("goal_noise", "relabel_sigma"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        for name in ("high_reward_scale", "low_reward_scale"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name}: must be finite, got {getattr(self, name)}")
        if self.seed_schedule not in ("sequential", "vmap"):
            raise ValueError(f"seed_schedule: must be 'sequential' or 'vmap', got "
                             f"{self.seed_schedule!r}")
        if self.goal_space not in ("relative", "absolute"):
            raise ValueError(f"goal_space: must be 'relative' or 'absolute', got "
                             f"{self.goal_space!r}")
        if self.goal_space == "absolute" and self.relabel:
            raise ValueError("relabel: HIRO's off-policy correction is defined for relative "
                             "goals; use relabel=False with goal_space='absolute'")
        if not isinstance(self.relabel_candidates, int) or self.relabel_candidates < 2:
            raise ValueError(
                "relabel_candidates: must be >= 2 (the original goal and s_{t+k} - s_t), "
                f"got {self.relabel_candidates}")


# ------------------------------------------------------------------------------------------------
# Goals: transition, intrinsic reward, off-policy relabelling
# ------------------------------------------------------------------------------------------------


def goal_transition(obs, goal, next_obs):
    """HIRO's ``h(s, g, s') = s + g - s'``: the relative goal that keeps ``s + g`` fixed.

    Example:
        >>> import jax.numpy as jnp
        >>> goal_transition(jnp.array([0.0, 1.0]), jnp.array([2.0, 0.0]),
        ...                 jnp.array([0.5, 1.0])).tolist()
        [1.5, 0.0]
    """
    return obs + goal - next_obs


def intrinsic_reward(obs, goal, next_obs, scale=1.0):
    """The low level's reward ``-scale * ||s + g - s'||`` (distance left to the target).

    Example:
        >>> import jax.numpy as jnp
        >>> float(intrinsic_reward(jnp.zeros(2), jnp.array([3.0, 4.0]), jnp.zeros(2)))
        -5.0
    """
    return -scale * jnp.linalg.norm(goal_transition(obs, goal, next_obs), axis=-1)


def candidate_log_likelihood(q_fn, states, actions, length, candidates, temperature=1.0):
    """Log-likelihood of the logged low-level actions under each candidate goal.

    For candidate ``g`` the goal at logged step ``i`` is what the goal transition gives,
    ``g_i = s_0 + g - s_i`` (``h`` applied ``i`` times telescopes to this), and the action
    probability is the Boltzmann policy ``softmax(Q(s_i ‖ g_i) / temperature)``. Leading batch
    axis ``...`` is optional; ``q_fn`` gets one flat ``[N, 2d]`` array, which is much faster on
    CPU than many small batched calls.

    Args:
        q_fn: ``inputs [N, 2d] -> Q-values [N, A]`` (the low level's network).
        states: ``[..., k, d]`` logged states ``s_0 .. s_{k-1}`` of the option.
        actions: ``[..., k]`` logged actions.
        length: ``[...]`` number of valid steps (an option is cut short when the episode ends).
        candidates: ``[..., C, d]`` relative goals proposed at ``s_0``.
        temperature: Boltzmann temperature.

    Returns:
        ``[..., C]`` summed log-probabilities over the valid steps.

    Example:
        >>> import jax.numpy as jnp
        >>> q_fn = lambda x: jnp.stack([x[..., 2], -x[..., 2]], -1)  # action 0 iff goal_x > 0
        >>> ll = candidate_log_likelihood(q_fn, jnp.zeros((3, 2)), jnp.zeros(3, int), 3,
        ...                               jnp.array([[-5.0, 0.0], [5.0, 0.0]]))
        >>> [round(float(v), 3) for v in ll]
        [-30.0, -0.0]
    """
    s = states[..., None, :, :]  # [..., 1, k, d]
    goals = s[..., :1, :] + candidates[..., :, None, :] - s  # [..., C, k, d]
    inputs = jnp.concatenate([jnp.broadcast_to(s, goals.shape), goals], axis=-1)
    q = q_fn(inputs.reshape(-1, inputs.shape[-1]))
    q = q.reshape(goals.shape[:-1] + q.shape[-1:]) / temperature  # [..., C, k, A]
    log_probs = q - jax.nn.logsumexp(q, axis=-1, keepdims=True)
    taken = jnp.take_along_axis(
        log_probs, jnp.broadcast_to(actions[..., None, :, None], q.shape[:-1] + (1,)).astype(
            jnp.int32), axis=-1)[..., 0]
    valid = jnp.arange(states.shape[-2]) < jnp.asarray(length)[..., None, None]
    return jnp.sum(jnp.where(valid, taken, 0.0), axis=-1)


def relabel_goal(q_fn, states, actions, length, goal, next_obs, key, goal_low, goal_high,
                 num_candidates=10, sigma=0.5, temperature=1.0):
    """HIRO's off-policy correction for high-level transitions (optional leading batch axis).

    Candidates: the original ``goal``, ``s_{t+k} - s_t`` and ``num_candidates - 2`` draws from
    ``N(s_{t+k} - s_t, (sigma * half_range)^2)``, all clipped to the goal box. Returns the
    candidate maximising :func:`candidate_log_likelihood` (ties go to the original goal) and
    its index (0 means the original goal was kept).

    Args:
        q_fn: ``inputs [N, 2d] -> Q-values [N, A]``.
        states, actions, length: the logged option, ``[..., k, d]``, ``[..., k]``, ``[...]``.
        goal: ``[..., d]`` the goal that was proposed; ``next_obs``: ``[..., d]`` ``s_{t+k}``.
        key: PRNG key for the samples.
        goal_low, goal_high: the goal box (scalars or ``[d]``).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> q_fn = lambda x: jnp.stack([x[..., 2], -x[..., 2]], -1)  # action 0 iff goal_x > 0
        >>> states = jnp.zeros((3, 2)).at[:, 0].set(jnp.arange(3.0))  # moved along +x
        >>> g, i = relabel_goal(q_fn, states, jnp.zeros(3, int), 3, jnp.array([-2.0, 0.0]),
        ...                     jnp.array([3.0, 0.0]), jax.random.key(0), -4.0, 4.0)
        >>> int(i) != 0, bool(g[0] > 0)
        (True, True)
    """
    d = goal.shape[-1]
    goal_low = jnp.broadcast_to(jnp.asarray(goal_low, goal.dtype), (d,))
    goal_high = jnp.broadcast_to(jnp.asarray(goal_high, goal.dtype), (d,))
    achieved = next_obs - states[..., 0, :]
    noise = jax.random.normal(key, goal.shape[:-1] + (num_candidates - 2, d), goal.dtype)
    samples = achieved[..., None, :] + sigma * (goal_high - goal_low) / 2.0 * noise
    candidates = jnp.clip(
        jnp.concatenate([goal[..., None, :], achieved[..., None, :], samples], axis=-2),
        goal_low, goal_high)  # [..., C, d]
    log_lik = candidate_log_likelihood(q_fn, states, actions, length, candidates, temperature)
    best = jnp.argmax(log_lik, axis=-1)
    return jnp.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :], best


# ------------------------------------------------------------------------------------------------
# State
# ------------------------------------------------------------------------------------------------


class HighTransition(NamedTuple):
    """One option as the high level stores it (states and actions padded to ``k``)."""

    obs: jnp.ndarray  # s_t
    goal: jnp.ndarray  # g_t as proposed
    reward: jnp.ndarray  # scaled sum of environment rewards over the option
    next_obs: jnp.ndarray  # s_{t+k} (or the state where the episode ended)
    done: jnp.ndarray  # the episode terminated (truncation still bootstraps)
    states: jnp.ndarray  # [k, d] logged s_t .. s_{t+k-1}
    actions: jnp.ndarray  # [k] logged low-level actions
    length: jnp.ndarray  # valid entries of states/actions


@struct.dataclass
class Option:
    """The option in progress (``length == 0``: a new goal is due)."""

    start_obs: jnp.ndarray
    goal: jnp.ndarray
    reward: jnp.ndarray
    length: jnp.ndarray
    states: jnp.ndarray
    actions: jnp.ndarray


@struct.dataclass
class HiroState:
    low: DQNState
    high: TD3State
    replay: Replay  # high-level transitions
    env_state: envs.EnvState
    obs: jnp.ndarray
    goal: jnp.ndarray  # the low level's current relative goal
    option: Option
    episode_return: jnp.ndarray
    episode_length: jnp.ndarray
    env_steps: jnp.ndarray


# ------------------------------------------------------------------------------------------------
# The algorithm
# ------------------------------------------------------------------------------------------------


def seeds_in_sequence(f):
    """``f`` itself on one seed; under ``vmap``, its batch runs element by element (``lax.map``)
    instead of as batched operations, and a ``cond`` inside ``f`` stays a branch per element.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> g = seeds_in_sequence(lambda x, y: (x @ x.T + y).sum())
        >>> x = jnp.ones((3, 2, 2))
        >>> jax.vmap(g, in_axes=(0, None))(x, 1.0).tolist()
        [12.0, 12.0, 12.0]
    """
    wrapped = jax.custom_batching.custom_vmap(f)

    @wrapped.def_vmap
    def rule(axis_size, in_batched, *args):
        def batched(x, b):
            return x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        args = jax.tree.map(batched, tuple(args), tuple(in_batched))
        out = jax.lax.map(lambda a: f(*a), args)
        return out, jax.tree.map(lambda _: True, out)

    return wrapped


def _accumulate(stats: dict, values: dict) -> dict:
    """Add ``values`` into the running epoch sums ``stats`` (same dtypes kept)."""
    return stats | {name: stats[name] + jnp.asarray(v).astype(stats[name].dtype)
                    for name, v in values.items()}


def make_hiro(config: HiroConfig) -> Algorithm:
    """HIRO as an :class:`~gara_jax.algorithms.base.Algorithm` (see the module docstring).

    ``train_epoch`` also reports ``low_loss``, ``critic_loss``, ``relabel_kept`` (fraction of
    sampled goals the relabelling left unchanged), ``goal_distance`` (mean distance to the target
    left when an option ends) and ``intrinsic_reward`` (mean per step).
    """
    env, env_params = envs.make(config.env, collision=config.collision)
    obs_dim, k = 4, config.k
    max_steps = int(env_params.max_steps)
    relative = config.goal_space == "relative"
    if relative:
        position_range = config.goal_position_range or float(env_params.n)
        goal_high = jnp.array([position_range] * 2 + [config.goal_velocity_range] * 2,
                              jnp.float32)
        goal_low = -goal_high
    else:  # the observation bounds
        n = float(env_params.n)
        goal_low = jnp.array([0.0, 0.0, -1.0, -1.0], jnp.float32)
        goal_high = jnp.array([n, n, 1.0, 1.0], jnp.float32)
    # Warm-up goals are drawn from what the actor can propose.
    if config.high.actor_output == "tanh_clipped":
        warm_low, warm_high = jnp.maximum(goal_low, -1.0), jnp.minimum(goal_high, 1.0)
    else:
        warm_low, warm_high = goal_low, goal_high
    dqn = make_dqn(config.low, 2 * obs_dim, env.num_actions)
    td3 = make_td3(config.high, obs_dim, obs_dim, goal_low, goal_high)
    n_blocks = config.steps_per_epoch // k

    def target_of(obs, goal):
        """The state the low level is asked to reach."""
        return obs + goal if relative else goal

    def next_goal_of(obs, goal, next_obs):
        return goal_transition(obs, goal, next_obs) if relative else goal

    def init(key) -> HiroState:
        k_low, k_high, k_env = jax.random.split(key, 3)
        obs, env_state = env.reset(k_env, env_params)
        zeros = jnp.zeros(obs_dim, jnp.float32)
        example = HighTransition(zeros, zeros, jnp.float32(0), zeros, jnp.bool_(False),
                                 jnp.zeros((k, obs_dim)), jnp.zeros(k, jnp.int32), jnp.int32(0))
        option = Option(zeros, zeros, jnp.float32(0), jnp.int32(0), jnp.zeros((k, obs_dim)),
                        jnp.zeros(k, jnp.int32))
        return HiroState(low=dqn.init(k_low), high=td3.init(k_high),
                         replay=replay_init(example, config.high.buffer_size),
                         env_state=env_state, obs=obs, goal=zeros, option=option,
                         episode_return=jnp.float32(0), episode_length=jnp.int32(0),
                         env_steps=jnp.int32(0))

    def propose_goal(state: HiroState, key):
        # Uniform goals while the high level warms up (TD3's start phase), then actor + noise.
        k_uniform, k_noise = jax.random.split(key)
        uniform = jax.random.uniform(k_uniform, (obs_dim,), minval=warm_low, maxval=warm_high)
        explored = td3.act(state.high, state.obs, k_noise, config.goal_noise)
        warm = state.replay.size < config.high.learning_starts
        return jnp.where(warm, uniform, explored)

    def env_step(carry, key):
        state, stats = carry
        k_goal, k_act, k_env, k_learn = jax.random.split(key, 4)
        option = state.option
        new_option = option.length == 0
        goal = jnp.where(new_option, propose_goal(state, k_goal), state.goal)
        option = option.replace(start_obs=jnp.where(new_option, state.obs, option.start_obs),
                                goal=jnp.where(new_option, goal, option.goal))

        low_obs = jnp.concatenate([state.obs, goal])
        action = dqn.act(state.low, low_obs, k_act)
        obs, env_state, reward, terminated, truncated, info = env.step_autoreset(
            k_env, state.env_state, action, env_params)
        next_obs = info["final_obs"]  # the true s' (obs is already reset where the episode ended)
        next_goal = next_goal_of(state.obs, goal, next_obs)
        target = target_of(state.obs, goal)
        r_low = -config.low_reward_scale * jnp.linalg.norm(target - next_obs)
        low, low_info = dqn.observe(
            state.low,
            Transition(low_obs, action, r_low, jnp.concatenate([next_obs, next_goal]), terminated),
            k_learn)

        # Log the step into the option; store the option when it ends.
        i = option.length
        states = option.states.at[i].set(state.obs)
        actions = option.actions.at[i].set(action)
        option_reward = option.reward + reward
        ended = terminated | truncated
        option_done = (i + 1 == k) | ended
        transition = HighTransition(option.start_obs, option.goal,
                                    config.high_reward_scale * option_reward, next_obs,
                                    terminated, states, actions, i + 1)
        replay = replay_add(state.replay, transition, option_done)
        option = Option(option.start_obs, option.goal,
                        jnp.where(option_done, 0.0, option_reward),
                        jnp.where(option_done, 0, i + 1), states, actions)

        episode_return = state.episode_return + reward
        episode_length = state.episode_length + 1
        stats = _accumulate(stats, {
            "low_loss": low_info["loss"],
            "low_updates": low_info["updated"],
            "intrinsic_reward": r_low,
            "options_done": option_done,
            "goal_distance": jnp.where(option_done, jnp.linalg.norm(target - next_obs), 0.0),
        })
        episode = {"episode_ended": ended, "episode_success": terminated,
                   "episode_length": episode_length, "episode_return": episode_return,
                   "episode_end_step": state.env_steps + 1}
        state = state.replace(low=low, replay=replay, env_state=env_state, obs=obs,
                              goal=next_goal, option=option,
                              episode_return=jnp.where(ended, 0.0, episode_return),
                              episode_length=jnp.where(ended, 0, episode_length),
                              env_steps=state.env_steps + 1)
        return (state, stats), episode

    def critic_step(high: TD3State, batch: Batch, key):
        return td3.critic_update(high, batch, key)

    def critic_and_actor_step(high: TD3State, batch: Batch, key):
        high, critic_loss = td3.critic_update(high, batch, key)
        return td3.actor_update(high, batch.obs)[0], critic_loss

    def when_ready(step):
        # Under vmap, `ready` differs per seed: with the "vmap" schedule this cond becomes a
        # select (both sides computed), which is why only the TD3 state and the sampled batch
        # go through it, never the replay buffers. With "sequential" it stays a branch per
        # seed.
        def guarded(ready, high, batch, key):
            return jax.lax.cond(ready, step, lambda h, *_: (h, jnp.float32(0)), high, batch, key)
        return seeds_in_sequence(guarded) if config.seed_schedule == "sequential" else guarded

    td3_steps = {False: when_ready(critic_step), True: when_ready(critic_and_actor_step)}

    def high_update(high: TD3State, replay: Replay, low_params, key, ready, with_actor: bool):
        k_sample, k_relabel, k_update = jax.random.split(key, 3)
        batch = replay_sample(replay, k_sample, config.high.batch_size)
        if config.relabel:
            goals, chosen = relabel_goal(
                lambda x: dqn.q_values(low_params, x), batch.states, batch.actions,
                batch.length, batch.goal, batch.next_obs, k_relabel, goal_low, goal_high,
                config.relabel_candidates, config.relabel_sigma, config.relabel_temperature)
        else:
            goals, chosen = batch.goal, jnp.zeros(config.high.batch_size, jnp.int32)
        high, critic_loss = td3_steps[with_actor](
            ready, high, Batch(batch.obs, goals, batch.reward, batch.next_obs, batch.done),
            k_update)
        return high, critic_loss, jnp.where(ready, jnp.mean(chosen == 0), 0.0)

    def block(carry, xs):
        key, index = xs
        keys = jax.random.split(key, k + 1)
        (state, stats), episode = jax.lax.scan(env_step, carry, keys[:k])
        ready = state.replay.size >= config.high.learning_starts
        # TD3's delayed actor step on every `policy_delay`-th block of the epoch. `index` is the
        # same for every seed, so under vmap this cond stays a branch and the actor step runs
        # only where it is due.
        due = index % config.high.policy_delay == config.high.policy_delay - 1
        high, critic_loss, kept = jax.lax.cond(
            due, partial(high_update, with_actor=True), partial(high_update, with_actor=False),
            state.high, state.replay, state.low.params, keys[k], ready)
        state = state.replace(high=high)
        stats = _accumulate(stats, {"critic_loss": critic_loss, "high_updates": ready,
                                    "relabel_kept": kept})
        return (state, stats), episode

    def train_epoch(state: HiroState, key):
        zero_i, zero_f = jnp.int32(0), jnp.float32(0)
        stats = {"low_loss": zero_f, "low_updates": zero_i, "intrinsic_reward": zero_f,
                 "options_done": zero_i, "goal_distance": zero_f, "critic_loss": zero_f,
                 "high_updates": zero_i, "relabel_kept": zero_f}
        (state, stats), episodes = jax.lax.scan(
            block, (state, stats), (jax.random.split(key, n_blocks), jnp.arange(n_blocks)))
        per = lambda total, count: total / jnp.maximum(count, 1).astype(jnp.float32)
        episodes = jax.tree.map(lambda x: x.reshape(-1), episodes)  # [n_blocks, k] -> steps
        metrics = epoch_metrics(episodes, state.env_steps) | {
            "n_goals": jnp.int32(0),
            "low_loss": per(stats["low_loss"], stats["low_updates"]),
            "critic_loss": per(stats["critic_loss"], stats["high_updates"]),
            "relabel_kept": per(stats["relabel_kept"], stats["high_updates"]),
            "goal_distance": per(stats["goal_distance"], stats["options_done"]),
            "intrinsic_reward": stats["intrinsic_reward"] / config.steps_per_epoch,
        }
        return state, metrics

    def evaluate(state: HiroState, key):
        """Greedy high and low levels, ``eval_episodes`` episodes from the start."""

        def episode(key):
            obs, env_state = env.reset(key, env_params)

            def step(carry, t):
                env_state, obs, goal, done, success, ret = carry
                goal = jnp.where(t % k == 0, td3.policy(state.high.actor_params, obs), goal)
                q = dqn.q_values(state.low.params, jnp.concatenate([obs, goal]))
                action = jnp.argmax(q).astype(jnp.int32)
                next_obs, env_state, reward, terminated, truncated, _ = env.step(
                    key, env_state, action, env_params)
                live = ~done
                carry = (env_state, next_obs, next_goal_of(obs, goal, next_obs),
                         done | terminated | truncated, success | (terminated & live),
                         ret + jnp.where(live, reward, 0.0))
                return carry, None

            init = (env_state, obs, jnp.zeros(obs_dim), jnp.bool_(False), jnp.bool_(False),
                    jnp.float32(0))
            carry, _ = jax.lax.scan(step, init, jnp.arange(max_steps))
            return carry[4], carry[5]

        success, ret = jax.vmap(episode)(jax.random.split(key, config.eval_episodes))
        return {"eval_success": jnp.mean(success.astype(jnp.float32)),
                "eval_return": jnp.mean(ret)}

    return Algorithm(name="hiro", config=config, init=init, train_epoch=train_epoch,
                     evaluate=evaluate, host_update=None)
