"""The GARA point-mass maze as a pure-functional JAX environment (gymnax 1.0 style).

The dynamics follow SPEC.md section 1 exactly, including the reference's quirks (the damping
asymmetry for small negative velocities, "bounds first, then walls in list order", and agents
stuck on a wall face); ``Maze(name, collision="final")`` has the authors' final collision
rules instead (SPEC.md's documented alternative). Everything here works under ``jit``,
``vmap`` and ``lax.scan``; the computation runs in the default float dtype (float32, or
float64 under ``jax_enable_x64``).

Example:
    >>> import jax, envs
    >>> env, params = envs.make("u_maze")
    >>> obs, state = env.reset(jax.random.key(0), params)
    >>> obs, state, reward, terminated, truncated, info = env.step(
    ...     jax.random.key(1), state, 1, params)
    >>> [round(float(v), 3) for v in obs]
    [0.1, 0.0, 0.1, 0.0]
"""

from __future__ import annotations

import numbers

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.layouts import LAYOUT_SPECS
from envs.spaces import Box, Discrete

LEFT, RIGHT, UP, DOWN = 0, 1, 2, 3
NUM_ACTIONS = 4
ACCELERATION = 0.1  # velocity change of the pushed component per step
DAMPING = 0.05  # decay of the other component per step
MAX_SPEED = 1.0

_U_MAZE = LAYOUT_SPECS["u_maze"]

#: Collision rules a :class:`Maze` offers. ``"reference"`` (the default): SPEC.md section 1
#: steps 3-5, the rules of the code that made the authors' result files and the golden data.
#: ``"final"``: the authors' final maze code's rules, SPEC.md's documented alternative (walls
#: checked after a bound clamp too, a contact only at ``t = 0`` lets the agent leave a face,
#: the wall entered first is the one hit).
COLLISION_RULES = ("reference", "final")


def _default_float():
    """float32, or float64 under x64 (resolved at trace time)."""
    return jnp.result_type(float)


# ----------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------


def _is_host_value(x) -> bool:
    return isinstance(x, numbers.Number | np.ndarray | np.generic | list | tuple)


def validate_params(n, walls, start, exit, exit_half_width, exit_reward, max_steps) -> None:
    """Raise ``ValueError`` naming the first invalid field. Host-side, on concrete values.

    Leading batch dimensions are allowed (a stack of parameter sets is checked elementwise).
    """
    n = np.asarray(n, dtype=np.float64)
    if not np.all(np.isfinite(n)) or not np.all(n > 0):
        raise ValueError(f"n must be finite and > 0, got {n}")
    walls = np.asarray(walls, dtype=np.float64)
    if walls.ndim < 2 or walls.shape[-1] != 4:
        raise ValueError(
            f"walls must have shape [W, 4] (rows x_lo, x_hi, y_lo, y_hi), got {walls.shape}"
        )
    if not np.all(np.isfinite(walls)):
        raise ValueError("walls must be finite")
    if np.any(walls[..., 0] > walls[..., 1]) or np.any(walls[..., 2] > walls[..., 3]):
        raise ValueError("walls rows must satisfy x_lo <= x_hi and y_lo <= y_hi")
    n_point = n[..., None]  # broadcasts against a trailing (x, y) axis
    for name, point in (("start", start), ("exit", exit)):
        point = np.asarray(point, dtype=np.float64)
        if point.ndim < 1 or point.shape[-1] != 2:
            raise ValueError(f"{name} must have shape [2] (x, y), got {point.shape}")
        if not np.all(np.isfinite(point)):
            raise ValueError(f"{name} must be finite, got {point}")
        if np.any(point < 0) or np.any(point > n_point):
            raise ValueError(f"{name} must lie inside the maze [0, n]^2, got {point} with n={n}")
    start = np.asarray(start, dtype=np.float64)[..., None, :]  # [..., 1, 2] against [..., W, 2]
    lo, hi = walls[..., [0, 2]], walls[..., [1, 3]]
    if np.any(np.all((lo < start) & (start < hi), axis=-1)):
        raise ValueError(f"start must not lie strictly inside a wall, got {start[..., 0, :]}")
    hw = np.asarray(exit_half_width, dtype=np.float64)
    if not np.all(np.isfinite(hw)) or not np.all(hw > 0):
        raise ValueError(f"exit_half_width must be finite and > 0, got {hw}")
    if not np.all(np.isfinite(np.asarray(exit_reward, dtype=np.float64))):
        raise ValueError(f"exit_reward must be finite, got {exit_reward}")
    steps = np.asarray(max_steps)
    if steps.dtype.kind not in "iuf" or not np.all(steps == np.floor(steps)):
        raise ValueError(f"max_steps must be an integer, got {max_steps!r}")
    if not np.all(steps >= 1):
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")


