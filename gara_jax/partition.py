"""Fixed-capacity partitions of the state space into goal boxes.

A :class:`Partition` holds at most ``max_goals`` boxes in padded arrays plus a ``count``, so that
partitions of different sizes (one per seed) stack and ``vmap``. Rows ``count ..
max_goals - 1`` are padding: the empty box ``lo = 1, hi = -1`` in every dimension. It contains no
state and is finite, so arithmetic on padded rows (centres, widths fed to a network) never makes
NaNs; :func:`locate` also masks them by ``count``.

A state belongs to the first box (lowest index) that contains it, as in the reference: boxes are
closed and neighbours share faces. A *ranked* partition (``rank`` set, see
:meth:`Partition.create`) orders its boxes by ``rank`` instead of by index, and
:func:`replace_box` puts the pieces of a replaced box in its place in that order, so a face
that belonged to the replaced box belongs to one of its pieces, not to a neighbour that came
after it (appended pieces come after every other box).

:func:`locate` is pure JAX. :meth:`Partition.create`, :func:`replace_box`, :func:`can_fit` and
:func:`check_tiling` are host-side and operate on one (unbatched) partition.
"""

from __future__ import annotations

from types import MappingProxyType

import flax.struct
import jax.numpy as jnp
import numpy as np

from gara_jax import boxes

PAD_LO = 1.0
PAD_HI = -1.0

# The U-maze (SPEC.md section 1, n = 3) state space over (x, y, vx, vy).
U_MAZE_LO = (0.0, 0.0, -1.0, -1.0)
U_MAZE_HI = (3.0, 3.0, 1.0, 1.0)


class PartitionFullError(ValueError):
    """Raised when an operation would need more than ``max_goals`` boxes."""


@flax.struct.dataclass
class Partition:
    """Goal boxes ``lo, hi [max_goals, D]`` of which the first ``count`` are in use.

    Example:
        >>> import jax.numpy as jnp
        >>> p = Partition.create([[0.0], [1.0]], [[1.0], [2.0]], max_goals=4)
        >>> p.max_goals, int(p.count), locate(p, jnp.array([[0.5], [1.0], [3.0]])).tolist()
        (4, 2, [0, 0, -1])
    """

    lo: jnp.ndarray
    hi: jnp.ndarray
    count: jnp.ndarray
    rank: jnp.ndarray | None = None  # [max_goals] first-box order; None: by index

    @property
    def max_goals(self) -> int:
        return self.lo.shape[-2]

    @property
    def dim(self) -> int:
        return self.lo.shape[-1]

    @classmethod
    def create(cls, lo, hi, max_goals: int, dtype=jnp.float32, rank=None) -> Partition:
        """A partition made of the boxes ``lo, hi [N, D]``, padded to ``max_goals`` rows.

        ``rank``: ``None`` (boxes ordered by index), ``True`` (a ranked partition, initially in
        index order) or the ``[max_goals]`` ranks themselves (a permutation of
        ``0 .. max_goals - 1``). Raises ``ValueError`` for invalid boxes and
        :class:`PartitionFullError` when ``N > max_goals``. The boxes are not checked to tile
        anything; see :func:`check_tiling`.
        """
        lo, hi = boxes.validate_boxes(lo, hi, "partition boxes")
        if lo.ndim != 2:
            raise ValueError(f"partition boxes: expected shape [N, D], got {lo.shape}")
        if int(max_goals) < 1:
            raise ValueError(f"max_goals: must be at least 1, got {max_goals}")
        n, d = lo.shape
        if n > max_goals:
            raise PartitionFullError(f"max_goals: {n} boxes do not fit in {max_goals}")
        plo = np.full((max_goals, d), PAD_LO, dtype=np.float64)
        phi = np.full((max_goals, d), PAD_HI, dtype=np.float64)
        plo[:n] = lo
        phi[:n] = hi
        if rank is True:
            rank = np.arange(max_goals)
        if rank is not None:
            rank = np.asarray(rank)
            if sorted(rank.tolist()) != list(range(max_goals)):
                raise ValueError(f"rank: must be a permutation of 0..{max_goals - 1}, got {rank}")
            rank = jnp.asarray(rank, jnp.int32)
        return cls(lo=jnp.asarray(plo, dtype), hi=jnp.asarray(phi, dtype),
                   count=jnp.asarray(n, jnp.int32), rank=rank)

    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """The ``count`` boxes in use, as NumPy arrays ``[count, D]`` (host-side)."""
        n = int(self.count)
        return np.asarray(self.lo)[:n], np.asarray(self.hi)[:n]


