"""Minimal gymnax-style spaces: ``sample(key)`` and ``contains(x)``, both jit-able."""

from __future__ import annotations

import jax
import jax.numpy as jnp


class Discrete:
    """The integers ``0 .. n - 1``.

    Example:
        >>> import jax
        >>> space = Discrete(4)
        >>> bool(space.contains(space.sample(jax.random.key(0))))
        True
    """

    def __init__(self, n: int, dtype=jnp.int32):
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        self.n = int(n)
        self.shape: tuple[int, ...] = ()
        self.dtype = dtype

    def sample(self, key: jax.Array) -> jax.Array:
        """A uniformly drawn element."""
        return jax.random.randint(key, self.shape, 0, self.n, dtype=self.dtype)

    def contains(self, x) -> jax.Array:
        """Whether ``x`` is a scalar integer value in ``[0, n)`` (a bool array)."""
        x = jnp.asarray(x)
        if x.shape != self.shape:
            return jnp.asarray(False)
        return (x >= 0) & (x < self.n) & (x == jnp.floor(x))

    def __repr__(self) -> str:
        return f"Discrete({self.n})"


class Box:
    """The closed box ``low <= x <= high`` (elementwise).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> space = Box(jnp.zeros(2), jnp.ones(2), (2,))
        >>> bool(space.contains(jnp.array([0.5, 1.0])))
        True
    """

    def __init__(self, low, high, shape: tuple[int, ...], dtype=None):
        self.shape = tuple(shape)
        self.dtype = jnp.result_type(float) if dtype is None else dtype
        self.low = jnp.broadcast_to(jnp.asarray(low, self.dtype), self.shape)
        self.high = jnp.broadcast_to(jnp.asarray(high, self.dtype), self.shape)

    def sample(self, key: jax.Array) -> jax.Array:
        """A uniformly drawn element."""
        return jax.random.uniform(key, self.shape, self.dtype, minval=self.low, maxval=self.high)

    def contains(self, x) -> jax.Array:
        """Whether ``x`` has this shape and lies inside the box (a bool array)."""
        x = jnp.asarray(x)
        if x.shape != self.shape:
            return jnp.asarray(False)
        return jnp.all((x >= self.low) & (x <= self.high))

    def __repr__(self) -> str:
        return f"Box(shape={self.shape}, dtype={jnp.dtype(self.dtype).name})"
