"""The training driver: many seeds in one jitted epoch, host-side refinement between epochs.

Seeds are independent streams: seed ``s`` uses ``jax.random.key(s)``, split into an init key
and a loop key, and epoch ``e`` uses ``fold_in(loop_key, e)``. So a seed's random stream does
not depend on which other seeds share the batch (its float results may, in the last bits, as
XLA compiles another batch size differently, unless ``batch_invariant``: see Devices below),
and a run can be resumed from its :class:`LoopState` (the per-seed agent states, the loop keys
and the next epoch index) at any epoch boundary.

Each epoch is one call of ``jit(vmap(train_epoch then evaluate))`` over seeds; algorithms with a
host step (GARA) then run ``host_update`` on the batched states before the next epoch. GARA with
``cadence="episode"`` (its reference presets) runs an epoch as several jitted segments instead:
each takes every seed to the end of its current episode (or of the epoch), drawing the keys an
epoch call would, and the host step then processes the seeds whose episode ended, before their
next episode (:func:`_episode_cadence_epoch`); the state metrics and the evaluation follow the
epoch's last segment. Epochs, metrics and checkpoints are the same ``steps_per_epoch`` blocks.
Such a run is one process only (``jax.distributed`` is refused for it).

Devices: the seed axis of every agent-state leaf is sharded over a 1-D mesh of ``devices``
(axis ``"seeds"``, ``NamedSharding(mesh, PartitionSpec("seeds"))``); seeds never communicate,
so each device runs the one-device jitted epoch on its own block of seeds
(:class:`gara_jax.sharding.SeedJit`); with ``batch_invariant`` (the default when there is more
than one device) the results are bitwise those of a one-device run made with it (see
:mod:`gara_jax.sharding` for what that takes and costs). The seed count must be a multiple of the
device count (a ``ValueError`` naming ``seeds`` and ``devices`` otherwise). Under
``jax.distributed`` the mesh spans every process's devices: each process computes its
addressable seeds and runs the host step on them, and the per-epoch metrics are gathered.

``total_steps`` is rounded *up* to whole epochs: a run takes ``ceil(total_steps /
steps_per_epoch)`` epochs (120,000 steps are 40 epochs of 3,000).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from gara_jax.algorithms import make_algorithm
from gara_jax.algorithms.base import Algorithm
from gara_jax.sharding import (
    SeedJit,
    batch_invariant_scope,
    check_divisible,
    relayout,
    seed_mesh,
    seed_sharding,
)


class PartitionSnapshot(NamedTuple):
    """A seed's goal partition at ``step`` env steps: boxes ``lo, hi`` (``[count, D]``)."""

    step: int
    lo: np.ndarray
    hi: np.ndarray
    count: int


class LoopState(NamedTuple):
    """Everything needed to continue a multi-seed run at an epoch boundary.

    ``states`` is the algorithm's agent-state pytree batched over seeds; ``keys`` the per-seed
    loop keys as raw key data (``uint32``, easy to save); ``epoch`` the next epoch to run.
    """

    states: Any
    keys: jax.Array
    epoch: int
    seeds: tuple[int, ...]


class EpochOutput(NamedTuple):
    """What :func:`train_epochs` yields after each epoch (host-side values).

    ``metrics`` maps names to ``[n_seeds]`` arrays; ``snapshots`` lists, per seed, the partition
    snapshots taken at this epoch (empty lists when the partition did not change);
    ``episodes`` the training episodes that ended in this epoch (:func:`episodes_of_epoch`),
    ``None`` for an algorithm without an ``episode_log``.
    """

    epoch: int
    n_epochs: int
    loop: LoopState
    metrics: dict
    host_info: dict | None
    snapshots: list
    epoch_s: float
    episodes: dict | None = None


@dataclasses.dataclass
class TrainResult:
    """Outcome of :func:`train_many`.

    Attributes:
        config: the algorithm config.
        algorithm: its name (``"gara"``, ``"gara_planning"``, ``"handcrafted"``, ``"hiro"``...).
        seeds: the seeds, in row order.
        metrics: name -> ``[n_seeds, n_epochs]`` array (at least ``env_steps``,
            ``train_success``, ``eval_success``, ``episode_return``, ``n_goals``).
        snapshots: per seed, the list of :class:`PartitionSnapshot` (step 0 and every epoch
            after which the partition changed); empty lists for algorithms without one.
        episodes: every training episode, per seed: ``{"success", "length", "end_step"}``,
            each a list of ``n_seeds`` 1-D NumPy arrays in episode order (success 0/1, length in
            steps, the seed's environment-step count when it ended); ``None`` for algorithms
            that do not log episodes. :mod:`gara_jax.results` turns it into the paper's curve.
        wall_time_s: wall time of the whole call (compilation included).
        first_epoch_s: wall time of the first epoch run (includes compilation).
        host_time_s: total time spent in ``host_update`` (GARA's refinement).
        host_info: one dict per epoch from ``host_update`` (``None`` entries without one).
        final: the :class:`LoopState` after the last epoch (pass as ``init_state`` to resume).
    """

    config: Any
    algorithm: str
    seeds: list
    metrics: dict
    snapshots: list
    wall_time_s: float
    first_epoch_s: float
    host_time_s: float
    host_info: list
    final: LoopState
    episodes: dict | None = None