def locate(partition: Partition, states):
    """Index of the first box containing each state ``[..., D]``, or -1 if none does.

    "First" is the lowest index, or in a ranked partition the lowest rank. jit- and vmap-able
    (vmap over a batch of partitions works too).

    Example:
        >>> import jax.numpy as jnp
        >>> p = gara_initial()
        >>> locate(p, jnp.array([[0.5, 1.0, 0.0, 0.0], [1.0, 1.0, 0.0, 0.0],
        ...                      [2.0, 1.0, 0.0, 0.0], [4.0, 1.0, 0.0, 0.0]])).tolist()
        [0, 0, 1, -1]
    """
    s = states[..., None, :]
    inside = jnp.all((partition.lo <= s) & (s <= partition.hi), axis=-1)  # [..., G]
    inside = inside & (jnp.arange(partition.max_goals) < partition.count)
    if partition.rank is None:
        first = jnp.argmax(inside, axis=-1).astype(jnp.int32)
    else:
        order = jnp.where(inside, partition.rank, partition.max_goals)
        first = jnp.argmin(order, axis=-1).astype(jnp.int32)
    return jnp.where(jnp.any(inside, axis=-1), first, jnp.int32(-1))


def can_fit(partition: Partition, k: int) -> bool:
    """Whether ``k`` more boxes fit, i.e. ``count + k <= max_goals``.

    Replacing one box by ``K`` boxes adds ``K - 1``: check ``can_fit(partition, K - 1)`` before
    :func:`replace_box` to skip (and count) a split that would not fit.

    Example:
        >>> p = gara_initial(max_goals=3)
        >>> can_fit(p, 1), can_fit(p, 2)
        (True, False)
    """
    return int(partition.count) + int(k) <= partition.max_goals


def replace_box(partition: Partition, index: int, new_lo, new_hi) -> tuple[Partition, np.ndarray]:
    """Replace box ``index`` by the boxes ``new_lo, new_hi [K, D]`` (host-side).

    New box 0 takes ``index``; the others are appended after the last box in use. In a ranked
    partition the new boxes also take the replaced box's place in the first-box order (new
    box ``j`` gets its rank plus ``j``, every later box moves ``K - 1`` down). Returns the
    new partition and the indices ``int32 [K]`` the new boxes got. The new boxes must lie inside
    the replaced one (they are meant to tile it). Never overwrites silently: raises
    :class:`PartitionFullError` when they do not fit (check ``can_fit(partition, K - 1)`` first
    to skip the split instead), ``ValueError`` for a bad index or bad boxes.

    Example:
        >>> p = gara_initial(max_goals=4)
        >>> p2, idx = replace_box(p, 1, [[1.0, 0, -1, -1], [2.0, 0, -1, -1]],
        ...                       [[2.0, 3, 1, 1], [3.0, 3, 1, 1]])
        >>> idx.tolist(), int(p2.count)
        ([1, 2], 3)
    """
    new_lo, new_hi = boxes.validate_boxes(new_lo, new_hi, "new boxes")
    if new_lo.ndim != 2 or new_lo.shape[1] != partition.dim or new_lo.shape[0] < 1:
        raise ValueError(f"new boxes: expected shape [K>=1, {partition.dim}], got {new_lo.shape}")
    count = int(partition.count)
    index = int(index)
    if not 0 <= index < count:
        raise ValueError(f"index: {index} is not a box in use (count {count})")
    k = new_lo.shape[0]
    if not can_fit(partition, k - 1):
        raise PartitionFullError(
            f"max_goals: replacing box {index} by {k} boxes needs {count + k - 1} > "
            f"{partition.max_goals}"
        )
    lo = np.array(partition.lo)
    hi = np.array(partition.hi)
    dt = lo.dtype
    cast_lo = new_lo.astype(dt)
    cast_hi = new_hi.astype(dt)
    if (cast_lo < lo[index]).any() or (cast_hi > hi[index]).any():
        raise ValueError(f"new boxes: not inside box {index} ({lo[index]}, {hi[index]})")
    indices = np.array([index] + list(range(count, count + k - 1)), dtype=np.int32)
    lo[indices] = cast_lo
    hi[indices] = cast_hi
    rank = partition.rank
    if rank is not None:
        rank = np.array(rank)
        placed = rank[index]
        in_use = np.arange(len(rank)) < count
        rank[in_use & (rank > placed)] += k - 1
        rank[indices] = placed + np.arange(k)
        rank[count + k - 1:] = np.arange(count + k - 1, len(rank))
        rank = jnp.asarray(rank, jnp.int32)
    new = partition.replace(lo=jnp.asarray(lo), hi=jnp.asarray(hi),
                            count=jnp.asarray(count + k - 1, jnp.int32), rank=rank)
    return new, indices


