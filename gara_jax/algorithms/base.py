"""The contract every training algorithm (GARA, Handcrafted, HIRO) implements.

CONTRACT (agreed between the engineers building GARA/Handcrafted and HIRO; keep it):

- ``init(key) -> AgentState``: one seed's whole state (a pytree; vmappable).
- ``train_epoch(state, key) -> (state, metrics)``: ``config.steps_per_epoch`` environment steps as
  one ``lax.scan``; jit- and vmap-able. ``metrics`` is a dict of per-seed scalars with at least
  ``env_steps`` (cumulative env steps after this epoch, int32), ``train_success`` (fraction of the
  episodes that ENDED in this epoch that reached the exit; 0 if none ended), ``episodes_ended``,
  ``episode_return`` (mean env return of the episodes ended this epoch; 0 if none) and ``n_goals``
  (goals in the partition; 0 for HIRO). It may also hold ``episode_log``, a dict of per-step
  ``[steps_per_epoch]`` arrays (``ended``, ``success``, ``length``, ``end_step``) from which the
  driver extracts every training episode (:func:`epoch_metrics` builds both).
- ``evaluate(state, key) -> {"eval_success": f32, "eval_return": f32}``: greedy policies,
  ``config.eval_episodes`` episodes from the start, vmapped inside; jit- and vmap-able.
- ``host_update(states, epoch) -> (states, info)``: optional host step between epochs, on the
  states batched over seeds (GARA's refinement); ``None`` for algorithms without one.
- ``greedy_rollout(state, key) -> dict``: optional, one evaluation episode step by step (for
  diagnostics; GARA and Handcrafted have it).
- ``train_segment(state, key, epoch) -> (state, segment)`` and ``state_metrics(state) ->
  dict``: optional (GARA), what the driver runs for ``cadence="episode"``: the steps of epoch
  ``epoch`` up to the end of the seed's current episode or of the epoch (``key``: the epoch's
  training key, as ``train_epoch`` gets it), and the per-seed metrics that ``train_epoch``
  reads off the state (``n_goals``, the epsilons); :func:`gara_jax.train.train_epochs`
  assembles the contract's epoch metrics from the segments.

Every config is a frozen dataclass with SPEC.md defaults, validated in ``__post_init__``
(``ValueError`` naming the field), JSON-serialisable via ``dataclasses.asdict``, with at least
``env: str = "u_maze"``, ``k: int = 5``, ``steps_per_epoch: int = 3000``,
``eval_episodes: int = 10`` and ``low: DQNConfig = DQNConfig()``.
``gara_jax.algorithms.make_algorithm(config) -> Algorithm`` dispatches on the config's type.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp


class Algorithm(NamedTuple):
    name: str  # "gara", "gara_planning", "handcrafted", "hiro"
    config: Any
    init: Callable
    train_epoch: Callable
    evaluate: Callable
    host_update: Callable | None = None
    greedy_rollout: Callable | None = None
    train_segment: Callable | None = None
    state_metrics: Callable | None = None


def epoch_metrics(stats, env_steps) -> dict:
    """The contract's per-episode metrics of an epoch, and its ``episode_log``.

    ``stats`` holds per-step arrays (the ``lax.scan`` outputs): ``episode_ended`` and
    ``episode_success`` (bools), ``episode_length``, ``episode_return`` and
    ``episode_end_step`` (the value at the step where an episode ended; ignored elsewhere).

    Example:
        >>> import jax.numpy as jnp
        >>> stats = dict(episode_ended=jnp.array([False, True, True]),
        ...              episode_success=jnp.array([False, True, False]),
        ...              episode_length=jnp.array([1, 2, 1]),
        ...              episode_return=jnp.array([0.0, 10.0, 0.0]),
        ...              episode_end_step=jnp.array([1, 2, 3]))
        >>> m = epoch_metrics(stats, jnp.int32(3))
        >>> float(m["train_success"]), int(m["episodes_ended"]), float(m["episode_return"])
        (0.5, 2, 5.0)
    """
    ended = stats["episode_ended"]
    n = jnp.sum(ended.astype(jnp.int32))
    mean = lambda v: jnp.where(n > 0, jnp.sum(jnp.where(ended, v, 0)) / jnp.maximum(n, 1), 0.0)
    return {
        "env_steps": env_steps,
        "train_success": mean(stats["episode_success"].astype(jnp.float32)),
        "episodes_ended": n,
        "episode_return": mean(stats["episode_return"]),
        "episode_log": {
            "ended": ended,
            "success": stats["episode_success"] & ended,
            "length": jnp.where(ended, stats["episode_length"], 0).astype(jnp.int32),
            "end_step": jnp.where(ended, stats["episode_end_step"], 0).astype(jnp.int32),
        },
    }
