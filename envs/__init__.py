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

#: Physics-simulated environments :func:`make` accepts beside the kinematic layouts.
PHYSICS_ENVS = ("point_u_maze",)

#: Every name :func:`make` accepts: the kinematic layouts, then the physics mazes.
ENV_NAMES = tuple(LAYOUTS) + PHYSICS_ENVS


def make(name: str, **overrides):
    """``(env, params)`` for a name of :data:`ENV_NAMES`; keyword overrides replace fields.

    The kinematic layouts of SPEC.md's table give a :class:`Maze`; ``"point_u_maze"`` gives
    the brax-simulated :class:`envs.point_maze.PointMaze` (brax is imported only then). Raises
    ``ValueError`` listing the valid names for an unknown name.

    Example:
        >>> env, params = make("four_rooms")
        >>> env.num_actions, params.walls.shape
        (4, (4, 4))
    """
    if name == "point_u_maze":
        from envs.point_maze import make_point_maze

        return make_point_maze(**overrides)
    if name not in LAYOUTS:
        raise ValueError(f"unknown environment {name!r}; valid names: {', '.join(ENV_NAMES)}")
    params = make_params(name, **overrides)
    return Maze(name), params


from envs import gym_adapter as _gym_adapter  # noqa: E402,F401  (registers the gymnasium ids)

__all__ = [
    "GYM_IDS",
    "LAYOUTS",
    "ENV_NAMES",
    "PHYSICS_ENVS",
    "EnvParams",
    "EnvState",
    "Maze",
    "make",
    "make_params",
    "random_rollout",
    "state_from_vector",
    "state_to_vector",
]