def check_tiling(partition: Partition, state_lo=U_MAZE_LO, state_hi=U_MAZE_HI) -> None:
    """Raise ``ValueError`` with the reason unless the boxes in use tile the state space exactly.

    Exact: no two boxes overlap in their interiors, all lie inside the domain and their volumes
    add up to the domain's in rational arithmetic (see :func:`gara_jax.boxes.check_tiles`).
    Padding rows must be the empty padding box.

    Example:
        >>> check_tiling(handcrafted())
    """
    lo, hi = partition.boxes()
    pad_lo = np.asarray(partition.lo)[int(partition.count):]
    pad_hi = np.asarray(partition.hi)[int(partition.count):]
    if (pad_lo != PAD_LO).any() or (pad_hi != PAD_HI).any():
        raise ValueError("partition: rows past count are not the empty padding box")
    boxes.check_tiles(lo, hi, state_lo, state_hi, name="partition")


#: The authors' partitions of every maze layout (SPEC.md sections 2 and 2.1), over (x, y) in
#: their order: rows ``(x_lo, x_hi, y_lo, y_hi, split)``, where ``split`` bisects the velocity
#: ranges (``""`` none, ``"vx"``, ``"vy"`` or ``"vx,vy"``; see :func:`layout_boxes`).
#: ``big_u_maze`` gets one box the authors do not have, ``[0,6]x[3,6]`` last: their boxes cover
#: ``y <= 3`` only, and a state can end up above (inside the wall ``y in [3, 4]`` after a bound
#: clamp, SPEC.md section 1), so the extra box makes the partition a tiling.
LAYOUT_PARTITIONS = MappingProxyType({
    "u_maze": {
        "handcrafted": ((0, 1, 0, 2, ""), (0, 1, 2, 3, ""), (1, 1.5, 2, 3, ""),
                        (1, 1.5, 0, 2, ""), (1.5, 3, 2, 3, ""), (1.5, 3, 0, 2, "")),
        "gara": ((0, 1, 0, 3, ""), (1, 3, 0, 3, "")),
    },
    "four_rooms": {
        "handcrafted": ((0, 1, 0, 2, ""), (0, 1, 2, 3, ""), (1, 3, 2, 3, ""), (1, 3, 0, 2, "")),
        "gara": ((0, 1, 0, 3, ""), (1, 3, 0, 3, "")),
    },
    "u_maze_6": {
        "handcrafted": ((0, 2, 0, 4, ""), (0, 2, 4, 6, ""), (2, 4, 4, 6, ""),
                        (2, 4, 0, 4, ""), (4, 6, 4, 6, ""), (4, 6, 0, 4, "")),
        "gara": ((0, 3, 0, 6, ""), (3, 6, 0, 6, "")),
    },
    "big_u_maze": {
        "handcrafted": ((0, 1, 0, 2, ""), (0, 1, 2, 3, ""), (1, 4, 0, 2, ""),
                        (1, 4, 2, 3, ""), (4, 6, 0, 2, ""), (4, 6, 2, 3, ""),
                        (0, 6, 3, 6, "")),
        "gara": ((0, 3, 0, 3, ""), (3, 6, 0, 3, ""), (0, 6, 3, 6, "")),
    },
    "labyrinth": {
        "handcrafted": ((0, 1, 0, 4, ""), (0, 1, 4, 6, "vx"), (1, 6, 0, 0.5, "vx"),
                        (1, 3, 0.5, 6, "vx,vy"), (3, 5.5, 0.5, 6, "vx,vy"),
                        (5.5, 6, 0, 6, "vy")),
        "gara": ((0, 3, 0, 3, ""), (0, 3, 3, 6, ""), (3, 6, 0, 3, ""), (3, 6, 3, 6, "")),
    },
})
#: Partition kinds of :data:`LAYOUT_PARTITIONS`.
PARTITION_KINDS = ("handcrafted", "gara")
#: Layouts whose authors' Handcrafted boxes overlap (the first-box rule decides a shared part):
#: in the labyrinth ``[1,6]x[0,0.5]`` and ``[5.5,6]x[0,6]`` share ``[5.5,6]x[0,0.5]``.
OVERLAPPING = frozenset({("labyrinth", "handcrafted")})


