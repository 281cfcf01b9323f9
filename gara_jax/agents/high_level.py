"""High level of the set-based agents (GARA, Handcrafted): tabular Q-learning and a planner.

Goals are the boxes of a padded partition of ``max_goals`` slots, of which the first ``n_goals``
are valid. Everything here is a pure function on small arrays, so it runs inside the training
``lax.scan`` and vmaps over seeds.

Two variants choose the next goal from the current one (SPEC.md section 3):

- **Q-learning**: ``Q[start_goal, target_goal]`` learned from the environment reward collected
  during the option, epsilon-greedy with a linearly decaying epsilon.
- **Planning**: a shortest path over the graph of goal transitions seen to succeed (an option
  from ``G_s`` targeting ``G_d`` entered ``G_d``) towards the goal holding the state where the
  exit reward was last obtained; a uniformly random goal with probability epsilon, or when no
  path is known yet.

Choices, after the reference implementation (documented because the SPEC leaves them open):

- Every valid goal is selectable, the current one included. Targeting the current goal is how
  the agent is sent to the exit once it stands in the goal that holds it (Handcrafted's
  ``[1.5, 3] x [0, 2]``), so excluding it would make the task unsolvable there. Pairs marked
  unreachable are not masked in the Q-learning variant (the reference only zeroes their
  Q-value when it splits), and are never planner edges (the reference's "unsafe" list).
- Ties between maximal Q-values are broken uniformly at random by default
  (``tie_break="random"``); the reference's ``argmax`` always took the lowest index
  (``tie_break="lowest"``), which makes a fresh table always pick goal 0.
- The Q-learning target is ``r + gamma * (1 - terminated) * max_g' Q[next_goal, g']``, and by
  default (``q_target_entry="reached"``) it updates ``Q[start, next_goal]``, the entry of the
  goal the option actually ended in, as the reference does (it writes its update into
  ``Q[start][reached_partition]``): hindsight relabelling of the high-level action, so the
  greedy high level chooses goals the low level really gets to. The textbook update of
  ``Q[start, target]`` (``q_target_entry="target"``) locks onto whatever target was chosen
  when the exit was first found, even a target the low level then learns to walk away from;
  with a fast epsilon decay (0.01 after 200 decisions, the reference's results version) it
  rarely recovers. On the
  U-maze, Handcrafted with the textbook update trained to about 10-20% success, with the
  hindsight update to nearly 100% (10 seeds, 120,000 steps).

Per-step cost under ``vmap``: ``lax.cond`` becomes a select, so work done "only at decisions"
runs every step. The planner therefore keeps a distance vector and relaxes it with one
synchronous Bellman-Ford sweep per environment step (``O(max_goals^2)``) instead of solving
shortest paths at each decision. A sweep recomputes every distance from its successors'
distances, so the vector converges to the exact hop counts within ``max_goals`` sweeps of the
last graph change, also when edges disappear (after a split); decisions happen every ``k``
steps, so the lag is small. :func:`shortest_distances` runs the full relaxation.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

INF = jnp.inf
#: What the high level's temporal difference is taken against (``HighLevelConfig.q_update``).
Q_UPDATES = ("written_entry", "authors")


@dataclasses.dataclass(frozen=True)
class HighLevelConfig:
    """High-level hyper-parameters (SPEC.md section 3 defaults).

    Attributes:
        alpha: tabular Q-learning step size.
        gamma: discount per option.
        epsilon_start, epsilon_decrement, epsilon_min: epsilon starts at ``epsilon_start`` and
            loses ``epsilon_decrement`` at every decision, down to ``epsilon_min``.
            The reference's final maze version decrements 0.0005 (0.01 after ~9,900 steps at
            ``k = 5``); its results version 0.005.
        planner_sweeps: Bellman-Ford sweeps of the planner's distance vector per env step.
        q_target_entry: ``"reached"`` (update the entry of the goal the option ended in, the
            reference's hindsight update), ``"target"`` (the targeted goal's entry), or
            ``"both"`` (both entries, with the same TD target: the hindsight update, and a
            failed target's value moves towards the value of where the option really ended).
        tie_break: greedy ties between equal Q-values: ``"random"`` (uniform) or ``"lowest"``
            (lowest goal index, the reference's ``argmax``).
        q_update: which entry the temporal difference is taken against (SPEC.md sections 3.3
            and 3.9.3). ``"written_entry"``: the entry being written, ``delta = r + gamma (1 -
            done) max Q[next_goal] - Q[start, written]`` (ordinary Q-learning of the written
            entry; this project's default). ``"authors"``: the *chosen target's* entry,
            ``delta = ... - Q[start, target]``, whatever entry ``q_target_entry`` writes
            ``Q[start, written] += alpha delta`` into: the reference's update, in both its
            final and its results version. The two agree when the option ended in its target
            or with ``q_target_entry="target"``.
    """

    alpha: float = 0.01
    gamma: float = 0.99
    epsilon_start: float = 1.0
    epsilon_decrement: float = 0.0005
    epsilon_min: float = 0.01
    planner_sweeps: int = 1
    q_target_entry: str = "reached"
    tie_break: str = "random"
    q_update: str = "written_entry"

    def __post_init__(self):
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f"alpha: must lie in (0, 1], got {self.alpha}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma: must lie in [0, 1], got {self.gamma}")
        if not 0.0 <= self.epsilon_min <= self.epsilon_start <= 1.0:
            raise ValueError(
                "epsilon_start/epsilon_min: need 0 <= epsilon_min <= epsilon_start <= 1, got "
                f"{self.epsilon_start}/{self.epsilon_min}")
        if not self.epsilon_decrement >= 0.0:
            raise ValueError(f"epsilon_decrement: must be >= 0, got {self.epsilon_decrement}")
        if int(self.planner_sweeps) != self.planner_sweeps or self.planner_sweeps < 1:
            raise ValueError(f"planner_sweeps: must be an integer >= 1, got {self.planner_sweeps}")
        if self.q_target_entry not in ("reached", "target", "both"):
            raise ValueError(
                "q_target_entry: must be 'reached', 'target' or 'both', got "
                f"{self.q_target_entry!r}")
        if self.tie_break not in ("random", "lowest"):
            raise ValueError(f"tie_break: must be 'random' or 'lowest', got {self.tie_break!r}")
        if self.q_update not in Q_UPDATES:
            raise ValueError(f"q_update: must be one of {Q_UPDATES}, got {self.q_update!r}")


@struct.dataclass
class HighState:
    """One seed's high-level learner (padded to ``max_goals``).

    Attributes:
        q: ``[G, G]`` option values ``Q[start_goal, target_goal]``.
        epsilon: current exploration rate.
        decisions: goals chosen so far.
        succeeded: ``[G, G]`` planner graph, ``True`` where an option from the row's goal
            entered the column's goal it targeted.
        dist: ``[G]`` planner hop counts to the exit goal (``inf`` where unknown).
        exit_state: ``[D]`` the last state where the exit reward was obtained.
        exit_known: whether ``exit_state`` holds such a state yet.
        alias: ``[G]`` int32 alias group of each Q row, or ``None`` (rows independent). Rows
            with the same group are one row, as the reference's Q rows after a split are one
            array object (GARA's ``q_rows_after_split="aliased"``, SPEC.md section 3.9.3):
            every update written into one of them is written into all of them.
    """

    q: jax.Array
    epsilon: jax.Array
    decisions: jax.Array
    succeeded: jax.Array
    dist: jax.Array
    exit_state: jax.Array
    exit_known: jax.Array
    alias: Any = None


def init_high_state(config: HighLevelConfig, max_goals: int, state_dim: int,
                    alias_groups: bool = False) -> HighState:
    """A fresh high-level learner: zero Q-table, empty planner graph; with ``alias_groups``,
    every Q row in its own alias group (see :class:`HighState`).

    Example:
        >>> hs = init_high_state(HighLevelConfig(), max_goals=6, state_dim=4)
        >>> hs.q.shape, float(hs.epsilon), bool(hs.exit_known)
        ((6, 6), 1.0, False)
    """
    return HighState(
        q=jnp.zeros((max_goals, max_goals), jnp.float32),
        epsilon=jnp.float32(config.epsilon_start),
        decisions=jnp.int32(0),
        succeeded=jnp.zeros((max_goals, max_goals), bool),
        dist=jnp.full((max_goals,), INF, jnp.float32),
        exit_state=jnp.zeros((state_dim,), jnp.float32),
        exit_known=jnp.asarray(False),
        alias=jnp.arange(max_goals, dtype=jnp.int32) if alias_groups else None,
    )


# ----------------------------------------------------------------------------------------------
# Goal choice
# ----------------------------------------------------------------------------------------------


def valid_goals(n_goals, max_goals: int) -> jax.Array:
    """``[max_goals]`` mask of the slots that hold a goal."""
    return jnp.arange(max_goals) < n_goals


def random_goal(key, n_goals) -> jax.Array:
    """A uniformly random valid goal index."""
    return jax.random.randint(key, (), 0, n_goals).astype(jnp.int32)


def argmax_random_tie(key, values, mask) -> jax.Array:
    """Index of a maximal entry of ``values`` among ``mask``, ties broken uniformly at random.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> v = jnp.array([1.0, 3.0, 3.0, 5.0])
        >>> mask = jnp.array([True, True, True, False])
        >>> int(argmax_random_tie(jax.random.key(0), v, mask)) in (1, 2)
        True
    """
    best = jnp.max(jnp.where(mask, values, -INF))
    ties = mask & (values >= best)
    noise = jax.random.uniform(key, values.shape)
    return jnp.argmax(jnp.where(ties, noise, -1.0)).astype(jnp.int32)


def target_goals(n_goals, max_goals: int, targets=None) -> jax.Array:
    """``[max_goals]``: the valid goals that ``targets`` (a ``[max_goals]`` bool mask, or
    ``None`` for all) allows as targets; all valid goals if it allows none of them."""
    valid = valid_goals(n_goals, max_goals)
    if targets is None:
        return valid
    kept = valid & targets
    return jnp.where(jnp.any(kept), kept, valid)


def q_goal(key, q, current, n_goals, epsilon, tie_break: str = "random",
           exclude_current=False, exclude=None, targets=None) -> jax.Array:
    """Epsilon-greedy goal from ``Q[current]`` over the valid goals (pass ``epsilon=0`` for greedy).

    Greedy ties are broken uniformly at random, or by the lowest index (``tie_break="lowest"``).
    ``targets`` (a ``[max_goals]`` bool mask, may be traced; ``None``: every goal) restricts
    the choice to the goals that may be targets at all (see :func:`target_goals`).
    ``exclude_current`` (a bool, may be traced) removes ``current`` from the choice, greedy and
    random alike (unless it is the only valid goal); ``exclude`` (a ``[max_goals]`` bool mask,
    may be traced) removes those goals likewise, unless it would remove every valid goal.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> q = jnp.zeros((4, 4)).at[1, 2].set(1.0)
        >>> int(q_goal(jax.random.key(0), q, 1, 3, 0.0))
        2
        >>> int(q_goal(jax.random.key(0), q.at[1, 1].set(5.0), 1, 3, 0.0, exclude_current=True))
        2
    """
    k_explore, k_random, k_tie = jax.random.split(key, 3)
    valid = target_goals(n_goals, q.shape[-1], targets)
    others = valid & (jnp.arange(q.shape[-1]) != current)
    valid = jnp.where(exclude_current & jnp.any(others), others, valid)
    if exclude is not None:
        kept = valid & ~exclude
        valid = jnp.where(jnp.any(kept), kept, valid)
    if tie_break == "lowest":
        greedy = jnp.argmax(jnp.where(valid, q[current], -INF)).astype(jnp.int32)
    else:
        greedy = argmax_random_tie(k_tie, q[current], valid)
    explore = jax.random.uniform(k_explore) < epsilon
    random = argmax_random_tie(k_random, jnp.zeros(q.shape[-1]), valid)
    return jnp.where(explore, random, greedy)


def plan_goal(key, dist, succeeded, current, n_goals, epsilon, targets=None) -> jax.Array:
    """The planner's next goal from ``current``: the next hop of a shortest known path to the exit.

    From a goal at distance 0 (it holds the exit) the planner targets that goal itself; with
    probability ``epsilon``, or when ``current`` has no known path, a uniformly random valid
    goal. ``dist`` comes from :func:`relax_distances` / :func:`shortest_distances`.
    ``targets`` restricts next hops and random goals as in :func:`q_goal`.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> succ = jnp.zeros((3, 3), bool).at[0, 1].set(True).at[1, 2].set(True)
        >>> dist = shortest_distances(succ, jnp.array([False, False, True]), 3)
        >>> int(plan_goal(jax.random.key(0), dist, succ, 0, 3, 0.0))
        1
    """
    max_goals = dist.shape[0]
    valid = target_goals(n_goals, max_goals, targets)
    k_explore, k_random, k_tie = jax.random.split(key, 3)
    at_exit = dist[current] == 0.0
    hop_cost = jnp.where(succeeded[current] & valid, dist, INF)
    hop_cost = hop_cost.at[current].set(INF)
    next_hop = argmax_random_tie(k_tie, -hop_cost, valid)
    known = jnp.isfinite(dist[current])
    explore = jax.random.uniform(k_explore) < epsilon
    planned = jnp.where(at_exit, jnp.asarray(current, jnp.int32), next_hop)
    if targets is None:  # unmasked: the draw of every earlier run, bit for bit
        random = random_goal(k_random, n_goals)
    else:
        random = argmax_random_tie(k_random, jnp.zeros(max_goals), valid)
    return jnp.where(explore | ~known, random, planned)


def decay_epsilon(config: HighLevelConfig, epsilon, decided) -> jax.Array:
    """Epsilon after a step: one linear decrement where ``decided`` (a goal was chosen)."""
    decayed = jnp.maximum(config.epsilon_min, epsilon - config.epsilon_decrement)
    return jnp.where(decided, decayed, epsilon)


# ----------------------------------------------------------------------------------------------
# Learning
# ----------------------------------------------------------------------------------------------


def q_update(q, start, target, reward, next_goal, terminated, n_goals, alpha, gamma,
             against=None, targets=None):
    """One tabular Q-learning update of the entry ``Q[start, target]``.

    ``Q[start, target] += alpha * (reward + gamma * (1 - terminated) * max_g Q[next_goal, g]
    - Q[start, against])``, the max over the valid goals that may be targets (``targets``, see
    :func:`target_goals`: what the next decision can choose); ``next_goal`` is the goal holding the
    state where the option ended. ``against`` defaults to ``target`` (ordinary Q-learning);
    the reference takes the difference against the chosen target's entry while writing into
    the reached goal's (SPEC.md section 3.9.3, ``HighLevelConfig.q_update="authors"``).

    Example:
        >>> import jax.numpy as jnp
        >>> q = jnp.zeros((3, 3)).at[2, 1].set(4.0)
        >>> q = q_update(q, 0, 2, 1.0, 2, False, 3, alpha=0.5, gamma=0.5)
        >>> float(q[0, 2])  # 0.5 * (1 + 0.5 * 4 - 0)
        1.5
        >>> float(q_update(q, 0, 1, 1.0, 2, False, 3, 0.5, 0.5, against=2)[0, 1])  # 0.5 * (3 - 1.5)
        0.75
    """
    valid = target_goals(n_goals, q.shape[-1], targets)
    bootstrap = jnp.max(jnp.where(valid, q[next_goal], -INF))
    td_target = reward + gamma * (1.0 - jnp.asarray(terminated, q.dtype)) * bootstrap
    old = q[start, target]
    base = old if against is None else q[start, against]
    return q.at[start, target].set(old + alpha * (td_target - base))


def clean_graph(succeeded, n_goals) -> jax.Array:
    """The planner graph without self-edges and without edges touching unused goal slots."""
    max_goals = succeeded.shape[0]
    valid = valid_goals(n_goals, max_goals)
    return succeeded & valid[:, None] & valid[None, :] & ~jnp.eye(max_goals, dtype=bool)


def relax_distances(dist, succeeded, exit_goals) -> jax.Array:
    """One synchronous Bellman-Ford sweep of the hop counts to the exit goals.

    ``dist'[i] = 0`` for an exit goal, else ``1 + min_j dist[j]`` over the successors ``j`` of
    ``i`` (``inf`` with none). Recomputed from the successors' distances every sweep, so stale
    values from a graph that changed are washed out too. Runs every environment step, so it is
    kept to one fused masked reduction: ``succeeded`` must be clean (:func:`clean_graph`),
    which :func:`learn_from_option` and GARA's split bookkeeping maintain.
    """
    via = jnp.min(jnp.where(succeeded, dist[None, :], INF), axis=1) + 1.0
    return jnp.where(exit_goals, 0.0, via)


def shortest_distances(succeeded, exit_goals, n_goals, sweeps: int | None = None) -> jax.Array:
    """Exact hop counts from every goal to the nearest exit goal (``inf`` if unreachable).

    Self-edges and unused slots (``>= n_goals``) are ignored.

    Example:
        >>> import jax.numpy as jnp
        >>> succ = jnp.zeros((4, 4), bool).at[0, 1].set(True).at[1, 2].set(True)
        >>> shortest_distances(succ, jnp.array([False, False, True, False]), 4).tolist()
        [2.0, 1.0, 0.0, inf]
    """
    max_goals = succeeded.shape[0]
    sweeps = max_goals if sweeps is None else sweeps
    graph = clean_graph(succeeded, n_goals)
    exits = exit_goals & valid_goals(n_goals, max_goals)
    dist = jnp.full((max_goals,), INF, jnp.float32)
    return jax.lax.fori_loop(0, sweeps, lambda _, d: relax_distances(d, graph, exits), dist)


class OptionOutcome(NamedTuple):
    """What the high level learns from at the end of an option (all scalars)."""

    start: jax.Array  # goal index the option started in
    target: jax.Array  # goal index it targeted
    next_goal: jax.Array  # goal index holding the state where it ended
    reward: jax.Array  # environment reward collected during the option
    terminated: jax.Array  # the episode terminated (exit reached) during the option
    reached: jax.Array  # the option entered its target
    exit_state: jax.Array  # [D] the state where it ended (used if the exit reward was obtained)
    blocked: jax.Array  # the pair (start, target) is marked unreachable: never a planner edge


def learn_from_option(config: HighLevelConfig, hs: HighState, outcome: OptionOutcome, n_goals,
                      ended, targets=None) -> HighState:
    """Apply an option's outcome where ``ended`` (else return ``hs`` unchanged, select-style).

    Updates the Q-table (both variants keep it, so the table is there to inspect), the planner
    graph (edge ``start -> target`` when the target was entered, ``start != target``, and the
    pair is not marked unreachable) and the exit state (when the option terminated with a
    positive reward). With ``hs.alias`` set, the updated row is written into every row of its
    alias group. ``targets``: the goals the next decision may choose (see :func:`q_update`).
    """
    column = outcome.target if config.q_target_entry == "target" else outcome.next_goal
    against = outcome.target if config.q_update == "authors" else None
    q = q_update(hs.q, outcome.start, column, outcome.reward, outcome.next_goal,
                 outcome.terminated, n_goals, config.alpha, config.gamma, against, targets)
    if config.q_target_entry == "both":
        # The same TD target (computed from the table before either write) for the target.
        also = q_update(hs.q, outcome.start, outcome.target, outcome.reward, outcome.next_goal,
                        outcome.terminated, n_goals, config.alpha, config.gamma,
                        targets=targets)
        entry = (outcome.start, outcome.target)
        q = q.at[entry].set(jnp.where(outcome.target != outcome.next_goal, also[entry], q[entry]))
    if hs.alias is not None:
        # The rows of an alias group are one row: the start's new row is theirs too.
        group = hs.alias == hs.alias[outcome.start]
        q = jnp.where(group[:, None], q[outcome.start][None, :], q)
    q = jnp.where(ended, q, hs.q)
    edge = ended & outcome.reached & ~outcome.blocked & (outcome.start != outcome.target)
    succeeded = hs.succeeded.at[outcome.start, outcome.target].set(
        hs.succeeded[outcome.start, outcome.target] | edge)
    found_exit = ended & outcome.terminated & (outcome.reward > 0)
    return hs.replace(
        q=q,
        succeeded=succeeded,
        exit_state=jnp.where(found_exit, outcome.exit_state, hs.exit_state),
        exit_known=hs.exit_known | found_exit,
    )
