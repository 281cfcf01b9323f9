"""Zonotope bounds through ReLU MLPs, batched over boxes (the reference's kind of analysis).

The authors' code bounds the forward model with Ai2 zonotopes (Gehr et al., 2018), and reads
the output as the zonotope's bounding box (SPEC.md section 3.6). A zonotope is a centre ``c``
and generator rows ``G``: the set ``{c + e G : e in [-1, 1]^m}``. An input box is the zonotope
with ``c`` its centre and ``G = diag(radius)``; an affine layer maps a zonotope to another one
exactly (``c W + b``, ``G W``), so the dependencies between neurons are kept through every
layer, which interval arithmetic forgets.

A ReLU on a neuron whose bounds ``[l, u]`` (the zonotope's interval hull) lie on one side of 0
is exact. An unstable neuron (``l < 0 < u``) is replaced by the minimal-area zonotope relaxation
of DeepZ (Singh et al., 2018): ``relu(z)`` lies in ``lam z + mu + mu e_new`` with the chord's
slope ``lam = u / (u - l)``, ``mu = -lam l / 2`` and a fresh noise symbol ``e_new`` for the
neuron. SPEC.md does not say which ReLU transformer the reference's Ai2 uses; Ai2's own is a
case split joined in the zonotope domain, and DeepZ's is the one that domain's authors later
made its standard. The bounds are pure zonotope bounds (not intersected with IBP), as the
reference's analysis has them.

Widths: with ``n_in`` inputs and hidden widths ``n_1 .. n_h`` the generator matrix has at most
``n_in + n_1 + ... + n_h`` rows (28 for the forward model's 12-8-8-4), so each box costs a few
small dense products per layer.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gara_jax.reach._layers import bounds_call, chunked

# Boxes per chunk of the sequential loop over large batches (the per-box generator matrices
# stay in cache), the same as CROWN's; measured with benchmarks/bounds_throughput.py.
CHUNK = 512


def relu_zonotope(lower, upper):
    """DeepZ's ReLU transformer on bounds ``[l, u]``: ``(slope, offset)`` per neuron.

    ``relu(z)`` lies in ``slope z + offset + offset e`` for ``z`` in ``[l, u]`` and a new noise
    symbol ``e`` in ``[-1, 1]``: ``slope = 1, offset = 0`` when ``l >= 0``; ``0, 0`` when
    ``u <= 0``; otherwise ``slope = u / (u - l)`` and ``offset = -slope l / 2``.
    """
    unstable = (lower < 0) & (upper > 0)
    gap = jnp.where(unstable, upper - lower, 1)
    slope = jnp.where(unstable, upper / gap, (lower >= 0).astype(lower.dtype))
    offset = jnp.where(unstable, -slope * lower * 0.5, 0)
    return slope, offset


def zonotope_preactivations(layers, lo, hi):
    """Zonotope bounds of every layer's pre-activation for boxes ``lo, hi [B, in]``:
    ``[(l, u)]`` with shapes ``[B, n_k]``."""
    centre = (lo + hi) * 0.5
    gens = jax.vmap(jnp.diag)((hi - lo) * 0.5)  # [B, m, n]: one generator row per noise symbol
    bounds = []
    for k, (w, b) in enumerate(layers):
        centre = centre @ w + b
        gens = gens @ w
        radius = jnp.abs(gens).sum(1)
        lk, uk = centre - radius, centre + radius
        bounds.append((lk, uk))
        if k < len(layers) - 1:
            slope, offset = relu_zonotope(lk, uk)
            centre = centre * slope + offset
            gens = jnp.concatenate([gens * slope[:, None, :], jax.vmap(jnp.diag)(offset)], axis=1)
    return bounds


def _zonotope_unchunked(layers, lo, hi):
    return zonotope_preactivations(layers, lo, hi)[-1]


def _zonotope(layers, lo, hi):
    return chunked(_zonotope_unchunked, layers, lo, hi, CHUNK)


_zonotope_jit = jax.jit(_zonotope)


def zonotope(layers, lo, hi, *, validate: bool = True):
    """Zonotope bounds (DeepZ's ReLU relaxation) on a ReLU MLP's outputs over input boxes.

    Args:
        layers: ``(kernel [in, out], bias [out])`` pairs, ReLU between layers and a linear
            output (or :class:`~gara_jax.networks.MLP` parameters).
        lo, hi: input boxes ``[..., in]``, any leading batch shape.
        validate: check for NaN and ``lo > hi`` (a host transfer; off for hot loops).

    Returns:
        ``(out_lo, out_hi)``, each ``[..., out]``: the bounding box of the output zonotope.
        Exact on affine networks and on point boxes; neither always tighter nor always looser
        than :func:`ibp` or :func:`~gara_jax.reach.crown`.

    Example:
        >>> import jax.numpy as jnp
        >>> layers = [(jnp.array([[1.0, -1.0]]), jnp.zeros(2)),
        ...           (jnp.array([[1.0], [1.0]]), jnp.zeros(1))]
        >>> lo, hi = zonotope(layers, jnp.array([-1.0]), jnp.array([2.0]))  # relu(x) + relu(-x)
        >>> [round(v, 6) for v in (lo.item(), hi.item())]  # sound for |x| on [-1, 2]
        [-0.333333, 2.0]
    """
    return bounds_call(_zonotope_jit, layers, lo, hi, validate)
