"""Seeds over devices: a 1-D device mesh, and jitted functions run device by device on it.

Every per-seed array (agent states, loop keys, metrics) has the seed axis first and is laid out
with ``NamedSharding(mesh, PartitionSpec("seeds"))`` over a 1-D mesh: device ``j`` of ``d``
holds seeds ``j * n/d`` to ``(j + 1) * n/d - 1``. Seeds never interact, so there is nothing
to communicate; :class:`SeedJit` runs the *one-device* program of a jitted, seed-vmapped
function on each device's block (dispatched asynchronously, so the devices run at the same
time) and lays the outputs back out over the mesh. Why not one SPMD program: XLA optimises a
partitioned program differently from a one-device one (on CPU we measured float32 results
that differ in the last bits after one epoch), and results that depend on the device count
would make runs irreproducible. The price is one compilation per device (the same program,
placed on each).

A device's block must reproduce the same seeds computed in a larger batch, which XLA does not
promise, so that is a choice, ``batch_invariant``, made per compiled function. Two things broke it
on CPU: XLA's YNNPACK dot fusions (on by default; a vmapped matrix product's per-seed result
differed between batches of 2 and 8 seeds), and a batch of exactly one seed, whose size-1 axis
XLA optimises away (GARA's forward-model MSE records differed in the last bit). With
``batch_invariant=True`` the function is compiled on CPU with the YNNPACK fusions off
(:data:`CPU_BATCH_INVARIANT_OPTIONS`) and a block of one seed runs as two copies of it (the copy
dropped); batches of 2 and 8 seeds then gave identical per-seed results in every array of every
algorithm we compared (``tests/test_sharding.py`` checks 8 seeds on 4 devices against one
device). It costs speed on CPU (YNNPACK's dots are faster: ``benchmarks/batch_invariance_cost.py``
measured 20-seed epochs 1.45x as long for Handcrafted, 1.34x for GARA, 1.33x for the paper's
HIRO and 1.09x for published HIRO on a 2-core CPU), so the training driver turns it on only for
runs over more than one device unless asked: a one-device run is then bitwise the run it always
was, and a run over several devices is bitwise the one-device run made with
``batch_invariant=True``.

Under ``jax.distributed`` the mesh spans every process's devices and each process runs the
blocks of its own (addressable) devices.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

#: The mesh axis the seeds are sharded over.
SEED_AXIS = "seeds"

#: XLA:CPU compiler options under which per-seed results do not depend on the batch size (see
#: the module docstring): YNNPACK fusions off.
CPU_BATCH_INVARIANT_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


_scope = threading.local()


@contextlib.contextmanager
def batch_invariant_scope(on: bool) -> Iterator[None]:
    """Within the block, :class:`SeedJit` functions made with ``batch_invariant=None`` run
    batch-invariant (``on=True``) or not (outside any block: not). The training driver wraps
    GARA's host step in it, so that the host step's device functions follow the run's choice.

    Example:
        >>> with batch_invariant_scope(True):
        ...     inside = current_batch_invariance()
        >>> inside, current_batch_invariance()
        (True, False)
    """
    before = getattr(_scope, "on", False)
    _scope.on = bool(on)
    try:
        yield
    finally:
        _scope.on = before


def current_batch_invariance() -> bool:
    """The innermost :func:`batch_invariant_scope`'s choice (``False`` outside any)."""
    return getattr(_scope, "on", False)


def resolve_devices(devices=None) -> list:
    """The devices a run uses: ``None`` all of them (``jax.devices()``: the local devices in one
    process, every process's under ``jax.distributed``), an int ``n`` the first ``n``, a
    sequence of devices, or a :class:`~jax.sharding.Mesh` (its devices).

    Example:
        >>> import jax
        >>> resolve_devices(1) == jax.devices()[:1], resolve_devices(None) == jax.devices()
        (True, True)
    """
    available = jax.devices()
    if devices is None:
        return list(available)
    if isinstance(devices, Mesh):
        return list(devices.devices.flat)
    if isinstance(devices, bool):
        raise ValueError(f"devices: must be None, a count or a sequence of devices, got {devices}")
    if isinstance(devices, int | np.integer):
        if not 1 <= devices <= len(available):
            raise ValueError(f"devices: a device count must be in [1, {len(available)}] "
                             f"(the devices available), got {devices}")
        return list(available[: int(devices)])
    out = list(devices) if isinstance(devices, Sequence) else None
    if not out or not all(isinstance(d, jax.Device) for d in out):
        raise ValueError(f"devices: must be None, a count or a sequence of devices, got "
                         f"{devices!r}")
    if len(set(out)) != len(out):
        raise ValueError(f"devices: must be distinct, got {out}")
    return out


