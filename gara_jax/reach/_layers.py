"""Shared plumbing for the bound functions: layer checks, batch flattening, the tuned jit."""

from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from gara_jax.networks import mlp_layers

# XLA:CPU hands some fusions (a dot with the reductions that follow it) to YNNPACK, which runs
# the reductions of the CROWN backward pass many times slower than XLA's own loops (measured in
# benchmarks/bounds_throughput.py). The option is per compiled function, so it leaks nowhere.
_CPU_COMPILER_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


class TunedJit:
    """``jax.jit`` with :data:`_CPU_COMPILER_OPTIONS` on CPU, plain ``jax.jit`` elsewhere or
    when this XLA does not know the option."""

    def __init__(self, fn, static_argnames=()):
        self._plain = jax.jit(fn, static_argnames=static_argnames)
        self._tuned = jax.jit(fn, static_argnames=static_argnames,
                              compiler_options=_CPU_COMPILER_OPTIONS)
        self._use_tuned: bool | None = None
        self.__wrapped__ = fn
        self.__doc__ = fn.__doc__

    def lower(self, *args, **kwargs):
        """``jax.jit(...).lower`` of the variant :meth:`__call__` uses (to time compilation)."""
        if self._use_tuned is None:
            self._use_tuned = jax.default_backend() == "cpu"
        return (self._tuned if self._use_tuned else self._plain).lower(*args, **kwargs)

    def __call__(self, *args, **kwargs):
        if self._use_tuned is None:
            self._use_tuned = jax.default_backend() == "cpu"
        if self._use_tuned:
            try:
                return self._tuned(*args, **kwargs)
            except Exception as err:  # an XLA without the option: fall back for good
                if "ynn_fusion_type" not in str(err):
                    raise
                self._use_tuned = False
        return self._plain(*args, **kwargs)


Layers = tuple[tuple[jnp.ndarray, jnp.ndarray], ...]


def as_layers(layers_or_params, name: str = "layers") -> Layers:
    """``(kernel, bias)`` pairs from a layer sequence or :class:`~gara_jax.networks.MLP` params.

    Arrays are passed through untouched when they already are JAX arrays (no device work).
    """
    if isinstance(layers_or_params, Mapping):
        layers_or_params = mlp_layers(layers_or_params)
    try:
        layers = tuple((_as_array(w), _as_array(b)) for w, b in layers_or_params)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name}: expected a sequence of (kernel, bias) pairs ({err})") from None
    if not layers:
        raise ValueError(f"{name}: empty layer sequence")
    return layers


def _as_array(x):
    return x if isinstance(x, jax.Array) else jnp.asarray(x)


def check_layers(layers, name: str = "layers", batch_ndim: int = 0) -> None:
    """Static shape checks: kernels ``[..., in, out]`` chain and biases are ``[..., out]``."""
    lead = None
    for k, (w, b) in enumerate(layers):
        if w.ndim != 2 + batch_ndim or b.ndim != 1 + batch_ndim:
            raise ValueError(
                f"{name}: layer {k} kernel/bias have shapes {w.shape}/{b.shape}; expected "
                f"{batch_ndim} leading axes then [in, out]/[out]")
        if b.shape[-1] != w.shape[-1] or b.shape[:-1] != w.shape[:-2]:
            raise ValueError(f"{name}: layer {k} bias {b.shape} does not match kernel {w.shape}")
        if lead is None:
            lead = w.shape[:-2]
        elif w.shape[:-2] != lead:
            raise ValueError(f"{name}: layer {k} has leading axes {w.shape[:-2]}, not {lead}")
        if k and layers[k - 1][0].shape[-1] != w.shape[-2]:
            raise ValueError(
                f"{name}: layer {k} takes {w.shape[-2]} inputs but layer {k - 1} gives "
                f"{layers[k - 1][0].shape[-1]}")


def prepare(layers, lo, hi, validate: bool):
    """Check a bound function's arguments; return layers, flattened ``[B, in]`` boxes, batch shape.

    Value checks (NaN, ``lo > hi``) run only on concrete arrays with ``validate`` set: they cost
    a transfer to the host, and inside ``jit`` the values are not known. Everything else is
    shape and dtype bookkeeping, with device work only where a cast or reshape is needed (this
    runs on every call: it must stay cheap next to the bounds on small batches).
    """
    layers = as_layers(layers)
    check_layers(layers)
    lo = _as_array(lo)
    hi = _as_array(hi)
    if lo.shape != hi.shape:
        raise ValueError(f"lo, hi: different shapes {lo.shape} and {hi.shape}")
    n_in = layers[0][0].shape[0]
    if lo.ndim == 0 or lo.shape[-1] != n_in:
        raise ValueError(f"lo, hi: expected shape [..., {n_in}], got {lo.shape}")
    if validate and not isinstance(lo, jax.core.Tracer) and not isinstance(hi, jax.core.Tracer):
        lo_np, hi_np = np.asarray(lo), np.asarray(hi)
        if np.isnan(lo_np).any() or np.isnan(hi_np).any():
            raise ValueError("lo, hi: NaN in input boxes")
        if (lo_np > hi_np).any():
            idx = tuple(int(i) for i in np.argwhere(lo_np > hi_np)[0])
            raise ValueError(f"lo, hi: lo > hi at index {idx}")
    # NumPy's promotion on already-canonical JAX dtypes: same answer, far less Python.
    dtype = np.result_type(lo.dtype, *{w.dtype for w, _ in layers})
    if not np.issubdtype(dtype, np.floating):
        dtype = jnp.result_type(float)
    batch = lo.shape[:-1]
    if lo.ndim != 2:
        lo = lo.reshape(-1, n_in)
        hi = hi.reshape(-1, n_in)
    if lo.dtype != dtype:
        lo, hi = lo.astype(dtype), hi.astype(dtype)
    if any(w.dtype != dtype or b.dtype != dtype for w, b in layers):  # e.g. float32 weights, x64
        layers = tuple((w.astype(dtype), b.astype(dtype)) for w, b in layers)
    return layers, lo, hi, batch


def bounds_call(core, layers, lo, hi, validate: bool):
    """The public bound functions' body: check and flatten the boxes, run the jitted ``core``
    on ``[B, in]``, restore the caller's batch shape on ``(out_lo, out_hi)``."""
    layers, lo, hi, batch = prepare(layers, lo, hi, validate)
    out_lo, out_hi = core(layers, lo, hi)
    if len(batch) != 1:
        n_out = layers[-1][0].shape[1]
        out_lo, out_hi = out_lo.reshape(batch + (n_out,)), out_hi.reshape(batch + (n_out,))
    return out_lo, out_hi


def chunked(fn, layers, lo, hi, size):
    """``fn(layers, lo, hi)`` on chunks of ``size`` boxes (a sequential loop; padded)."""
    n = lo.shape[0]
    if n <= size:
        return fn(layers, lo, hi)
    n_chunks = -(-n // size)
    pad = n_chunks * size - n
    if pad:  # zero boxes: valid inputs, results dropped
        lo = jnp.concatenate([lo, jnp.zeros((pad, lo.shape[1]), lo.dtype)])
        hi = jnp.concatenate([hi, jnp.zeros((pad, hi.shape[1]), hi.dtype)])
    shape = (n_chunks, size, lo.shape[1])
    out = jax.lax.map(lambda box: fn(layers, *box), (lo.reshape(shape), hi.reshape(shape)))
    return jax.tree.map(lambda x: x.reshape((n_chunks * size,) + x.shape[2:])[:n], out)
