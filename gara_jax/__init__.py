"""gara-jax: GARA (Goal Abstraction via Reachability Analysis) in JAX."""

__version__ = "0.1.0"

import envs.gym_adapter  # noqa: E402,F401  (registers the gara_jax/* Gymnasium ids)

# The functional API, imported on first use so that ``import gara_jax`` stays light.
_EXPORTS = {
    "GaraConfig": "gara_jax.algorithms",
    "HandcraftedConfig": "gara_jax.algorithms",
    "HiroConfig": "gara_jax.algorithms",  # present once gara_jax.algorithms.hiro exists
    "make_algorithm": "gara_jax.algorithms",
    "make_train": "gara_jax.train",
    "train_many": "gara_jax.train",
    "TrainResult": "gara_jax.train",
}


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'gara_jax' has no attribute {name!r}")


__all__ = list(_EXPORTS)
