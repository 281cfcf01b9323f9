"""The U-maze as a rigid-body simulation: a ball on a plane, stepped by brax.

``point_u_maze`` is the U-maze of SPEC.md section 1 (same walls, bounds, start, exit box, reward,
termination and 300-step truncation) with the kinematic rules replaced by physics. The MJCF
model (:func:`maze_mjcf`) has a floor plane, the maze's walls as static boxes, four static
boxes around the bounds, and a ball of radius ``ball_radius`` (0.1) and mass 1 on two slide
joints (x and y), like MuJoCo's point-mass mazes. Each of the 4 discrete actions (0 LEFT,
1 RIGHT, 2 UP, 3 DOWN) applies a force of ``force`` along -x, +x, +y or -y through motors on
the joints for one control interval of ``substeps`` physics steps; linear velocity damping
``damping`` slows the ball down. Contacts are inelastic and frictionless, so the ball stops
against a wall and can slide along it, as in the kinematic maze.

Units are the kinematic maze's: the control interval is one unit of time, so velocities are
displacements per step and ``(x, y, vx, vy)`` means what it means there. The bound boxes are
set back by the ball's radius, so the ball's centre ranges over ``[0, n]^2`` exactly as the
kinematic agent does and SPEC.md section 2's partitions apply unchanged; the maze's walls keep
the centre one radius away from their faces. Velocities are clipped to ``[-1, 1]`` after each
control interval (they stay below ``force / damping`` = 0.29 anyway) and the observation is
the state clipped to the observation space (contacts are soft: a ball pressed against a bound
sits a few thousandths past it).

Calibration. With ``force = 0.1`` (the kinematic maze's 0.1 velocity change per push),
``damping = 0.35`` and 5 substeps, the uniformly random policy reaches the exit from the start
within 300 steps in 8.7% of 20,000 episodes (standard error 0.2, successful episodes last
224 steps on average; the kinematic maze: 8.9% and 206); the sticky random policy of SPEC.md
(repeat with probability 0.7) 44.9% (kinematic: 61.0%);
``damping`` 0.3 gives 15%, 0.4 gives 5%. Measured by the tests' ``random_rollout`` helper.

Pipeline. brax's *positional* pipeline (position-based dynamics): measured on a 2-core CPU,
1024 balls in parallel, it stepped 46,000 control steps per second at 5 substeps with the ball
at most 0.005 past a wall. The *spring* pipeline was faster (67,000 at 10 substeps) but let the
ball 0.04 into walls and its joint springs diverged once velocity damping was on; the
*generalized* pipeline ran 5,000 steps per second and diverged at this time step with the
default contact stiffness; the *mjx* pipeline ran 2,000 and diverged as well.

Example:
    >>> import jax, envs
    >>> env, params = envs.make("point_u_maze")
    >>> obs, state = env.reset(jax.random.key(0), params)
    >>> step = jax.jit(env.step)   # brax's step compiles once; unjitted it runs op by op
    >>> obs, state, reward, terminated, truncated, info = step(
    ...     jax.random.key(1), state, 1, params)
    >>> [round(float(v), 2) for v in obs]
    [0.05, 0.0, 0.08, 0.0]
"""

from __future__ import annotations

import contextlib
import functools
import io
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.layouts import layout_spec
from envs.maze import (
    NUM_ACTIONS,
    EnvState,
    _is_host_value,
    state_from_vector,
    state_to_vector,
    validate_params,
)
from envs.spaces import Box, Discrete

__all__ = [
    "BALL_RADIUS",
    "DAMPING",
    "FORCE",
    "MAX_SPEED",
    "SUBSTEPS",
    "EnvParams",
    "EnvState",
    "PointMaze",
    "maze_mjcf",
    "state_from_vector",
    "state_to_vector",
]

FORCE = 0.1  # push per action, in velocity units per step (ball mass 1)
DAMPING = 0.35  # linear velocity damping rate per unit time (one control interval)
BALL_RADIUS = 0.1
SUBSTEPS = 5  # physics steps per control interval
MAX_SPEED = 1.0
CONTACT_TOLERANCE = 0.01  # a ball this close to a wall or bound counts as touching it
_BOUND_THICKNESS = 0.5
# Unit force directions of LEFT, RIGHT, UP, DOWN.
_DIRECTIONS = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


