"""The contract every training algorithm (GARA, Handcrafted, HIRO) implements.

CONTRACT (agreed between the engineers building GARA/Handcrafted and HIRO; keep it):

- ``init(key) -> AgentState``: one seed's whole state (a pytree; vmappable).
- ``train_epoch(state, key) -> (state, metrics)``: ``config.steps_per_epoch`` environment steps as
  one ``lax.scan``; jit- and vmap-able. ``metrics`` is a dict of per-seed scalars with at least
  ``env_steps`` (cumulative env steps after this epoch, int32), ``train_success`` (fraction of the
  episodes that ENDED in this epoch that reached the exit; 0 if none ended), ``episodes_ended``,
  ``episode_return`` (mean env return of the episodes ended this epoch; 0 if none) and ``n_goals``
  (goals in the partition; 0 for HIRO).
- ``evaluate(state, key) -> {"eval_success": f32, "eval_return": f32}``: greedy policies,
  ``config.eval_episodes`` episodes from the start, vmapped inside; jit- and vmap-able.
- ``host_update(states, epoch) -> (states, info)``: optional host step between epochs, on the
  states batched over seeds (GARA's refinement); ``None`` for algorithms without one.

Every config is a frozen dataclass with SPEC.md defaults, validated in ``__post_init__``
(``ValueError`` naming the field), JSON-serialisable via ``dataclasses.asdict``, with at least
``env: str = "u_maze"``, ``k: int = 5``, ``steps_per_epoch: int = 3000``,
``eval_episodes: int = 10`` and ``low: DQNConfig = DQNConfig()``.
``gara_jax.algorithms.make_algorithm(config) -> Algorithm`` dispatches on the config's type.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple


class Algorithm(NamedTuple):
    name: str  # "gara", "gara_planning", "handcrafted", "hiro"
    config: Any
    init: Callable
    train_epoch: Callable
    evaluate: Callable
    host_update: Callable | None = None