EPISODE_FIELDS = ("success", "length", "end_step")


def episodes_of_epoch(log) -> dict:
    """Per-seed episode arrays from an epoch's ``episode_log`` (``[n_seeds, steps]`` arrays).

    Example:
        >>> import numpy as np
        >>> log = dict(ended=np.array([[False, True, True]]), success=np.array([[0, 1, 0]]),
        ...            length=np.array([[0, 2, 1]]), end_step=np.array([[0, 2, 3]]))
        >>> eps = episodes_of_epoch(log)
        >>> eps["success"][0].tolist(), eps["end_step"][0].tolist()
        ([1, 0], [2, 3])
    """
    ended = np.asarray(log["ended"], bool)
    return {name: [np.asarray(log[name])[i][ended[i]].astype(np.int32)
                   for i in range(len(ended))] for name in EPISODE_FIELDS}


def n_epochs_for(config, total_steps: int) -> int:
    """Epochs needed to cover ``total_steps`` (rounded up to whole epochs).

    Example:
        >>> from gara_jax.algorithms import HandcraftedConfig
        >>> n_epochs_for(HandcraftedConfig(), 120_000), n_epochs_for(HandcraftedConfig(), 1)
        (40, 1)
    """
    if isinstance(total_steps, bool) or int(total_steps) != total_steps or total_steps < 1:
        raise ValueError(f"total_steps: must be a positive integer, got {total_steps!r}")
    return math.ceil(int(total_steps) / config.steps_per_epoch)


def seed_list(seeds) -> list[int]:
    """Validated seeds: a positive count ``n`` means ``0..n-1``; else distinct ints >= 0.

    Example:
        >>> seed_list(3), seed_list([7, 2])
        ([0, 1, 2], [7, 2])
    """
    if isinstance(seeds, bool):
        raise ValueError(f"seeds: must be a count or a sequence of ints, got {seeds!r}")
    if isinstance(seeds, int | np.integer):
        if seeds < 1:
            raise ValueError(f"seeds: a seed count must be >= 1, got {seeds}")
        return list(range(int(seeds)))
    if not isinstance(seeds, Sequence | np.ndarray) or len(seeds) == 0:
        raise ValueError(f"seeds: must be a count or a non-empty sequence of ints, got {seeds!r}")
    out = []
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, int | np.integer) or s < 0:
            raise ValueError(f"seeds: every seed must be an int >= 0, got {s!r}")
        out.append(int(s))
    if len(set(out)) != len(out):
        raise ValueError(f"seeds: must be distinct, got {out}")
    return out


def _split_seed_keys(keys):
    """Per-seed ``(init_key, loop_key_data)`` from typed keys ``[S]``."""
    pairs = jax.vmap(lambda k: jax.random.split(k))(keys)
    return pairs[:, 0], jax.random.key_data(pairs[:, 1])


def _epoch_fn(alg: Algorithm):
    def run(state, key_data, epoch):
        key = jax.random.fold_in(jax.random.wrap_key_data(key_data), epoch)
        k_train, k_eval = jax.random.split(key)
        state, metrics = alg.train_epoch(state, k_train)
        metrics = dict(metrics)
        metrics.update(alg.evaluate(state, k_eval))
        return state, metrics

    return run


_SEGMENT_AXIS = "segment_seeds"


def _segment_fn(alg: Algorithm):
    """``cadence="episode"``: the epoch's steps up to each seed's episode end (vmapped over
    seeds with the axis name :data:`_SEGMENT_AXIS`, so that seeds done idle cheaply)."""
    def run(state, key_data, epoch):
        key = jax.random.fold_in(jax.random.wrap_key_data(key_data), epoch)
        k_train, _ = jax.random.split(key)  # the epoch's training key, as in _epoch_fn
        return alg.train_segment(state, k_train, epoch, axis_name=_SEGMENT_AXIS)

    return run


def _finish_fn(alg: Algorithm):
    """``cadence="episode"``: the epoch's state metrics and evaluation (its key as in
    :func:`_epoch_fn`)."""
    def run(state, key_data, epoch):
        key = jax.random.fold_in(jax.random.wrap_key_data(key_data), epoch)
        _, k_eval = jax.random.split(key)
        metrics = dict(alg.state_metrics(state))
        metrics.update(alg.evaluate(state, k_eval))
        return metrics

    return run


def cadence_of(config) -> str:
    """``"episode"`` for a config whose host step runs after every episode (GARA's
    ``cadence``), else ``"epoch"``."""
    return getattr(config, "cadence", "epoch")