# ----------------------------------------------------------------------------------------------
# The MJCF model
# ----------------------------------------------------------------------------------------------


def _check_geometry(n, walls, ball_radius, substeps) -> None:
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"n must be finite and > 0, got {n}")
    if not (np.isfinite(ball_radius) and 0 < ball_radius < n / 4):
        raise ValueError(f"ball_radius must be in (0, n/4), got {ball_radius}")
    if isinstance(substeps, bool) or not isinstance(substeps, int | np.integer) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    walls = np.asarray(walls, np.float64)
    if walls.ndim != 2 or walls.shape[1] != 4 or not np.all(np.isfinite(walls)):
        raise ValueError(f"walls must be finite rows [x_lo, x_hi, y_lo, y_hi], got {walls}")
    if np.any(walls[:, 0] >= walls[:, 1]) or np.any(walls[:, 2] >= walls[:, 3]):
        raise ValueError("walls must have x_lo < x_hi and y_lo < y_hi (boxes need a thickness)")


def maze_mjcf(n: float, walls, ball_radius: float = BALL_RADIUS, substeps: int = SUBSTEPS) -> str:
    """The MJCF text of a maze: floor, walls and bounds as static boxes, a ball on slide joints.

    The time step is ``1 / substeps`` (one control interval is one unit of time). Gravity is off
    and the floor does not collide (the joints hold the ball at its height), so the ball only
    touches walls. Walls are twice the ball's height, so contact normals stay horizontal. The
    motors have gear 1 and no control limit: the control is the force itself. Damping and
    force are not in the text; :class:`PointMaze` sets them per call from :class:`EnvParams`.

    Example:
        >>> text = maze_mjcf(3.0, [[1.0, 1.5, -1.0, 2.0]])
        >>> text.count('type="box"'), 'type="slide"' in text
        (5, True)
    """
    _check_geometry(float(n), walls, float(ball_radius), substeps)
    n, r = float(n), float(ball_radius)
    t = _BOUND_THICKNESS
    # The bounds are set back by r so that the ball's centre ranges over [0, n].
    bounds = [
        (-r - t, -r, -t, n + t),
        (n + r, n + r + t, -t, n + t),
        (-t, n + t, -r - t, -r),
        (-t, n + t, n + r, n + r + t),
    ]
    boxes = [
        f'    <geom name="{kind}{i}" type="box" pos="{(a + b) / 2!r} {(c + d) / 2!r} {2 * r!r}" '
        f'size="{(b - a) / 2!r} {(d - c) / 2!r} {2 * r!r}"/>'
        for kind, rows in (("wall", np.asarray(walls, np.float64).tolist()), ("bound", bounds))
        for i, (a, b, c, d) in enumerate(rows)
    ]
    body = "\n".join(boxes)
    return f"""<mujoco model="point_maze">
  <option timestep="{1.0 / substeps!r}" gravity="0 0 0"/>
  <custom>
    <numeric name="elasticity" data="0"/>
  </custom>
  <default>
    <geom contype="1" conaffinity="1" friction="0 0 0"/>
  </default>
  <worldbody>
    <geom name="floor" type="plane" pos="{n / 2!r} {n / 2!r} 0"
          size="{n / 2 + t!r} {n / 2 + t!r} 0.1" contype="0" conaffinity="0"/>
{body}
    <body name="ball" pos="0 0 {r!r}">
      <joint name="ball_x" type="slide" axis="1 0 0"/>
      <joint name="ball_y" type="slide" axis="0 1 0"/>
      <geom name="ball" type="sphere" size="{r!r}" mass="1" contype="2" conaffinity="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="ball_x" gear="1" ctrllimited="false"/>
    <motor joint="ball_y" gear="1" ctrllimited="false"/>
  </actuator>
</mujoco>
"""


