"""Small Flax MLPs shared by the learners, and their view as a layer sequence for the bounds.

The reference networks are Keras ``Dense`` stacks (Glorot-uniform kernels, zero biases, ReLU on
hidden layers, linear output); :class:`MLP` reproduces that initialisation.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax.numpy as jnp

Layer = tuple[jnp.ndarray, jnp.ndarray]  # (kernel [in, out], bias [out])


class MLP(nn.Module):
    """ReLU MLP with a linear output layer.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> net = MLP(hidden=(8, 8), out=4)
        >>> params = net.init(jax.random.key(0), jnp.zeros(12))
        >>> net.apply(params, jnp.ones((5, 12))).shape
        (5, 4)
    """

    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        init = nn.initializers.glorot_uniform()
        for width in self.hidden:
            x = nn.relu(nn.Dense(width, kernel_init=init)(x))
        return nn.Dense(self.out, kernel_init=init)(x)


def mlp_layers(params) -> list[Layer]:
    """The ``(kernel, bias)`` sequence of an :class:`MLP`'s parameters, input layer first.

    This is the form :func:`gara_jax.reach.ibp` and :func:`gara_jax.reach.crown` take. Works on
    batched (vmapped) parameters too: leading axes are kept.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> params = MLP(hidden=(8, 8), out=4).init(jax.random.key(0), jnp.zeros(12))
        >>> [k.shape for k, _ in mlp_layers(params)]
        [(12, 8), (8, 8), (8, 4)]
    """
    inner = params["params"] if "params" in params else params
    names = sorted((n for n in inner if n.startswith("Dense_")), key=lambda n: int(n[6:]))
    if not names:
        raise ValueError("params: no Dense_<i> layers found; expected MLP parameters")
    return [(inner[n]["kernel"], inner[n]["bias"]) for n in names]
