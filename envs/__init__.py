"""Pure-functional JAX maze environments (gymnax style) and their Gymnasium adapter.

Example:
    >>> import jax, envs
    >>> env, params = envs.make("u_maze")
    >>> obs, state = env.reset(jax.random.key(0), params)
    >>> obs.tolist()
    [0.0, 0.0, 0.0, 0.0]

Importing this package registers the Gymnasium ids (``gara_jax/UMaze-v0`` and friends).
"""

from envs.layouts import GYM_IDS, LAYOUTS
from envs.maze import (
    EnvParams,
    EnvState,
    Maze,
    make_params,
    random_rollout,
    state_from_vector,
    state_to_vector,
)


#: Every name :func:`make` accepts (the kinematic layouts; other simulators add theirs).
ENV_NAMES = tuple(LAYOUTS)


def make(name: str, **overrides) -> tuple[Maze, EnvParams]:
    """``(env, params)`` for a layout of SPEC.md's table; keyword overrides replace fields.

    Raises ``ValueError`` listing the valid names for an unknown layout.

    Example:
        >>> env, params = make("four_rooms")
        >>> env.num_actions, params.walls.shape
        (4, (4, 4))
    """
    params = make_params(name, **overrides)
    return Maze(name), params


from envs import gym_adapter as _gym_adapter  # noqa: E402,F401  (registers the gymnasium ids)

__all__ = [
    "GYM_IDS",
    "LAYOUTS",
    "ENV_NAMES",
    "EnvParams",
    "EnvState",
    "Maze",
    "make",
    "make_params",
    "random_rollout",
    "state_from_vector",
    "state_to_vector",
]