def _import_brax():
    # mujoco.mjx prints a notice when its optional warp backend is missing; keep it quiet.
    with contextlib.redirect_stdout(io.StringIO()):
        from brax.io import mjcf
        from brax.positional import pipeline
    return mjcf, pipeline


@functools.lru_cache(maxsize=32)
def _system(n: float, walls: tuple, ball_radius: float, substeps: int, x64: bool):
    """The brax ``System`` of a geometry, built once per geometry and float width."""
    del x64  # part of the cache key only: the System's arrays take the default float dtype
    mjcf, _ = _import_brax()
    # Concrete arrays even when first asked for inside a trace (a cached tracer would leak).
    with warnings.catch_warnings(), jax.ensure_compile_time_eval():
        warnings.simplefilter("ignore", UserWarning)  # brax's "not actively maintained" notice
        return mjcf.loads(maze_mjcf(n, walls, ball_radius, substeps))


# ----------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------

_U_MAZE = layout_spec("u_maze")


def _validate_physics(force, damping) -> None:
    force = np.asarray(force, np.float64)
    if not np.all(np.isfinite(force)) or not np.all(force > 0):
        raise ValueError(f"force must be finite and > 0, got {force}")
    damping = np.asarray(damping, np.float64)
    if not np.all(np.isfinite(damping)) or not np.all(damping >= 0):
        raise ValueError(f"damping must be finite and >= 0, got {damping}")


@struct.dataclass
class EnvParams:
    """Point-maze parameters; the defaults are the U-maze with the calibrated physics.

    Attributes:
        n, walls: the maze ``[0, n]^2`` and its ``[W, 4]`` wall rows, as in
            :class:`envs.maze.EnvParams`. They describe the MJCF model of the environment they
            belong to (observation bounds, rendering, box-based code read them); the physics
            reads the model, so :meth:`PointMaze.check_params` rejects a mismatch.
        start: initial centre of the ball (at rest).
        exit, exit_half_width: the exit is reached when ``|x - ex| < hw`` and ``|y - ey| < hw``.
        exit_reward: reward for reaching the exit (every other step gives 0).
        max_steps: episodes are truncated when ``time`` reaches this.
        force: size of the push of an action (velocity units per step, the ball's mass is 1).
        damping: linear velocity damping rate per step: ``dv/dt = push - damping v``, so a
            held push reaches ``force / damping``.

    All fields are pytree leaves; concrete values are validated when the object is built.

    Example:
        >>> EnvParams().force, EnvParams().damping
        (0.1, 0.35)
        >>> EnvParams(force=-1.0)
        Traceback (most recent call last):
        ...
        ValueError: force must be finite and > 0, got -1.0
    """

    n: float = _U_MAZE["n"]
    walls: jax.Array = struct.field(default_factory=lambda: np.asarray(_U_MAZE["walls"]))
    start: jax.Array = struct.field(default_factory=lambda: np.asarray(_U_MAZE["start"]))
    exit: jax.Array = struct.field(default_factory=lambda: np.asarray(_U_MAZE["exit"]))
    exit_half_width: float = 0.5
    exit_reward: float = 10.0
    max_steps: int = 300
    force: float = FORCE
    damping: float = DAMPING

    def __post_init__(self):
        # As envs.maze.EnvParams: only concrete host values are checked (flax rebuilds the
        # object with tracers and vmap axis specs when it unflattens a pytree).
        values = [getattr(self, f) for f in self.__dataclass_fields__]
        if not all(_is_host_value(v) for v in values):
            return
        for name in ("walls", "start", "exit"):
            value = getattr(self, name)
            if isinstance(value, list | tuple):
                object.__setattr__(self, name, np.asarray(value, dtype=np.float64))
        validate_params(
            self.n, self.walls, self.start, self.exit, self.exit_half_width, self.exit_reward,
            self.max_steps,
        )
        _validate_physics(self.force, self.damping)

    @classmethod
    def create(cls, **fields) -> EnvParams:
        """Validated parameters from any concrete values (lists, NumPy or JAX arrays)."""
        unknown = set(fields) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown EnvParams field(s): {', '.join(sorted(unknown))}")
        host = {k: jax.device_get(v) for k, v in fields.items()}
        for name in ("walls", "start", "exit"):
            if name in host:
                host[name] = np.asarray(host[name], np.float64)
        for name in ("n", "exit_half_width", "exit_reward", "force", "damping"):
            if name in host and np.ndim(host[name]) == 0:
                host[name] = float(host[name])
        if "max_steps" in host and np.ndim(host["max_steps"]) == 0:
            steps = host["max_steps"]
            if np.asarray(steps).dtype.kind not in "iuf" or steps != np.floor(steps):
                raise ValueError(f"max_steps must be an integer, got {steps!r}")
            host["max_steps"] = int(steps)
        return cls(**host)