class _Compiled(NamedTuple):
    alg: Algorithm
    init: SeedJit  # vmap(init) from seed ints: (states, loop key data)
    run: SeedJit  # vmap(train_epoch then evaluate), states donated
    mesh: Mesh
    segment: SeedJit | None = None  # cadence="episode": vmap(train_segment), states donated
    finish: SeedJit | None = None  # cadence="episode": vmap(state metrics, evaluate)


def _build(config, mesh: Mesh, batch_invariant: bool) -> _Compiled:
    alg = make_algorithm(config)

    def init(seed_ints):
        init_keys, loop_keys = _split_seed_keys(jax.vmap(jax.random.key)(seed_ints))
        return jax.vmap(alg.init)(init_keys), loop_keys

    # The old states are not reused after an epoch, so XLA may update them in place.
    run = SeedJit(jax.vmap(_epoch_fn(alg), in_axes=(0, 0, None)), batched=(0, 1),
                  batch_invariant=batch_invariant, donate_argnums=0)
    segment = finish = None
    if cadence_of(config) == "episode":
        segment = SeedJit(jax.vmap(_segment_fn(alg), in_axes=(0, 0, None),
                                   axis_name=_SEGMENT_AXIS), batched=(0, 1),
                          batch_invariant=batch_invariant, donate_argnums=0)
        finish = SeedJit(jax.vmap(_finish_fn(alg), in_axes=(0, 0, None)), batched=(0, 1),
                         batch_invariant=batch_invariant)
    return _Compiled(alg, SeedJit(init, batch_invariant=batch_invariant), run, mesh, segment,
                     finish)


_build_cached = functools.lru_cache(maxsize=8)(_build)


def resolve_batch_invariant(batch_invariant: bool | None, mesh: Mesh) -> bool:
    """``batch_invariant`` as given, or (``None``) whether ``mesh`` has more than one device.

    Example:
        >>> resolve_batch_invariant(None, seed_mesh(1)), resolve_batch_invariant(True, seed_mesh(1))
        (False, True)
    """
    if batch_invariant is None:
        return mesh.devices.size > 1
    if not isinstance(batch_invariant, bool | np.bool_):
        raise ValueError(f"batch_invariant: must be None, True or False, got {batch_invariant!r}")
    return bool(batch_invariant)


def compiled(config, devices=None, batch_invariant: bool | None = None) -> _Compiled:
    """The algorithm and its jitted, seed-vmapped, seed-sharded functions on
    ``seed_mesh(devices)``, cached per (hashable) config, mesh and ``batch_invariant``
    (:func:`resolve_batch_invariant`), so that repeated runs of one config compile once per
    process."""
    mesh = seed_mesh(devices)
    invariant = resolve_batch_invariant(batch_invariant, mesh)
    try:
        hash(config)
    except TypeError:
        return _build(config, mesh, invariant)
    return _build_cached(config, mesh, invariant)


def _global_array(values, sharding):
    """A host array (the same on every process) laid out with ``sharding``."""
    values = np.asarray(values)
    return jax.make_array_from_callback(values.shape, sharding, lambda idx: values[idx])


def _fully_addressable(tree) -> bool:
    return all(getattr(x, "is_fully_addressable", True) for x in jax.tree.leaves(tree))


def fetch(tree):
    """``tree`` as host NumPy arrays: ``jax.device_get``, or, for arrays spread over several
    processes (``jax.distributed``), every process's part gathered (a collective: every
    process must call it).

    Example:
        >>> import jax.numpy as jnp
        >>> fetch({"a": jnp.arange(3)})["a"].tolist()
        [0, 1, 2]
    """
    if _fully_addressable(tree):
        return jax.device_get(tree)
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)


def place(loop: LoopState, devices=None) -> LoopState:
    """``loop`` with its states and keys sharded over ``seed_mesh(devices)`` (no copy for
    leaves already laid out so; host arrays must be the same on every process).

    Example:
        >>> from gara_jax.algorithms import HandcraftedConfig
        >>> loop = place(init_loop(HandcraftedConfig(), 2), 1)
        >>> loop.keys.sharding.spec == seed_sharding(seed_mesh(1)).spec
        True
    """
    mesh = seed_mesh(devices)
    check_divisible(len(loop.seeds), mesh)
    sharding = seed_sharding(mesh)

    def put(x):
        if isinstance(x, jax.Array) and x.sharding == sharding:
            return x
        if isinstance(x, jax.Array) and x.is_fully_addressable and (
                jax.process_count() == 1):
            return jax.device_put(x, sharding)
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            impl = jax.random.key_impl(x)
            return jax.random.wrap_key_data(put(jax.random.key_data(x)), impl=impl)
        return _global_array(fetch(x), sharding)

    return loop._replace(states=jax.tree.map(put, loop.states), keys=put(loop.keys))