@struct.dataclass
class EnvParams:
    """Maze parameters; the defaults are the paper's U-maze.

    Attributes:
        n: the maze is ``[0, n]^2``.
        walls: ``[W, 4]`` closed rectangles ``[x_lo, x_hi, y_lo, y_hi]``, checked in this order.
        start: initial position (the agent starts at rest).
        exit: centre of the exit square.
        exit_half_width: the exit is reached when ``|x - ex| < hw`` and ``|y - ey| < hw``.
        exit_reward: reward for reaching the exit (every other step gives 0).
        max_steps: episodes are truncated when ``time`` reaches this.

    All fields are pytree leaves, so one jitted function serves every layout with the same
    number of walls. Concrete host values (Python numbers, lists, NumPy arrays) are validated
    when the object is built; build from JAX arrays through :meth:`create`, which validates too.
    Under ``jit``/``vmap`` (tracers inside) nothing is checked.

    Example:
        >>> p = EnvParams.create(n=3.0, walls=[[1, 1.5, -1, 2]], start=[0, 0], exit=[3, 0])
        >>> p.walls.shape
        (1, 4)
        >>> EnvParams.create(n=-1.0)
        Traceback (most recent call last):
        ...
        ValueError: n must be finite and > 0, got -1.0
    """

    n: float = _U_MAZE["n"]
    walls: jax.Array = struct.field(default_factory=lambda: np.asarray(_U_MAZE["walls"]))
    start: jax.Array = struct.field(default_factory=lambda: np.asarray(_U_MAZE["start"]))
    exit: jax.Array = struct.field(default_factory=lambda: np.asarray(_U_MAZE["exit"]))
    exit_half_width: float = 0.5
    exit_reward: float = 10.0
    max_steps: int = 300

    def __post_init__(self):
        # flax rebuilds this object with tracers, None or vmap axis specs when it unflattens a
        # pytree; only validate (and normalise lists) when every field is a concrete host value.
        values = [getattr(self, f) for f in self.__dataclass_fields__]
        if not all(_is_host_value(v) for v in values):
            return
        if not all(
            isinstance(v, np.ndarray | list | tuple) for v in (self.walls, self.start, self.exit)
        ):
            return
        for name in ("walls", "start", "exit"):
            value = getattr(self, name)
            if isinstance(value, list | tuple):
                object.__setattr__(self, name, np.asarray(value, dtype=np.float64))
        validate_params(*(getattr(self, f) for f in self.__dataclass_fields__))

    @classmethod
    def create(
        cls,
        n=_U_MAZE["n"],
        walls=_U_MAZE["walls"],
        start=_U_MAZE["start"],
        exit=_U_MAZE["exit"],
        exit_half_width=0.5,
        exit_reward=10.0,
        max_steps=300,
    ) -> EnvParams:
        """Validated parameters from any concrete values (lists, NumPy or JAX arrays).

        Arrays are stored as float64 NumPy arrays, so they take the default float dtype when
        they enter a jitted function (float32, or float64 under x64).
        """
        host = jax.device_get((n, walls, start, exit, exit_half_width, exit_reward, max_steps))
        try:
            validate_params(*host)
        except jax.errors.TracerArrayConversionError as err:
            raise ValueError("EnvParams.create needs concrete values, not traced ones") from err
        n, walls, start, exit, exit_half_width, exit_reward, max_steps = host
        walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        return cls(
            n=float(n),
            walls=walls,
            start=np.asarray(start, dtype=np.float64),
            exit=np.asarray(exit, dtype=np.float64),
            exit_half_width=float(exit_half_width),
            exit_reward=float(exit_reward),
            max_steps=int(max_steps),
        )


