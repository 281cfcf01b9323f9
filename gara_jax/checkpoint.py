"""Saving and restoring a multi-seed run at an epoch boundary.

A checkpoint is one ``.npz`` holding the :class:`~gara_jax.train.LoopState` leaves (PRNG keys as
raw key data) plus a JSON blob of whatever the caller wants to keep with it (metrics so far,
snapshots, timings). It is written through a temporary file and a rename, so a process killed
mid-write leaves the previous checkpoint intact. Restoring needs a template ``LoopState`` of
the same config and seeds (a fresh :func:`~gara_jax.train.init_loop`) for the tree structure.
"""

from __future__ import annotations

import io
import json

import jax
import numpy as np

from gara_jax.results import atomic_write_bytes
from gara_jax.train import LoopState


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def save(path, loop: LoopState, extra: dict | None = None) -> None:
    """Write ``loop`` and the JSON-serialisable ``extra`` to ``path`` atomically.

    Example:
        >>> import tempfile, os, jax.numpy as jnp
        >>> loop = LoopState(states={"w": jnp.ones(2)}, keys=jnp.zeros((1, 2), jnp.uint32),
        ...                  epoch=3, seeds=(0,))
        >>> p = os.path.join(tempfile.mkdtemp(), "c.npz")
        >>> save(p, loop, {"note": "hi"})
        >>> back, extra = load(p, loop._replace(epoch=0))
        >>> back.epoch, extra["note"], back.states["w"].tolist()
        (3, 'hi', [1.0, 1.0])
    """
    leaves = jax.tree.leaves(jax.device_get(
        jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else x, loop.states)))
    arrays = {f"leaf_{i}": np.asarray(x) for i, x in enumerate(leaves)}
    arrays["keys"] = np.asarray(jax.device_get(loop.keys))
    meta = {"epoch": int(loop.epoch), "seeds": list(loop.seeds), "n_leaves": len(leaves),
            "extra": extra or {}}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load(path, template: LoopState) -> tuple[LoopState, dict]:
    """The :class:`LoopState` saved at ``path`` (structure from ``template``) and its extra dict.

    Raises ``ValueError`` if the file does not match the template (other seeds or state shape).
    """
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
            leaves.append(jax.numpy.asarray(x))
        keys = jax.numpy.asarray(data["keys"])
    loop = LoopState(states=jax.tree.unflatten(treedef, leaves), keys=keys,
                     epoch=int(meta["epoch"]), seeds=tuple(meta["seeds"]))
    return loop, meta["extra"]
