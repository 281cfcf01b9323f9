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
neuron (``relu="deepz"``), the transformer the zonotope domain's authors later made its
standard. ``relu="box"`` replaces an unstable neuron by its interval ``[0, u]`` on a fresh,
independent noise symbol (``u/2 + u/2 e_new``), so it keeps no dependency on the inputs:
usually looser than DeepZ, and never looser than IBP. It is our model of Ai2's own ReLU, a
case split (``z >= 0`` kept, ``z < 0`` set to 0) joined in the zonotope domain: the usual
join keeps a noise coefficient only where both branches agree, and on the neuron they never
do (``g`` against 0), so the neuron leaves the join as the interval hull of ``[0, u]`` and
``{0}`` on a new symbol, while the other neurons keep theirs. SPEC.md names Ai2 but not its
join, so this is a reading, not a fact of the reference. The bounds are pure zonotope bounds
(not intersected with IBP), as the reference's analysis has them.

Widths: with ``n_in`` inputs and hidden widths ``n_1 .. n_h`` the generator matrix has at most
``n_in + n_1 + ... + n_h`` rows (28 for the forward model's 12-8-8-4), so each box costs a few
small dense products per layer.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from gara_jax.reach._layers import bounds_call, chunked

# Boxes per chunk of the sequential loop over large batches (the per-box generator matrices
# stay in cache): CROWN's value, not tuned for zonotopes.
CHUNK = 512

RELU_TRANSFORMERS = ("deepz", "box")


def relu_zonotope(lower, upper, relu: str = "deepz"):
    """A zonotope ReLU transformer on bounds ``[l, u]``: ``(slope, offset)`` per neuron.

    ``relu(z)`` lies in ``slope z + offset + offset e`` for ``z`` in ``[l, u]`` and a new noise
    symbol ``e`` in ``[-1, 1]``: ``slope = 1, offset = 0`` when ``l >= 0``; ``0, 0`` when
    ``u <= 0``; otherwise (``"deepz"``) ``slope = u / (u - l)`` and ``offset = -slope l / 2``,
    or (``"box"``) ``slope = 0`` and ``offset = u / 2``.
    """
    unstable = (lower < 0) & (upper > 0)
    stable_slope = (lower >= 0).astype(lower.dtype)
    if relu == "box":
        return jnp.where(unstable, 0, stable_slope), jnp.where(unstable, upper * 0.5, 0)
    gap = jnp.where(unstable, upper - lower, 1)
    slope = jnp.where(unstable, upper / gap, stable_slope)
    offset = jnp.where(unstable, -slope * lower * 0.5, 0)
    return slope, offset


def zonotope_preactivations(layers, lo, hi, relu: str = "deepz"):
    """Zonotope bounds of every layer's pre-activation for boxes ``lo, hi [B, in]``:
    ``[(l, u)]`` with shapes ``[B, n_k]``; ``relu`` names the transformer
    (:func:`relu_zonotope`)."""
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
            slope, offset = relu_zonotope(lk, uk, relu)
            centre = centre * slope + offset
            gens = jnp.concatenate([gens * slope[:, None, :], jax.vmap(jnp.diag)(offset)], axis=1)
    return bounds


def _zonotope(layers, lo, hi, relu="deepz"):
    return chunked(lambda *a: zonotope_preactivations(*a, relu)[-1], layers, lo, hi, CHUNK)


_zonotope_jit = jax.jit(_zonotope, static_argnames="relu")


def zonotope(layers, lo, hi, *, relu: str = "deepz", validate: bool = True):
    """Zonotope bounds on a ReLU MLP's outputs over input boxes (jit-compiled, batched).

    Args:
        layers: ``(kernel [in, out], bias [out])`` pairs, ReLU between layers and a linear
            output (or :class:`~gara_jax.networks.MLP` parameters).
        lo, hi: input boxes ``[..., in]``, any leading batch shape.
        relu: the transformer of an unstable ReLU, ``"deepz"`` (DeepZ's minimal-area
            relaxation) or ``"box"`` (its interval ``[0, u]``, a fresh noise symbol).
        validate: check for NaN and ``lo > hi`` (a host transfer; off for hot loops).

    Returns:
        ``(out_lo, out_hi)``, each ``[..., out]``: the bounding box of the output zonotope.
        Exact on affine networks and on point boxes. With ``"deepz"`` neither always tighter
        nor always looser than :func:`~gara_jax.reach.ibp` or :func:`~gara_jax.reach.crown`;
        with ``"box"`` never looser than IBP.

    Example:
        >>> import jax.numpy as jnp
        >>> layers = [(jnp.array([[1.0, -1.0]]), jnp.zeros(2)),
        ...           (jnp.array([[1.0], [1.0]]), jnp.zeros(1))]
        >>> lo, hi = zonotope(layers, jnp.array([-1.0]), jnp.array([2.0]))  # relu(x) + relu(-x)
        >>> [round(v, 6) for v in (lo.item(), hi.item())]  # sound for |x| on [-1, 2]
        [-0.333333, 2.0]
        >>> lo, hi = zonotope(layers, jnp.array([-1.0]), jnp.array([2.0]), relu="box")
        >>> [round(v, 6) for v in (lo.item(), hi.item())]  # [0, 2] + [0, 1]: IBP's box here
        [0.0, 3.0]
    """
    if relu not in RELU_TRANSFORMERS:
        raise ValueError(f"relu: must be one of {RELU_TRANSFORMERS}, got {relu!r}")
    return bounds_call(functools.partial(_zonotope_jit, relu=relu), layers, lo, hi, validate)
