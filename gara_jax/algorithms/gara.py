"""GARA and Handcrafted: a two-level (feudal) agent whose goals are boxes of a state partition.

Read top to bottom: configs, the agent's state, then :func:`make_gara` with the pieces of one
environment step (high-level decision, low-level action, intrinsic reward, option bookkeeping),
the epoch (one ``lax.scan``), the greedy evaluation, and GARA's host-side refinement between
epochs. Handcrafted is the same agent on SPEC.md's fixed 6-box partition with no refinement
(and no high-level memory, which only the refinement reads).

One environment step, for one seed (everything vmaps over seeds):

1. *High level.* When no option is running (every ``k`` steps and at each episode start) the
   goal ``G_s`` holding the state is located and a target ``G_d`` chosen (Q-table
   epsilon-greedy, or the planner).
2. *Low level.* The goal-conditioned DQN acts epsilon-greedily on ``s ‖ G_d.lo ‖ G_d.hi``; the
   environment steps with auto-reset.
3. *Intrinsic reward* (SPEC.md section 3): ``+1`` the first time in the option that the next
   state lies in ``G_d``, ``0`` for later steps inside it, ``-0.1`` for steps outside, plus the
   environment reward. As in the reference, the low-level transition stops bootstrapping only
   when the episode terminates (``terminal_on_entry=True`` also stops it on the first entry),
   so the low level learns to enter its goal and stay there until the option ends.
4. *Option end* (``k`` steps, or the episode ended): tabular Q update with the environment
   reward collected during the option (by default on the goal the option actually ended in,
   see :class:`~gara_jax.agents.high_level.HighLevelConfig`), planner graph update, and (GARA)
   the option pushed to the high-level memory as states and target bounds; with
   ``hindsight_memory`` an option that ended in another goal than its target is also stored
   as one towards that goal, as the reference does.

Between epochs GARA's :func:`host_update` runs SPEC.md's refinement trigger on every seed:
a pair ``(G_s, G_d)``, ``s != d``, explored during the last epoch, neither known reachable nor
marked unreachable, with at least ``min_steps`` environment steps of experience. "Experience"
is counted from the high-level memory (the summed lengths of the pair's stored options, the
goals derived from the stored states and target bounds), so it stays right after splits
without any bookkeeping; it is also exactly the data the forward model is trained on. Forward
models for all triggered (seed, pair) jobs are trained in one batched call until their loss
has stabilised, analysed with one batched :func:`gara_jax.reach.refine_many`, and the splits
applied to each seed's padded partition, Q-table and marks (see :func:`_apply_split`).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

import envs
from gara_jax.agents import forward_model as fm
from gara_jax.agents import high_level as hl
from gara_jax.agents.dqn import DQNConfig, DQNState, Transition, make_dqn
from gara_jax.algorithms.base import Algorithm
from gara_jax.networks import mlp_layers

REFINE_METHODS = ("crown", "ibp")
#: Environments with the U-maze's geometry and (x, y, vx, vy) observations, on which SPEC.md
#: section 2's partitions apply: the kinematic maze and the rigid-body one.
U_MAZE_ENVS = ("u_maze", "point_u_maze")


# ----------------------------------------------------------------------------------------------
# Configs
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class HandcraftedConfig:
    """The two-level agent on SPEC.md's fixed 6-box U-maze partition (no refinement).

    Attributes:
        env: maze layout name (see ``envs.LAYOUTS``); the handcrafted partition is the U-maze's.
        k: environment steps per option (the high level decides every ``k`` steps).
        steps_per_epoch: environment steps per jitted training epoch.
        eval_episodes: greedy evaluation episodes per seed after every epoch.
        low: the low-level DQN's hyper-parameters.
        high: the high level's hyper-parameters.
        planning: choose goals with the shortest-path planner instead of the Q-table.
        max_goals: partition capacity (padding of every goal-indexed array).
        reach_reward: intrinsic reward for entering the target goal (once per option).
        outside_penalty: intrinsic reward of a step that ends outside the target goal.
        eval_epsilon_high, eval_epsilon_low: exploration during evaluation (0: greedy).
        terminal_on_entry: stop the low level's bootstrap on entering its goal (the reference
            does not).
        goal_membership: when the low level is "inside" its target for the intrinsic reward:
            ``"box"``, anywhere in the closed target box (the reference); ``"partition"``,
            only where the state belongs to the target goal by the first-box rule (SPEC.md
            section 2), so a face shared with a lower-index goal does not count. With
            ``"box"``, pressing against the U-maze wall at ``x = 1`` "enters" GARA's initial
            right-hand goal ``[1, 3] x [0, 3]``.

    The low level defaults to the reference's DQN loss (``DQNConfig(loss="all_actions")``,
    see :class:`~gara_jax.agents.dqn.DQNConfig`); with the textbook loss on the taken action
    only, the greedy policies of a snapshot are much less reliable.

    Example:
        >>> HandcraftedConfig().max_goals
        6
        >>> HandcraftedConfig(k=0)
        Traceback (most recent call last):
        ...
        ValueError: k: must be an integer >= 1, got 0
    """

    env: str = "u_maze"
    k: int = 5
    steps_per_epoch: int = 3000
    eval_episodes: int = 10
    low: DQNConfig = DQNConfig(loss="all_actions")
    high: hl.HighLevelConfig = hl.HighLevelConfig()
    planning: bool = False
    max_goals: int = 6
    reach_reward: float = 1.0
    outside_penalty: float = -0.1
    eval_epsilon_high: float = 0.0
    eval_epsilon_low: float = 0.0
    terminal_on_entry: bool = False
    goal_membership: str = "box"

    def __post_init__(self):
        _validate_common(self)


@dataclasses.dataclass(frozen=True)
class GaraConfig(HandcraftedConfig):
    """GARA: the two-level agent that refines its goal partition by reachability analysis.

    Attributes (beyond :class:`HandcraftedConfig`'s):
        max_goals: partition capacity; a split that would exceed it is skipped and counted.
        memory_capacity: high-level memory size (options).
        forward: the forward model's hyper-parameters.
        min_steps: environment steps of experience a pair needs before it is analysed.
        tau1, tau2, min_volume_ratio: the reachability thresholds (SPEC.md section 3).
        refine_method: ``"crown"`` (tighter output boxes: fewer spurious "undecided" splits)
            or ``"ibp"``.
        max_jobs_per_seed: analyses per seed per host step; pairs are taken by decreasing
            experience, skipping any that touches a goal being split in the same step.
        hindsight_memory: also store each option that ended in another goal than its target
            as an option towards that goal (the reference's relabelling).

    Example:
        >>> cfg = GaraConfig(planning=True)
        >>> cfg.tau1, cfg.min_steps, cfg.refine_method
        (0.7, 5000, 'crown')
        >>> GaraConfig(refine_method="zonotope")
        Traceback (most recent call last):
        ...
        ValueError: refine_method: must be one of ('crown', 'ibp'), got 'zonotope'
    """

    max_goals: int = 64  # capacity for refinement (Handcrafted needs 6)
    memory_capacity: int = 10_000
    forward: fm.ForwardModelConfig = fm.ForwardModelConfig()
    min_steps: int = 5000
    tau1: float = 0.7
    tau2: float = 0.1
    min_volume_ratio: float = 0.05
    refine_method: str = "crown"
    hindsight_memory: bool = True
    max_jobs_per_seed: int = 4

    def __post_init__(self):
        super().__post_init__()
        _positive_int(self, "memory_capacity", "max_jobs_per_seed")
        if int(self.min_steps) != self.min_steps or self.min_steps < 0:
            raise ValueError(f"min_steps: must be an integer >= 0, got {self.min_steps}")
        if not 0.0 < self.tau1 <= 1.0:
            raise ValueError(f"tau1: must lie in (0, 1], got {self.tau1}")
        if not 0.0 <= self.tau2 < self.tau1:
            raise ValueError(f"tau2: must lie in [0, tau1), got {self.tau2}")
        if not 0.0 < self.min_volume_ratio < 1.0:
            raise ValueError(f"min_volume_ratio: must lie in (0, 1), got {self.min_volume_ratio}")
        if self.refine_method not in REFINE_METHODS:
            raise ValueError(
                f"refine_method: must be one of {REFINE_METHODS}, got {self.refine_method!r}")
        if not isinstance(self.forward, fm.ForwardModelConfig):
            raise ValueError(f"forward: must be a ForwardModelConfig, got {self.forward!r}")


def _positive_int(cfg, *names):
    for name in names:
        value = getattr(cfg, name)
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ValueError(f"{name}: must be an integer >= 1, got {value}")


def _validate_common(cfg):
    if cfg.env not in envs.ENV_NAMES:
        raise ValueError(f"env: unknown environment {cfg.env!r}; valid: {envs.ENV_NAMES}")
    _positive_int(cfg, "k", "steps_per_epoch", "eval_episodes", "max_goals")
    if not isinstance(cfg.low, DQNConfig):
        raise ValueError(f"low: must be a DQNConfig, got {cfg.low!r}")
    if not isinstance(cfg.high, hl.HighLevelConfig):
        raise ValueError(f"high: must be a HighLevelConfig, got {cfg.high!r}")
    if not isinstance(cfg.planning, bool):
        raise ValueError(f"planning: must be a bool, got {cfg.planning!r}")
    if not np.isfinite(cfg.reach_reward) or not np.isfinite(cfg.outside_penalty):
        raise ValueError("reach_reward/outside_penalty: must be finite")
    if cfg.goal_membership not in ("box", "partition"):
        raise ValueError(
            f"goal_membership: must be 'box' or 'partition', got {cfg.goal_membership!r}")
    for name in ("eval_epsilon_high", "eval_epsilon_low"):
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise ValueError(f"{name}: must lie in [0, 1], got {getattr(cfg, name)}")
    for name in ("terminal_on_entry",) + (("hindsight_memory",) if hasattr(
            cfg, "hindsight_memory") else ()):
        if not isinstance(getattr(cfg, name), bool):
            raise ValueError(f"{name}: must be a bool, got {getattr(cfg, name)!r}")


def algorithm_name(config) -> str:
    """``gara``, ``gara_planning``, ``handcrafted`` or ``handcrafted_planning``."""
    base = "gara" if isinstance(config, GaraConfig) else "handcrafted"
    return base + ("_planning" if config.planning else "")


# ----------------------------------------------------------------------------------------------
# State
# ----------------------------------------------------------------------------------------------


@struct.dataclass
class Option:
    """The option being executed. ``steps == 0`` means none: the high level decides next step.

    ``stale`` marks an option whose goal indices predate a refinement (set by the host); its end
    still goes to the memory (states and bounds) but not to the index-based learners.
    """

    start_obs: jax.Array  # [D] state where it started
    start_goal: jax.Array  # goal holding start_obs
    target: jax.Array  # targeted goal index
    target_lo: jax.Array  # [D] targeted box (kept as bounds: the low level's input)
    target_hi: jax.Array
    steps: jax.Array  # env steps taken in this option
    env_reward: jax.Array  # environment reward collected so far
    reached: jax.Array  # the target was entered during this option
    stale: jax.Array


@struct.dataclass
class GaraState:
    """One seed's agent (a pytree; batched over seeds by ``vmap``).

    ``reachable``/``unreachable`` are the refinement's verdicts per goal pair, ``blocked`` the
    pairs whose split did not fit in ``max_goals`` (not analysed again). ``host_key`` seeds the
    host step (forward-model initialisation) reproducibly.
    """

    obs: jax.Array
    env_state: Any
    dqn: DQNState
    high: hl.HighState
    partition: Any  # gara_jax.partition.Partition
    option: Option
    memory: fm.HighMemory
    reachable: jax.Array
    unreachable: jax.Array
    blocked: jax.Array
    env_steps: jax.Array
    episode_return: jax.Array
    host_key: jax.Array


def initial_partition(config):
    """The partition an agent starts from: SPEC.md section 2's handcrafted or GARA boxes."""
    from gara_jax import partition as part

    if config.env not in U_MAZE_ENVS:
        raise ValueError(
            f"env: the handcrafted and initial GARA partitions are defined for the U-maze "
            f"environments {U_MAZE_ENVS} only, got {config.env!r}")
    if isinstance(config, GaraConfig):
        return part.gara_initial(max_goals=config.max_goals)
    return part.handcrafted(max_goals=config.max_goals)


def intrinsic_reward(next_state, target_lo, target_hi, reached, reach_reward=1.0,
                     outside_penalty=-0.1, in_target=None):
    """The low level's goal reward for a step ending in ``next_state`` (SPEC.md section 3).

    ``reach_reward`` the first time during the option that the state lies in the (closed)
    target box, 0 for later steps inside it, ``outside_penalty`` for steps outside. Returns
    ``(reward, inside, first_entry)``. ``in_target`` (a bool) further restricts "inside", e.g.
    to the states that *belong* to the target goal under the partition's first-box rule.

    Example:
        >>> import jax.numpy as jnp
        >>> lo, hi = jnp.zeros(2), jnp.ones(2)
        >>> [round(float(intrinsic_reward(jnp.array(s), lo, hi, r)[0]), 3)
        ...  for s, r in [([0.5, 1.0], False), ([0.5, 0.5], True), ([2.0, 0.5], True)]]
        [1.0, 0.0, -0.1]
    """
    inside = jnp.all((next_state >= target_lo) & (next_state <= target_hi))
    if in_target is not None:
        inside = inside & in_target
    first_entry = inside & jnp.logical_not(reached)
    reward = jnp.where(first_entry, reach_reward, jnp.where(inside, 0.0, outside_penalty))
    return reward, inside, first_entry


# ----------------------------------------------------------------------------------------------
# The agent
# ----------------------------------------------------------------------------------------------


def make_gara(config: GaraConfig | HandcraftedConfig) -> Algorithm:
    """Build GARA (``GaraConfig``) or Handcrafted (``HandcraftedConfig``) as pure functions.

    Returns an :class:`~gara_jax.algorithms.base.Algorithm`; ``host_update`` is ``None`` for
    Handcrafted.

    Example:
        >>> import jax
        >>> alg = make_gara(HandcraftedConfig(steps_per_epoch=10, eval_episodes=2))
        >>> state = alg.init(jax.random.key(0))
        >>> state, metrics = jax.jit(alg.train_epoch)(state, jax.random.key(1))
        >>> int(metrics["env_steps"]), int(metrics["n_goals"])
        (10, 6)
    """
    from gara_jax import partition as part

    refining = isinstance(config, GaraConfig)
    env, env_params = envs.make(config.env)
    max_steps = int(env_params.max_steps)
    dim = 4
    G = config.max_goals
    dqn = make_dqn(config.low, input_dim=3 * dim, num_actions=env.num_actions)
    high_cfg = config.high
    partition0 = initial_partition(config)
    memory_capacity = config.memory_capacity if refining else 1

    def locate(partition, s):
        # A valid tiling covers every state; clamp so a stray -1 can never index out of range.
        return jnp.maximum(part.locate(partition, s), 0).astype(jnp.int32)

    def choose_goal(key, high, partition, here, epsilon):
        if config.planning:
            return hl.plan_goal(key, high.dist, high.succeeded, here, partition.count, epsilon)
        return hl.q_goal(key, high.q, here, partition.count, epsilon)

    def exit_goals(high, partition):
        goal = locate(partition, high.exit_state)
        return (jnp.arange(G) == goal) & high.exit_known

    # -- init ------------------------------------------------------------------------------

    def init(key) -> GaraState:
        k_env, k_dqn, k_host = jax.random.split(key, 3)
        obs, env_state = env.reset(k_env, env_params)
        pairs = jnp.zeros((G, G), bool)
        option = Option(
            start_obs=obs, start_goal=jnp.int32(0), target=jnp.int32(0),
            target_lo=jnp.zeros(dim, jnp.float32), target_hi=jnp.zeros(dim, jnp.float32),
            steps=jnp.int32(0), env_reward=jnp.float32(0.0), reached=jnp.asarray(False),
            stale=jnp.asarray(False))
        return GaraState(
            obs=obs, env_state=env_state, dqn=dqn.init(k_dqn),
            high=hl.init_high_state(high_cfg, G, dim),
            partition=jax.tree.map(jnp.asarray, partition0), option=option,
            memory=fm.init_memory(memory_capacity, dim),
            reachable=pairs, unreachable=pairs, blocked=pairs,
            env_steps=jnp.int32(0), episode_return=jnp.float32(0.0),
            host_key=jax.random.key_data(k_host))

    # -- one environment step --------------------------------------------------------------

    def step(s: GaraState, key):
        k_high, k_act, k_env, k_dqn = jax.random.split(key, 4)
        partition, option, high = s.partition, s.option, s.high

        # 1. High level: a new option where none is running.
        deciding = option.steps == 0
        here = locate(partition, s.obs)
        target = choose_goal(k_high, high, partition, here, high.epsilon)
        fresh = Option(
            start_obs=s.obs, start_goal=here, target=target,
            target_lo=partition.lo[target], target_hi=partition.hi[target],
            steps=jnp.int32(0), env_reward=jnp.float32(0.0), reached=jnp.asarray(False),
            stale=jnp.asarray(False))
        option = jax.tree.map(lambda a, b: jnp.where(deciding, a, b), fresh, option)
        high = high.replace(epsilon=hl.decay_epsilon(high_cfg, high.epsilon, deciding),
                            decisions=high.decisions + deciding)

        # 2. Low level acts; the environment steps (auto-reset at episode end).
        goal_in = jnp.concatenate([option.target_lo, option.target_hi])
        x = jnp.concatenate([s.obs, goal_in])
        action = dqn.act(s.dqn, x, k_act)
        obs, env_state, reward, terminated, truncated, info = env.step_autoreset(
            k_env, s.env_state, action, env_params)
        next_s = info["final_obs"]  # the true next state, before any reset

        # 3. Intrinsic reward and the low-level transition.
        next_goal = locate(partition, next_s)
        in_target = None
        if config.goal_membership == "partition":
            # The state must belong to the target goal (first box containing it), not just lie
            # on a face it shares with a lower-index goal; indices predating a split fall back
            # to the box test.
            in_target = (next_goal == option.target) | option.stale
        intrinsic, inside, first_entry = intrinsic_reward(
            next_s, option.target_lo, option.target_hi, option.reached, config.reach_reward,
            config.outside_penalty, in_target)
        transition = Transition(x, action, intrinsic + reward,
                                jnp.concatenate([next_s, goal_in]),
                                terminated | (first_entry & config.terminal_on_entry))
        dqn_state, dqn_info = dqn.observe(s.dqn, transition, k_dqn)

        # 4. Option bookkeeping; learning at option end.
        option = option.replace(steps=option.steps + 1, env_reward=option.env_reward + reward,
                                reached=option.reached | inside)
        episode_over = terminated | truncated
        ended = (option.steps >= config.k) | episode_over
        outcome = hl.OptionOutcome(
            start=option.start_goal, target=option.target,
            next_goal=next_goal, reward=option.env_reward,
            terminated=terminated, reached=option.reached, exit_state=next_s,
            blocked=s.unreachable[option.start_goal, option.target])
        high = hl.learn_from_option(high_cfg, high, outcome, partition.count,
                                    ended & ~option.stale)
        if config.planning:
            dist = high.dist
            for _ in range(high_cfg.planner_sweeps):
                dist = hl.relax_distances(dist, high.succeeded, exit_goals(high, partition))
            high = high.replace(dist=dist)
        env_steps = s.env_steps + 1
        memory = s.memory
        if refining:
            memory = fm.push_memory(memory, option.start_obs, next_s, option.target_lo,
                                    option.target_hi, option.env_reward, option.steps,
                                    env_steps, where=ended)
            if config.hindsight_memory:
                # Also store the option as one towards the goal it actually ended in.
                memory = fm.push_memory(
                    memory, option.start_obs, next_s, partition.lo[next_goal],
                    partition.hi[next_goal], option.env_reward, option.steps, env_steps,
                    where=ended & (next_goal != option.target))
        option = option.replace(steps=jnp.where(ended, 0, option.steps))

        episode_return = s.episode_return + reward
        stats = dict(
            episodes_ended=episode_over.astype(jnp.int32),
            successes=terminated.astype(jnp.int32),
            returns=jnp.where(episode_over, episode_return, 0.0),
            options_ended=ended.astype(jnp.int32),
            options_reached=(ended & option.reached).astype(jnp.int32),
            low_loss=dqn_info["loss"],
            low_updates=dqn_info["updated"].astype(jnp.int32),
        )
        s = s.replace(obs=obs, env_state=env_state, dqn=dqn_state, high=high, option=option,
                      memory=memory, env_steps=env_steps,
                      episode_return=jnp.where(episode_over, 0.0, episode_return))
        return s, stats

    # -- one epoch ---------------------------------------------------------------------------

    def train_epoch(state: GaraState, key):
        keys = jax.random.split(key, config.steps_per_epoch)
        state, stats = jax.lax.scan(step, state, keys)
        total = jax.tree.map(lambda v: jnp.sum(v, axis=0), stats)
        ended = total["episodes_ended"]
        per_episode = lambda v: jnp.where(ended > 0, v / jnp.maximum(ended, 1), 0.0)
        metrics = {
            "env_steps": state.env_steps,
            "train_success": per_episode(total["successes"].astype(jnp.float32)),
            "episodes_ended": ended,
            "episode_return": per_episode(total["returns"]),
            "n_goals": state.partition.count.astype(jnp.int32),
            "option_success": total["options_reached"]
            / jnp.maximum(total["options_ended"], 1).astype(jnp.float32),
            "low_loss": total["low_loss"] / jnp.maximum(total["low_updates"], 1),
            "low_epsilon": state.dqn.epsilon,
            "high_epsilon": state.high.epsilon,
        }
        return state, metrics

    # -- greedy evaluation -------------------------------------------------------------------

    def evaluate(state: GaraState, key):
        """Greedy high and low levels, ``eval_episodes`` episodes from the start."""
        partition, high = state.partition, state.high
        params = state.dqn.params

        def episode(key):
            k_reset, k_run = jax.random.split(key)
            obs, env_state = env.reset(k_reset, env_params)
            carry = dict(obs=obs, env_state=env_state, lo=jnp.zeros(dim), hi=jnp.zeros(dim),
                         steps=jnp.int32(0), done=jnp.asarray(False),
                         success=jnp.asarray(False), ret=jnp.float32(0.0))

            def one(c, key):
                deciding = c["steps"] == 0
                k_goal, k_explore, k_random = jax.random.split(key, 3)
                goal = choose_goal(k_goal, high, partition, locate(partition, c["obs"]),
                                   config.eval_epsilon_high)
                lo = jnp.where(deciding, partition.lo[goal], c["lo"])
                hi = jnp.where(deciding, partition.hi[goal], c["hi"])
                x = jnp.concatenate([c["obs"], lo, hi])
                action = jnp.argmax(dqn.q_values(params, x)).astype(jnp.int32)
                if config.eval_epsilon_low > 0:
                    explore = jax.random.uniform(k_explore) < config.eval_epsilon_low
                    action = jnp.where(explore, jax.random.randint(k_random, (), 0, 4), action)
                obs, env_state, reward, term, trunc, _ = env.step(
                    key, c["env_state"], action, env_params)
                live = ~c["done"]
                keep = lambda new, old: jnp.where(live, new, old)
                return dict(
                    obs=keep(obs, c["obs"]),
                    env_state=jax.tree.map(keep, env_state, c["env_state"]),
                    lo=lo, hi=hi, steps=(c["steps"] + 1) % config.k,
                    done=c["done"] | term | trunc, success=c["success"] | (live & term),
                    ret=c["ret"] + jnp.where(live, reward, 0.0)), None

            c, _ = jax.lax.scan(one, carry, jax.random.split(k_run, max_steps))
            return c["success"], c["ret"]

        success, ret = jax.vmap(episode)(jax.random.split(key, config.eval_episodes))
        return {"eval_success": jnp.mean(success.astype(jnp.float32)),
                "eval_return": jnp.mean(ret)}

    host_update = _make_host_update(config, locate, exit_goals) if refining else None
    return Algorithm(name=algorithm_name(config), config=config, init=init,
                     train_epoch=train_epoch, evaluate=evaluate, host_update=host_update)


# ----------------------------------------------------------------------------------------------
# GARA's host step: trigger, forward models, reachability analysis, splits
# ----------------------------------------------------------------------------------------------


def _make_host_update(config: GaraConfig, locate, exit_goals):
    G = config.max_goals
    forward = fm.make_forward_model(config.forward, state_dim=4)

    @jax.jit
    @jax.vmap
    def memory_goals(state: GaraState):
        """Goal indices of every stored option and the per-pair experience (device side)."""
        mem, partition = state.memory, state.partition
        start = locate(partition, mem.start)
        target = fm.match_boxes(mem.target_lo, mem.target_hi, partition.lo, partition.hi,
                                partition.count)
        since = state.env_steps - config.steps_per_epoch
        steps, recent = fm.pair_experience(start, target, mem, since, G)
        return start, target, steps, recent

    @jax.jit
    @jax.vmap
    def replan(state: GaraState):
        """Exact planner distances on the refined partitions."""
        high = state.high
        dist = hl.shortest_distances(high.succeeded, exit_goals(high, state.partition),
                                     state.partition.count)
        return high.replace(dist=dist)

    def host_update(states: GaraState, epoch: int):
        from gara_jax import partition as part
        from gara_jax import reach

        t0 = time.perf_counter()
        start_goal, target_goal, steps, recent = jax.device_get(memory_goals(states))
        host = jax.device_get(dict(
            count=states.partition.count, lo=states.partition.lo, hi=states.partition.hi,
            reachable=states.reachable, unreachable=states.unreachable, blocked=states.blocked,
            mem_start=states.memory.start, mem_end=states.memory.end,
            mem_tlo=states.memory.target_lo, mem_thi=states.memory.target_hi,
            size=states.memory.size, host_key=states.host_key))
        n_seeds = len(host["count"])

        # 1. The trigger, per seed; then non-conflicting jobs by decreasing experience.
        jobs = []  # (seed, s, d)
        for i in range(n_seeds):
            n = int(host["count"][i])
            ok = (recent[i] & (steps[i] >= config.min_steps) & ~host["reachable"][i]
                  & ~host["unreachable"][i] & ~host["blocked"][i])
            ok[np.arange(G), np.arange(G)] = False
            ok[n:, :] = False
            ok[:, n:] = False
            pairs = sorted(zip(*np.nonzero(ok), strict=True), key=lambda p: -steps[i][p])
            splitting, touched = set(), set()
            for s_idx, d_idx in pairs:
                if len([j for j in jobs if j[0] == i]) >= config.max_jobs_per_seed:
                    break
                if s_idx in touched or s_idx in splitting or d_idx in splitting:
                    continue
                jobs.append((i, int(s_idx), int(d_idx)))
                splitting.add(s_idx)
                touched.update((s_idx, d_idx))
        info = dict(epoch=epoch, triggered=len(jobs), stable=0, analysed=0, splits=0,
                    reaches=0, no_reach=0, capacity_skips=0, changed=np.zeros(n_seeds, bool),
                    fit_s=0.0, refine_s=0.0)
        if not jobs:
            info["host_s"] = time.perf_counter() - t0
            return states, info

        # 2. Forward models, one fresh model per job, all trained in one batched call.
        datasets = []
        for i, s_idx, d_idx in jobs:
            rows = np.nonzero((np.arange(len(start_goal[i])) < host["size"][i])
                              & (start_goal[i] == s_idx) & (target_goal[i] == d_idx))[0]
            x = np.concatenate([host["mem_start"][i][rows], host["mem_tlo"][i][rows],
                                host["mem_thi"][i][rows]], axis=1)
            datasets.append((x, host["mem_end"][i][rows]))
        n_jobs = len(jobs)
        # Jobs padded to a power of two (at least 8) and rows to the memory capacity: only a
        # few shapes ever get compiled, whatever the number of jobs and their data sizes.
        padded_jobs = max(8, 1 << int(np.ceil(np.log2(n_jobs))))
        datasets += [(np.zeros((0, 12), np.float32), np.zeros((0, 4), np.float32))] * (
            padded_jobs - n_jobs)
        x, y, mask = fm.pad_jobs(datasets, config.forward.batch_size,
                                 min_rows=config.memory_capacity,
                                 max_rows=config.memory_capacity)
        # Job keys depend only on the job's own seed, the epoch and the pair: reproducible.
        seed_keys = jax.random.wrap_key_data(jnp.asarray(host["host_key"]))
        job_keys = [jax.random.fold_in(jax.random.fold_in(seed_keys[i], epoch), s_idx * G + d_idx)
                    for i, s_idx, d_idx in jobs]
        job_keys = jnp.stack(job_keys + [job_keys[0]] * (padded_jobs - n_jobs))
        k_init = jax.vmap(lambda k: jax.random.fold_in(k, 0))(job_keys)
        k_fit = jax.vmap(lambda k: jax.random.fold_in(k, 1))(job_keys)
        t_fit = time.perf_counter()
        fit = forward.fit(forward.init(k_init), x, y, mask, k_fit)
        stable = np.asarray(fit.stable)[:n_jobs]
        info["fit_s"] = time.perf_counter() - t_fit
        info["stable"] = int(stable.sum())
        chosen = [j for j in range(n_jobs) if stable[j]]
        if not chosen:
            info["host_s"] = time.perf_counter() - t0
            return states, info

        # 3. One batched reachability analysis for every stable job.
        t_ref = time.perf_counter()
        params = jax.tree.map(lambda p: p[np.asarray(chosen)], fit.params)
        lo, hi = host["lo"], host["hi"]
        results = reach.refine_many(
            mlp_layers(params),
            np.stack([lo[jobs[j][0]][jobs[j][1]] for j in chosen]),
            np.stack([hi[jobs[j][0]][jobs[j][1]] for j in chosen]),
            np.stack([lo[jobs[j][0]][jobs[j][2]] for j in chosen]),
            np.stack([hi[jobs[j][0]][jobs[j][2]] for j in chosen]),
            tau1=config.tau1, tau2=config.tau2, min_volume_ratio=config.min_volume_ratio,
            method=config.refine_method)
        info["refine_s"] = time.perf_counter() - t_ref

        # 4. Apply the verdicts seed by seed on host copies, then write everything back.
        arrays = jax.device_get(dict(q=states.high.q, succeeded=states.high.succeeded,
                                     stale=states.option.stale))
        seeds = {}
        for j, result in zip(chosen, results, strict=True):
            i, s_idx, d_idx = jobs[j]
            if i not in seeds:
                seeds[i] = dict(
                    partition=part.Partition.create(lo[i][: host["count"][i]],
                                                    hi[i][: host["count"][i]], G),
                    q=arrays["q"][i].copy(), succeeded=arrays["succeeded"][i].copy(),
                    reachable=host["reachable"][i].copy(),
                    unreachable=host["unreachable"][i].copy(), blocked=host["blocked"][i].copy())
            outcome = _apply_split(seeds[i], s_idx, d_idx, result)
            info["analysed"] += 1
            info["splits"] += outcome == "split"
            info["reaches"] += outcome == "reaches"
            info["no_reach"] += outcome == "no_reach"
            info["capacity_skips"] += outcome == "capacity"
            info["changed"][i] |= outcome == "split"

        new = dict(lo=lo, hi=hi, count=host["count"], q=arrays["q"],
                   succeeded=arrays["succeeded"], reachable=host["reachable"],
                   unreachable=host["unreachable"], blocked=host["blocked"],
                   stale=arrays["stale"])
        new = {k: np.array(v) for k, v in new.items()}  # writable copies
        for i, seed in seeds.items():
            p = seed["partition"]
            new["lo"][i], new["hi"][i], new["count"][i] = p.lo, p.hi, p.count
            for name in ("q", "succeeded", "reachable", "unreachable", "blocked"):
                new[name][i] = seed[name]
            new["stale"][i] |= info["changed"][i]
        partition = states.partition.replace(
            lo=jnp.asarray(new["lo"], states.partition.lo.dtype),
            hi=jnp.asarray(new["hi"], states.partition.hi.dtype),
            count=jnp.asarray(new["count"], states.partition.count.dtype))
        high = states.high.replace(q=jnp.asarray(new["q"]),
                                   succeeded=jnp.asarray(new["succeeded"]))
        states = states.replace(
            partition=partition, high=high,
            reachable=jnp.asarray(new["reachable"]), unreachable=jnp.asarray(new["unreachable"]),
            blocked=jnp.asarray(new["blocked"]),
            option=states.option.replace(stale=jnp.asarray(new["stale"])))
        if config.planning:
            states = states.replace(high=replan(states))
        info["host_s"] = time.perf_counter() - t0
        return states, info

    return host_update


def _apply_split(seed: dict, s: int, d: int, result) -> str:
    """Apply one analysis of the pair ``(G_s, G_d)`` to a seed's host-side arrays (in place).

    ``G_s`` is replaced by the reaching boxes then the non-reaching ones (the first keeps index
    ``s``, the others are appended). What indexes goals is updated as follows:

    - Q-table: the rows *and* columns of every piece are copies of ``G_s``'s (the reference
      copies rows; a piece, as a target, is best estimated by the whole box's value), then
      ``Q[piece, d] = 0`` for the non-reaching pieces (as the reference does).
    - Planner graph: rows and columns copied likewise; then the edge ``piece -> d`` is set for
      reaching pieces and removed for non-reaching ones.
    - Reachability marks: a piece's *row* (the piece as a start) inherits ``G_s``'s verdicts
      towards other goals (a subset of a box that reaches, or misses, a goal does so too);
      its *column* (the piece as a target) is cleared, since the old verdicts were about a
      larger target. Then reaching pieces are marked reachable towards ``G_d`` and the others
      unreachable.

    An analysis whose boxes merge back into ``G_s`` changes no box: if all of ``G_s`` reaches,
    the pair is marked reachable; if none of it does, nothing is marked (as in the reference,
    which only marks the non-reaching pieces of a split), so the pair is analysed again later
    with a better-trained low level. A split that does not fit in the capacity is skipped and
    the pair marked ``blocked``. Returns ``"split"``, ``"reaches"``, ``"no_reach"`` or
    ``"capacity"``.
    """
    from gara_jax import partition as part

    reach_lo = np.asarray(result.reaching_lo).reshape(-1, 4)
    reach_hi = np.asarray(result.reaching_hi).reshape(-1, 4)
    miss_lo = np.asarray(result.nonreaching_lo).reshape(-1, 4)
    miss_hi = np.asarray(result.nonreaching_hi).reshape(-1, 4)
    n_reach = len(reach_lo)
    boxes_lo = np.concatenate([reach_lo, miss_lo])
    boxes_hi = np.concatenate([reach_hi, miss_hi])
    if len(boxes_lo) <= 1:
        if n_reach == 0:
            # Nothing of G_s reaches G_d (yet): as in the reference, the pair stays open and is
            # analysed again once explored anew, with a better low-level policy and more data.
            return "no_reach"
        seed["reachable"][s, d] = True
        return "reaches"
    if not part.can_fit(seed["partition"], len(boxes_lo) - 1):
        seed["blocked"][s, d] = True
        return "capacity"
    seed["partition"], pieces = part.replace_box(seed["partition"], s, boxes_lo, boxes_hi)
    pieces = [int(p) for p in np.asarray(pieces)]
    q, succ = seed["q"], seed["succeeded"]
    row_q, col_q, diag_q = q[s].copy(), q[:, s].copy(), q[s, s]
    row_e, col_e = succ[s].copy(), succ[:, s].copy()
    row_r, row_u = seed["reachable"][s].copy(), seed["unreachable"][s].copy()
    for p in pieces:
        q[p], q[:, p] = row_q, col_q
        succ[p], succ[:, p] = row_e, col_e
        seed["reachable"][p], seed["unreachable"][p] = row_r, row_u
        seed["blocked"][p] = False
    for p in pieces:
        for a in pieces:
            q[p, a], succ[p, a] = diag_q, False
        seed["reachable"][:, p] = False
        seed["unreachable"][:, p] = False
        seed["blocked"][:, p] = False
    for n, p in enumerate(pieces):
        hits = n < n_reach
        seed["reachable"][p, d], seed["unreachable"][p, d] = hits, not hits
        succ[p, d] = hits
        if not hits:
            q[p, d] = 0.0
    return "split"