#: The boxes of :data:`LAYOUT_PARTITIONS` that are not the authors' (``(x_lo, x_hi, y_lo, y_hi)``,
#: full velocity ranges): they only make a partition a tiling, over a region the agent cannot
#: get into from the start (``big_u_maze``: the wall ``y in [3, 4]`` and the closed-off strip
#: above it). The authors' high levels have no such goal; ``non_targets="layout"`` makes every
#: goal inside one of them a goal that is never targeted.
LAYOUT_FILLERS = MappingProxyType({"big_u_maze": ((0, 6, 3, 6),)})


def layout_fillers(layout: str) -> tuple[np.ndarray, np.ndarray]:
    """The filler regions ``lo, hi [N, 4]`` of a layout (:data:`LAYOUT_FILLERS`; ``N = 0``
    for a layout whose partitions are all the authors').

    Example:
        >>> lo, hi = layout_fillers("big_u_maze")
        >>> lo.tolist(), hi.tolist(), len(layout_fillers("u_maze")[0])
        ([[0.0, 3.0, -1.0, -1.0]], [[6.0, 6.0, 1.0, 1.0]], 0)
    """
    if layout not in LAYOUT_PARTITIONS:
        raise ValueError(f"layout: no built-in partitions for {layout!r}; valid: "
                         f"{', '.join(LAYOUT_PARTITIONS)}")
    rows = LAYOUT_FILLERS.get(layout, ())
    lo = np.array([(x0, y0, -1.0, -1.0) for x0, _, y0, _ in rows], float).reshape(-1, 4)
    hi = np.array([(x1, y1, 1.0, 1.0) for _, x1, _, y1 in rows], float).reshape(-1, 4)
    return lo, hi


def inside_regions(lo, hi, region_lo, region_hi):
    """``bool [G]``: which boxes ``lo/hi [G, D]`` lie inside (closed) one of the regions
    ``region_lo/region_hi [N, D]`` (traceable).

    Example:
        >>> import numpy as np
        >>> lo, hi = np.array([[0., 3.], [0., 0.]]), np.array([[3., 6.], [3., 3.]])
        >>> inside_regions(lo, hi, np.array([[0., 3.]]), np.array([[6., 6.]])).tolist()
        [True, False]
    """
    lo, hi = jnp.asarray(lo), jnp.asarray(hi)
    inside = (lo[:, None, :] >= region_lo[None]) & (hi[:, None, :] <= region_hi[None])
    return jnp.any(jnp.all(inside, axis=-1), axis=-1)


