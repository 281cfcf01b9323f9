"""Test-session setup: one persistent compilation cache per run, shared by the xdist workers.

The suite compiles many identical programs in different test files and in the subprocesses
that some tests start (``gara-jax reproduce``, the sharded and distributed runs). JAX's
persistent cache (``gara_jax.compile_cache``) lets every process after the first read them
back. The folder is fresh for every run, so that a run's time and results never depend on an
earlier run; the controller creates it and passes it to the workers and to every subprocess
through ``GARA_JAX_COMPILE_CACHE``, and removes it at the end.

``GARA_JAX_COMPILE_CACHE=0 python -m pytest ...`` runs the suite without the cache;
``GARA_JAX_COMPILE_CACHE=/some/dir`` keeps it in that folder (not removed), so that a later
run reuses it.

Most tests run tiny configs for a few hundred steps, so compiling is most of their time: the
suite compiles with XLA's optimisations off (``jax_disable_most_optimizations``, also passed to
every subprocess through ``JAX_DISABLE_MOST_OPTIMIZATIONS``), which roughly halves the compile
time. A module marked ``pytestmark = pytest.mark.optimized`` gets optimised programs: the
learning tests (whose run time dominates) and those that compare two different programs bit for
bit (XLA's unoptimised code need not round the same in both). ``GARA_JAX_TEST_OPTIMIZED=1``
compiles every test optimised, as a user's run does.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import jax
import pytest

from gara_jax import compile_cache

_OWNED = "_GARA_JAX_TEST_CACHE_OWNED"  # set when this session created (and removes) the folder
_ALL_OPTIMIZED = os.environ.get("GARA_JAX_TEST_OPTIMIZED") == "1"
_NO_OPT = "JAX_DISABLE_MOST_OPTIMIZATIONS"


def _set_optimized(on: bool) -> None:
    """Compile from now on with (``on``) or without XLA's optimisations, in this process and in
    the subprocesses it starts; programs compiled before are dropped from memory, so that no
    test runs a program compiled the other way (the flag is not part of jit's cache key)."""
    if jax.config.read("jax_disable_most_optimizations") == (not on):
        return
    jax.config.update("jax_disable_most_optimizations", not on)
    os.environ[_NO_OPT] = "0" if on else "1"
    jax.clear_caches()
    from gara_jax import train

    train._build_cached.cache_clear()


def pytest_configure(config):
    is_worker = hasattr(config, "workerinput")
    if not is_worker and not os.environ.get(compile_cache.ENV_VAR):
        os.environ[compile_cache.ENV_VAR] = tempfile.mkdtemp(prefix="gara-jax-test-cache-")
        os.environ[_OWNED] = "1"
    # Inherited by the xdist workers (started after this hook) and by every subprocess.
    compile_cache.enable()
    _set_optimized(_ALL_OPTIMIZED)


@pytest.fixture(scope="module", autouse=True)
def _xla_optimizations(request):
    """Optimised compiles for a module marked ``optimized`` (module-scoped and autouse, so it
    runs before the module's own fixtures compile anything), unoptimised for the others."""
    _set_optimized(_ALL_OPTIMIZED or request.node.get_closest_marker("optimized") is not None)
    yield


def pytest_unconfigure(config):
    if not hasattr(config, "workerinput") and os.environ.pop(_OWNED, None):
        shutil.rmtree(os.environ.pop(compile_cache.ENV_VAR), ignore_errors=True)


# --- opt-in: where the suite spends its compile time --------------------------------------
# GARA_JAX_TEST_COMPILE_REPORT=FILE appends one JSON line per test (this process's compiles
# only, not those of the subprocesses a test starts): backend compile, tracing and lowering
# seconds, and how many programs came from the persistent cache.
_REPORT = os.environ.get("GARA_JAX_TEST_COMPILE_REPORT")
if _REPORT:
    import json

    import pytest
    from jax import monitoring

    _now = {"compile_s": 0.0, "trace_s": 0.0, "lower_s": 0.0, "compiles": 0, "cache_hits": 0}
    _EVENTS = {"/jax/core/compile/backend_compile_duration": "compile_s",
               "/jax/core/compile/jaxpr_trace_duration": "trace_s",
               "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s"}

    def _on_duration(event, seconds, **_):
        if event in _EVENTS:
            _now[_EVENTS[event]] += seconds
            _now["compiles"] += event.endswith("backend_compile_duration")

    def _on_event(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            _now["cache_hits"] += 1

    monitoring.register_event_duration_secs_listener(_on_duration)
    monitoring.register_event_listener(_on_event)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        before = dict(_now)
        yield
        row = {k: round(_now[k] - before[k], 3) for k in _now}
        with open(_REPORT, "a") as f:
            f.write(json.dumps({"test": item.nodeid, **row}) + "\n")
