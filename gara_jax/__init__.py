"""gara-jax: GARA (Goal Abstraction via Reachability Analysis) in JAX."""

__version__ = "0.1.0"