def make_params(name: str = "u_maze", **overrides) -> EnvParams:
    """Validated :class:`EnvParams` of a named layout, with optional field overrides.

    Example:
        >>> make_params("u_maze_6", max_steps=100).n
        6.0
    """
    from envs.layouts import layout_spec

    spec = layout_spec(name)
    spec.update(overrides)
    return EnvParams.create(**spec)


# ----------------------------------------------------------------------------------------------
# State
# ----------------------------------------------------------------------------------------------


@struct.dataclass
class EnvState:
    """The maze state, one array per coordinate: ``x, y, vx, vy`` and the step counter ``time``.

    Each field has the environment's batch shape (a scalar for one environment, ``[B]`` under
    ``vmap``). Keeping the coordinates apart, rather than in ``[..., 2]`` position/velocity
    arrays, lets XLA vectorise the batched step over the batch axis (see
    ``benchmarks/env_throughput.py``). ``pos`` and ``vel`` are read-only ``[..., 2]`` views
    kept for compatibility; build states with :func:`state_from_vector` or :meth:`create`.

    Example:
        >>> state = EnvState.create(pos=[1.0, 2.0], vel=[0.5, 0.0])
        >>> state.pos.tolist(), state.vel.tolist(), int(state.time)
        ([1.0, 2.0], [0.5, 0.0], 0)
    """

    x: jax.Array
    y: jax.Array
    vx: jax.Array
    vy: jax.Array
    time: jax.Array

    @property
    def pos(self) -> jax.Array:
        """Position ``(x, y)``, shape ``[..., 2]``."""
        return jnp.stack([self.x, self.y], axis=-1)

    @property
    def vel(self) -> jax.Array:
        """Velocity ``(vx, vy)``, shape ``[..., 2]``."""
        return jnp.stack([self.vx, self.vy], axis=-1)

    @classmethod
    def create(cls, pos, vel, time=0) -> EnvState:
        """A state from ``[..., 2]`` position and velocity arrays (``time`` broadcast, int32)."""
        pos, vel = _as_float(pos), _as_float(vel)
        if pos.shape[-1:] != (2,) or vel.shape[-1:] != (2,):
            raise ValueError(
                f"pos and vel must have a trailing axis of size 2, got {pos.shape} and {vel.shape}"
            )
        batch = jnp.broadcast_shapes(pos.shape[:-1], vel.shape[:-1])
        return cls(
            x=jnp.broadcast_to(pos[..., 0], batch),
            y=jnp.broadcast_to(pos[..., 1], batch),
            vx=jnp.broadcast_to(vel[..., 0], batch),
            vy=jnp.broadcast_to(vel[..., 1], batch),
            time=jnp.broadcast_to(jnp.asarray(time, jnp.int32), batch),
        )


def _as_float(a) -> jax.Array:
    """``a`` as a JAX array; floating dtypes are kept, others become the default float."""
    a = jnp.asarray(a)
    return a if jnp.issubdtype(a.dtype, jnp.floating) else a.astype(_default_float())


def state_from_vector(s) -> EnvState:
    """An :class:`EnvState` at ``time = 0`` from an ``(x, y, vx, vy)`` vector.

    Leading batch dimensions are kept. Floating inputs keep their dtype (within what JAX
    allows); integer inputs become the default float dtype.

    Example:
        >>> state_from_vector([1.0, 2.0, 0.5, 0.0]).pos.tolist()
        [1.0, 2.0]
    """
    s = _as_float(s)
    if s.shape[-1:] != (4,):
        raise ValueError(f"state vector must have a trailing axis of size 4, got {s.shape}")
    return EnvState(
        x=s[..., 0],
        y=s[..., 1],
        vx=s[..., 2],
        vy=s[..., 3],
        time=jnp.zeros(s.shape[:-1], jnp.int32),
    )


def state_to_vector(state: EnvState) -> jax.Array:
    """The observation ``(x, y, vx, vy)`` of a state (leading batch dimensions kept).

    Example:
        >>> state_to_vector(state_from_vector([1.0, 2.0, 0.5, 0.0])).tolist()
        [1.0, 2.0, 0.5, 0.0]
    """
    return jnp.stack([state.x, state.y, state.vx, state.vy], axis=-1)


