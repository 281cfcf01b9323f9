"""Axis-aligned boxes as ``(lo, hi)`` arrays: membership, volume, intersection, coverage, bisection.

A box over ``D`` dimensions is a pair of arrays ``lo, hi`` of shape ``[..., D]``; every function
here accepts any number of leading batch dimensions and broadcasts them. Boxes are closed:
``x`` is in ``(lo, hi)`` when ``lo <= x <= hi`` in every dimension. A box with ``hi < lo`` in some
dimension is empty (that is what :func:`intersect` returns for disjoint boxes).

The array functions are pure ``jax.numpy`` (jit/vmap-able). :func:`merge_adjacent`,
:func:`validate_boxes` and :func:`check_tiles` are host-side helpers on NumPy arrays.
"""

from __future__ import annotations

from fractions import Fraction

import jax.numpy as jnp
import numpy as np


def validate_boxes(lo, hi, name: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """Check that ``lo``/``hi`` describe boxes; return them as float NumPy arrays.

    Raises ``ValueError`` naming ``name`` when the shapes differ, there is no dimension axis,
    a value is NaN or ``lo > hi`` somewhere.

    Example:
        >>> lo, hi = validate_boxes([0.0, 0.0], [1.0, 2.0], "goal")
        >>> validate_boxes([1.0], [0.0], "goal")
        Traceback (most recent call last):
        ...
        ValueError: goal: lo > hi at index (0,) (1.0 > 0.0)
    """
    lo = np.asarray(lo)
    hi = np.asarray(hi)
    if not np.issubdtype(lo.dtype, np.floating):
        lo = lo.astype(np.float64)
    if not np.issubdtype(hi.dtype, np.floating):
        hi = hi.astype(np.float64)
    if lo.shape != hi.shape:
        raise ValueError(f"{name}: lo and hi have different shapes {lo.shape} and {hi.shape}")
    if lo.ndim == 0:
        raise ValueError(f"{name}: boxes need a trailing dimension axis, got scalars")
    if np.isnan(lo).any() or np.isnan(hi).any():
        raise ValueError(f"{name}: NaN in box bounds")
    bad = lo > hi
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{name}: lo > hi at index {idx} ({lo[idx]} > {hi[idx]})")
    return lo, hi


def contains(lo, hi, x):
    """Whether the closed box ``[lo, hi]`` contains the point ``x`` (all shapes ``[..., D]``).

    Example:
        >>> import jax.numpy as jnp
        >>> contains(jnp.zeros(2), jnp.ones(2), jnp.array([[1.0, 0.5], [1.1, 0.5]]))
        Array([ True, False], dtype=bool)
    """
    return jnp.all((lo <= x) & (x <= hi), axis=-1)


def volume(lo, hi):
    """Volume of boxes ``[..., D]``; empty boxes (``hi < lo`` somewhere) have volume 0.

    Example:
        >>> import jax.numpy as jnp
        >>> float(volume(jnp.array([0.0, 0.0]), jnp.array([2.0, 3.0])))
        6.0
    """
    return jnp.prod(jnp.maximum(hi - lo, 0), axis=-1)


def intersect(lo1, hi1, lo2, hi2):
    """Intersection of two boxes. Disjoint boxes give an empty box (``hi < lo`` somewhere),
    whose :func:`volume` is 0 and which :func:`contains` nothing.

    Example:
        >>> import jax.numpy as jnp
        >>> a, b = jnp.array([0.0]), jnp.array([1.0])
        >>> lo, hi = intersect(a, a + 2, b, b + 2)
        >>> lo.tolist(), hi.tolist()
        ([1.0], [2.0])
    """
    return jnp.maximum(lo1, lo2), jnp.minimum(hi1, hi2)


COVERAGE_RULES = ("final", "results")


def coverage(r_lo, r_hi, t_lo, t_hi, rule: str = "final"):
    """Coverage ratios ``(c1, c2)`` of a reached box ``R`` and a target box ``T``.

    ``c1 = vol(R ∩ T) / vol(R)`` and ``c2 = vol(R ∩ T) / vol(T)``, both volumes taken over the
    dimensions where ``R`` has non-zero width (SPEC.md, section 3.6). ``rule`` says what a
    dimension where ``R`` and ``T`` do not intersect does:

    - ``"final"`` (the authors' final maze version, SPEC.md section 3.6): it makes both ratios
      0. Dimensions where ``R`` is degenerate do not enter the volumes, but ``R ∩ T`` must be
      non-empty there: a point coordinate outside ``T``'s range makes both ratios 0 (otherwise
      a degenerate ``R`` lying outside ``T`` would count as covering it).
    - ``"results"`` (the version that made the authors' result files, SPEC.md section 3.9.2):
      it is *skipped*, left out of all three volumes. So a predicted box entirely left of
      ``x = 1`` but inside ``T`` in every other dimension has ``c1 = 1`` towards
      ``T = [1, 3] x ...``. Closed intervals that touch intersect (in a point, width 0), so
      they are not skipped. With every dimension skipped the volumes are empty products and
      both ratios are 1 (our reading; SPEC.md does not say).

    ``c2`` is 0 when ``T`` has zero width in a dimension that enters the volumes where ``R``
    has not (then ``vol(R ∩ T)`` is 0 too). If ``R`` is a single point, both ratios are 1
    when it lies in ``T`` and, under ``"final"``, 0 otherwise.

    Example:
        >>> import jax.numpy as jnp
        >>> c1, c2 = coverage(jnp.array([0.0, 5.0]), jnp.array([2.0, 5.0]),
        ...                   jnp.array([1.0, 0.0]), jnp.array([5.0, 9.0]))
        >>> float(c1), float(c2)
        (0.5, 0.25)
        >>> r_lo, r_hi = jnp.array([0.0, 1.0]), jnp.array([0.5, 2.0])  # left of x = 1
        >>> t_lo, t_hi = jnp.array([1.0, 0.0]), jnp.array([3.0, 3.0])
        >>> [round(float(c), 3) for c in coverage(r_lo, r_hi, t_lo, t_hi)]
        [0.0, 0.0]
        >>> [round(float(c), 3) for c in coverage(r_lo, r_hi, t_lo, t_hi, rule="results")]
        [1.0, 0.333]
    """
    if rule not in COVERAGE_RULES:
        raise ValueError(f"rule: must be one of {COVERAGE_RULES}, got {rule!r}")
    r_w = r_hi - r_lo
    wide = r_w > 0
    i_lo, i_hi = jnp.maximum(r_lo, t_lo), jnp.minimum(r_hi, t_hi)
    i_w = jnp.maximum(i_hi - i_lo, 0)
    t_w = t_hi - t_lo
    one = jnp.ones_like(r_w)
    if rule == "results":
        # A dimension where R and T do not intersect is left out of all three volumes.
        wide = wide & (i_lo <= i_hi)
    inter = jnp.prod(jnp.where(wide, i_w, one), axis=-1)
    vol_r = jnp.prod(jnp.where(wide, r_w, one), axis=-1)
    vol_t = jnp.prod(jnp.where(wide, t_w, one), axis=-1)
    if rule == "final":
        # Degenerate coordinates of R must lie inside T, else R ∩ T is empty.
        hits = jnp.all(wide | ((t_lo <= r_lo) & (r_lo <= t_hi)), axis=-1)
        inter = jnp.where(hits, inter, 0)
    c1 = inter / vol_r
    c2 = jnp.where(vol_t > 0, inter / jnp.where(vol_t > 0, vol_t, 1), 0)
    return c1, c2


def bisect(lo, hi, dim):
    """Split boxes at the midpoint of dimension ``dim`` (an int or an int array of batch shape).

    Returns ``((lo_a, hi_a), (lo_b, hi_b))``: ``a`` is the lower half, ``b`` the upper half; they
    share the face at the midpoint and together tile the box.

    Example:
        >>> import jax.numpy as jnp
        >>> (la, ha), (lb, hb) = bisect(jnp.zeros(2), jnp.array([2.0, 4.0]), 1)
        >>> ha.tolist(), lb.tolist()
        ([2.0, 2.0], [0.0, 2.0])
    """
    lo = jnp.asarray(lo)
    hi = jnp.asarray(hi)
    dim = jnp.asarray(dim)
    mask = jnp.arange(lo.shape[-1]) == dim[..., None]
    mid = (lo + hi) * 0.5
    return (lo, jnp.where(mask, mid, hi)), (jnp.where(mask, mid, lo), hi)


def _face_merge_dim(lo1, hi1, lo2, hi2) -> int | None:
    """The dimension along which two boxes share a full face, or None."""
    diff = (lo1 != lo2) | (hi1 != hi2)
    if diff.sum() != 1:
        return None
    d = int(np.argmax(diff))
    if hi1[d] == lo2[d] or hi2[d] == lo1[d]:
        return d
    return None


def merge_adjacent(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Merge boxes that share a full face until no two do (host-side, NumPy).

    Two boxes merge when they agree in all dimensions but one and touch along it; their union
    is then a box. Greedy and deterministic: the lowest-index pair is merged first and the union
    takes the lower index. The result covers exactly the same set.

    Example:
        >>> import numpy as np
        >>> lo, hi = merge_adjacent(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
        ...                         np.array([[1.0, 1.0], [2.0, 1.0], [1.0, 2.0]]))
        >>> lo.tolist(), hi.tolist()
        ([[0.0, 0.0], [0.0, 1.0]], [[2.0, 1.0], [1.0, 2.0]])
    """
    lo = np.asarray(lo)
    hi = np.asarray(hi)
    if lo.ndim != 2 or lo.shape != hi.shape:
        raise ValueError(f"lo, hi: expected two arrays of shape [N, D], got {lo.shape}, {hi.shape}")
    lo_list = [r.copy() for r in lo]
    hi_list = [r.copy() for r in hi]
    merged = True
    while merged:
        merged = False
        for i in range(len(lo_list)):
            for j in range(i + 1, len(lo_list)):
                d = _face_merge_dim(lo_list[i], hi_list[i], lo_list[j], hi_list[j])
                if d is None:
                    continue
                lo_list[i][d] = min(lo_list[i][d], lo_list[j][d])
                hi_list[i][d] = max(hi_list[i][d], hi_list[j][d])
                del lo_list[j], hi_list[j]
                merged = True
                break
            if merged:
                break
    if not lo_list:
        return lo[:0].copy(), hi[:0].copy()
    return np.stack(lo_list), np.stack(hi_list)


def _boxes_in_domain(lo, hi, domain_lo, domain_hi, name):
    """Validated boxes ``[N, D]`` and domain, every box inside the domain (else ``ValueError``)."""
    lo, hi = validate_boxes(lo, hi, name)
    dlo, dhi = validate_boxes(domain_lo, domain_hi, "domain")
    if lo.ndim != 2 or lo.shape[1] != dlo.shape[-1]:
        raise ValueError(f"{name}: expected shape [N, {dlo.shape[-1]}], got {lo.shape}")
    outside = (lo < dlo) | (hi > dhi)
    if outside.any():
        i = int(np.argwhere(outside)[0][0])
        raise ValueError(f"{name}: box {i} ({lo[i]}, {hi[i]}) leaves the domain")
    return lo, hi, dlo, dhi


def check_tiles(lo, hi, domain_lo, domain_hi, name: str = "boxes") -> None:
    """Raise ``ValueError`` unless boxes ``[N, D]`` tile the domain box exactly.

    Exact (no tolerance): every box lies in the domain, no two boxes overlap in their interiors,
    and the volumes add up to the domain's, summed in rational arithmetic. Together these mean
    the union is the whole domain. Volumes are taken over the dimensions where the domain has
    non-zero width; in the others every box must span the domain. Host-side, ``O(N^2)``.

    Example:
        >>> import numpy as np
        >>> check_tiles(np.array([[0.0], [1.0]]), np.array([[1.0], [3.0]]), [0.0], [3.0])
        >>> check_tiles(np.array([[0.0], [1.0]]), np.array([[2.0], [3.0]]), [0.0], [3.0])
        Traceback (most recent call last):
        ...
        ValueError: boxes: boxes 0 and 1 overlap in their interiors
    """
    lo, hi, dlo, dhi = _boxes_in_domain(lo, hi, domain_lo, domain_hi, name)
    wide = dhi > dlo
    flat = ~wide
    if flat.any():
        short = (lo[:, flat] > dlo[flat]) | (hi[:, flat] < dhi[flat])
        if short.any():
            i = int(np.argwhere(short)[0][0])
            raise ValueError(f"{name}: box {i} does not span the domain's degenerate dimensions")
    n = lo.shape[0]
    for i in range(n):
        overlap = np.all(np.minimum(hi[i, wide], hi[i + 1:, wide])
                         > np.maximum(lo[i, wide], lo[i + 1:, wide]), axis=-1)
        if overlap.any():
            j = i + 1 + int(np.argmax(overlap))
            raise ValueError(f"{name}: boxes {i} and {j} overlap in their interiors")

    def exact_volume(a, b):
        v = Fraction(1)
        for x, y in zip(a[wide], b[wide], strict=True):
            v *= Fraction(float(y)) - Fraction(float(x))
        return v

    total = sum((exact_volume(lo[i], hi[i]) for i in range(n)), Fraction(0))
    domain = exact_volume(dlo, dhi)
    if total != domain:
        raise ValueError(
            f"{name}: boxes do not cover the domain (volume {float(total)} of {float(domain)})"
        )


def check_covers(lo, hi, domain_lo, domain_hi, name: str = "boxes",
                 max_cells: int = 1_000_000) -> None:
    """Raise ``ValueError`` unless boxes ``[N, D]`` lie in the domain and their union is all of it.

    Unlike :func:`check_tiles`, boxes may overlap (a first-box rule decides who owns a shared
    point, as in the authors' labyrinth partition, SPEC.md 2.1). Exact: the domain is cut at
    every box bound into grid cells and each cell's centre must lie in some box; the message
    names an uncovered point. Host-side; raises if the grid would exceed ``max_cells``.

    Example:
        >>> import numpy as np
        >>> check_covers(np.array([[0.0], [0.5]]), np.array([[2.0], [3.0]]), [0.0], [3.0])
        >>> check_covers(np.array([[0.0], [2.0]]), np.array([[1.0], [3.0]]), [0.0], [3.0])
        Traceback (most recent call last):
        ...
        ValueError: boxes: no box contains the point [1.5] of the domain
    """
    lo, hi, dlo, dhi = _boxes_in_domain(lo, hi, domain_lo, domain_hi, name)
    # Cell centres along each dimension (the domain's value itself where it is degenerate).
    centres = []
    for d in range(dlo.shape[0]):
        cuts = np.unique(np.concatenate([[dlo[d], dhi[d]], lo[:, d], hi[:, d]]))
        centres.append((cuts[:-1] + cuts[1:]) / 2 if len(cuts) > 1 else cuts)
    cells = int(np.prod([len(c) for c in centres]))
    if cells > max_cells:
        raise ValueError(f"{name}: {cells} grid cells to check exceed max_cells={max_cells}")
    points = np.stack(np.meshgrid(*centres, indexing="ij"), axis=-1).reshape(-1, dlo.shape[0])
    inside = np.any(np.all((lo <= points[:, None]) & (points[:, None] <= hi), axis=-1), axis=-1)
    if not inside.all():
        raise ValueError(f"{name}: no box contains the point {points[~inside][0].tolist()} of "
                         "the domain")
