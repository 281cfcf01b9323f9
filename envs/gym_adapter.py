"""Gymnasium adapter around the JAX maze, and the registration of its ids.

Ids: ``gara_jax/UMaze-v0``, ``gara_jax/FourRooms-v0``, ``gara_jax/UMaze6-v0``,
``gara_jax/BigUMaze-v0``, ``gara_jax/Labyrinth-v0`` and the brax-simulated
``gara_jax/PointUMaze-v0`` (registered when :mod:`envs` or :mod:`gara_jax` is imported; brax is
imported only when the point maze is made).

Episode length: the environment truncates by itself when ``max_steps`` (300 by default, a
constructor keyword) steps have been taken, exactly like the JAX environment, so the ids are
registered without a ``TimeLimit`` wrapper (``spec.max_episode_steps`` is ``None``). Pass
``max_steps=N`` to change it; ``gymnasium.make(..., max_episode_steps=N)`` still works and can
only shorten episodes.

Example:
    >>> import gymnasium, envs
    >>> env = gymnasium.make("gara_jax/UMaze-v0", render_mode="rgb_array")
    >>> obs, info = env.reset(seed=0)
    >>> obs, reward, terminated, truncated, info = env.step(1)
    >>> env.render().shape
    (256, 256, 3)
"""

from __future__ import annotations

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np

from envs.layouts import GYM_IDS
from envs.maze import Maze, make_params, state_from_vector, state_to_vector
from envs.render import render_rgb


class MazeEnv(gymnasium.Env):
    """One maze behind the Gymnasium API; observations are float32 ``(x, y, vx, vy)``.

    Args:
        layout: a name of :data:`envs.LAYOUTS`.
        render_mode: ``None`` or ``"rgb_array"``.
        max_steps: truncation length (default: the layout's 300).
        render_size: side of rendered frames in pixels.

    ``reset(options={"state": (x, y, vx, vy)})`` starts from any state. An action outside
    ``{0, 1, 2, 3}`` raises ``ValueError``. ``set_goal_boxes(lo, hi)`` overlays boxes on frames.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        layout: str = "u_maze",
        render_mode: str | None = None,
        max_steps: int | None = None,
        render_size: int = 256,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, "
                f"got {render_mode!r}"
            )
        overrides = {} if max_steps is None else {"max_steps": max_steps}
        self.layout = layout
        self._maze, self.params = self._make(layout, overrides)
        self.max_steps = int(self.params.max_steps)
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self._device_params = jax.device_put(self.params)
        self._step_fn = jax.jit(self._packed_step)
        self._reset_fn = jax.jit(self._maze.reset)
        n = float(self.params.n)
        self.observation_space = gymnasium.spaces.Box(
            low=np.array([0.0, 0.0, -1.0, -1.0], np.float32),
            high=np.array([n, n, 1.0, 1.0], np.float32),
            dtype=np.float32,
        )
        self.action_space = gymnasium.spaces.Discrete(Maze.num_actions)
        self._key = jax.random.key(0)
        self._state = None
        self._boxes = None

    def _make(self, layout: str, overrides: dict):
        """The JAX environment and its parameters (the point maze overrides this)."""
        return Maze(layout), make_params(layout, **overrides)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        # The maze is deterministic; the key only exists for API symmetry with gymnax.
        self._key = jax.random.key(int(self.np_random.integers(2**31)))
        if options is not None and options.get("state") is not None:
            vector = np.asarray(options["state"], np.float64)
            if vector.shape != (4,) or not self.observation_space.contains(
                vector.astype(np.float32)
            ):
                raise ValueError(
                    f"options['state'] must be (x, y, vx, vy) inside {self.observation_space}, "
                    f"got {options['state']!r}"
                )
            self._state = state_from_vector(vector)
        else:
            _, self._state = self._reset_fn(self._key, self._device_params)
        return self._obs(), {}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(
                f"action must be an integer in [0, {self.action_space.n}), got {action!r}"
            )
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._state, packed = self._step_fn(
            self._key, self._state, np.int32(action), self._device_params
        )
        packed = np.asarray(packed)  # one device-to-host transfer per step
        obs = packed[:4].astype(np.float32)
        reward, terminated, truncated, hit_bound, hit_wall = packed[4:].tolist()
        info = {"hit_bound": bool(hit_bound), "hit_wall": bool(hit_wall)}
        return obs, reward, bool(terminated), bool(truncated), info

    def _packed_step(self, key, state, action, params):
        obs, state, reward, terminated, truncated, info = self._maze.step(
            key, state, action, params
        )
        flags = [reward, terminated, truncated, info["hit_bound"], info["hit_wall"]]
        return state, jnp.concatenate([obs, jnp.stack(flags).astype(obs.dtype)])

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called without a render_mode; pass render_mode='rgb_array' to make()"
            )
            return None
        obs = self._obs() if self._state is not None else np.r_[self.params.start, 0.0, 0.0]
        return render_rgb(
            self.params, obs, boxes=self._boxes, size=self.render_size,
            agent_radius=getattr(self._maze, "ball_radius", None),
        )

    def set_goal_boxes(self, lo, hi) -> None:
        """Overlay goal boxes ``[G, >=2]`` (only x, y are drawn); ``(None, None)`` clears them."""
        if lo is None and hi is None:
            self._boxes = None
            return
        lo, hi = np.atleast_2d(np.asarray(lo, np.float64)), np.atleast_2d(np.asarray(hi))
        if lo.shape != hi.shape or lo.shape[-1] < 2 or lo.ndim != 2:
            raise ValueError(f"lo and hi must both have shape [G, >=2], got {lo.shape}, {hi.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("goal boxes must be finite")
        self._boxes = (lo, hi.astype(np.float64))

    def _obs(self) -> np.ndarray:
        return np.asarray(state_to_vector(self._state), dtype=np.float32)


class PointMazeEnv(MazeEnv):
    """``point_u_maze`` (the brax-simulated U-maze) behind the same Gymnasium API as
    :class:`MazeEnv`; frames draw the ball at its true radius.

    Example:
        >>> import gymnasium, envs
        >>> env = gymnasium.make("gara_jax/PointUMaze-v0", max_steps=50)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, env.unwrapped.max_steps
        ((4,), 50)
    """

    def __init__(
        self, render_mode: str | None = None, max_steps: int | None = None, render_size: int = 256
    ):
        super().__init__("u_maze", render_mode, max_steps, render_size)

    def _make(self, layout: str, overrides: dict):
        from envs.point_maze import make_point_maze

        return make_point_maze(**overrides)


#: Gymnasium ids of the physics mazes, beside :data:`envs.layouts.GYM_IDS`.
PHYSICS_GYM_IDS = {"point_u_maze": "gara_jax/PointUMaze-v0"}


def register_envs() -> None:
    """Register one Gymnasium id per layout, and the point maze's (idempotent)."""
    entries = [(env_id, "MazeEnv", {"layout": layout}) for layout, env_id in GYM_IDS.items()]
    entries += [(env_id, "PointMazeEnv", {}) for env_id in PHYSICS_GYM_IDS.values()]
    for env_id, cls, kwargs in entries:
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point=f"envs.gym_adapter:{cls}",
                kwargs=kwargs,
                max_episode_steps=None,
            )


register_envs()