def starting_partitions(config, partitions, n_seeds: int):
    """``partitions`` (one per seed) as one seed-batched, validated
    :class:`~gara_jax.partition.Partition` for GARA ``config``'s states.

    Each item is a :class:`~gara_jax.partition.Partition` (one seed's, e.g. from
    :func:`final_partitions`), a :class:`PartitionSnapshot` or a pair ``(lo, hi)`` of
    ``[N, D]`` boxes. Every partition must tile the environment's observation space exactly
    (:func:`gara_jax.partition.check_tiling`; the U-maze's is ``[0, 3]^2 x [-1, 1]^2``: no
    overlaps, no gaps) and fit in ``config.max_goals``. With ``piece_order="parent"`` a
    partition's ``rank`` is kept (index order if it has none); otherwise a ranked partition is refused. Raises
    ``ValueError`` naming ``initial_partitions`` (and the seed's row) otherwise.

    Example:
        >>> from gara_jax.algorithms import GaraConfig
        >>> from gara_jax.partition import handcrafted
        >>> p = starting_partitions(GaraConfig(max_goals=8), [handcrafted(8)] * 2, 2)
        >>> p.lo.shape, p.count.tolist()
        ((2, 8, 4), [6, 6])
        >>> starting_partitions(GaraConfig(), [([[0.0, 0, -1, -1]], [[1.0, 3, 1, 1]])], 1)
        Traceback (most recent call last):
        ...
        ValueError: initial_partitions[0]: partition: boxes do not cover the domain ...
    """
    from gara_jax import partition as part
    from gara_jax.algorithms import GaraConfig

    if not isinstance(config, GaraConfig):
        raise ValueError("initial_partitions: only GARA (a GaraConfig) starts from a given "
                         f"partition, got a {type(config).__name__}")
    if isinstance(partitions, part.Partition) or not isinstance(
            partitions, Sequence) or len(partitions) != n_seeds:
        got = len(partitions) if isinstance(partitions, Sequence) else type(partitions).__name__
        raise ValueError(f"initial_partitions: one partition per seed ({n_seeds}), got {got}")
    import envs

    ranked = config.piece_order == "parent"
    env, env_params = envs.make(config.env)
    space = env.observation_space(env_params)
    state_lo, state_hi = np.asarray(space.low), np.asarray(space.high)
    rows = []
    for i, item in enumerate(partitions):
        try:
            rank = None
            if isinstance(item, part.Partition):
                if np.ndim(item.lo) != 2:
                    raise ValueError(f"one seed's partition ([G, D] boxes), got boxes of "
                                     f"shape {np.shape(item.lo)}")
                lo, hi = item.boxes()
                rank = None if item.rank is None else np.asarray(item.rank)
            elif isinstance(item, PartitionSnapshot):
                lo, hi = item.lo, item.hi
            elif isinstance(item, Sequence) and len(item) == 2:
                lo, hi = item
            else:
                raise ValueError(f"expected a Partition, a PartitionSnapshot or (lo, hi), got "
                                 f"{type(item).__name__}")
            if rank is not None and not ranked:
                raise ValueError("a ranked partition, but piece_order is not 'parent'")
            if ranked and rank is not None and len(rank) != config.max_goals:
                raise ValueError(f"its rank has {len(rank)} entries, max_goals is "
                                 f"{config.max_goals}")
            if np.shape(lo)[-1:] != state_lo.shape:
                raise ValueError(f"boxes over the observation's {len(state_lo)} dimensions, "
                                 f"got shape {np.shape(lo)}")
            p = part.Partition.create(lo, hi, config.max_goals,
                                      rank=(True if rank is None else rank) if ranked else None)
            part.check_tiling(p, state_lo, state_hi)
        except ValueError as err:  # PartitionFullError included
            raise ValueError(f"initial_partitions[{i}]: {err}") from None
        rows.append(p)
    return jax.tree.map(lambda *a: jnp.stack(a), *rows)


def final_partitions(result) -> list:
    """Each seed's partition at the end of a run (a :class:`TrainResult` or a
    :class:`LoopState`), as one-seed :class:`~gara_jax.partition.Partition` objects: what
    ``initial_partitions`` takes."""
    loop = result.final if isinstance(result, TrainResult) else result
    partition = fetch(loop.states.partition)
    return [jax.tree.map(lambda a, i=i: jnp.asarray(a[i]), partition)
            for i in range(len(loop.seeds))]


