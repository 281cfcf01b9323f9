"""JAX's persistent compilation cache for gara-jax's commands, benchmarks and test sessions.

Every ``gara-jax`` run compiles the same epoch programs again (seconds per program on a 2-core
CPU: the compile column of ``benchmarks/train_throughput.py``). With the cache on, a program
compiled once is read back from disk by every later process that compiles the same program
(same shapes, same config, same jax/jaxlib, same XLA flags: JAX's cache key covers all of
them). A program read from the cache computes what the compiled one does
(``tests/test_compile_cache.py`` checks it on one program).

Where it lives, in order:

1. ``GARA_JAX_COMPILE_CACHE=0`` (or ``off``, ``false``, ``no``): off.
2. ``GARA_JAX_COMPILE_CACHE=/some/dir``: that folder.
3. Otherwise ``$XDG_CACHE_HOME/gara-jax/jax``, or ``~/.cache/gara-jax/jax`` where
   ``XDG_CACHE_HOME`` is unset.

``gara-jax`` (every subcommand) and the benchmark scripts call :func:`enable` at start;
``--no-compile-cache`` turns it off for one run. The test suite uses a fresh folder per run,
shared by its xdist workers (``tests/conftest.py``). The library itself never turns the cache
on: code that imports ``gara_jax`` decides for itself (``gara_jax.compile_cache.enable()``).

The folder grows with every distinct program (a few MB each); delete it at any time, or
bound it with ``jax.config.update("jax_compilation_cache_max_size", BYTES)``.

Example:
    >>> from gara_jax import compile_cache
    >>> compile_cache.default_dir().parts[-2:]
    ('gara-jax', 'jax')
    >>> compile_cache.resolve(disable=True) is None     # what --no-compile-cache asks
    True
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "GARA_JAX_COMPILE_CACHE"
OFF_VALUES = frozenset({"0", "off", "false", "no"})
ON_VALUES = frozenset({"", "1", "on", "true", "yes"})

# Programs that compile faster than this are not written (JAX's own default is 1.0 s). The
# epoch programs take seconds; the many small host-step and evaluation programs a fraction of
# one, and across a run they add up, so the bar is lower than JAX's.
MIN_COMPILE_TIME_S = 0.1


def default_dir() -> Path:
    """``$XDG_CACHE_HOME/gara-jax/jax``, or ``~/.cache/gara-jax/jax``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "gara-jax" / "jax"


def resolve(disable: bool = False) -> Path | None:
    """The cache folder the environment asks for, or ``None`` when the cache is off.

    Args:
        disable: ``True`` (a ``--no-compile-cache`` flag) turns it off whatever the
            environment says.

    Raises:
        ValueError: ``GARA_JAX_COMPILE_CACHE`` names an existing file, not a folder.
    """
    value = os.environ.get(ENV_VAR, "").strip()
    if disable or value.lower() in OFF_VALUES:
        return None
    if value.lower() in ON_VALUES:
        return default_dir()
    path = Path(value).expanduser()
    if path.exists() and not path.is_dir():
        raise ValueError(f"{ENV_VAR}={value!r} is a file, not a folder for the compilation cache")
    return path


def enable(path: str | os.PathLike | None = None, *,
           min_compile_time_s: float = MIN_COMPILE_TIME_S) -> Path | None:
    """Turn JAX's persistent compilation cache on; returns its folder (``None``: left off).

    Call it before the first computation of the process: JAX reads the setting when it
    first compiles.

    Args:
        path: the folder; ``None`` takes :func:`resolve`'s answer.
        min_compile_time_s: programs that compile faster are not written.
    """
    folder = Path(path).expanduser() if path is not None else resolve()
    if folder is None:
        return None
    folder.mkdir(parents=True, exist_ok=True)
    import jax

    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder


def add_argument(parser) -> None:
    """Add ``--no-compile-cache`` to an ``argparse`` parser (commands and benchmarks)."""
    parser.add_argument("--no-compile-cache", action="store_true",
                        help=f"do not use JAX's persistent compilation cache (default: on, in "
                             f"{ENV_VAR} or ~/.cache/gara-jax/jax; {ENV_VAR}=0 also turns it off)")


def setup(no_compile_cache: bool = False) -> Path | None:
    """:func:`enable` as a command line asks; with ``no_compile_cache`` the environment
    variable is set to off as well, so that subprocesses the command starts agree."""
    if no_compile_cache:
        os.environ[ENV_VAR] = "0"
        import jax

        jax.config.update("jax_compilation_cache_dir", None)
        return None
    return enable()