def seed_mesh(devices=None) -> Mesh:
    """The 1-D device mesh (axis ``"seeds"``) over ``resolve_devices(devices)``.

    Example:
        >>> dict(seed_mesh(1).shape)
        {'seeds': 1}
    """
    if isinstance(devices, Mesh):
        return devices
    return Mesh(np.asarray(resolve_devices(devices), dtype=object), (SEED_AXIS,))


def seed_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (seed) axis split over ``mesh``'s devices, the other axes whole."""
    return NamedSharding(mesh, PartitionSpec(SEED_AXIS))


def check_divisible(n_seeds: int, mesh: Mesh) -> None:
    """``ValueError`` naming ``seeds``/``devices`` unless ``n_seeds`` is a multiple of the
    mesh's device count (every device gets the same number of seeds).

    Example:
        >>> check_divisible(3, seed_mesh(1)) is None
        True
    """
    n_dev = mesh.devices.size
    if n_seeds % n_dev:
        fits = max(d for d in range(1, n_dev + 1) if n_seeds % d == 0)
        raise ValueError(f"seeds/devices: {n_seeds} seeds do not divide over {n_dev} devices; "
                         f"use a seed count that is a multiple of {n_dev}, or devices={fits}")


def _mesh_of(tree) -> Mesh | None:
    for x in jax.tree.leaves(tree):
        sharding = getattr(x, "sharding", None)
        if isinstance(sharding, NamedSharding) and sharding.mesh.axis_names == (SEED_AXIS,):
            return sharding.mesh
    return None


def _local_devices(mesh: Mesh) -> list:
    me = jax.process_index()
    return [d for d in mesh.devices.flat if d.process_index == me]


def _blocks(x, mesh: Mesh, n_seeds: int, devices: list) -> list:
    """``x``'s block of seeds on each of ``devices`` (no copy when already laid out so)."""
    if isinstance(x, jax.Array) and (_is_seed_sharded(x) or not x.is_fully_addressable):
        by_device = {s.device: s.data for s in x.addressable_shards}
        return [by_device[d] for d in devices]
    per = n_seeds // mesh.devices.size
    index = {d: j for j, d in enumerate(mesh.devices.flat)}
    host = np.asarray(jax.device_get(x))
    return [jax.device_put(host[index[d] * per: (index[d] + 1) * per], d) for d in devices]


def _is_seed_sharded(x) -> bool:
    sharding = x.sharding
    return (isinstance(sharding, NamedSharding) and sharding.mesh.axis_names == (SEED_AXIS,)
            and sharding.spec[:1] == (SEED_AXIS,))


def relayout(tree, mesh: Mesh, n_seeds: int):
    """``tree``'s seed-sharded leaves laid out over ``mesh`` (its devices must hold the same
    blocks: e.g. a process's own devices and the global mesh), without copying.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> x = jax.device_put(jnp.arange(2), seed_sharding(seed_mesh(1)))
        >>> relayout({"x": x}, seed_mesh(1), 2)["x"].tolist()
        [0, 1]
    """
    devices = _local_devices(mesh)
    return assemble([jax.tree.map(lambda x, j=j: {s.device: s.data
                                                 for s in x.addressable_shards}[devices[j]],
                                  tree) for j in range(len(devices))], mesh, n_seeds)