def init_loop(config, seeds, *, devices=None, batch_invariant: bool | None = None,
              initial_partitions=None) -> LoopState:
    """Fresh per-seed agent states (epoch 0) for ``seeds`` (a count or a sequence), sharded
    over ``seed_mesh(devices)`` (``batch_invariant``: as in :func:`train_many`).

    ``initial_partitions`` (GARA only; one per seed, in seed order, see
    :func:`starting_partitions`): each seed starts from the given partition instead of
    SPEC.md section 2's two boxes. Only the partition is taken: everything else (Q-table,
    planner graph, reachability marks, pair counts, memory, forward model, low level) is
    the fresh agent's, so a Planning run started from a Q-learning run's final partitions is
    the authors' (SPEC.md 3.9.3: one partition list passed to both agents, each agent with its
    own learners), and it may refine the partition further.

    Example:
        >>> from gara_jax.algorithms import HandcraftedConfig
        >>> loop = init_loop(HandcraftedConfig(), [3, 5])
        >>> loop.epoch, loop.seeds, loop.keys.shape
        (0, (3, 5), (2, 2))
    """
    seeds = seed_list(seeds)
    comp = compiled(config, devices, batch_invariant)
    check_divisible(len(seeds), comp.mesh)
    start = None
    if initial_partitions is not None:
        start = fetch(starting_partitions(config, initial_partitions, len(seeds)))
    states, loop_keys = comp.init(_global_array(np.asarray(seeds, np.int32),
                                                seed_sharding(comp.mesh)))
    if start is not None:
        sharding = seed_sharding(comp.mesh)
        states = states.replace(partition=jax.tree.map(
            lambda v, like: _global_array(np.asarray(v, like.dtype), sharding), start,
            states.partition))
    return LoopState(states=states, keys=loop_keys, epoch=0, seeds=tuple(seeds))


