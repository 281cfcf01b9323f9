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
    COLLISION_RULES,
    EnvParams,
    EnvState,
    Maze,
    absorbing_states,
    make_params,
    random_rollout,
    state_from_vector,
    state_to_vector,
)

#: Physics-simulated environments :func:`make` accepts beside the kinematic layouts.
PHYSICS_ENVS = ("point_u_maze",)

#: Every name :func:`make` accepts: the kinematic layouts, then the physics mazes.
ENV_NAMES = tuple(LAYOUTS) + PHYSICS_ENVS


#: Environments added by :func:`register`: name -> factory ``(**overrides) -> (env, params)``.
_REGISTERED: dict = {}


def register(name: str, factory) -> None:
    """Make ``make(name)`` (and so every config's ``env=name``) build ``factory(**overrides)``.

    ``factory`` returns ``(env, params)`` of an environment with this package's functional
    interface (``reset``, ``step_autoreset``, ``observation_space``, ``num_actions``; see
    :class:`Maze`) whose observation space is a box. Registering a name again replaces the
    factory; a built-in name cannot be registered (``ValueError``). Registration lives in the
    process: code that trains in another process registers there too.

    Example:
        >>> register("u_maze_short", lambda **o: make("u_maze", **{"max_steps": 50, **o}))
        >>> make("u_maze_short")[1].max_steps
        50
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: must be a non-empty string, got {name!r}")
    if name in ENV_NAMES:
        raise ValueError(f"name: {name!r} is a built-in environment and cannot be registered")
    if not callable(factory):
        raise ValueError(f"factory: must be callable, got {factory!r}")
    _REGISTERED[name] = factory


def names() -> tuple[str, ...]:
    """Every name :func:`make` accepts now: :data:`ENV_NAMES`, then the registered ones."""
    return ENV_NAMES + tuple(_REGISTERED)


def validate_collision(name: str, collision: str) -> None:
    """Raise ``ValueError`` (field ``collision``) unless environment ``name`` has these rules.

    Every environment has the ``"reference"`` rules; the other :data:`COLLISION_RULES` exist
    for the kinematic layouts only.

    Example:
        >>> validate_collision("point_u_maze", "final")
        Traceback (most recent call last):
        ...
        ValueError: collision: 'final' rules exist for the kinematic layouts only, not 'point_u_maze'
    """
    if collision not in COLLISION_RULES:
        raise ValueError(f"collision: must be one of {COLLISION_RULES}, got {collision!r}")
    if collision != "reference" and name not in LAYOUTS:
        raise ValueError(f"collision: {collision!r} rules exist for the kinematic layouts only, "
                         f"not {name!r}")


def make(name: str, collision: str = "reference", **overrides):
    """``(env, params)`` for a name of :func:`names`; keyword overrides replace fields.

    The kinematic layouts of SPEC.md's table give a :class:`Maze`, whose ``collision`` keyword
    (``"reference"``, the default, or ``"final"``; see :class:`Maze`) picks the wall rules;
    ``"point_u_maze"`` gives the brax-simulated :class:`envs.point_maze.PointMaze` (brax is
    imported only then). Raises ``ValueError`` listing the valid names for an unknown name, and
    for a ``collision`` other than ``"reference"`` on an environment that is not a layout.

    Example:
        >>> env, params = make("four_rooms")
        >>> env.num_actions, params.walls.shape
        (4, (4, 4))
        >>> make("u_maze", collision="final")[0]
        Maze('u_maze', collision='final')
    """
    validate_collision(name, collision)
    if name == "point_u_maze":
        from envs.point_maze import make_point_maze

        return make_point_maze(**overrides)
    if name in _REGISTERED:
        return _REGISTERED[name](**overrides)
    if name not in LAYOUTS:
        raise ValueError(f"unknown environment {name!r}; valid names: {', '.join(names())}")
    return Maze(name, collision=collision), make_params(name, **overrides)


from envs import gym_adapter as _gym_adapter  # noqa: E402,F401  (registers the gymnasium ids)

__all__ = [
    "COLLISION_RULES",
    "GYM_IDS",
    "LAYOUTS",
    "ENV_NAMES",
    "PHYSICS_ENVS",
    "EnvParams",
    "EnvState",
    "Maze",
    "absorbing_states",
    "make",
    "names",
    "register",
    "validate_collision",
    "make_params",
    "random_rollout",
    "state_from_vector",
    "state_to_vector",
]
