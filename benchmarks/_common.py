"""What the benchmark scripts share: the machine description and writing the result JSON.

The scripts run as ``python benchmarks/NAME.py`` (or are loaded by path in the tests), so
they import this module after putting their own folder on ``sys.path``.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path

import jax
import numpy as np


def load_average() -> float | None:
    """The 1-minute load average, ``None`` where the OS has none."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def jaxlib_version() -> str | None:
    try:
        import jaxlib

        return jaxlib.__version__
    except (ImportError, AttributeError):
        return None


def machine_info() -> dict:
    """Platform, CPU count, library versions, JAX backend and device (starts the backend)."""
    device = jax.devices()[0]
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "jax": jax.__version__,
        "jaxlib": jaxlib_version(),
        "backend": jax.default_backend(),
        "device": str(getattr(device, "device_kind", device)),
        "x64": bool(jax.config.jax_enable_x64),
        "cpu_async_dispatch": bool(jax.config.values["jax_cpu_enable_async_dispatch"]),
        "load_average_1min_at_start": load_average(),
        # With the persistent cache on, a "compile" time can be a read of a cached program.
        "compile_cache": jax.config.values["jax_compilation_cache_dir"],
    }


def write_result(out: Path, result: dict) -> None:
    """Write ``result`` as indented JSON to ``out`` (creating its folder) and say so."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")
