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
promise. Two things broke it on CPU, and are worked around here: XLA's experimental YNNPACK
fusions (a vmapped matrix product's per-seed gradient differed at batch 1 and 8), so on CPU
the functions are compiled with them off; and a batch of exactly one seed, whose size-1 axis
XLA optimises away (GARA's forward-model MSE records differed in the last bit), so a block of
one seed is run as two copies of it and the copy dropped. Batches of 2 and 8 seeds gave
identical per-seed results in every array of every algorithm we compared
(``tests/test_sharding.py`` checks 8 seeds on 4 devices against one device).

Under ``jax.distributed`` the mesh spans every process's devices and each process runs the
blocks of its own (addressable) devices.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

#: The mesh axis the seeds are sharded over.
SEED_AXIS = "seeds"

# See the module docstring: per-seed results that do not depend on the batch size on CPU.
CPU_COMPILER_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


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
    seed mesh (:func:`seed_sharding`) of more than one device, each of this process's devices
    runs the one-device program on its block and the outputs (seed axis first) come back laid
    out over the same mesh; otherwise it is a plain jitted call. Extra keyword arguments go to
    ``jax.jit`` (e.g. ``donate_argnums``); on CPU, :data:`CPU_COMPILER_OPTIONS` are added.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> double = SeedJit(jax.vmap(lambda x, c: 2 * x + c, in_axes=(0, None)), batched=(0,))
        >>> x = jax.device_put(jnp.arange(4.0), seed_sharding(seed_mesh(1)))
        >>> double(x, 1.0).tolist()
        [1.0, 3.0, 5.0, 7.0]
    """

    def __init__(self, fn: Callable, batched: Sequence[int] | None = None, **jit_kwargs):
        self._fn, self._batched, self._kwargs = fn, batched, jit_kwargs
        self._jits: dict[str, Callable] = {}
        self.__wrapped__ = fn
        self.__doc__ = fn.__doc__

    def jitted(self, platform: str) -> Callable:
        """The ``jax.jit`` of ``fn`` used on ``platform`` (e.g. to lower and time it)."""
        if platform not in self._jits:
            options = CPU_COMPILER_OPTIONS if platform == "cpu" else None
            self._jits[platform] = jax.jit(self._fn, compiler_options=options, **self._kwargs)
        return self._jits[platform]

    def __call__(self, *args):
        batched = range(len(args)) if self._batched is None else self._batched
        mesh = _mesh_of([args[i] for i in batched])
        platform = (jax.devices()[0] if mesh is None else mesh.devices.flat[0]).platform
        run = self.jitted(platform)
        if mesh is None:
            return run(*args)
        n_seeds = int(jax.tree.leaves(args[batched[0]])[0].shape[0])
        devices = _local_devices(mesh)
        single = n_seeds == mesh.devices.size  # one seed per device: run it twice, see above
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
