"""Set-based reachability: IBP, CROWN and zonotope bounds of ReLU MLPs, and goal refinement.

Example:
    >>> import jax, jax.numpy as jnp
    >>> from gara_jax.networks import MLP
    >>> params = MLP(hidden=(8, 8), out=4).init(jax.random.key(0), jnp.zeros(12))
    >>> layers = layers_from_flax(params)
    >>> lo, hi = -jnp.ones((3, 12)), jnp.ones((3, 12))
    >>> (c_lo, c_hi), (i_lo, i_hi) = crown(layers, lo, hi), ibp(layers, lo, hi)
    >>> bool(jnp.all(c_lo <= c_hi)), c_lo.shape
    (True, (3, 4))
"""

from gara_jax.networks import mlp_layers as layers_from_flax
from gara_jax.reach.crown import crown
from gara_jax.reach.ibp import ibp
from gara_jax.reach.refine import RefineResult, refine, refine_many
from gara_jax.reach.zonotope import zonotope

__all__ = ["RefineResult", "crown", "ibp", "layers_from_flax", "refine", "refine_many",
           "zonotope"]