# ----------------------------------------------------------------------------------------------
# Dynamics, one coordinate at a time
# ----------------------------------------------------------------------------------------------


def _damp(v: jax.Array) -> jax.Array:
    # The reference's rule, asymmetry included: v in (-0.05, 0) becomes v + 0.05 > 0.
    positive = jnp.maximum(0.0, v - DAMPING)
    negative = jnp.maximum(0.0, v + DAMPING)
    return jnp.where(v > 0, positive, jnp.where(v < 0, negative, jnp.zeros_like(v)))


def _accelerate(vx: jax.Array, vy: jax.Array, action: jax.Array):
    """New ``(vx, vy)``: push one component, damp the other (SPEC step 1)."""
    horizontal = action <= RIGHT
    increase = (action == RIGHT) | (action == UP)

    def push(v):
        return jnp.where(
            increase,
            jnp.minimum(MAX_SPEED, v + ACCELERATION),
            jnp.maximum(-MAX_SPEED, v - ACCELERATION),
        )

    new_vx = jnp.where(horizontal, push(vx), _damp(vx))
    new_vy = jnp.where(horizontal, _damp(vy), push(vy))
    return new_vx, new_vy


def _axis_times(p, v, lo, hi):
    """Entry and exit ``t`` of ``p + v t`` in ``[lo, hi]`` along one axis (SPEC step 4).

    ``v > 0``: ``[(lo - p)/v, (hi - p)/v]``; ``v < 0``: ``[(hi - p)/v, (lo - p)/v]`` (the
    reference's own divisions, so that float64 reproduces it bit for bit); ``v = 0``: every
    ``t`` when ``p`` is strictly inside ``(lo, hi)``, else none. Returns
    ``((entry numerator, denominator), (t_in, t_out))``.
    """
    moving, forward = v != 0, v > 0
    safe_v = jnp.where(moving, v, jnp.ones_like(v))
    num_in = jnp.where(forward, lo, hi) - p
    t_in = num_in / safe_v
    t_out = (jnp.where(forward, hi, lo) - p) / safe_v
    inside = (lo < p) & (p < hi)
    t_in = jnp.where(moving, t_in, jnp.where(inside, -jnp.inf, jnp.inf))
    t_out = jnp.where(moving, t_out, jnp.inf)
    return (num_in, safe_v), (t_in, t_out)


# What a step did, as one number per environment (see :func:`_stop_code`): a value t* in
# [0, 1] means stopped by a wall at p + v t*.
_FREE = 2.0  # no collision: move the whole way, keep the velocity
_HIT_BOUND = 3.0  # left the maze: clamp to the bounds, stop


def _stop_code(x, y, vx, vy, params: EnvParams) -> jax.Array:
    """How the move with the (already updated) velocity ends, as one number per environment.

    Bounds first: ``_HIT_BOUND`` if ``p + v`` leaves ``[0, n]^2``; otherwise ``t*`` of the
    first wall in list order whose time interval meets ``[0, 1]`` (SPEC 3-5); otherwise
    ``_FREE``.

    The result is returned as one final division ``numerator / denominator`` (the winning
    ``(face - p) / v``, or ``code / 1``), which is bit-identical to ``t*`` and makes XLA keep
    the code in one buffer: it does not duplicate a division into several consumers, whereas
    cheap elementwise work is recomputed inside every consumer's loop. Every output of a step
    depends on this code, so without the final division XLA's CPU backend recomputes the whole
    collision test once per output (about 3x slower).
    """
    dtype = x.dtype
    n = jnp.asarray(params.n, dtype)
    cx, cy = x + vx, y + vy
    hit_bound = (cx < 0) | (cx > n) | (cy < 0) | (cy > n)
    walls = jnp.asarray(params.walls, dtype)
    one = jnp.ones_like(x)
    num, den = jnp.full_like(x, _FREE), one
    # Unrolled and visited from the last wall to the first, so that the first hit in list
    # order wins; plain selects vectorise better under vmap than an argmax + gather.
    for i in reversed(range(walls.shape[0])):
        (nx_in, dx), (tx_in, tx_out) = _axis_times(x, vx, walls[i, 0], walls[i, 1])
        (ny_in, dy), (ty_in, ty_out) = _axis_times(y, vy, walls[i, 2], walls[i, 3])
        t_leave = jnp.minimum(jnp.minimum(tx_out, ty_out), 1.0)
        hit = jnp.maximum(jnp.maximum(tx_in, ty_in), 0.0) <= t_leave
        # t_enter = max(tx_in, ty_in, 0), kept as the fraction it came from.
        use_x = (tx_in >= ty_in) & (tx_in > 0)
        use_y = ~use_x & (ty_in > 0)
        num = jnp.where(hit, jnp.where(use_x, nx_in, jnp.where(use_y, ny_in, 0.0)), num)
        den = jnp.where(hit, jnp.where(use_x, dx, jnp.where(use_y, dy, one)), den)
    num = jnp.where(hit_bound, jnp.asarray(_HIT_BOUND, dtype), num)
    den = jnp.where(hit_bound, one, den)
    return num / den


