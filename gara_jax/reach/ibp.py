"""Interval bound propagation (IBP) through ReLU MLPs."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gara_jax.reach._layers import bounds_call, chunked

# Boxes per chunk of the sequential loop over large batches (keeps the [chunk, width]
# intermediates in cache); measured best of 256..2048 in benchmarks/bounds_throughput.py.
CHUNK = 1024


def ibp_preactivations(layers, lo, hi):
    """IBP bounds of every layer's pre-activation, ``[(l, u)]`` with shapes ``[B, n_k]``.

    Centre/radius form: an affine map sends the box with centre ``c`` and radius ``r`` to centre
    ``c W + b`` and radius ``r |W|`` exactly, two dense products per layer.
    """
    c = (lo + hi) * 0.5
    r = (hi - lo) * 0.5
    bounds = []
    for k, (w, b) in enumerate(layers):
        c = c @ w + b
        r = r @ jnp.abs(w)
        lk, uk = c - r, c + r
        bounds.append((lk, uk))
        if k < len(layers) - 1:
            lk, uk = jnp.maximum(lk, 0), jnp.maximum(uk, 0)
            c = (lk + uk) * 0.5
            r = (uk - lk) * 0.5
    return bounds


def _ibp_unchunked(layers, lo, hi):
    return ibp_preactivations(layers, lo, hi)[-1]


def _ibp(layers, lo, hi):
    return chunked(_ibp_unchunked, layers, lo, hi, CHUNK)


# Plain jit: unlike CROWN (see _layers.TunedJit), IBP gains from XLA's YNNPACK fusions.
_ibp_jit = jax.jit(_ibp)


def ibp(layers, lo, hi, *, validate: bool = True):
    """Interval bounds on a ReLU MLP's outputs over input boxes (jit-compiled, batched).

    Args:
        layers: ``(kernel [in, out], bias [out])`` pairs, ReLU between layers and a linear
            output (or :class:`~gara_jax.networks.MLP` parameters).
        lo, hi: input boxes ``[..., in]``, any leading batch shape.
        validate: check for NaN and ``lo > hi`` (a host transfer; off for hot loops).

    Returns:
        ``(out_lo, out_hi)``, each ``[..., out]``.

    Example:
        >>> import jax.numpy as jnp
        >>> layers = [(jnp.array([[1.0, -1.0]]), jnp.zeros(2)),
        ...           (jnp.array([[1.0], [1.0]]), jnp.zeros(1))]
        >>> lo, hi = ibp(layers, jnp.array([-1.0]), jnp.array([2.0]))  # relu(x) + relu(-x) = |x|
        >>> lo.tolist(), hi.tolist()
        ([0.0], [3.0])
    """
    return bounds_call(_ibp_jit, layers, lo, hi, validate)