def state_space(n: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``(x, y, vx, vy)`` box of a maze of size ``n``: ``[0, n]^2 x [-1, 1]^2``.

    Example:
        >>> [a.tolist() for a in state_space(6.0)]
        [[0.0, 0.0, -1.0, -1.0], [6.0, 6.0, 1.0, 1.0]]
    """
    return (np.array([0.0, 0.0, -1.0, -1.0]), np.array([float(n), float(n), 1.0, 1.0]))


def layout_boxes(layout: str, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """The authors' boxes ``lo, hi [N, 4]`` of a layout's ``kind`` partition (SPEC.md 2, 2.1).

    A split row becomes 2 boxes (bisected at the velocity midpoint 0, lower half first) or 4
    (``"vx,vy"``: (vx low, vy low), (vx low, vy high), (vx high, vy low), (vx high, vy high)).

    Example:
        >>> lo, hi = layout_boxes("labyrinth", "handcrafted")
        >>> len(lo), lo[1].tolist(), hi[1].tolist()
        (15, [0.0, 4.0, -1.0, -1.0], [1.0, 6.0, 0.0, 1.0])
    """
    if layout not in LAYOUT_PARTITIONS:
        raise ValueError(f"layout: no built-in partitions for {layout!r}; valid: "
                         f"{', '.join(LAYOUT_PARTITIONS)}")
    if kind not in PARTITION_KINDS:
        raise ValueError(f"kind: must be one of {PARTITION_KINDS}, got {kind!r}")
    halves = {"": [((-1, -1), (1, 1))],
              "vx": [((-1, -1), (0, 1)), ((0, -1), (1, 1))],
              "vy": [((-1, -1), (1, 0)), ((-1, 0), (1, 1))],
              "vx,vy": [((-1, -1), (0, 0)), ((-1, 0), (0, 1)),
                        ((0, -1), (1, 0)), ((0, 0), (1, 1))]}
    lo, hi = [], []
    for x_lo, x_hi, y_lo, y_hi, split in LAYOUT_PARTITIONS[layout][kind]:
        for v_lo, v_hi in halves[split]:
            lo.append((x_lo, y_lo, *v_lo))
            hi.append((x_hi, y_hi, *v_hi))
    return np.array(lo, np.float64), np.array(hi, np.float64)


def from_boxes(lo, hi, state_lo, state_hi, max_goals: int | None = None, *,
               overlap: bool = False, name: str = "boxes", dtype=jnp.float32) -> Partition:
    """A validated partition of the state space ``[state_lo, state_hi]`` made of ``lo, hi``.

    The boxes must tile the space exactly (:func:`gara_jax.boxes.check_tiles`); with
    ``overlap=True`` they may overlap and must only cover it (:func:`gara_jax.boxes.check_covers`;
    the first box containing a state owns it). ``max_goals`` defaults to the box count. Raises
    ``ValueError`` naming ``name`` otherwise (and :class:`PartitionFullError` when the boxes
    exceed ``max_goals``).

    Example:
        >>> p = from_boxes([[0.0, 0], [1.0, 0]], [[1.0, 2], [2.0, 2]], [0, 0], [2, 2])
        >>> int(p.count)
        2
        >>> from_boxes([[0.0, 0]], [[1.0, 2]], [0, 0], [2, 2], name="initial_boxes")
        Traceback (most recent call last):
        ...
        ValueError: initial_boxes: boxes do not cover the domain (volume 2.0 of 4.0)
    """
    lo, hi = boxes.validate_boxes(lo, hi, name)
    state_lo, state_hi = boxes.validate_boxes(state_lo, state_hi, "state space")
    if lo.ndim != 2 or lo.shape[1] != state_lo.shape[-1]:
        raise ValueError(f"{name}: expected boxes of shape [N, {state_lo.shape[-1]}] (the "
                         f"state's dimensions), got {lo.shape}")
    check = boxes.check_covers if overlap else boxes.check_tiles
    check(lo, hi, state_lo, state_hi, name=name)
    max_goals = len(lo) if max_goals is None else max_goals
    return Partition.create(lo, hi, max_goals, dtype=dtype)


def layout_partition(layout: str, kind: str, max_goals: int | None = None) -> Partition:
    """The authors' ``kind`` partition of a maze layout, validated (see :func:`layout_boxes`).

    Example:
        >>> p = layout_partition("four_rooms", "handcrafted", max_goals=8)
        >>> int(p.count), p.max_goals
        (4, 8)
    """
    from envs.layouts import layout_spec

    lo, hi = layout_boxes(layout, kind)
    state_lo, state_hi = state_space(layout_spec(layout)["n"])
    return from_boxes(lo, hi, state_lo, state_hi, max_goals,
                      overlap=(layout, kind) in OVERLAPPING, name=f"{layout} {kind} partition")


def save_boxes(path, partition: Partition) -> None:
    """Write the boxes in use of ``partition`` to a JSON file ``{"lo": [...], "hi": [...]}``.

    :func:`load_boxes` reads them back, e.g. to start a run from another run's final partition
    (``GaraConfig(initial_boxes=load_boxes(path))``). The first-box order is written as
    the boxes' order (a ranked partition's boxes are sorted by rank).

    Example:
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "p.json")
        >>> save_boxes(path, gara_initial())
        >>> [len(b) for b in load_boxes(path)]
        [2, 2]
    """
    import json

    lo, hi = partition.boxes()
    if partition.rank is not None:
        order = np.argsort(np.asarray(partition.rank)[: len(lo)], kind="stable")
        lo, hi = lo[order], hi[order]
    with open(path, "w") as f:
        json.dump({"lo": lo.tolist(), "hi": hi.tolist()}, f)


def load_boxes(path) -> tuple[tuple, tuple]:
    """The ``(lo, hi)`` boxes a :func:`save_boxes` file holds, as nested tuples of floats."""
    import json

    with open(path) as f:
        data = json.load(f)
    if not isinstance(data, dict) or set(data) != {"lo", "hi"}:
        raise ValueError(f"{path}: expected a JSON object with keys 'lo' and 'hi'")
    return boxes_as_tuples(data["lo"], data["hi"])


def boxes_as_tuples(lo, hi) -> tuple[tuple, tuple]:
    """``lo, hi`` (any nested sequence or array) as nested tuples of floats: hashable, so a
    config field can hold them.

    Example:
        >>> boxes_as_tuples([[0, 1]], [[2, 3]])
        (((0.0, 1.0),), ((2.0, 3.0),))
    """
    return (tuple(tuple(float(v) for v in row) for row in np.asarray(lo)),
            tuple(tuple(float(v) for v in row) for row in np.asarray(hi)))


def handcrafted(max_goals: int = 6, layout: str = "u_maze") -> Partition:
    """The reference's handcrafted partition of a maze layout (SPEC.md 2 and 2.1).

    On the U-maze (the default): 6 boxes over (x, y) with full velocity ranges ``[-1, 1]``:
    ``[0,1]x[0,2]``, ``[0,1]x[2,3]``, ``[1,1.5]x[2,3]``, ``[1,1.5]x[0,2]``, ``[1.5,3]x[2,3]``,
    ``[1.5,3]x[0,2]``. Other layouts: :data:`LAYOUT_PARTITIONS`.

    Example:
        >>> int(handcrafted(max_goals=8).count)
        6
    """
    return layout_partition(layout, "handcrafted", max_goals)


def gara_initial(max_goals: int = 64, state_lo=U_MAZE_LO, state_hi=U_MAZE_HI,
                 split_x: float | None = None) -> Partition:
    """GARA's initial 2-box partition: the state space split along ``x`` (SPEC.md section 2).

    For the U-maze (the default domain) the boxes are ``[0,1]x[0,3]`` and ``[1,3]x[0,3]`` with
    full velocity ranges. For another domain ``(state_lo, state_hi)`` over any number of
    dimensions (``x`` first), ``x`` is split at ``split_x``, by default one third of the way
    along, which is where the reference splits the n = 3 maze (at its first wall). The other
    layouts' initial partitions: ``layout_partition(layout, "gara")``.

    Example:
        >>> gara_initial().boxes()[1][0].tolist()
        [1.0, 3.0, 1.0, 1.0]
    """
    state_lo, state_hi = boxes.validate_boxes(state_lo, state_hi, "state_lo/state_hi")
    if state_lo.ndim != 1:
        raise ValueError(f"state_lo/state_hi: expected one box [D], got shape {state_lo.shape}")
    if split_x is None:
        split_x = state_lo[0] + (state_hi[0] - state_lo[0]) / 3.0
    if not state_lo[0] < split_x < state_hi[0]:
        raise ValueError(f"split_x: {split_x} is not inside ({state_lo[0]}, {state_hi[0]})")
    lo = np.stack([state_lo, state_lo])
    hi = np.stack([state_hi, state_hi])
    hi[0, 0] = split_x
    lo[1, 0] = split_x
    return Partition.create(lo, hi, max_goals)
