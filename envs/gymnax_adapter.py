"""The mazes as gymnax ``Environment`` s, so that gymnax's wrappers and PureJaxRL-style code run on
them unchanged (needs the ``gymnax`` extra: ``pip install -e ".[gymnax]"``).

:class:`GymnaxMaze` subclasses ``gymnax.environments.environment.Environment`` around any of
this package's environments (the kinematic :class:`envs.maze.Maze` or the brax
:class:`envs.point_maze.PointMaze`). Its ``step`` is the wrapped environment's
``step_autoreset`` with gymnax's info keys added (``terminated``, ``truncated``,
``final_observation``), so the dynamics, the 300-step truncation and the auto-reset are exactly
the wrapped environment's; ``step_env``/``reset_env`` are the non-resetting pieces gymnax's base
class defines, and the spaces are gymnax's own ``Discrete``/``Box``.

Example:
    >>> import jax
    >>> from gymnax.wrappers.purerl import LogWrapper
    >>> env, params = make_gymnax("u_maze")
    >>> env = LogWrapper(env)
    >>> obs, state = env.reset(jax.random.key(0), params)
    >>> obs, state, reward, terminated, truncated, info = env.step(
    ...     jax.random.key(1), state, 1, params)
    >>> sorted(k for k in info if k.startswith("returned_episode"))
    ['returned_episode', 'returned_episode_lengths', 'returned_episode_returns', \
'returned_episode_valid']
"""

from __future__ import annotations

import jax.numpy as jnp
from gymnax.environments import environment, spaces

import envs


class GymnaxMaze(environment.Environment):
    """A gymnax ``Environment`` that runs one of this package's environments.

    Args:
        env: a :class:`envs.maze.Maze` or :class:`envs.point_maze.PointMaze`.
        params: its default parameters (``env.default_params`` when omitted); ``step`` and
            ``reset`` use them when called with ``params=None``, as gymnax's do.

    The state and parameter types are the wrapped environment's. gymnax's wrappers jit with
    ``self`` static, so adapters hash by the wrapped environment and compare equal when they
    wrap equal environments with the same default-parameters object.
    """

    def __init__(self, env, params=None):
        self._env = env
        self._params = env.default_params if params is None else params

    def __eq__(self, other) -> bool:
        return (
            type(other) is type(self)
            and other._env == self._env
            and other._params is self._params
        )

    def __hash__(self) -> int:
        return hash((type(self), self._env))

    def __repr__(self) -> str:
        return f"GymnaxMaze({self._env!r})"

    @property
    def wrapped(self):
        """The wrapped environment."""
        return self._env

    @property
    def default_params(self):
        return self._params

    def step(self, key, state, action, params=None):
        """One step with auto-reset: ``(obs, state, reward, terminated, truncated, info)``."""
        params = self._params if params is None else params
        obs, state, reward, terminated, truncated, info = self._env.step_autoreset(
            key, state, action, params
        )
        info = {
            **info,
            "terminated": terminated,
            "truncated": truncated,
            "final_observation": info["final_obs"],
        }
        return obs, state, reward, terminated, truncated, info

    def reset(self, key, params=None):
        """``(obs, state)`` at the start of an episode."""
        return self._env.reset(key, self._params if params is None else params)

    def step_env(self, key, state, action, params):
        obs, state, reward, terminated, _, info = self._env.step(key, state, action, params)
        return obs, state, reward, terminated, info

    def reset_env(self, key, params):
        return self._env.reset(key, params)

    def observe(self, key, state, action, params):
        del key, action
        return envs.state_to_vector(state)

    def is_terminated(self, state, params):
        exit_ = jnp.asarray(params.exit, state.x.dtype)
        hw = jnp.asarray(params.exit_half_width, state.x.dtype)
        return (jnp.abs(state.x - exit_[0]) < hw) & (jnp.abs(state.y - exit_[1]) < hw)

    def is_truncated(self, state, params):
        return (state.time >= params.max_steps) & ~self.is_terminated(state, params)

    @property
    def name(self) -> str:
        return self._env.name

    @property
    def num_actions(self) -> int:
        return self._env.num_actions

    def action_space(self, params=None) -> spaces.Discrete:
        return spaces.Discrete(self._env.num_actions)

    def observation_space(self, params) -> spaces.Box:
        space = self._env.observation_space(params)
        return spaces.Box(space.low, space.high, space.shape, space.dtype)

    def state_space(self, params) -> spaces.Dict:
        space = self._env.observation_space(params)
        low, high = space.low, space.high
        return spaces.Dict(
            {
                "x": spaces.Box(low[0], high[0], (), space.dtype),
                "y": spaces.Box(low[1], high[1], (), space.dtype),
                "vx": spaces.Box(low[2], high[2], (), space.dtype),
                "vy": spaces.Box(low[3], high[3], (), space.dtype),
                "time": spaces.Discrete(int(params.max_steps) + 1),
            }
        )


def make_gymnax(name: str, **overrides) -> tuple[GymnaxMaze, object]:
    """``(gymnax_env, params)`` for a name of :data:`envs.ENV_NAMES` (overrides as
    :func:`envs.make`).

    Example:
        >>> env, params = make_gymnax("point_u_maze")
        >>> env.name, env.num_actions
        ('point_u_maze', 4)
    """
    env, params = envs.make(name, **overrides)
    return GymnaxMaze(env, params), params

