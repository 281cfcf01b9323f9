"""CROWN bounds (Zhang et al., 2018) through ReLU MLPs, batched over boxes.

The standard backward algorithm: every pre-activation (hidden layers and output) is bounded by
a backward pass from that layer to the input, through linear relaxations of the ReLUs below it
that use the bounds already computed for their inputs. ReLU on ``[l, u]``: stable neurons are
exact; an unstable one (``l < 0 < u``) is bounded above by the chord ``u (z - l) / (u - l)``
and below by ``a z`` with the adaptive slope ``a = 1`` if ``u > -l`` else 0. Intermediate bounds
are pure CROWN (not intersected with IBP), which is what the golden reference does.

How the work is laid out (this is what makes it fast on CPU):

- Boxes live on the *last* axis ("feature-major" ``[n, B]``), so every product is one dense
  matrix product with a long dimension ``B`` (or ``R * B``), never a batch of tiny ones.
- The first step of each backward pass starts from a constant matrix ``W_k^T``; after the
  relaxation its lower and upper coefficient matrices are
  ``A_lo = (W^T diag(a + s) - |W^T| diag(s - a)) / 2`` and ``A_hi = (... + ...) / 2`` (``a``
  lower, ``s`` upper slopes). Pushing those through the layer below needs only the two products
  ``(W_{k-1} * W_k^T) @ (a + s)`` and ``(W_{k-1} * |W_k^T|) @ (s - a)`` with constant left
  factors: no per-box matrix is formed before the product.
- Later steps (data-dependent signs) stack the lower rows and the negated upper rows, so one
  "lower bound" pass serves both.
- Sums over a feature axis: true reductions where XLA should materialise the result once
  (several consumers), unrolled sums of slices (one fused loop) elsewhere.
- Large batches run as a sequential loop over chunks of :data:`CHUNK` boxes, so that the
  per-box coefficients stay in cache; on CPU, XLA's YNNPACK fusions are turned off for these
  functions (see ``_layers.TunedJit``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gara_jax.reach._layers import TunedJit, bounds_call, chunked


def relu_relaxation(lower, upper):
    """CROWN's relaxation of ``relu`` on ``[l, u]``: ``(lower slope, upper slope, upper offset)``.

    ``a z <= relu(z) <= s z + t`` for ``z`` in ``[l, u]`` (the lower offset is always 0).
    Stable neurons get ``a = s = 1`` (``l >= 0``; ``a = 0`` if ``l = u = 0``, equally exact) or
    ``a = s = 0`` (``u <= 0``), ``t = 0``; an
    unstable one the chord ``s = u / (u - l)``, ``t = -l s`` and the adaptive ``a = [u > -l]``.
    Written without branches: XLA recomputes it inside the loops that use it, where selects
    would cost more than this handful of arithmetic.
    """
    up = jnp.maximum(upper, 0)
    ln = jnp.minimum(lower, 0)
    gap = up - ln  # 0 only when l = u = 0, where any slope is exact
    s = up / jnp.where(gap > 0, gap, 1)
    t = -ln * s
    a = (lower + upper > 0).astype(lower.dtype)
    return a, s, t


def _sum0(x):
    """Sum over the leading axis as a tree of slice additions (one fused, vectorised loop)."""
    n = x.shape[0]
    if n > 64:
        return x.sum(0)
    terms = [x[i] for i in range(n)]
    while len(terms) > 1:
        pairs = [terms[i] + terms[i + 1] for i in range(0, len(terms) - 1, 2)]
        terms = pairs + ([terms[-1]] if len(terms) % 2 else [])
    return terms[0]


def _transpose(x):
    """``x.T`` for ``x [B, n]``, computed as a product with the identity so that XLA
    materialises it once instead of fusing a strided transpose into every consumer."""
    return jnp.einsum("bi,ij->jb", x, jnp.eye(x.shape[1], dtype=x.dtype))


def _add_pairs(x, y):
    """``(x.sum(0), y.sum(0))`` in one pass over both (a variadic reduction)."""
    zero = jnp.zeros((), x.dtype)
    return jax.lax.reduce((x, y), (zero, zero), lambda p, q: (p[0] + q[0], p[1] + q[1]), (0,))


def crown_preactivations_fm(layers, xc, xr):
    """CROWN bounds of every layer's pre-activation, feature-major.

    Args:
        layers: ``(kernel [in, out], bias [out])`` pairs.
        xc, xr: centres and radii of the input boxes, ``[in, B]``.

    Returns:
        ``[(l, u)]``, one pair per layer, each ``[n_k, B]``.
    """
    w0, b0 = layers[0]
    batch = xc.shape[1]
    # The first layer is affine in the input: CROWN and IBP coincide there.
    zc = w0.T @ xc + b0[:, None]
    zr = jnp.abs(w0).T @ xr
    bounds = [(zc - zr, zc + zr)]
    relax = [relu_relaxation(*bounds[0])]
    for k in range(1, len(layers)):
        wk, bk = layers[k]
        n_k = wk.shape[1]
        wt = wk.T
        at = jnp.abs(wt)
        a, s, t = relax[k - 1]
        plus, minus = a + s, s - a
        w_below, b_below = layers[k - 1]
        n_below = w_below.shape[0]
        # Offsets of the lower bounds and of the negated upper bounds, [2 n_k, B], in one
        # product: the relaxation offsets t (through the negative, resp. positive, weights) and
        # the bias (for the first layer: the centre) of the pre-activation below, through
        # A_lo = (W^T diag(plus) - |W^T| diag(minus)) / 2 and A_hi = (... + ...) / 2.
        bias_in = zc if k == 1 else b_below[:, None]
        left = jnp.concatenate([
            jnp.concatenate([jnp.minimum(wt, 0), 0.5 * wt, -0.5 * at], axis=1),
            jnp.concatenate([-jnp.maximum(wt, 0), -0.5 * wt, -0.5 * at], axis=1)], axis=0)
        right = jnp.concatenate([t, plus * bias_in, minus * bias_in], axis=0)
        const = jnp.concatenate([bk, -bk])[:, None] + left @ right
        # Coefficients of the input of layer k-1: A_lo W_{k-1}^T and A_hi W_{k-1}^T, from
        # products of constant matrices with the per-box slopes.
        q_plus = w_below[:, None, :] * (0.5 * wt)[None]  # [n_below, n_k, n_{k-1}]
        q_minus = w_below[:, None, :] * (0.5 * at)[None]
        c_plus = (q_plus.reshape(n_below * n_k, -1) @ plus).reshape(n_below, n_k, batch)
        c_minus = (q_minus.reshape(n_below * n_k, -1) @ minus).reshape(n_below, n_k, batch)
        if k == 1:
            xr3 = xr[:, None, :]
            rad_lo, rad_hi = _add_pairs(jnp.abs(c_plus - c_minus) * xr3,
                                        jnp.abs(c_plus + c_minus) * xr3)
            lk, uk = const[:n_k] - rad_lo, -const[n_k:] + rad_hi
        else:
            # Lower-bound rows and negated upper-bound rows, [n_below, 2 n_k, B]: one
            # lower-bound pass below then serves both.
            rows = 2 * n_k
            coef = jnp.concatenate([c_plus - c_minus, -(c_plus + c_minus)], axis=1)
            for j in range(k - 2, -1, -1):
                a, s, t = relax[j]
                neg = jnp.minimum(coef, 0)
                const = const + _sum0(neg * t[:, None, :])
                coef = jnp.maximum(coef, 0) * a[:, None, :] + neg * s[:, None, :]
                wj, bj = layers[j]
                # Bias row appended to the kernel: the bias term comes out of the same product.
                w_aug = jnp.concatenate([wj, bj[None, :]], axis=0)
                pushed = (w_aug @ coef.reshape(coef.shape[0], -1)).reshape(-1, rows, batch)
                const = const + pushed[-1]
                coef = pushed[:-1]
            # A true reduction (simple operands): materialised once, not re-done per consumer.
            const = const + (coef * xc[:, None, :] - jnp.abs(coef) * xr[:, None, :]).sum(0)
            lk, uk = const[:n_k], -const[n_k:]
        bounds.append((lk, uk))
        if k < len(layers) - 1:
            relax.append(relu_relaxation(lk, uk))
    return bounds


def crown_preactivations(layers, lo, hi):
    """CROWN bounds of every layer's pre-activation for boxes ``lo, hi [B, in]``: ``[(l, u)]``
    with shapes ``[B, n_k]``."""
    xc = _transpose((lo + hi) * 0.5)
    xr = _transpose((hi - lo) * 0.5)
    return [(lk.T, uk.T) for lk, uk in crown_preactivations_fm(layers, xc, xr)]


# Boxes per chunk of the sequential loop over large batches: the backward passes make
# ``n_below * 2 n_k`` coefficients per box and layer (768 + 256 for 12-32-32-4), and past a few
# hundred boxes these no longer stay in cache. Measured best of 256..2048 on 12-8-8-4 and
# 12-32-32-4 (benchmarks/bounds_throughput.py); 65536 boxes run 2-2.5x faster than unchunked.
CHUNK = 512


def _crown_unchunked(layers, lo, hi):
    return crown_preactivations(layers, lo, hi)[-1]


def _crown(layers, lo, hi):
    return chunked(_crown_unchunked, layers, lo, hi, CHUNK)


_crown_jit = TunedJit(_crown)


def crown(layers, lo, hi, *, validate: bool = True):
    """CROWN bounds on a ReLU MLP's outputs over input boxes (jit-compiled, batched).

    Args:
        layers: ``(kernel [in, out], bias [out])`` pairs, ReLU between layers and a linear
            output (or :class:`~gara_jax.networks.MLP` parameters).
        lo, hi: input boxes ``[..., in]``, any leading batch shape.
        validate: check for NaN and ``lo > hi`` (a host transfer; off for hot loops).

    Returns:
        ``(out_lo, out_hi)``, each ``[..., out]``. Usually much tighter than :func:`ibp`, but
        not always; their intersection is sound and never looser than either.

    Example:
        >>> import jax.numpy as jnp
        >>> layers = [(jnp.array([[1.0, -1.0]]), jnp.zeros(2)),
        ...           (jnp.array([[1.0], [-1.0]]), jnp.zeros(1))]
        >>> lo, hi = crown(layers, jnp.array([-1.0]), jnp.array([2.0]))  # relu(x) - relu(-x) = x
        >>> [round(v, 6) for v in (lo.item(), hi.item())]  # sound; IBP gives [-1, 2] here
        [-2.0, 2.0]
    """
    return bounds_call(_crown_jit, layers, lo, hi, validate)