def _move_final(x, y, vx, vy, params: EnvParams):
    """The move under the authors' final collision rules: ``(x, y, vx, vy, hit_bound, hit_wall)``.

    SPEC.md section 1 names three changes to the rules of :func:`_stop_code`, read here as
    :func:`envs.reference.final_rules_step` reads them (the plain-Python cross-check): the move
    is the segment from the state to the candidate clamped to ``[0, n]^2``, and walls are
    checked on it even when a bound was crossed; a segment that meets a wall only at ``t = 0``
    (leaving a face the agent rests on) is free; the wall hit is the one entered first over all
    walls (list order on a tie). A collision stops the agent at the entry point, at rest.
    """
    dtype = x.dtype
    n = jnp.asarray(params.n, dtype)
    cx, cy = x + vx, y + vy
    hit_bound = (cx < 0) | (cx > n) | (cy < 0) | (cy > n)
    # Clamped candidate and the displacement to it (exactly ``v`` when nothing was clamped).
    kx, ky = jnp.clip(cx, 0.0, n), jnp.clip(cy, 0.0, n)
    dx, dy = jnp.where(hit_bound, kx - x, vx), jnp.where(hit_bound, ky - y, vy)
    walls = jnp.asarray(params.walls, dtype)
    best = jnp.full_like(x, jnp.inf)
    for i in range(walls.shape[0]):
        _, (tx_in, tx_out) = _axis_times(x, dx, walls[i, 0], walls[i, 1])
        _, (ty_in, ty_out) = _axis_times(y, dy, walls[i, 2], walls[i, 3])
        t_enter = jnp.maximum(jnp.maximum(tx_in, ty_in), 0.0)
        t_leave = jnp.minimum(jnp.minimum(tx_out, ty_out), 1.0)
        hit = (t_enter <= t_leave) & (t_leave > 0) & (t_enter < best)
        best = jnp.where(hit, t_enter, best)
    hit_wall = best <= 1.0
    t = jnp.where(hit_wall, best, 1.0)
    new_x = jnp.where(hit_wall, x + dx * t, jnp.where(hit_bound, kx, cx))
    new_y = jnp.where(hit_wall, y + dy * t, jnp.where(hit_bound, ky, cy))
    stopped = hit_wall | hit_bound
    zero = jnp.zeros_like(vx)
    return (new_x, new_y, jnp.where(stopped, zero, vx), jnp.where(stopped, zero, vy),
            hit_bound & ~hit_wall, hit_wall)


def _computed_once(flag: jax.Array) -> jax.Array:
    """``flag`` (bool) unchanged, but computed once per step rather than once per consumer.

    XLA duplicates cheap elementwise work into the loop of every consumer. ``terminated`` feeds
    the reward, ``truncated``, ``discount``, the auto-reset of all five state fields and whatever
    the caller does with them, so the move and the exit test before it would be recomputed in
    each of those loops; on CPU each of them is then also big enough to be split across threads,
    which costs a synchronisation per loop and step. A square root (exact at 0 and 1) is an
    operation XLA does not duplicate, so the flag goes through one and is stored once: up to
    3x the steps/s at batch 1024 with XLA's default threading on 2 CPU cores
    (benchmarks/env_throughput.py).
    """
    return jnp.sqrt(flag.astype(jnp.float32)) > 0.5