# ----------------------------------------------------------------------------------------------
# The environment
# ----------------------------------------------------------------------------------------------


def _box_distance(x, y, wall):
    """Distance from ``(x, y)`` to the closed rectangle ``wall`` (negative inside: depth)."""
    dx = jnp.maximum(wall[0] - x, x - wall[1])
    dy = jnp.maximum(wall[2] - y, y - wall[3])
    outside = jnp.sqrt(jnp.maximum(dx, 0.0) ** 2 + jnp.maximum(dy, 0.0) ** 2)
    return jnp.where((dx < 0) & (dy < 0), jnp.maximum(dx, dy), outside)


class PointMaze:
    """A ball in a maze, simulated by brax; the same functional API as :class:`envs.maze.Maze`.

    Args:
        layout: a name of :data:`envs.LAYOUTS` whose walls have a thickness (not
            ``labyrinth``); only ``u_maze`` is calibrated (``envs.make("point_u_maze")``).
        ball_radius: radius of the ball.
        substeps: physics steps per control interval (static: it is a loop length).

    Actions: 0 LEFT, 1 RIGHT, 2 UP, 3 DOWN; out-of-range integers are clipped as in
    :class:`envs.maze.Maze`. The state is :class:`envs.maze.EnvState` (``x, y, vx, vy, time``);
    each step rebuilds brax's pipeline state from it, so states can be stored, compared and
    made with :func:`envs.maze.state_from_vector` as for the kinematic maze. ``key`` arguments
    are accepted for gymnax compatibility; the dynamics are deterministic.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> env = PointMaze()
        >>> params = env.default_params
        >>> keys = jax.random.split(jax.random.key(0), 8)
        >>> obs, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
        >>> step = jax.jit(jax.vmap(env.step_autoreset, in_axes=(0, 0, 0, None)))
        >>> obs, states, r, term, trunc, info = step(keys, states, jnp.ones(8, int), params)
        >>> obs.shape, info["final_obs"].shape
        ((8, 4), (8, 4))
    """

    num_actions = NUM_ACTIONS

    def __init__(
        self, layout: str = "u_maze", ball_radius: float = BALL_RADIUS, substeps: int = SUBSTEPS
    ):
        spec = layout_spec(layout)
        self.layout = layout
        self.n = float(spec["n"])
        self.walls = tuple(tuple(float(v) for v in row) for row in spec["walls"])
        self.ball_radius = float(ball_radius)
        self.substeps = substeps
        try:
            _check_geometry(self.n, self.walls, self.ball_radius, substeps)
        except ValueError as err:
            raise ValueError(f"{err} (layout {layout!r})") from err
        start = np.asarray(spec["start"], np.float64)
        for wall in self.walls:
            if float(_box_distance(start[0], start[1], np.asarray(wall))) < self.ball_radius:
                raise ValueError(
                    f"ball_radius: a ball of radius {ball_radius} at the start {start.tolist()} "
                    f"overlaps the wall {wall}"
                )

    @property
    def name(self) -> str:
        return f"point_{self.layout}"

    def __repr__(self) -> str:
        return (
            f"PointMaze({self.layout!r}, ball_radius={self.ball_radius}, "
            f"substeps={self.substeps})"
        )

    # Value semantics, so that jit caches hit when a PointMaze is a static argument.
    def _key(self):
        return (self.layout, self.ball_radius, self.substeps)

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other._key() == self._key()

    def __hash__(self) -> int:
        return hash((type(self), self._key()))

    @property
    def system(self):
        """The brax ``System`` compiled from :func:`maze_mjcf` (cached per geometry)."""
        x64 = bool(jax.config.jax_enable_x64)
        return _system(self.n, self.walls, self.ball_radius, self.substeps, x64)

    @property
    def default_params(self) -> EnvParams:
        """The layout's start and exit with the calibrated physics."""
        spec = layout_spec(self.layout)
        return EnvParams.create(**spec)

    def check_params(self, params: EnvParams) -> None:
        """Raise ``ValueError`` if ``params`` (concrete) do not describe this model's geometry."""
        if not np.isclose(float(np.asarray(params.n)), self.n):
            raise ValueError(f"n: this model's maze has n={self.n}, params say {params.n}")
        walls = np.asarray(params.walls, np.float64)
        if walls.shape != (len(self.walls), 4) or not np.allclose(walls, self.walls):
            raise ValueError(
                f"walls: this model's walls are {list(self.walls)}, params say {walls.tolist()}; "
                "build a PointMaze of another layout to change them"
            )
        start = np.asarray(params.start, np.float64)
        for wall in self.walls:
            if float(_box_distance(start[0], start[1], np.asarray(wall))) < self.ball_radius:
                raise ValueError(f"start: the ball at {start.tolist()} overlaps the wall {wall}")

    def reset(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """The ball at ``params.start``, at rest, ``time = 0``. Returns ``(obs, state)``."""
        del key
        dtype = jnp.result_type(float)
        start = jnp.asarray(params.start, dtype)
        zero = jnp.zeros((), dtype)
        state = EnvState(x=start[0], y=start[1], vx=zero, vy=zero, time=jnp.zeros((), jnp.int32))
        return self._observe(state, params), state

    def step(self, key: jax.Array, state: EnvState, action, params: EnvParams):
        """One control interval, without auto-reset.

        Returns ``(obs, state, reward, terminated, truncated, info)`` as
        :meth:`envs.maze.Maze.step`: ``terminated`` when the ball's centre is in the exit
        square, ``truncated`` at ``max_steps``. ``info`` holds ``final_obs``, ``discount``,
        ``hit_bound`` and ``hit_wall`` (the ball ends the step within
        ``CONTACT_TOLERANCE`` of a bound or of a wall).
        """
        del key
        next_state = self._simulate(state, action, params)
        x, y, n = next_state.x, next_state.y, jnp.asarray(params.n, next_state.x.dtype)
        tol = CONTACT_TOLERANCE
        hit_bound = (x <= tol) | (x >= n - tol) | (y <= tol) | (y >= n - tol)
        walls = jnp.asarray(params.walls, x.dtype)
        hit_wall = jnp.zeros_like(hit_bound)
        for i in range(walls.shape[0]):
            hit_wall = hit_wall | (_box_distance(x, y, walls[i]) <= self.ball_radius + tol)

        dtype = x.dtype
        exit_ = jnp.asarray(params.exit, dtype)
        half_width = jnp.asarray(params.exit_half_width, dtype)
        terminated = (jnp.abs(x - exit_[0]) < half_width) & (jnp.abs(y - exit_[1]) < half_width)
        truncated = (next_state.time >= params.max_steps) & ~terminated
        reward = jnp.where(terminated, jnp.asarray(params.exit_reward, dtype), 0.0)
        obs = self._observe(next_state, params)
        info = {
            "final_obs": obs,
            "discount": 1.0 - terminated.astype(dtype),
            "hit_bound": hit_bound,
            "hit_wall": hit_wall,
        }
        return obs, next_state, reward, terminated, truncated, info

    def step_autoreset(self, key: jax.Array, state: EnvState, action, params: EnvParams):
        """:meth:`step`, then a reset where the episode ended; ``info["final_obs"]`` is the
        true next observation (see :meth:`envs.maze.Maze.step_autoreset`)."""
        key_step, key_reset = jax.random.split(key)
        _, next_state, reward, terminated, truncated, info = self.step(
            key_step, state, action, params
        )
        _, reset_state = self.reset(key_reset, params)
        done = terminated | truncated
        state = jax.tree.map(lambda r, s: jnp.where(done, r, s), reset_state, next_state)
        return self._observe(state, params), state, reward, terminated, truncated, info

    def _simulate(self, state: EnvState, action, params: EnvParams) -> EnvState:
        """The state after ``substeps`` physics steps pushed by ``action``."""
        _, pipeline = _import_brax()
        dtype = state.x.dtype
        action = jnp.clip(jnp.asarray(action).astype(jnp.int32), 0, NUM_ACTIONS - 1)
        ctrl = jnp.asarray(params.force, dtype) * jnp.asarray(_DIRECTIONS, dtype)[action]
        # The positional pipeline multiplies velocities by exp(vel_damping * dt) twice per
        # physics step (after the force and after the collision update).
        system = self.system.replace(vel_damping=-0.5 * jnp.asarray(params.damping, dtype))
        with warnings.catch_warnings():
            # brax's contact code reads mjx Data fields that mujoco 3.17 marks as deprecated.
            warnings.filterwarnings(
                "ignore", "Accessing .* directly from `Data`", DeprecationWarning
            )
            physics = pipeline.init(
                system, jnp.stack([state.x, state.y]), jnp.stack([state.vx, state.vy])
            )

            def substep(physics, _):
                return pipeline.step(system, physics, ctrl), None

            physics, _ = jax.lax.scan(substep, physics, None, length=self.substeps)
        q, qd = physics.q.astype(dtype), jnp.clip(physics.qd, -MAX_SPEED, MAX_SPEED).astype(dtype)
        return EnvState(x=q[0], y=q[1], vx=qd[0], vy=qd[1], time=state.time + 1)

    def _observe(self, state: EnvState, params: EnvParams) -> jax.Array:
        # Soft contacts leave the centre a few thousandths past a bound; the observation stays
        # inside the observation space.
        obs = state_to_vector(state)
        n = jnp.asarray(params.n, obs.dtype)
        top = jnp.asarray(MAX_SPEED, obs.dtype)
        low = jnp.array([0.0, 0.0, -MAX_SPEED, -MAX_SPEED], obs.dtype)
        return jnp.clip(obs, low, jnp.stack([n, n, top, top]))

    def observation_space(self, params: EnvParams) -> Box:
        """``(x, y, vx, vy)`` in ``[0, n]^2 x [-1, 1]^2``."""
        n = jnp.asarray(params.n, jnp.result_type(float))
        return Box(
            low=jnp.array([0.0, 0.0, -MAX_SPEED, -MAX_SPEED]),
            high=jnp.stack([n, n, jnp.asarray(MAX_SPEED), jnp.asarray(MAX_SPEED)]).astype(n.dtype),
            shape=(4,),
        )

    def action_space(self, params: EnvParams | None = None) -> Discrete:
        """``Discrete(4)``: LEFT, RIGHT, UP, DOWN."""
        del params
        return Discrete(NUM_ACTIONS)


def make_point_maze(**overrides) -> tuple[PointMaze, EnvParams]:
    """``(env, params)`` of ``point_u_maze``; keyword overrides replace :class:`EnvParams` fields.

    The geometry (``n``, ``walls``) is the model's and cannot be overridden here.

    Example:
        >>> env, params = make_point_maze(max_steps=100)
        >>> env.name, params.max_steps
        ('point_u_maze', 100)
    """
    for name in ("n", "walls"):
        if name in overrides:
            raise ValueError(
                f"{name}: the point maze's geometry is compiled into its MJCF model; "
                "build PointMaze(layout=...) for another maze"
            )
    env = PointMaze("u_maze")
    spec = layout_spec("u_maze")
    spec.update(overrides)
    params = EnvParams.create(**spec)
    env.check_params(params)
    return env, params