def assemble(blocks: list, mesh: Mesh, n_seeds: int):
    """One array per leaf laid out over ``mesh`` from the per-device blocks (trees) of this
    process's devices, in mesh order (no copy).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> mesh = seed_mesh(1)
        >>> out = assemble([{"a": jnp.arange(3)}], mesh, 3)
        >>> out["a"].tolist(), out["a"].sharding == seed_sharding(mesh)
        ([0, 1, 2], True)
    """
    sharding = seed_sharding(mesh)

    def one(*parts):
        shape = (n_seeds, *parts[0].shape[1:])
        return jax.make_array_from_single_device_arrays(shape, sharding, list(parts))

    return jax.tree.map(one, *blocks)


def _twice(x):
    return jax.numpy.concatenate([x, x])


class SeedJit:
    """``jax.jit(fn)`` for a seed-vmapped ``fn``, run device by device on seed-sharded inputs.

    ``batched`` names the positional arguments that have the seed axis first (default: all);
    the others are passed whole to every device. When the batched inputs are laid out over a
    seed mesh (:func:`seed_sharding`), each of this process's devices runs the one-device
    program on its block and the outputs (seed axis first) come back laid out over the same
    mesh; otherwise it is a plain jitted call. ``batch_invariant=True`` makes each seed's
    result independent of how many seeds share its block (see the module docstring: on CPU
    the function is compiled with :data:`CPU_BATCH_INVARIANT_OPTIONS`, and a one-seed block
    runs as two copies); ``None`` follows :func:`batch_invariant_scope`. Extra keyword
    arguments go to ``jax.jit`` (e.g. ``donate_argnums``).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> double = SeedJit(jax.vmap(lambda x, c: 2 * x + c, in_axes=(0, None)), batched=(0,))
        >>> x = jax.device_put(jnp.arange(4.0), seed_sharding(seed_mesh(1)))
        >>> double(x, 1.0).tolist()
        [1.0, 3.0, 5.0, 7.0]
    """

    def __init__(self, fn: Callable, batched: Sequence[int] | None = None, *,
                 batch_invariant: bool | None = None, **jit_kwargs):
        self._fn, self._batched, self._kwargs = fn, batched, jit_kwargs
        self.batch_invariant = None if batch_invariant is None else bool(batch_invariant)
        self._jits: dict[tuple[str, bool], Callable] = {}
        self.__wrapped__ = fn
        self.__doc__ = fn.__doc__

    def invariant(self) -> bool:
        """Whether a call now runs batch-invariant (``batch_invariant``, or the scope's)."""
        return current_batch_invariance() if self.batch_invariant is None else self.batch_invariant

    def jitted(self, platform: str, invariant: bool | None = None) -> Callable:
        """The ``jax.jit`` of ``fn`` used on ``platform`` (e.g. to lower and time it)."""
        invariant = self.invariant() if invariant is None else invariant
        if (platform, invariant) not in self._jits:
            options = CPU_BATCH_INVARIANT_OPTIONS if invariant and platform == "cpu" else None
            self._jits[platform, invariant] = jax.jit(self._fn, compiler_options=options,
                                                      **self._kwargs)
        return self._jits[platform, invariant]

    def __call__(self, *args):
        batched = range(len(args)) if self._batched is None else self._batched
        mesh = _mesh_of([args[i] for i in batched])
        platform = (jax.devices()[0] if mesh is None else mesh.devices.flat[0]).platform
        invariant = self.invariant()
        run = self.jitted(platform, invariant)
        if mesh is None:
            return run(*args)
        n_seeds = int(jax.tree.leaves(args[batched[0]])[0].shape[0])
        devices = _local_devices(mesh)
        # One seed per device: run it twice (see the module docstring).
        single = invariant and n_seeds == mesh.devices.size
        per_arg = {}
        for i in batched:
            leaves, treedef = jax.tree.flatten(args[i])
            per_arg[i] = (treedef, [_blocks(x, mesh, n_seeds, devices) for x in leaves])
        outs = []
        for j in range(len(devices)):
            call = list(args)
            for i, (treedef, blocks) in per_arg.items():
                call[i] = jax.tree.unflatten(treedef, [_twice(b[j]) if single else b[j]
                                                       for b in blocks])
            outs.append(run(*call))  # asynchronous: every device starts before any finishes
        if single:
            outs = [jax.tree.map(lambda x: x[:1], out) for out in outs]
        return assemble(outs, mesh, n_seeds)
