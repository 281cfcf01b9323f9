"""Training algorithms behind one contract (:class:`~gara_jax.algorithms.base.Algorithm`).

``make_algorithm(config)`` dispatches on the config's type: :class:`GaraConfig` (GARA, with
``planning`` for the planner variant), :class:`HandcraftedConfig` and, where
``gara_jax.algorithms.hiro`` is present, ``HiroConfig``.

Example:
    >>> from gara_jax.algorithms import make_algorithm, HandcraftedConfig
    >>> make_algorithm(HandcraftedConfig()).name
    'handcrafted'
"""

from __future__ import annotations

import importlib
import importlib.util

from gara_jax.algorithms.base import Algorithm
from gara_jax.algorithms.gara import GaraConfig, HandcraftedConfig, make_gara


def _hiro():
    """The HIRO module if it exists (its own import errors are not hidden), else ``None``."""
    if importlib.util.find_spec("gara_jax.algorithms.hiro") is None:
        return None
    return importlib.import_module("gara_jax.algorithms.hiro")


def make_algorithm(config) -> Algorithm:
    """The :class:`Algorithm` for a config object.

    Raises ``ValueError`` for an object that is no known algorithm config.
    """
    if isinstance(config, GaraConfig | HandcraftedConfig):
        return make_gara(config)
    hiro = _hiro()
    if hiro is not None and isinstance(config, hiro.HiroConfig):
        return hiro.make_hiro(config)
    raise ValueError(f"config: not an algorithm config: {type(config).__name__}")


def __getattr__(name):
    # HiroConfig / make_hiro are re-exported lazily, once hiro.py exists.
    if name in ("HiroConfig", "make_hiro"):
        hiro = _hiro()
        if hiro is not None:
            return getattr(hiro, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Algorithm", "GaraConfig", "HandcraftedConfig", "make_algorithm", "make_gara"]
