"""Starting a multi-process (multi-host) run with ``jax.distributed``.

Every process runs the same command; they find each other through a coordinator. The
standard environment variables say where and who:

- ``JAX_COORDINATOR_ADDRESS``: ``host:port`` of process 0's coordinator service;
- ``JAX_NUM_PROCESSES``: how many processes take part;
- ``JAX_PROCESS_ID``: this process's index, ``0 .. JAX_NUM_PROCESSES - 1``;
- ``JAX_LOCAL_DEVICE_IDS`` (optional, read by JAX): which local accelerators this process uses.

Where they are not set, JAX's own cluster detection (SLURM, Open MPI, Kubernetes, Cloud TPU)
fills them in. After :func:`initialize_from_env`, ``jax.devices()`` lists every process's
devices: the training driver shards the seeds over all of them and each process computes the
seeds of its own devices (:mod:`gara_jax.sharding`). On CPU the processes exchange data through
JAX's gloo collectives (the default CPU collectives implementation of jax 0.10).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

ENV_VARS = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")


def settings_from_env(environ: Mapping[str, str] | None = None) -> dict:
    """The ``jax.distributed.initialize`` arguments the environment sets (``None`` if unset).

    Example:
        >>> settings_from_env({"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234",
        ...                    "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"})
        {'coordinator_address': '10.0.0.1:1234', 'num_processes': 2, 'process_id': 1}
        >>> settings_from_env({"JAX_NUM_PROCESSES": "two"})
        Traceback (most recent call last):
        ...
        ValueError: JAX_NUM_PROCESSES: must be an integer, got 'two'
    """
    environ = os.environ if environ is None else environ
    out = {"coordinator_address": environ.get("JAX_COORDINATOR_ADDRESS") or None}
    for var, name in (("JAX_NUM_PROCESSES", "num_processes"), ("JAX_PROCESS_ID", "process_id")):
        text = environ.get(var)
        if text in (None, ""):
            out[name] = None
            continue
        try:
            out[name] = int(text)
        except ValueError:
            raise ValueError(f"{var}: must be an integer, got {text!r}") from None
    n, i = out["num_processes"], out["process_id"]
    if n is not None and n < 1:
        raise ValueError(f"JAX_NUM_PROCESSES: must be >= 1, got {n}")
    if n is not None and i is not None and not 0 <= i < n:
        raise ValueError(f"JAX_PROCESS_ID: must be in [0, {n}), got {i}")
    return out


def initialize_from_env(environ: Mapping[str, str] | None = None) -> tuple[int, int]:
    """``jax.distributed.initialize`` from :func:`settings_from_env`; returns
    ``(process_index, process_count)``. Must run before any other JAX call of the process.

    Raises ``ValueError`` naming the variables when neither they nor a detected cluster say
    how to connect.
    """
    import jax

    settings = settings_from_env(environ)
    try:
        jax.distributed.initialize(**settings)
    except ValueError as err:
        raise ValueError(f"--distributed: {err} (set {', '.join(ENV_VARS)}, or run under a "
                         f"cluster manager JAX detects)") from err
    return jax.process_index(), jax.process_count()
