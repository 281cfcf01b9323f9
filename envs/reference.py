"""Plain-Python, one-environment-at-a-time implementations of the maze rules (SPEC.md section 1).

This is how the authors' reference code runs: one step per call, in a Python loop. Two forms of
the same rules, which give identical states (float64, the same operations in the same order):

* :func:`reference_step` works on Python floats (the faster of the two in CPython);
* :func:`reference_step_numpy` works on small NumPy arrays (position and velocity as
  ``[2]`` vectors), the style of the authors' code.

They are the baseline loops of ``benchmarks/env_throughput.py`` and an independent cross-check of
the JAX environment in the tests; they share no code with :mod:`envs.maze`.

Example:
    >>> env = ReferenceMaze.from_layout("u_maze")
    >>> env.reset()
    (0.0, 0.0, 0.0, 0.0)
    >>> obs, reward, terminated, truncated = env.step(1)
    >>> [round(v, 3) for v in obs]
    [0.1, 0.0, 0.1, 0.0]
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from envs.layouts import layout_spec

State = tuple[float, float, float, float]


def _damp(v: float) -> float:
    if v > 0:
        return max(0.0, v - 0.05)
    if v < 0:
        return max(0.0, v + 0.05)  # the reference's asymmetry, kept on purpose
    return 0.0


def _axis_interval(p: float, v: float, lo: float, hi: float) -> tuple[float, float]:
    """Closed interval of ``t`` where ``p + v t`` lies in ``[lo, hi]`` (empty: lo > hi)."""
    if v > 0:
        return (lo - p) / v, (hi - p) / v
    if v < 0:
        return (hi - p) / v, (lo - p) / v
    if lo < p < hi:
        return 0.0, 1.0
    return math.inf, -math.inf


def reference_step(
    state: Sequence[float], action: int, n: float, walls: Sequence[Sequence[float]]
) -> State:
    """The next ``(x, y, vx, vy)`` after ``action`` (0 LEFT, 1 RIGHT, 2 UP, 3 DOWN).

    Example:
        >>> reference_step((0.9, 0.5, 0.2, 0.0), 1, 3.0, [(1.0, 1.5, -1.0, 2.0)])
        (1.0, 0.5, 0.0, 0.0)
    """
    x, y, vx, vy = _accelerate(state, action)
    nx, ny = x + vx, y + vy
    if nx < 0 or nx > n or ny < 0 or ny > n:
        nx = 0.0 if nx < 0 else (n if nx > n else nx)
        ny = 0.0 if ny < 0 else (n if ny > n else ny)
        return nx, ny, 0.0, 0.0

    for x_lo, x_hi, y_lo, y_hi in walls:
        tx_lo, tx_hi = _axis_interval(x, vx, x_lo, x_hi)
        ty_lo, ty_hi = _axis_interval(y, vy, y_lo, y_hi)
        t_enter = max(0.0, tx_lo, ty_lo)
        t_leave = min(1.0, tx_hi, ty_hi)
        if t_enter <= t_leave:
            return x + vx * t_enter, y + vy * t_enter, 0.0, 0.0
    return nx, ny, vx, vy


def final_rules_step(
    state: Sequence[float], action: int, n: float, walls: Sequence[Sequence[float]]
) -> State:
    """:func:`reference_step` under the authors' *final* collision rules (SPEC.md section 1).

    Three changes to the rules of :func:`reference_step`, as SPEC states them, read as follows:

    - walls are checked even when the candidate position left the maze: the move is the
      segment from the state to the clamped candidate;
    - a contact only at ``t = 0`` (the segment touches a wall in the single point it starts
      from, i.e. the agent moves away from a face it rests on) is not a collision;
    - the wall hit is the one entered first (the smallest entry time over all walls, the
      first in list order on a tie), not the first in list order.

    A collision stops the agent where it enters the wall, at rest, as before.

    Example:
        >>> wall = [(1.0, 1.5, -1.0, 2.0)]
        >>> reference_step((1.0, 0.5, 0.0, 0.0), 0, 3.0, wall)  # stuck on the face
        (1.0, 0.5, 0.0, 0.0)
        >>> [round(v, 3) for v in final_rules_step((1.0, 0.5, 0.0, 0.0), 0, 3.0, wall)]
        [0.9, 0.5, -0.1, 0.0]
        >>> final_rules_step((0.5, 0.0, 0.7, 0.0), 3, 3.0, wall)  # no passing into the wall
        (1.0, 0.0, 0.0, 0.0)
    """
    x, y, vx, vy = _accelerate(state, action)
    nx, ny = x + vx, y + vy
    clamped = nx < 0 or nx > n or ny < 0 or ny > n
    if clamped:
        nx = 0.0 if nx < 0 else (n if nx > n else nx)
        ny = 0.0 if ny < 0 else (n if ny > n else ny)
        dx, dy = nx - x, ny - y
    else:
        dx, dy = vx, vy
    best = math.inf
    for x_lo, x_hi, y_lo, y_hi in walls:
        tx_lo, tx_hi = _axis_interval(x, dx, x_lo, x_hi)
        ty_lo, ty_hi = _axis_interval(y, dy, y_lo, y_hi)
        t_enter = max(0.0, tx_lo, ty_lo)
        t_leave = min(1.0, tx_hi, ty_hi)
        if t_enter <= t_leave and t_leave > 0 and t_enter < best:
            best = t_enter
    if best <= 1.0:
        return x + dx * best, y + dy * best, 0.0, 0.0
    if clamped:
        return nx, ny, 0.0, 0.0
    return nx, ny, vx, vy


def _accelerate(state: Sequence[float], action: int) -> State:
    """Position unchanged, velocity after the push and the damping (SPEC step 1)."""
    x, y, vx, vy = (float(v) for v in state)
    if action == 0:
        vx, vy = max(-1.0, vx - 0.1), _damp(vy)
    elif action == 1:
        vx, vy = min(1.0, vx + 0.1), _damp(vy)
    elif action == 2:
        vx, vy = _damp(vx), min(1.0, vy + 0.1)
    elif action == 3:
        vx, vy = _damp(vx), max(-1.0, vy - 0.1)
    else:
        raise ValueError(f"action must be 0, 1, 2 or 3, got {action!r}")
    return x, y, vx, vy


def _damp_numpy(v: np.ndarray) -> np.ndarray:
    return np.where(
        v > 0, np.maximum(0.0, v - 0.05), np.where(v < 0, np.maximum(0.0, v + 0.05), 0.0)
    )


# Per action: which velocity component is pushed, and by how much.
_PUSH_AXIS = (0, 0, 1, 1)
_PUSH_SIGN = (-1.0, 1.0, 1.0, -1.0)


def reference_step_numpy(state: np.ndarray, action: int, n: float, walls: np.ndarray) -> np.ndarray:
    """:func:`reference_step` on NumPy arrays: the next ``(x, y, vx, vy)`` as a float64 ``[4]``.

    ``walls`` is a ``[W, 4]`` array of ``[x_lo, x_hi, y_lo, y_hi]`` rows.

    Example:
        >>> reference_step_numpy(np.array([0.9, 0.5, 0.2, 0.0]), 1, 3.0,
        ...                      np.array([[1.0, 1.5, -1.0, 2.0]])).tolist()
        [1.0, 0.5, 0.0, 0.0]
    """
    if action not in (0, 1, 2, 3):
        raise ValueError(f"action must be 0, 1, 2 or 3, got {action!r}")
    action = int(action)
    state = np.asarray(state, dtype=np.float64)
    pos, vel = state[:2], _damp_numpy(state[2:])
    axis = _PUSH_AXIS[action]
    if _PUSH_SIGN[action] > 0:
        vel[axis] = min(1.0, state[2 + axis] + 0.1)
    else:
        vel[axis] = max(-1.0, state[2 + axis] - 0.1)

    candidate = pos + vel
    outside = (candidate < 0) | (candidate > n)
    if outside.any():
        return np.concatenate([np.clip(candidate, 0.0, n), np.zeros(2)])

    walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    moving, forward = vel != 0, vel > 0
    safe_v = np.where(moving, vel, 1.0)
    for wall in walls:
        lo, hi = wall[[0, 2]], wall[[1, 3]]
        t_lo = (np.where(forward, lo, hi) - pos) / safe_v
        t_hi = (np.where(forward, hi, lo) - pos) / safe_v
        inside = (lo < pos) & (pos < hi)
        t_lo = np.where(moving, t_lo, np.where(inside, 0.0, np.inf))
        t_hi = np.where(moving, t_hi, np.where(inside, 1.0, -np.inf))
        t_enter = max(0.0, t_lo.max())
        t_leave = min(1.0, t_hi.min())
        if t_enter <= t_leave:
            return np.concatenate([pos + vel * t_enter, np.zeros(2)])
    return np.concatenate([candidate, vel])


class ReferenceMaze:
    """A stateful single maze: ``reset()``, ``step(action)`` like the reference code.

    ``step`` returns ``(obs, reward, terminated, truncated)`` with the same meaning as the JAX
    environment.
    """

    def __init__(
        self,
        n: float = 3.0,
        walls: Sequence[Sequence[float]] = ((1.0, 1.5, -1.0, 2.0),),
        start: Sequence[float] = (0.0, 0.0),
        exit: Sequence[float] = (3.0, 0.0),
        exit_half_width: float = 0.5,
        exit_reward: float = 10.0,
        max_steps: int = 300,
    ):
        self.n = float(n)
        self.walls = [tuple(float(v) for v in w) for w in walls]
        self.start = (float(start[0]), float(start[1]))
        self.exit = (float(exit[0]), float(exit[1]))
        self.exit_half_width = float(exit_half_width)
        self.exit_reward = float(exit_reward)
        self.max_steps = int(max_steps)
        self.state: State = (*self.start, 0.0, 0.0)
        self.time = 0

    @classmethod
    def from_layout(cls, name: str, **overrides) -> ReferenceMaze:
        """The reference maze of a named layout (see :data:`envs.LAYOUTS`)."""
        spec = layout_spec(name)
        spec.update(overrides)
        return cls(**spec)

    def reset(self, state: Sequence[float] | None = None) -> State:
        """Back to the start at rest (or to ``state``), ``time = 0``."""
        self.state = (*self.start, 0.0, 0.0) if state is None else tuple(map(float, state))
        self.time = 0
        return self.state

    def step(self, action: int) -> tuple[State, float, bool, bool]:
        """Apply ``action``; returns ``(obs, reward, terminated, truncated)``."""
        self.state = reference_step(self.state, action, self.n, self.walls)
        self.time += 1
        x, y = self.state[0], self.state[1]
        hw = self.exit_half_width
        terminated = abs(x - self.exit[0]) < hw and abs(y - self.exit[1]) < hw
        truncated = self.time >= self.max_steps and not terminated
        return self.state, (self.exit_reward if terminated else 0.0), terminated, truncated


class NumpyReferenceMaze(ReferenceMaze):
    """:class:`ReferenceMaze` stepping :func:`reference_step_numpy`: the state is a float64
    ``[4]`` NumPy array and the exit test is vectorised, as in the authors' NumPy code.

    Example:
        >>> env = NumpyReferenceMaze.from_layout("u_maze")
        >>> env.reset().tolist()
        [0.0, 0.0, 0.0, 0.0]
        >>> obs, reward, terminated, truncated = env.step(1)
        >>> [round(float(v), 3) for v in obs]
        [0.1, 0.0, 0.1, 0.0]
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._walls = np.asarray(self.walls, dtype=np.float64).reshape(-1, 4)
        self._exit = np.asarray(self.exit, dtype=np.float64)
        self.state = self.reset()

    def reset(self, state: Sequence[float] | None = None) -> np.ndarray:
        """Back to the start at rest (or to ``state``), ``time = 0``."""
        start = (*self.start, 0.0, 0.0) if state is None else state
        self.state = np.array(start, dtype=np.float64)
        self.time = 0
        return self.state

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool]:
        """Apply ``action``; returns ``(obs, reward, terminated, truncated)``."""
        self.state = reference_step_numpy(self.state, action, self.n, self._walls)
        self.time += 1
        terminated = bool(np.all(np.abs(self.state[:2] - self._exit) < self.exit_half_width))
        truncated = self.time >= self.max_steps and not terminated
        return self.state, (self.exit_reward if terminated else 0.0), terminated, truncated