def _local_states(states, mesh: Mesh, n_seeds: int):
    """The process's own seeds of ``states``, over its own devices (all of them in one
    process), without copying."""
    if jax.process_count() == 1:
        return states
    local = Mesh(np.asarray([d for d in mesh.devices.flat
                             if d.process_index == jax.process_index()], dtype=object),
                 mesh.axis_names)
    return relayout(states, local, n_seeds * local.devices.size // mesh.devices.size)


def _global_states(local, mesh: Mesh, n_seeds: int):
    """Inverse of :func:`_local_states`; also lays out over ``mesh`` whatever the host step
    wrote back some other way."""
    if jax.process_count() == 1:
        sharding = seed_sharding(mesh)
        return jax.tree.map(lambda x: x if getattr(x, "sharding", None) == sharding
                            else jax.device_put(x, sharding), local)
    return relayout(local, mesh, n_seeds)


_SUMMED_INFO = ("triggered", "stable", "analysed", "splits", "reaches", "no_reach",
                "capacity_skips", "fit_updates", "start_skips", "exit_analysed", "exit_splits")


def _gather_info(info: dict) -> dict:
    """One process's host-step ``info`` combined over processes (identity in one process):
    counts summed, ``changed`` concatenated in seed order, times the slowest process's."""
    if jax.process_count() == 1:
        return info
    from jax.experimental import multihost_utils

    counts = {k: np.asarray(info[k], np.int64) for k in _SUMMED_INFO if k in info}
    times = {k: np.asarray(v, np.float64) for k, v in info.items() if k.endswith("_s")}
    changed = np.asarray(info.get("changed", np.zeros(0, bool)))
    every = multihost_utils.process_allgather(dict(counts=counts, times=times))
    out = dict(info)
    out.update({k: int(np.sum(v)) for k, v in every["counts"].items()})
    out.update({k: float(np.max(v)) for k, v in every["times"].items()})
    out["changed"] = np.asarray(multihost_utils.process_allgather(changed, tiled=True), bool)
    return out


def _snapshots(states) -> list | None:
    part = getattr(states, "partition", None)
    if part is None:
        return None
    lo, hi, n, steps = fetch((part.lo, part.hi, part.count, states.env_steps))
    return [PartitionSnapshot(int(steps[i]), np.asarray(lo[i][: n[i]]), np.asarray(hi[i][: n[i]]),
                              int(n[i])) for i in range(len(n))]


def _episode_cadence_epoch(comp: _Compiled, loop: LoopState, epoch: int):
    """One epoch of ``cadence="episode"``: ``(states, metrics, info, snapshots, episodes)``.

    Jitted segments (``train_segment``) take every seed to the end of its current episode
    or of the epoch; after each, the host step processes the seeds whose episode ended
    (``host_update(..., only=ended)``, their episodes' rows and indices), then the next
    segment starts. The epoch ends when every seed has taken ``steps_per_epoch`` steps;
    then the state metrics and the evaluation run (:func:`_finish_fn`). ``info`` sums the
    host steps' counts (``host_calls`` of them, ``episodes_processed`` episodes) and keeps
    each call's own info under ``calls``, and the epoch's ``segments`` and their
    ``segment_iterations`` (loop iterations: each segment runs as long as its slowest seed).
    """
    alg, config = comp.alg, comp.alg.config
    spe, n = config.steps_per_epoch, len(loop.seeds)
    states = loop.states
    taken = np.zeros(n, np.int64)
    sums = {name: np.zeros(n, np.float64) for name in (
        "success", "ended", "ret", "options_ended", "options_reached", "low_loss",
        "low_updates")}
    episodes = {name: [[] for _ in range(n)] for name in EPISODE_FIELDS}
    snaps, calls = [[] for _ in range(n)], []
    segments = iterations = 0
    while (taken < spe).any():
        states, seg = comp.segment(states, loop.keys, epoch)
        seg = {k: np.asarray(v) for k, v in fetch(seg).items()}
        if not seg["steps"].any():
            raise RuntimeError(f"cadence 'episode': the states are not at epoch {epoch}'s "
                               "steps (env_steps past the epoch's end)")
        taken += seg["steps"]
        segments, iterations = segments + 1, iterations + int(seg["steps"].max())
        ended = seg["ended"].astype(bool)
        for name in ("options_ended", "options_reached", "low_loss", "low_updates"):
            sums[name] += seg[name]
        sums["ended"] += ended
        sums["success"] += ended & seg["success"].astype(bool)
        sums["ret"] += np.where(ended, seg["ret"], 0.0)
        for i in np.flatnonzero(ended):
            episodes["success"][i].append(int(seg["success"][i]))
            episodes["length"][i].append(int(seg["length"][i]))
            episodes["end_step"][i].append(int(seg["end_step"][i]))
        if not ended.any():
            continue
        count = np.asarray(fetch(states.episode.count))
        with batch_invariant_scope(comp.run.batch_invariant):
            states, info = alg.host_update(states, epoch, only=ended,
                                           since=seg["end_step"] - seg["length"],
                                           key_index=count - 1)
        states = _global_states(states, comp.mesh, n)
        info["seeds"] = ended
        calls.append(info)
        changed = np.asarray(info.get("changed", np.zeros(n, bool)))
        if changed.any():
            current = _snapshots(states)
            for i in np.flatnonzero(changed):
                snaps[i].append(current[i])
    finish = {k: np.asarray(v) for k, v in fetch(comp.finish(states, loop.keys, epoch)).items()}
    n_ended = sums["ended"]
    mean = lambda v: np.where(n_ended > 0, v / np.maximum(n_ended, 1), 0.0).astype(  # noqa: E731
        np.float32)
    metrics = dict(
        env_steps=np.asarray(fetch(states.env_steps)), train_success=mean(sums["success"]),
        episodes_ended=n_ended.astype(np.int32), episode_return=mean(sums["ret"]),
        n_goals=finish.pop("n_goals"),
        option_success=(sums["options_reached"] / np.maximum(sums["options_ended"], 1)).astype(
            np.float32),
        low_loss=(sums["low_loss"] / np.maximum(sums["low_updates"], 1)).astype(np.float32),
        **finish)
    info = _sum_infos(calls, n, epoch)
    # The batch steps as long as its slowest seed: loop iterations against steps per seed.
    info.update(segments=segments, segment_iterations=iterations)
    jax.block_until_ready(states)
    episodes = {name: [np.asarray(v, np.int32) for v in per_seed]
                for name, per_seed in episodes.items()}
    return states, metrics, info, snaps, episodes


def _sum_infos(calls: list, n_seeds: int, epoch: int) -> dict:
    """An epoch's host steps as one ``info``: counts and times summed, ``changed`` and
    ``updated`` or-ed, each call's own info under ``calls``."""
    info = dict(epoch=epoch, host_calls=len(calls),
                episodes_processed=int(sum(np.sum(c["seeds"]) for c in calls)),
                changed=np.zeros(n_seeds, bool), updated=np.zeros(n_seeds, bool),
                fit_s=0.0, refine_s=0.0, host_s=0.0, calls=calls)
    info.update({k: 0 for k in _SUMMED_INFO})
    info["verdicts"] = [v for c in calls for v in c.get("verdicts", [])]
    for c in calls:
        for k in (*_SUMMED_INFO, "fit_s", "refine_s", "host_s"):
            info[k] += c.get(k, 0)
        for k in ("changed", "updated"):
            info[k] |= np.asarray(c.get(k, np.zeros(n_seeds, bool)), bool)
    return info


def train_epochs(config, seeds, total_steps: int, *, init_state: LoopState | None = None,
                 devices=None, batch_invariant: bool | None = None) -> Iterator[EpochOutput]:
    """Run a multi-seed training epoch by epoch, yielding an :class:`EpochOutput` after each.

    The generator form is what checkpointing builds on: save ``out.loop`` after any epoch and
    pass it back as ``init_state`` to continue (the remaining epochs then run exactly as they
    would have). The agent states are *donated* to the next epoch (updated in place), so a
    yielded ``out.loop.states`` is only valid until the generator resumes: save or
    ``jax.device_get`` it before asking for the next epoch. ``init_state`` is consumed likewise.

    ``devices`` (``None``: all, an int: the first ``n``, or a sequence of devices) is the mesh
    the seeds are sharded over (see the module docstring); the seed count must be a multiple
    of the device count. An ``init_state`` laid out otherwise is re-laid onto it first.
    ``batch_invariant``: as in :func:`train_many`.

    Example:
        >>> from gara_jax.algorithms import HandcraftedConfig
        >>> cfg = HandcraftedConfig(steps_per_epoch=20, eval_episodes=1)
        >>> [out.epoch for out in train_epochs(cfg, 2, total_steps=40)]
        [0, 1]
    """
    comp = compiled(config, devices, batch_invariant)
    alg, run, mesh = comp.alg, comp.run, comp.mesh
    n_epochs = n_epochs_for(config, total_steps)
    check_divisible(len(seed_list(seeds)), mesh)
    if init_state is None:
        loop = init_loop(config, seeds, devices=mesh, batch_invariant=run.batch_invariant)
    else:
        if init_state.epoch > n_epochs:
            raise ValueError(f"init_state: epoch {init_state.epoch} is past the run's "
                             f"{n_epochs} epochs")
        loop = place(init_state, mesh)
    if comp.segment is not None and jax.process_count() > 1:
        raise ValueError("cadence: 'episode' runs in one process (jax.distributed is not "
                         "supported for it yet)")
    for epoch in range(loop.epoch, n_epochs):
        t0 = time.perf_counter()
        if comp.segment is not None:
            states, metrics, info, snaps, episodes = _episode_cadence_epoch(comp, loop, epoch)
            loop = LoopState(states=states, keys=loop.keys, epoch=epoch + 1, seeds=loop.seeds)
            yield EpochOutput(epoch, n_epochs, loop, metrics, info, snaps,
                              time.perf_counter() - t0, episodes)
            continue
        states, metrics = run(loop.states, loop.keys, epoch)
        metrics = fetch(metrics)
        log = metrics.pop("episode_log", None)
        episodes = None if log is None else episodes_of_epoch(log)
        metrics = {k: np.asarray(v) for k, v in metrics.items()}
        info = None
        snaps = [[] for _ in loop.seeds]
        if alg.host_update is not None:
            n = len(loop.seeds)
            with batch_invariant_scope(run.batch_invariant):  # its SeedJits follow the run's
                local, info = alg.host_update(_local_states(states, mesh, n), epoch)
            states, info = _global_states(local, mesh, n), _gather_info(info)
            changed = np.asarray(info.get("changed", np.zeros(len(loop.seeds), bool)))
            if changed.any():
                current = _snapshots(states)
                for i in np.flatnonzero(changed):
                    snaps[i].append(current[i])
        jax.block_until_ready(states)
        loop = LoopState(states=states, keys=loop.keys, epoch=epoch + 1, seeds=loop.seeds)
        yield EpochOutput(epoch, n_epochs, loop, metrics, info, snaps, time.perf_counter() - t0,
                          episodes)


def train_many(config, seeds, total_steps: int, *,
               progress: Callable[[int, int, dict], None] | None = None,
               callback: Callable[[EpochOutput], bool | None] | None = None,
               init_state: LoopState | None = None, devices=None,
               batch_invariant: bool | None = None,
               initial_partitions=None) -> TrainResult:
    """Train ``config``'s algorithm on several seeds at once and collect the curves.

    Args:
        config: ``GaraConfig``, ``HandcraftedConfig`` or ``HiroConfig``.
        seeds: a seed count ``n`` (seeds ``0..n-1``) or a sequence of distinct ints.
        total_steps: environment steps per seed, rounded up to whole epochs.
        progress: called as ``progress(epochs_done, n_epochs, metrics)`` after every epoch
            (``metrics``: name -> ``[n_seeds]``), e.g. to drive a progress bar.
        callback: called with each :class:`EpochOutput`; returning ``True`` stops the run after
            that epoch (the result then holds the epochs run so far). Use it to checkpoint
            ``out.loop``.
        init_state: a :class:`LoopState` to continue from (its seeds must match ``seeds``);
            its states are consumed (donated to the first epoch run).
        devices: ``None`` (all devices), a count ``n`` (the first ``n``) or a sequence of
            devices to shard the seeds over; the seed count must be a multiple of the device
            count (``ValueError`` naming ``seeds`` and ``devices`` otherwise).
        batch_invariant: compile so that each seed's result does not depend on how many seeds
            share its device (:mod:`gara_jax.sharding`; on CPU it turns XLA's YNNPACK dots
            off, which is slower). ``None``: only when there is more than one device. A run
            over several devices gives, bit for bit, the results of a one-device run with
            ``batch_invariant=True``; a one-device run with the default gives results that
            differ from those in the last bits (and, through training, beyond).
        initial_partitions: GARA only: one partition per seed to start from (e.g.
            ``final_partitions(q_result)`` of a Q-learning run on the same seeds, for the
            authors' Planning runs, SPEC.md 3.9.3); only the partition is taken, see
            :func:`init_loop`. Not with ``init_state``.

    Returns:
        A :class:`TrainResult` covering the epochs run by this call.

    Example:
        >>> from gara_jax.algorithms import HandcraftedConfig
        >>> cfg = HandcraftedConfig(steps_per_epoch=20, eval_episodes=1)
        >>> res = train_many(cfg, seeds=2, total_steps=50)
        >>> res.metrics["eval_success"].shape, res.metrics["env_steps"][0].tolist()
        ((2, 3), [20, 40, 60])
    """
    t_start = time.perf_counter()
    seeds = seed_list(seeds)
    if init_state is not None and list(init_state.seeds) != seeds:
        raise ValueError(f"init_state: its seeds {list(init_state.seeds)} differ from {seeds}")
    comp = compiled(config, devices, batch_invariant)
    alg, invariant = comp.alg, comp.run.batch_invariant
    check_divisible(len(seeds), comp.mesh)
    if init_state is not None and initial_partitions is not None:
        raise ValueError("initial_partitions: a run resumed from init_state keeps its own "
                         "partitions; pass one or the other")
    loop = (init_loop(config, seeds, devices=comp.mesh, batch_invariant=invariant,
                      initial_partitions=initial_partitions)
            if init_state is None else init_state)
    start = _snapshots(loop.states)
    snapshots = [[] for _ in seeds] if start is None else [
        [s] if loop.epoch == 0 else [] for s in start]
    rows, host_info, first_epoch_s, host_s = [], [], None, 0.0
    episodes = None
    for out in train_epochs(config, seeds, total_steps, init_state=loop, devices=comp.mesh,
                            batch_invariant=invariant):
        rows.append(out.metrics)
        if out.episodes is not None:
            episodes = {name: [[] for _ in seeds] for name in EPISODE_FIELDS} if (
                episodes is None) else episodes
            for name in EPISODE_FIELDS:
                for i, values in enumerate(out.episodes[name]):
                    episodes[name][i].append(values)
        host_info.append(out.host_info)
        if out.host_info is not None:
            host_s += float(out.host_info.get("host_s", 0.0))
        for i, snaps in enumerate(out.snapshots):
            snapshots[i].extend(snaps)
        first_epoch_s = out.epoch_s if first_epoch_s is None else first_epoch_s
        loop = out.loop
        if progress is not None:
            progress(out.epoch + 1, out.n_epochs, out.metrics)
        if callback is not None and callback(out):
            break
    metrics = {k: np.stack([r[k] for r in rows], axis=1) for k in rows[0]} if rows else {}
    if episodes is not None:
        episodes = {name: [np.concatenate(parts) for parts in per_seed]
                    for name, per_seed in episodes.items()}
    return TrainResult(config=config, algorithm=alg.name, seeds=seeds, metrics=metrics,
                       snapshots=snapshots, wall_time_s=time.perf_counter() - t_start,
                       first_epoch_s=first_epoch_s or 0.0, host_time_s=host_s,
                       host_info=host_info, final=loop, episodes=episodes)


def make_train(config, total_steps: int = 120_000):
    """``train(key) -> (final_state, metrics)`` for one seed, PureJaxRL style.

    For algorithms without a host step (Handcrafted, HIRO) ``train`` is a pure function of the
    key (one ``lax.scan`` over epochs): jit it, and ``vmap`` it over keys for many seeds.
    ``metrics`` maps names to ``[n_epochs]`` arrays. GARA needs the host between epochs, so
    its ``train`` runs the epoch loop in Python for the one seed (not jittable; use
    :func:`train_many` for many seeds). Both use the key the way :func:`train_many` uses
    ``jax.random.key(seed)``.

    Example:
        >>> import jax
        >>> from gara_jax.algorithms import HandcraftedConfig
        >>> train = make_train(HandcraftedConfig(steps_per_epoch=20, eval_episodes=1), 40)
        >>> state, metrics = jax.jit(train)(jax.random.key(0))
        >>> metrics["env_steps"].tolist()
        [20, 40]
    """
    alg = compiled(config, 1).alg
    n_epochs = n_epochs_for(config, total_steps)
    epoch_fn = _epoch_fn(alg)

    if alg.host_update is None:
        def train(key):
            init_key, loop_key = _split_seed_keys(key[None])
            state = alg.init(init_key[0])

            def body(state, epoch):
                return epoch_fn(state, loop_key[0], epoch)

            return jax.lax.scan(body, state, jnp.arange(n_epochs))

        return train

    def train_hosted(key):
        init_key, loop_key = _split_seed_keys(jnp.asarray(key)[None])
        loop = LoopState(states=jax.jit(jax.vmap(alg.init))(init_key), keys=loop_key, epoch=0,
                         seeds=(0,))
        rows = []
        for out in train_epochs(config, [0], total_steps, init_state=loop, devices=1):
            rows.append(out.metrics)
            loop = out.loop
        state = jax.tree.map(lambda a: a[0], loop.states)
        return state, {k: np.stack([r[k][0] for r in rows]) for k in rows[0]}

    return train_hosted
