"""Goal refinement by reachability analysis (SPEC.md section 3).

Given a forward model ``F(s, G) -> s'`` (a ReLU MLP on ``s ‖ G.lo ‖ G.hi``), a start box ``G_s``
and a target box ``G_d``, split ``G_s`` into the boxes whose states reach ``G_d`` and those that
do not. A box is analysed by bounding ``F`` over it with the goal inputs held at ``G_d``'s bounds
(zero-width input dimensions), which gives an output box ``R``; with the coverage ratios
``c1 = vol(R ∩ G_d) / vol(R)`` and ``c2 = vol(R ∩ G_d) / vol(G_d)``
(:func:`gara_jax.boxes.coverage`):

- ``c1 >= tau1``: the box reaches;
- else ``c2 <= tau2``: it does not;
- else, while its volume is above ``min_volume_ratio`` of ``G_s``'s, it is bisected at the
  midpoint of the dimension with the largest *smear* (bound on ``sum_o |dF_o / ds_j|`` times the
  width of dimension ``j``) and both halves are analysed; a box too small to split reaches iff
  ``c1 >= small_box_c1`` (the reference: 0.5; ``None``: it never reaches).

The frontier is processed breadth-first, all jobs and all boxes of a depth level in one jitted,
batched bounds call. Sizes are padded to powers of two so that few shapes get compiled.
Afterwards, halves that got the same verdict are merged back into their parent, and adjacent
boxes of the same verdict are merged (:func:`gara_jax.boxes.merge_adjacent`; ``merge="siblings"``
stops after the first step).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gara_jax import boxes
from gara_jax.networks import mlp_layers
from gara_jax.reach._layers import TunedJit, check_layers
from gara_jax.reach.crown import crown_preactivations
from gara_jax.reach.ibp import ibp_preactivations
from gara_jax.reach.zonotope import zonotope_preactivations

METHODS = ("ibp", "crown", "zonotope", "zonotope_box")
#: What is merged after an analysis: ``"full"``, same-verdict sibling halves and then adjacent
#: same-verdict boxes until no two share a face; ``"siblings"``, the sibling halves only.
MERGE_RULES = ("full", "siblings")
MIN_BUCKET = 8  # smallest padded frontier per job: fewer shapes to compile
#: How an undecided box picks its bisection dimension (``refine_many``'s ``split_rule``).
SPLIT_RULES = ("smear", "separation")


class RefineResult(NamedTuple):
    """The outcome of one refinement of ``G_s`` towards ``G_d``.

    ``reaching_lo/hi [R, D]`` and ``nonreaching_lo/hi [U, D]`` (NumPy) tile ``G_s`` exactly;
    each list is merged and sorted lexicographically by ``(lo, hi)``. ``n_analysed`` counts the
    boxes whose bounds were computed, ``depth`` is the deepest bisection level analysed (0: only
    ``G_s`` itself).
    """

    reaching_lo: np.ndarray
    reaching_hi: np.ndarray
    nonreaching_lo: np.ndarray
    nonreaching_hi: np.ndarray
    n_analysed: int
    depth: int


def _gradient_smear(layers, pre, lo, hi, dim):
    """Smear of each of the first ``dim`` inputs: ``sum_o max |dF_o/dx_j|`` times width.

    The Jacobian is bounded by interval arithmetic through the ReLU derivative pattern: a neuron
    with pre-activation bounds ``[l, u]`` has derivative 1 if ``l > 0``, 0 if ``u <= 0``, and
    anything in ``[0, 1]`` otherwise.
    """
    g_lo = g_hi = jnp.broadcast_to(layers[0][0][:dim], (lo.shape[0],) + layers[0][0][:dim].shape)
    for k in range(1, len(layers)):
        pre_lo, pre_hi = pre[k - 1]
        on = (pre_lo > 0)[:, None, :]
        off = (pre_hi <= 0)[:, None, :]
        g_lo = jnp.where(on, g_lo, jnp.where(off, 0, jnp.minimum(g_lo, 0)))
        g_hi = jnp.where(on, g_hi, jnp.where(off, 0, jnp.maximum(g_hi, 0)))
        w = layers[k][0]
        centre = (g_lo + g_hi) * 0.5 @ w
        radius = (g_hi - g_lo) * 0.5 @ jnp.abs(w)
        g_lo, g_hi = centre - radius, centre + radius
    grad = jnp.maximum(jnp.abs(g_lo), jnp.abs(g_hi)).sum(-1)  # [B, dim]
    return grad * (hi - lo)[:, :dim]


def _analyse_job(layers, s_lo, s_hi, t_lo, t_hi, c_lo, c_hi, i_lo, i_hi, q_lo, q_hi, margin,
                 method, coverage="final"):
    """Coverage ratios and smear for boxes ``s_lo/s_hi [B, D]`` of one job: the boxes are
    clipped into ``i_lo/i_hi`` (the job's input box), the network's goal inputs are
    ``t_lo/t_hi``, the coverage is measured against ``c_lo/c_hi`` (``G_d``, or the job's own
    coverage box) shrunk by ``margin`` times its width on every side, and the bounded output box
    is first clipped into ``q_lo/q_hi`` (onto its nearest face where it lies outside)."""
    s_lo, s_hi = jnp.clip(s_lo, i_lo, i_hi), jnp.clip(s_hi, i_lo, i_hi)
    n = s_lo.shape[0]
    dim = s_lo.shape[1]
    goal_lo = jnp.broadcast_to(t_lo, (n, dim))
    goal_hi = jnp.broadcast_to(t_hi, (n, dim))
    lo = jnp.concatenate([s_lo, goal_lo, goal_hi], axis=1)
    hi = jnp.concatenate([s_hi, goal_lo, goal_hi], axis=1)
    if method.startswith("zonotope"):  # the reference's domain, alone (SPEC.md 3.6)
        relu = "box" if method == "zonotope_box" else "deepz"
        pre = zonotope_preactivations(layers, lo, hi, relu)
    else:
        pre = ibp_preactivations(layers, lo, hi)
    if method == "crown":
        # Both are sound, so their intersection is too, and never looser than either.
        pre = [boxes.intersect(l1, u1, l2, u2)
               for (l1, u1), (l2, u2) in zip(pre, crown_preactivations(layers, lo, hi),
                                             strict=True)]
    r_lo, r_hi = pre[-1]
    r_lo, r_hi = jnp.clip(r_lo, q_lo, q_hi), jnp.clip(r_hi, q_lo, q_hi)
    inset = margin * (c_hi - c_lo)
    c1, c2 = boxes.coverage(r_lo, r_hi, c_lo + inset, c_hi - inset, rule=coverage)
    smear = _gradient_smear(layers, pre, lo, hi, dim)
    return c1, c2, smear


def _analyse(layers, s_lo, s_hi, t_lo, t_hi, c_lo, c_hi, i_lo, i_hi, q_lo, q_hi, margin,
             method, coverage="final"):
    return jax.vmap(lambda *a: _analyse_job(*a, margin, method, coverage))(
        layers, s_lo, s_hi, t_lo, t_hi, c_lo, c_hi, i_lo, i_hi, q_lo, q_hi)


_analyse_jit = TunedJit(_analyse, static_argnames=("method", "coverage"))


def _optional_boxes(lo, hi, name: str, shape):
    """``lo, hi`` validated to ``shape``, or the unbounded box when both are ``None``."""
    if (lo is None) != (hi is None):
        raise ValueError(f"{name}: give both or neither")
    if lo is None:
        return np.full(shape, -np.inf), np.full(shape, np.inf)
    lo, hi = boxes.validate_boxes(lo, hi, name)
    if lo.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {lo.shape}")
    return lo, hi


def _next_pow2(n: int, floor: int = 1) -> int:
    return max(floor, 1 << max(0, int(n - 1).bit_length()))


def _stacked_layers(stacked, n_jobs_name="stacked_layers"):
    if isinstance(stacked, Mapping):
        stacked = mlp_layers(stacked)
    try:
        # Host copies: the per-job padding below is then NumPy indexing, which compiles
        # nothing (a device gather would compile once per job count).
        layers = tuple((np.asarray(w), np.asarray(b)) for w, b in stacked)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{n_jobs_name}: expected (kernel, bias) pairs ({err})") from None
    if not layers:
        raise ValueError(f"{n_jobs_name}: empty layer sequence")
    check_layers(layers, n_jobs_name, batch_ndim=1)
    return layers


def _sorted_boxes(lo, hi, dim, dtype, merge):
    if not lo:
        empty = np.zeros((0, dim), dtype)
        return empty, empty.copy()
    lo, hi = np.stack(lo), np.stack(hi)
    if merge == "full":
        lo, hi = boxes.merge_adjacent(lo, hi)
    order = np.lexsort(np.concatenate([lo, hi], axis=1).T[::-1])
    return lo[order], hi[order]


def _collect(tree, dim, dtype, n_analysed, depth, merge) -> RefineResult:
    """Merge same-verdict siblings bottom-up, then (``merge="full"``) adjacent boxes; build
    the result."""
    for node in reversed(tree):
        kids = node["children"]
        if kids is not None:
            a, b = tree[kids[0]], tree[kids[1]]
            if a["children"] is None and b["children"] is None and a["verdict"] == b["verdict"]:
                node["children"], node["verdict"] = None, a["verdict"]
    leaves = {True: ([], []), False: ([], [])}
    stack = [0]
    while stack:
        node = tree[stack.pop()]
        if node["children"] is None:
            leaves[node["verdict"]][0].append(node["lo"])
            leaves[node["verdict"]][1].append(node["hi"])
        else:
            stack.extend(reversed(node["children"]))
    r_lo, r_hi = _sorted_boxes(*leaves[True], dim, dtype, merge)
    u_lo, u_hi = _sorted_boxes(*leaves[False], dim, dtype, merge)
    return RefineResult(r_lo, r_hi, u_lo, u_hi, n_analysed, depth)


def refine_many(stacked_layers, start_lo, start_hi, target_lo, target_hi, *, tau1: float = 0.7,
                tau2: float = 0.1, min_volume_ratio: float = 0.05,
                method: str = "crown", small_box_c1: float | None = None,
                coverage: str = "final", target_margin: float = 0.0,
                split_dims: Sequence[int] | None = None,
                merge: str = "full", cover_lo=None, cover_hi=None, input_lo=None,
                input_hi=None, split_rule: str = "smear", reach_lo=None,
                reach_hi=None) -> list[RefineResult]:
    """Refine ``J`` independent jobs, each with its own forward model, in batched bound calls.

    Args:
        stacked_layers: the ``J`` forward models as ``(kernel [J, in, out], bias [J, out])``
            pairs (or :class:`~gara_jax.networks.MLP` parameters with a leading ``J`` axis).
            Input size ``3 D`` (``s ‖ goal.lo ‖ goal.hi``), output size ``D``.
        start_lo, start_hi: the boxes ``G_s`` to split, ``[J, D]``.
        target_lo, target_hi: the target boxes ``G_d``, ``[J, D]``.
        tau1: ``c1`` at or above which a box reaches.
        tau2: ``c2`` at or below which a box does not reach.
        min_volume_ratio: boxes at or below this fraction of ``G_s``'s volume are not split.
        method: ``"ibp"``, ``"crown"`` (CROWN intersected with IBP), ``"zonotope"`` or
            ``"zonotope_box"`` (:func:`gara_jax.reach.zonotope` with ``relu="deepz"`` or
            ``"box"``, alone: the reference's Ai2 kind of analysis).
        small_box_c1: a box too small to split (or with no width left) reaches iff its ``c1``
            is at least this; ``None``: such a box does not reach.
        coverage: the coverage rule, ``"final"`` or ``"results"``: what a dimension where
            ``R`` and ``G_d`` do not intersect does (:func:`gara_jax.boxes.coverage`; SPEC.md
            sections 3.6 and 3.9.2).
        target_margin: the coverage is measured against ``G_d`` shrunk on every side by this
            fraction of its width in each dimension (``[0, 0.5)``; 0: ``G_d`` itself). The
            forward model's goal inputs stay ``G_d``'s bounds.
        split_dims: the dimensions a box may be bisected along (``None``: all). The largest
            smear among them picks the dimension; a box with no width left in them is treated
            as too small to split.
        reach_lo, reach_hi: ``[J, D]``, a box every true successor state lies in (e.g. the
            state space; ``None``: none). Each bounded reachable box is intersected with it
            before the coverage is measured, which stays sound: the states the bounds leave
            out cannot be reached. Where a bound lies wholly outside it, it is moved onto the
            nearest face.
        split_rule: which of the ``split_dims`` an undecided box is bisected along.
            ``"smear"`` (the reference, SPEC.md 3.6): the largest smear (gradient bound times
            width; ties: widest, then lowest index). ``"separation"``: the bisection whose two
            halves' ``c1`` differ most, each candidate's halves bounded in one extra batched
            call (ties: the smear order), so a box is cut where reaching changes, not where
            the model's output is most sensitive.
        merge: ``"full"``: after the analysis, same-verdict sibling halves are merged back
            into their parent, then adjacent same-verdict boxes until no two share a full
            face; ``"siblings"``: only the first step, so two same-verdict boxes from
            different branches of the bisection stay apart (as in the partitions of the
            authors' result files, SPEC.md 3.9.1).
        cover_lo, cover_hi: ``[J, D]``, the boxes the coverage is measured against, where they
            differ from the targets (``None``: the targets). The forward models' goal inputs
            stay ``target_lo/target_hi``: this asks where the options *towards* ``G_d`` end,
            measured against another box (GARA's ``exit_analysis``: options towards the goal
            holding the exit, measured against a box around the exit).
        input_lo, input_hi: ``[J, D]``, boxes the analysed boxes are clipped into before the
            forward model is bounded over them (``None``: no clipping). The pieces still tile
            ``G_s``; only the set of states the bounds hold for is narrowed (GARA's
            ``input_range="data"``: the velocities the pair's own data has). A box outside the
            input box along a dimension is analysed at the input box's nearest face there.

    Returns:
        One :class:`RefineResult` per job. Boxes are in ``start_lo``'s floating dtype (float64
        unless it is float32); midpoints are computed in that dtype, so the pieces tile ``G_s``
        exactly.

    Example:
        >>> import jax, jax.numpy as jnp, numpy as np
        >>> from gara_jax.networks import MLP
        >>> keys = jax.random.split(jax.random.key(0), 2)
        >>> params = jax.vmap(lambda k: MLP((8, 8), 4).init(k, jnp.zeros(12)))(keys)
        >>> lo, hi = np.zeros((2, 4)), np.ones((2, 4))
        >>> res = refine_many(params, lo, hi, lo + 0.5, hi + 0.5)
        >>> len(res), res[0].reaching_lo.shape[1]
        (2, 4)
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if not 0.0 <= tau2 <= 1.0 or not 0.0 < tau1 <= 1.0:
        raise ValueError(f"tau1, tau2: need 0 < tau1 <= 1 and 0 <= tau2 <= 1, got {tau1}, {tau2}")
    if not 0.0 < min_volume_ratio <= 1.0:
        raise ValueError(f"min_volume_ratio: must be in (0, 1], got {min_volume_ratio}")
    if small_box_c1 is not None and not 0.0 <= small_box_c1 <= 1.0:
        raise ValueError(f"small_box_c1: must be None or lie in [0, 1], got {small_box_c1}")
    if merge not in MERGE_RULES:
        raise ValueError(f"merge: must be one of {MERGE_RULES}, got {merge!r}")
    if split_rule not in SPLIT_RULES:
        raise ValueError(f"split_rule: must be one of {SPLIT_RULES}, got {split_rule!r}")
    if coverage not in boxes.COVERAGE_RULES:
        raise ValueError(f"coverage: must be one of {boxes.COVERAGE_RULES}, got {coverage!r}")
    if not 0.0 <= target_margin < 0.5:
        raise ValueError(f"target_margin: must lie in [0, 0.5), got {target_margin}")
    layers = _stacked_layers(stacked_layers)
    s_lo, s_hi = boxes.validate_boxes(start_lo, start_hi, "start_lo/start_hi")
    t_lo, t_hi = boxes.validate_boxes(target_lo, target_hi, "target_lo/target_hi")
    if s_lo.ndim != 2 or t_lo.shape != s_lo.shape:
        raise ValueError(
            f"start_lo/target_lo: expected matching shapes [J, D], got {s_lo.shape}, {t_lo.shape}")
    if (cover_lo is None) != (cover_hi is None):
        raise ValueError("cover_lo/cover_hi: give both or neither")
    if cover_lo is None:
        c_lo, c_hi = t_lo, t_hi
    else:
        c_lo, c_hi = boxes.validate_boxes(cover_lo, cover_hi, "cover_lo/cover_hi")
        if c_lo.shape != t_lo.shape:
            raise ValueError(f"cover_lo/cover_hi: expected shape {t_lo.shape}, got {c_lo.shape}")
    i_lo, i_hi = _optional_boxes(input_lo, input_hi, "input_lo/input_hi", s_lo.shape)
    q_lo, q_hi = _optional_boxes(reach_lo, reach_hi, "reach_lo/reach_hi", s_lo.shape)
    n_jobs, dim = s_lo.shape
    if n_jobs == 0:
        return []
    splittable = np.ones(dim, bool)
    if split_dims is not None:
        dims = np.asarray(split_dims, int).reshape(-1)
        if dims.size == 0 or dims.min() < 0 or dims.max() >= dim or len(set(dims)) != dims.size:
            raise ValueError(f"split_dims: must be distinct dimensions in [0, {dim}), got "
                             f"{split_dims!r}")
        splittable = np.isin(np.arange(dim), dims)
    j_layers = layers[0][0].shape[0]
    if j_layers != n_jobs:
        raise ValueError(f"stacked_layers: {j_layers} networks for {n_jobs} jobs")
    if layers[0][0].shape[1] != 3 * dim or layers[-1][0].shape[2] != dim:
        raise ValueError(
            f"stacked_layers: expected input size {3 * dim} (s, goal lo, goal hi) and output "
            f"size {dim}, got {layers[0][0].shape[1]} and {layers[-1][0].shape[2]}")
    dtype = np.float32 if s_lo.dtype == np.float32 else np.float64
    s_lo, s_hi = s_lo.astype(dtype), s_hi.astype(dtype)

    # Pad the job axis to a power of two (copies of job 0, ignored) to bound compilations.
    j_pad = _next_pow2(n_jobs)
    pad = np.concatenate([np.arange(n_jobs), np.zeros(j_pad - n_jobs, int)])
    layers_pad = tuple((w[pad], b[pad]) for w, b in layers) if j_pad > n_jobs else layers
    net_dtype = layers[0][0].dtype
    t_lo_pad = jnp.asarray(t_lo[pad], net_dtype)
    t_hi_pad = jnp.asarray(t_hi[pad], net_dtype)
    c_lo_pad = jnp.asarray(c_lo[pad], net_dtype)
    c_hi_pad = jnp.asarray(c_hi[pad], net_dtype)
    i_lo_pad = jnp.asarray(i_lo[pad], net_dtype)
    i_hi_pad = jnp.asarray(i_hi[pad], net_dtype)
    q_lo_pad = jnp.asarray(q_lo[pad], net_dtype)
    q_hi_pad = jnp.asarray(q_hi[pad], net_dtype)

    trees = [[dict(lo=s_lo[j], hi=s_hi[j], depth=0, children=None, verdict=False)]
             for j in range(n_jobs)]
    frontier = [[0] for _ in range(n_jobs)]
    n_analysed = [0] * n_jobs
    depth = [0] * n_jobs

    def analyse(per_job):
        """``c1, c2, smear`` of ``per_job[j]``, a list of ``(lo, hi)`` boxes per job."""
        width = _next_pow2(max(len(f) for f in per_job), MIN_BUCKET)
        b_lo = np.repeat(s_lo[pad][:, None, :], width, axis=1)
        b_hi = np.repeat(s_hi[pad][:, None, :], width, axis=1)
        for j, job_boxes in enumerate(per_job):
            for i, (lo_i, hi_i) in enumerate(job_boxes):
                b_lo[j, i], b_hi[j, i] = lo_i, hi_i
        return jax.device_get(_analyse_jit(
            layers_pad, jnp.asarray(b_lo, net_dtype), jnp.asarray(b_hi, net_dtype),
            t_lo_pad, t_hi_pad, c_lo_pad, c_hi_pad, i_lo_pad, i_hi_pad, q_lo_pad, q_hi_pad,
            jnp.asarray(target_margin, net_dtype),
            method=method,
            coverage=coverage))

    def halves(node, split):
        mid = node["lo"][split] + (node["hi"][split] - node["lo"][split]) / dtype(2)
        lo_a, hi_a = node["lo"], node["hi"].copy()
        lo_b, hi_b = node["lo"].copy(), node["hi"]
        hi_a[split] = lo_b[split] = mid
        return (lo_a, hi_a), (lo_b, hi_b)

    while any(frontier):
        c1, c2, smear = analyse([[(trees[j][n]["lo"], trees[j][n]["hi"]) for n in nodes]
                                 for j, nodes in enumerate(frontier)])
        to_split = [[] for _ in range(n_jobs)]  # (node, dimensions in preference order)
        new_frontier = [[] for _ in range(n_jobs)]
        for j, nodes in enumerate(frontier):
            tree = trees[j]
            for i, n in enumerate(nodes):
                node = tree[n]
                n_analysed[j] += 1
                depth[j] = max(depth[j], node["depth"])
                if c1[j, i] >= tau1:
                    node["verdict"] = True
                    continue
                width_i = np.where(splittable, node["hi"] - node["lo"], 0)
                # Halving volume: at depth d the box has 2^-d of G_s's volume (over the
                # dimensions where G_s has width, the only ones ever split).
                if c2[j, i] <= tau2:
                    node["verdict"] = False
                    continue
                if 0.5 ** node["depth"] <= min_volume_ratio or not (width_i > 0).any():
                    node["verdict"] = small_box_c1 is not None and c1[j, i] >= small_box_c1
                    continue
                # Largest smear; ties: widest, then lowest index. Only dimensions with width.
                order = np.lexsort((np.arange(dim), -width_i, -smear[j, i]))
                to_split[j].append((n, [int(d) for d in order if width_i[d] > 0]))
        if split_rule == "separation" and any(len(d) > 1 for job in to_split for _, d in job):
            # Bound both halves of every candidate bisection; keep the one whose halves'
            # c1 differ most (a stable sort keeps the smear order among ties).
            cands = [[h for n, dims in job for d in dims for h in halves(trees[j][n], d)]
                     for j, job in enumerate(to_split)]
            h_c1 = analyse(cands)[0]
            for j, job in enumerate(to_split):
                k = 0
                for idx, (n, dims) in enumerate(job):
                    gap = [abs(float(h_c1[j, k + 2 * m]) - float(h_c1[j, k + 2 * m + 1]))
                           for m in range(len(dims))]
                    k += 2 * len(dims)
                    job[idx] = (n, [dims[m] for m in np.argsort(-np.asarray(gap),
                                                                 kind="stable")])
        for j, job in enumerate(to_split):
            tree = trees[j]
            for n, dims in job:
                node = tree[n]
                node["children"] = (len(tree), len(tree) + 1)
                for lo_c, hi_c in halves(node, dims[0]):
                    tree.append(dict(lo=lo_c, hi=hi_c, depth=node["depth"] + 1, children=None,
                                     verdict=False))
                new_frontier[j].extend(node["children"])
        frontier = new_frontier
    return [_collect(trees[j], dim, dtype, n_analysed[j], depth[j], merge)
            for j in range(n_jobs)]


def refine(layers_or_params, start_lo, start_hi, target_lo, target_hi, *, tau1: float = 0.7,
           tau2: float = 0.1, min_volume_ratio: float = 0.05,
           method: str = "crown", small_box_c1: float | None = None,
           coverage: str = "final", target_margin: float = 0.0,
           split_dims: Sequence[int] | None = None, merge: str = "full",
           split_rule: str = "smear") -> RefineResult:
    """Split the start box ``G_s`` into boxes that reach ``G_d`` and boxes that do not.

    The single-job form of :func:`refine_many`; ``layers_or_params`` is one forward model (a
    ``(kernel, bias)`` sequence or :class:`~gara_jax.networks.MLP` parameters) and the boxes
    are ``[D]``.

    Example:
        >>> import numpy as np
        >>> d = 4
        >>> eye = np.eye(d, 3 * d)  # F(s, G) = s + (1, 0, 0, 0), via relu(s) - relu(-s)
        >>> layers = [(np.concatenate([eye, -eye], 0).T, np.zeros(2 * d)),
        ...           (np.concatenate([np.eye(d), -np.eye(d)]), np.array([1.0, 0, 0, 0]))]
        >>> res = refine(layers, [0.0, 0, 0, 0], [4.0, 1, 1, 1], [2.0, 0, 0, 0], [3.5, 1, 1, 1])
        >>> res.reaching_lo.tolist(), res.reaching_hi.tolist()
        ([[1.0, 0.0, 0.0, 0.0]], [[2.5, 1.0, 1.0, 1.0]])
    """
    if isinstance(layers_or_params, Mapping):
        layers_or_params = mlp_layers(layers_or_params)
    if not isinstance(layers_or_params, Sequence) or not layers_or_params:
        raise ValueError("layers_or_params: expected (kernel, bias) pairs or MLP parameters")
    stacked = [(jnp.asarray(w)[None], jnp.asarray(b)[None]) for w, b in layers_or_params]
    s_lo, s_hi = boxes.validate_boxes(start_lo, start_hi, "start_lo/start_hi")
    t_lo, t_hi = boxes.validate_boxes(target_lo, target_hi, "target_lo/target_hi")
    if s_lo.ndim != 1 or t_lo.shape != s_lo.shape:
        raise ValueError(
            f"start_lo/target_lo: expected matching shapes [D], got {s_lo.shape}, {t_lo.shape}")
    return refine_many(stacked, s_lo[None], s_hi[None], t_lo[None], t_hi[None], tau1=tau1,
                       tau2=tau2, min_volume_ratio=min_volume_ratio, method=method,
                       small_box_c1=small_box_c1, coverage=coverage,
                       target_margin=target_margin, split_dims=split_dims, merge=merge,
                       split_rule=split_rule)[0]
