"""Saving and restoring a multi-seed run at an epoch boundary, with orbax.

A checkpoint is a directory managed by an ``orbax.checkpoint.CheckpointManager``: one step per
saved epoch (the newest kept), each holding the :class:`~gara_jax.train.LoopState` arrays
(``states`` and ``keys``, PRNG keys as raw key data) and a JSON item with the epoch, the
seeds, every array's path, shape and dtype, and whatever the caller keeps with it (``extra``:
metrics so far, snapshots, timings).

- **Sharded arrays are written as they lie**: each process writes its own shards (orbax's
  tensorstore writer); nothing is gathered on one device or host first. Restoring lays the
  arrays out as the template's are (another device count works: the layout is not saved).
- **Atomic**: orbax writes a step into a temporary directory and renames it when complete,
  and the previous step is deleted only after that; a process killed mid-write leaves the
  previous checkpoint readable (an unfinished temporary directory is ignored).
- **Exact resume**: the arrays come back bit for bit (tested).
- **A mismatched run** (other seeds, another config's state shapes) raises ``ValueError``
  naming what differs, before any array is read.

The previous format, one ``.npz`` file per run, is still read by :func:`load` (pass the
``.npz`` path); :func:`convert` rewrites one as an orbax checkpoint.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import jax
import numpy as np

from gara_jax.results import atomic_write_bytes
from gara_jax.train import LoopState, fetch, place

FORMAT = "gara-jax loop state, orbax, v1"


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _plain(tree):
    """PRNG key leaves as their raw key data (orbax and NumPy store plain arrays)."""
    return jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else x, tree)


def _leaf_table(tree) -> list:
    return [[jax.tree_util.keystr(path), list(x.shape), str(x.dtype)]
            for path, x in jax.tree_util.tree_flatten_with_path(_plain(tree))[0]]


def _manager(path, *, create: bool):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=1, create=create,
                                           enable_async_checkpointing=False)
    return ocp.CheckpointManager(Path(path).absolute(), options=options,
                                 item_names=("arrays", "meta"))


def latest_epoch(path) -> int | None:
    """The epoch count of the newest complete checkpoint under ``path`` (``None`` if none).

    Example:
        >>> import tempfile
        >>> latest_epoch(tempfile.mkdtemp()) is None
        True
    """
    if not Path(path).is_dir():
        return None
    with _manager(path, create=False) as mngr:
        return mngr.latest_step()


def save(path, loop: LoopState, extra: dict | None = None) -> None:
    """Write ``loop`` (and the JSON-serialisable ``extra``) as the checkpoint of epoch
    ``loop.epoch`` under the directory ``path``, replacing the previous one once complete.

    Every process of a ``jax.distributed`` run must call it (each writes its own shards).

    Example:
        >>> import tempfile, os, jax.numpy as jnp
        >>> loop = LoopState(states={"w": jnp.ones(2)}, keys=jnp.zeros((1, 2), jnp.uint32),
        ...                  epoch=3, seeds=(0,))
        >>> p = os.path.join(tempfile.mkdtemp(), "run")
        >>> save(p, loop, {"note": "hi"})
        >>> back, extra = load(p, loop._replace(epoch=0))
        >>> back.epoch, extra["note"], back.states["w"].tolist(), latest_epoch(p)
        (3, 'hi', [1.0, 1.0], 3)
    """
    import orbax.checkpoint as ocp

    arrays = {"states": _plain(loop.states), "keys": _plain(loop.keys)}
    meta = {"format": FORMAT, "epoch": int(loop.epoch), "seeds": list(loop.seeds),
            "leaves": _leaf_table(arrays), "extra": extra or {}}
    with _manager(path, create=True) as mngr:
        mngr.save(int(loop.epoch), args=ocp.args.Composite(
            arrays=ocp.args.StandardSave(arrays), meta=ocp.args.JsonSave(meta)), force=True)
        mngr.wait_until_finished()


def _restore_template(template: LoopState):
    """Abstract arrays (shape, dtype, layout) of ``template``, keys as raw key data."""
    def abstract(x):
        x = jax.random.key_data(x) if _is_key(x) else x
        sharding = getattr(x, "sharding", None)
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)

    return jax.tree.map(abstract, {"states": template.states, "keys": template.keys})


def _rewrap(tree, template):
    return jax.tree.map(lambda x, t: jax.random.wrap_key_data(x, impl=jax.random.key_impl(t))
                        if _is_key(t) else x, tree, template)


def load(path, template: LoopState) -> tuple[LoopState, dict]:
    """The newest :class:`LoopState` saved under ``path`` and its extra dict.

    ``template`` (a fresh :func:`~gara_jax.train.init_loop` of the same config and seeds)
    gives the tree structure and the layout to restore onto. A path to a ``.npz`` file reads
    the previous single-file format. Raises ``ValueError`` if the checkpoint does not match the
    template (other seeds, other state shapes) or if there is none.
    """
    path = Path(path)
    if path.suffix == ".npz" and path.is_file():
        return load_npz(path, template)
    import orbax.checkpoint as ocp

    epoch = latest_epoch(path)
    if epoch is None:
        raise ValueError(f"checkpoint {path}: no complete checkpoint there")
    with _manager(path, create=False) as mngr:
        meta = mngr.restore(epoch, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        _check(path, meta, template)
        abstract = _restore_template(template)
        arrays = mngr.restore(epoch, args=ocp.args.Composite(
            arrays=ocp.args.StandardRestore(abstract)))["arrays"]
    loop = LoopState(states=_rewrap(arrays["states"], template.states),
                     keys=_rewrap(arrays["keys"], template.keys), epoch=int(meta["epoch"]),
                     seeds=tuple(meta["seeds"]))
    return loop, meta["extra"]


def _check(path, meta: dict, template: LoopState) -> None:
    if meta.get("format") != FORMAT:
        raise ValueError(f"checkpoint {path}: not a {FORMAT!r} checkpoint")
    if tuple(meta["seeds"]) != tuple(template.seeds):
        raise ValueError(f"checkpoint {path}: seeds {meta['seeds']} differ from this run's "
                         f"{list(template.seeds)}")
    want = _leaf_table({"states": template.states, "keys": template.keys})
    if len(meta["leaves"]) != len(want):
        raise ValueError(f"checkpoint {path}: {len(meta['leaves'])} arrays, this run's state "
                         f"has {len(want)} (another algorithm or config?)")
    for got, expected in zip(meta["leaves"], want, strict=True):
        if got != expected:
            raise ValueError(f"checkpoint {path}: array {got[0]} is {got[2]}{tuple(got[1])}, "
                             f"this run's {expected[0]} is {expected[2]}{tuple(expected[1])} "
                             f"(another config?)")


def convert(npz_path, path, template: LoopState) -> LoopState:
    """Rewrite a checkpoint of the previous ``.npz`` format as an orbax checkpoint at ``path``.

    Example:
        >>> import tempfile, os, jax.numpy as jnp
        >>> loop = LoopState(states={"w": jnp.ones(2)}, keys=jnp.zeros((1, 2), jnp.uint32),
        ...                  epoch=2, seeds=(0,))
        >>> d = tempfile.mkdtemp()
        >>> save_npz(os.path.join(d, "old.npz"), loop, {"k": 1})
        >>> convert(os.path.join(d, "old.npz"), os.path.join(d, "new"), loop).epoch
        2
        >>> load(os.path.join(d, "new"), loop)[1]
        {'k': 1}
    """
    loop, extra = load_npz(npz_path, template)
    save(path, loop, extra)
    return loop


# ----------------------------------------------------------------------------------------------
# The previous format: one .npz file (read, and written by convert's tests)
# ----------------------------------------------------------------------------------------------


def save_npz(path, loop: LoopState, extra: dict | None = None) -> None:
    """The previous format: ``loop`` gathered to the host and written as one ``.npz`` file
    (atomically, through a temporary file and a rename)."""
    leaves = jax.tree.leaves(fetch(_plain(loop.states)))
    arrays = {f"leaf_{i}": np.asarray(x) for i, x in enumerate(leaves)}
    arrays["keys"] = np.asarray(fetch(loop.keys))
    meta = {"epoch": int(loop.epoch), "seeds": list(loop.seeds), "n_leaves": len(leaves),
            "extra": extra or {}}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_npz(path, template: LoopState) -> tuple[LoopState, dict]:
    """Read the previous ``.npz`` format (structure and layout from ``template``)."""
    with np.load(path) as data:
        meta = json.loads(bytes(data["meta"]).decode())
        leaves_t, treedef = jax.tree.flatten(template.states)
        if meta["n_leaves"] != len(leaves_t) or tuple(meta["seeds"]) != tuple(template.seeds):
            raise ValueError(f"checkpoint {path}: does not match this run's config and seeds")
        leaves = []
        for i, t in enumerate(leaves_t):
            x = data[f"leaf_{i}"]
            if _is_key(t):
                leaves.append(jax.random.wrap_key_data(x, impl=jax.random.key_impl(t)))
                continue
            if x.shape != t.shape or x.dtype != t.dtype:
                raise ValueError(f"checkpoint {path}: leaf {i} is {x.dtype}{x.shape}, "
                                 f"expected {t.dtype}{t.shape}")
            leaves.append(x)
        keys = np.asarray(data["keys"])
    loop = LoopState(states=jax.tree.unflatten(treedef, leaves), keys=keys,
                     epoch=int(meta["epoch"]), seeds=tuple(meta["seeds"]))
    mesh = _mesh_of_template(template)
    return (place(loop, mesh) if mesh is not None else loop), meta["extra"]


def _mesh_of_template(template: LoopState):
    sharding = getattr(template.keys, "sharding", None)
    return getattr(sharding, "mesh", None)