def _apply_stop(p, v, code, n):
    """New coordinate and velocity component along one axis, given the stop code."""
    moved = p + v * jnp.minimum(code, 1.0)  # p + v exactly unless stopped by a wall (v * 1 == v)
    clamped = jnp.where(moved < 0, jnp.zeros_like(moved), jnp.where(moved > n, n, moved))
    new_p = jnp.where(code == _HIT_BOUND, clamped, moved)
    new_v = jnp.where(code == _FREE, v, jnp.zeros_like(v))
    return new_p, new_v


class Maze:
    """The maze environment; stateless, all state lives in :class:`EnvState`.

    Actions: 0 LEFT, 1 RIGHT, 2 UP, 3 DOWN (accelerations of 0.1 on one velocity component,
    damping of 0.05 on the other). Actions must be integers; inside ``step`` an out-of-range
    action is *clipped* to the nearest valid one (``-1`` acts as LEFT, ``7`` as DOWN) and
    non-integer values are truncated by ``astype(int32)``; jitted code cannot raise, so
    validate upstream (the Gymnasium adapter raises).

    ``key`` arguments are accepted for gymnax compatibility; the maze itself is deterministic.

    ``collision`` picks the wall rules (:data:`COLLISION_RULES`): ``"reference"``, SPEC.md
    section 1 as written (the golden data's rules), or ``"final"``, the authors' final maze
    code's rules (see :func:`envs.reference.final_rules_step`). ``envs.make(name,
    collision="final")`` builds the latter.

    Example:
        >>> import jax, jax.numpy as jnp, envs
        >>> env, params = envs.make("u_maze")
        >>> step = jax.jit(jax.vmap(env.step_autoreset, in_axes=(0, 0, 0, None)))
        >>> keys = jax.random.split(jax.random.key(0), 8)
        >>> obs, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
        >>> obs, states, r, term, trunc, info = step(keys, states, jnp.ones(8, int), params)
        >>> obs.shape, info["final_obs"].shape
        ((8, 4), (8, 4))
    """

    num_actions = NUM_ACTIONS

    def __init__(self, name: str = "u_maze", collision: str = "reference"):
        if collision not in COLLISION_RULES:
            raise ValueError(f"collision: must be one of {COLLISION_RULES}, got {collision!r}")
        self.name = name
        self.collision = collision

    def __repr__(self) -> str:
        if self.collision == "reference":
            return f"Maze({self.name!r})"
        return f"Maze({self.name!r}, collision={self.collision!r})"

    # Value semantics, so that jit caches hit when a Maze is a static argument.
    def __eq__(self, other) -> bool:
        return (type(other) is type(self) and other.name == self.name
                and other.collision == self.collision)

    def __hash__(self) -> int:
        return hash((type(self), self.name, self.collision))

    @property
    def default_params(self) -> EnvParams:
        """The parameters of this environment's named layout."""
        return make_params(self.name)

    def reset(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """Start of an episode: ``params.start`` at rest, ``time = 0``. Returns ``(obs, state)``."""
        del key  # the start is deterministic
        dtype = _default_float()
        start = jnp.asarray(params.start, dtype)
        zero = jnp.zeros((), dtype)
        state = EnvState(x=start[0], y=start[1], vx=zero, vy=zero, time=jnp.zeros((), jnp.int32))
        return state_to_vector(state), state

    def step(self, key: jax.Array, state: EnvState, action, params: EnvParams):
        """One transition, without auto-reset.

        Returns ``(obs, state, reward, terminated, truncated, info)``: ``terminated`` when the
        new position is in the exit square (reward ``exit_reward``, else 0), ``truncated`` when
        ``time`` reaches ``max_steps`` without termination. ``info`` holds ``final_obs`` (equal
        to ``obs`` here), ``discount`` (``1 - terminated``), ``hit_bound`` and ``hit_wall``.
        Stepping past the end simply continues the dynamics.
        """
        del key
        next_state, reward, terminated, truncated, hit_bound, hit_wall = self._transition(
            state, action, params
        )
        obs = state_to_vector(next_state)
        info = {
            "final_obs": obs,
            "discount": 1.0 - terminated.astype(obs.dtype),
            "hit_bound": hit_bound,
            "hit_wall": hit_wall,
        }
        return obs, next_state, reward, terminated, truncated, info

    def step_autoreset(self, key: jax.Array, state: EnvState, action, params: EnvParams):
        """:meth:`step`, then a reset where the episode ended (``terminated | truncated``).

        ``reward``/``terminated``/``truncated`` describe the transition taken; ``obs`` and the
        state are the reset ones where it ended, and ``info["final_obs"]`` is always the true
        next observation (what a TD target needs).
        """
        key_step, key_reset = jax.random.split(key)
        _, next_state, reward, terminated, truncated, info = self.step(
            key_step, state, action, params
        )
        _, reset_state = self.reset(key_reset, params)
        done = terminated | truncated
        # Field by field (each with the batch shape), so the selects stay elementwise.
        state = jax.tree.map(lambda r, s: jnp.where(done, r, s), reset_state, next_state)
        return state_to_vector(state), state, reward, terminated, truncated, info

    def _transition(self, state: EnvState, action, params: EnvParams):
        """``(next_state, reward, terminated, truncated, hit_bound, hit_wall)``, per coordinate."""
        action = jnp.clip(jnp.asarray(action).astype(jnp.int32), 0, NUM_ACTIONS - 1)
        vx, vy = _accelerate(state.vx, state.vy, action)
        if self.collision == "final":
            x, y, vx, vy, hit_bound, hit_wall = _move_final(state.x, state.y, vx, vy, params)
        else:
            code = _stop_code(state.x, state.y, vx, vy, params)
            n = jnp.asarray(params.n, vx.dtype)
            x, vx = _apply_stop(state.x, vx, code, n)
            y, vy = _apply_stop(state.y, vy, code, n)
            hit_bound = code == _HIT_BOUND
            hit_wall = code <= 1.0
        time = state.time + 1

        dtype = x.dtype
        exit_ = jnp.asarray(params.exit, dtype)
        half_width = jnp.asarray(params.exit_half_width, dtype)
        terminated = (jnp.abs(x - exit_[0]) < half_width) & (jnp.abs(y - exit_[1]) < half_width)
        terminated = _computed_once(terminated)
        truncated = (time >= params.max_steps) & ~terminated
        reward = jnp.where(terminated, jnp.asarray(params.exit_reward, dtype), 0.0)
        next_state = EnvState(x=x, y=y, vx=vx, vy=vy, time=time)
        return next_state, reward, terminated, truncated, hit_bound, hit_wall

    def observation_space(self, params: EnvParams) -> Box:
        """``(x, y, vx, vy)`` in ``[0, n]^2 x [-1, 1]^2``."""
        n = jnp.asarray(params.n, _default_float())
        return Box(
            low=jnp.array([0.0, 0.0, -MAX_SPEED, -MAX_SPEED]),
            high=jnp.stack([n, n, jnp.asarray(MAX_SPEED), jnp.asarray(MAX_SPEED)]).astype(n.dtype),
            shape=(4,),
        )

    def action_space(self, params: EnvParams | None = None) -> Discrete:
        """``Discrete(4)``: LEFT, RIGHT, UP, DOWN."""
        del params
        return Discrete(NUM_ACTIONS)


# ----------------------------------------------------------------------------------------------
# Absorbing states
# ----------------------------------------------------------------------------------------------


def absorbing_states(env: Maze, params: EnvParams, resolution: float = 0.25) -> np.ndarray:
    """Positions outside every wall where an agent at rest can never move again: ``[M, 2]``.

    A position qualifies when every action taken at rest there returns the agent to that
    position at rest, so that by induction it stays there until the episode times out. Tried:
    a grid of step ``resolution`` over ``[0, n]^2`` joined with every wall's edge coordinates
    (where such corners lie), leaving out the points strictly inside a wall. Under the
    reference rules (SPEC.md section 1) an agent stopped on a face while strictly inside the
    wall's range on the other axis cannot move away from it, so where two walls overlap, the
    inner corners of the overlap (each strictly inside the other wall's range) are absorbing;
    under the final rules they are not. Sorted by ``(x, y)``.

    Example:
        >>> import envs
        >>> absorbing_states(*envs.make("big_u_maze")).tolist()
        [[4.0, 3.0], [4.5, 3.0]]
        >>> absorbing_states(*envs.make("big_u_maze", collision="final")).shape
        (0, 2)
    """
    if not isinstance(env, Maze):
        raise ValueError(f"env: absorbing_states takes a kinematic Maze, got {type(env).__name__}")
    if not resolution > 0:
        raise ValueError(f"resolution: must be positive, got {resolution!r}")
    n = float(params.n)
    walls = np.asarray(params.walls, np.float64).reshape(-1, 4)
    grid = np.arange(0.0, n + resolution / 2, resolution)
    xs = np.unique(np.clip(np.concatenate([grid, walls[:, 0], walls[:, 1]]), 0.0, n))
    ys = np.unique(np.clip(np.concatenate([grid, walls[:, 2], walls[:, 3]]), 0.0, n))
    x, y = (a.ravel() for a in np.meshgrid(xs, ys, indexing="ij"))
    inside = np.any((x[:, None] > walls[:, 0]) & (x[:, None] < walls[:, 1])
                    & (y[:, None] > walls[:, 2]) & (y[:, None] < walls[:, 3]), axis=1)
    x, y = x[~inside], y[~inside]
    dtype = _default_float()
    zero = jnp.zeros(x.shape, dtype)
    rest = EnvState(x=jnp.asarray(x, dtype), y=jnp.asarray(y, dtype), vx=zero, vy=zero,
                    time=jnp.zeros(x.shape, jnp.int32))

    @jax.jit
    def stays(state):
        def one(action):
            nxt = env._transition(state, jnp.full(x.shape, action), params)[0]
            return ((nxt.x == state.x) & (nxt.y == state.y) & (nxt.vx == 0) & (nxt.vy == 0))
        return jnp.all(jnp.stack([one(a) for a in range(NUM_ACTIONS)]), axis=0)

    keep = np.asarray(stays(rest))
    return np.stack([x[keep], y[keep]], axis=1)


# ----------------------------------------------------------------------------------------------
# Random-policy rollouts (sanity figures, the demo, the benchmark)
# ----------------------------------------------------------------------------------------------


def random_rollout(
    env: Maze, params: EnvParams, key: jax.Array, num_steps: int, sticky_prob: float = 0.0
):
    """One episode of a (sticky) uniformly random policy from the start, for ``num_steps`` steps.

    With probability ``sticky_prob`` the previous action is repeated, otherwise a uniform one is
    drawn (the first action is always uniform). ``num_steps`` must be static; use
    ``params.max_steps`` for full episodes. Returns ``(success, length)``: whether the exit was
    reached, and the number of steps until the episode ended (termination or truncation, capped
    at ``num_steps``). vmap it over keys for many episodes.

    Example:
        >>> import jax, envs
        >>> env, params = envs.make("u_maze")
        >>> keys = jax.random.split(jax.random.key(0), 64)
        >>> success, length = jax.vmap(random_rollout, in_axes=(None, None, 0, None, None))(
        ...     env, params, keys, 300, 0.7)
        >>> success.shape, length.dtype.name
        ((64,), 'int32')
    """
    key_actions, key_sticky, key_reset = jax.random.split(key, 3)
    uniform = jax.random.randint(key_actions, (num_steps,), 0, NUM_ACTIONS, dtype=jnp.int32)
    repeat = jax.random.uniform(key_sticky, (num_steps,)) < sticky_prob
    _, state = env.reset(key_reset, params)

    def body(carry, inputs):
        state, prev_action, done, success, length = carry
        fresh, rep, t = inputs
        action = jnp.where(rep & (t > 0), prev_action, fresh)
        _, state, _, terminated, truncated, _ = env.step(key_reset, state, action, params)
        ended_now = ~done & (terminated | truncated)
        success = success | (~done & terminated)
        length = jnp.where(ended_now, t + 1, length)
        return (state, action, done | terminated | truncated, success, length), None

    init = (state, jnp.int32(0), jnp.asarray(False), jnp.asarray(False), jnp.int32(num_steps))
    steps = jnp.arange(num_steps, dtype=jnp.int32)
    (_, _, _, success, length), _ = jax.lax.scan(body, init, (uniform, repeat, steps))
    return success, length
