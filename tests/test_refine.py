"""Refinement: exact on closed-form networks, tiles G_s, deterministic, batched = single."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gara_jax import boxes
from gara_jax.networks import MLP
from gara_jax.reach import RefineResult, refine, refine_many

D = 4


def translation_net(shift, x_only=False, const=(0.5, 0.5, 0.5), scale=1.0):
    """A hand-set forward model ``F(s, G)`` (input ``s ‖ G.lo ‖ G.hi``) via relu(v) - relu(-v).

    ``x_only=False``: ``F = scale s + shift``. ``x_only=True``: ``F = (scale x + shift[0],
    *const)``, which depends on ``x`` alone, so every split is along ``x``.
    """
    keep = scale * (np.eye(D, 3 * D)[:1] if x_only else np.eye(D, 3 * D))
    w1 = np.concatenate([keep, -keep], 0).T  # [12, 2k]: relu(v), relu(-v)
    k = keep.shape[0]
    w2 = np.concatenate([np.eye(k, D), -np.eye(k, D)], 0)  # [2k, 4]
    b2 = np.array(shift, float)
    if x_only:
        b2 = b2 + np.array([0.0, *const])
    return [(w1.astype(np.float32), np.zeros(2 * k, np.float32)),
            (w2.astype(np.float32), b2.astype(np.float32))]


def expected_1d(a, b, dx, t0, t1, tau1=0.7, tau2=0.1, ratio=0.05):
    """SPEC.md's rule on x-intervals for F = x + dx, with exact arithmetic; merged intervals."""
    verdicts = []

    def visit(lo, hi, depth):
        overlap = max(0.0, min(hi + dx, t1) - max(lo + dx, t0))
        if overlap / (hi - lo) >= tau1:
            verdicts.append((lo, hi, True))
        elif overlap / (t1 - t0) <= tau2 or 0.5**depth <= ratio:
            verdicts.append((lo, hi, False))
        else:
            mid = (lo + hi) / 2
            visit(lo, mid, depth + 1)
            visit(mid, hi, depth + 1)

    visit(a, b, 0)
    merged = []
    for lo, hi, v in verdicts:  # left to right
        if merged and merged[-1][2] == v and merged[-1][1] == lo:
            merged[-1] = (merged[-1][0], hi, v)
        else:
            merged.append((lo, hi, v))
    return ([(lo, hi) for lo, hi, v in merged if v], [(lo, hi) for lo, hi, v in merged if not v])


def x_intervals(lo, hi):
    return sorted(zip(lo[:, 0].tolist(), hi[:, 0].tolist(), strict=True))


@pytest.mark.parametrize("method", ["crown", "ibp", "zonotope", "zonotope_box"])
def test_translation_closed_form(method):
    # x' = x + 1 lands in [2, 3.5] iff x in [1, 2.5]; SPEC's rule finds exactly that here.
    start_lo, start_hi = np.array([0.0, 0, 0, 0]), np.array([4.0, 1, 1, 1])
    res = refine(translation_net([1.0, 0, 0, 0]), start_lo, start_hi,
                 np.array([2.0, 0, 0, 0]), np.array([3.5, 1, 1, 1]), method=method)
    assert res.reaching_lo.tolist() == [[1.0, 0, 0, 0]]
    assert res.reaching_hi.tolist() == [[2.5, 1, 1, 1]]
    assert x_intervals(res.nonreaching_lo, res.nonreaching_hi) == [(0.0, 1.0), (2.5, 4.0)]
    boxes.check_tiles(np.concatenate([res.reaching_lo, res.nonreaching_lo]),
                      np.concatenate([res.reaching_hi, res.nonreaching_hi]), start_lo, start_hi)
    assert res.n_analysed == 9 and res.depth == 3


@pytest.mark.parametrize("dx, t0, t1", [
    (1.0, 2.0, 3.5), (0.5, 0.0, 1.25), (-1.25, 0.5, 2.0), (2.0, 2.0, 2.75), (0.25, 1.0, 8.0)])
def test_x_translation_matches_hand_computation(dx, t0, t1):
    start_lo, start_hi = np.array([0.0, 0, -1, -1]), np.array([4.0, 3, 1, 1])
    res = refine(translation_net([dx, 0, 0, 0], x_only=True), start_lo, start_hi,
                 np.array([t0, 0, -1, -1]), np.array([t1, 3, 1, 1]))
    want_reach, want_miss = expected_1d(0.0, 4.0, dx, t0, t1)
    assert x_intervals(res.reaching_lo, res.reaching_hi) == want_reach
    assert x_intervals(res.nonreaching_lo, res.nonreaching_hi) == want_miss
    # Only x is ever split: the other dimensions are G_s's.
    for lo, hi in ((res.reaching_lo, res.reaching_hi), (res.nonreaching_lo, res.nonreaching_hi)):
        assert (lo[:, 1:] == start_lo[1:]).all() and (hi[:, 1:] == start_hi[1:]).all()


@pytest.mark.parametrize("margin", [0.0625, 0.125])
def test_target_margin_measures_coverage_inside_the_target(margin):
    """With ``target_margin`` the coverage is that of ``G_d`` shrunk by ``margin`` of its width
    on every side: the hand computation with the shrunk x-interval (the x-only model's other
    outputs, 0.5, lie inside the shrunk y and velocity ranges; margins whose bounds float32
    holds exactly)."""
    start_lo, start_hi = np.array([0.0, 0, -1, -1]), np.array([4.0, 3, 1, 1])
    t_lo, t_hi = np.array([2.0, 0, -1, -1]), np.array([3.5, 3, 1, 1])
    net = translation_net([1.0, 0, 0, 0], x_only=True)
    res = refine(net, start_lo, start_hi, t_lo, t_hi, target_margin=margin)
    inset = margin * 1.5
    want_reach, want_miss = expected_1d(0.0, 4.0, 1.0, 2.0 + inset, 3.5 - inset)
    assert x_intervals(res.reaching_lo, res.reaching_hi) == want_reach
    assert x_intervals(res.nonreaching_lo, res.nonreaching_hi) == want_miss
    plain = refine(net, start_lo, start_hi, t_lo, t_hi)
    assert x_intervals(plain.reaching_lo, plain.reaching_hi) == expected_1d(
        0.0, 4.0, 1.0, 2.0, 3.5)[0]
    # Every dimension shrinks: at 0.25 the y range is [0.75, 2.25], which the predicted
    # y = 0.5 misses, so nothing reaches.
    assert len(refine(net, start_lo, start_hi, t_lo, t_hi, target_margin=0.25).reaching_lo) == 0
    with pytest.raises(ValueError, match="target_margin"):
        refine(net, start_lo, start_hi, t_lo, t_hi, target_margin=0.5)


def test_cover_box_is_measured_while_the_goal_inputs_stay_the_target():
    """``cover_lo/cover_hi``: coverage against another box, the forward model still fed the
    target's bounds. The hand-set model moves x by the target's ``lo`` x (input 4), so the
    result is the hand computation for a shift of 1 (the target's) against the cover box's
    x-interval, not for a shift of 2 (the cover box's)."""
    w1 = np.zeros((12, 2), np.float32)
    w1[0], w1[4] = (1.0, -1.0), (1.0, -1.0)  # v = x + target.lo_x; relu(v), relu(-v)
    w2 = np.zeros((2, 4), np.float32)
    w2[0, 0], w2[1, 0] = 1.0, -1.0
    net = [(w1, np.zeros(2, np.float32)), (w2, np.array([0, 0.5, 0.5, 0.5], np.float32))]
    start_lo, start_hi = np.array([[0.0, 0, -1, -1]]), np.array([[4.0, 3, 1, 1]])
    t_lo, t_hi = np.array([[1.0, 0, -1, -1]]), np.array([[4.0, 3, 1, 1]])
    c_lo, c_hi = np.array([[2.0, 0, -1, -1]]), np.array([[3.5, 3, 1, 1]])
    stacked = [(w[None], b[None]) for w, b in net]
    (res,) = refine_many(stacked, start_lo, start_hi, t_lo, t_hi, cover_lo=c_lo, cover_hi=c_hi)
    want_reach, want_miss = expected_1d(0.0, 4.0, 1.0, 2.0, 3.5)
    assert x_intervals(res.reaching_lo, res.reaching_hi) == want_reach
    assert x_intervals(res.nonreaching_lo, res.nonreaching_hi) == want_miss
    (fed_cover,) = refine_many(stacked, start_lo, start_hi, c_lo, c_hi)
    assert x_intervals(fed_cover.reaching_lo, fed_cover.reaching_hi) == expected_1d(
        0.0, 4.0, 2.0, 2.0, 3.5)[0] != want_reach
    with pytest.raises(ValueError, match="cover_lo/cover_hi"):
        refine_many(stacked, start_lo, start_hi, t_lo, t_hi, cover_lo=c_lo)
    with pytest.raises(ValueError, match="cover_lo/cover_hi"):
        refine_many(stacked, start_lo, start_hi, t_lo, t_hi, cover_lo=c_lo[:, :3],
                    cover_hi=c_hi[:, :3])


def test_input_box_narrows_the_states_bounded_over():
    """``input_lo/input_hi``: the identity-plus-shift model keeps vx, so over G_s's vx range
    [-1, 1] no box lies within the target's [-0.25, 0.25] (c1 <= 0.25 < tau1) and nothing
    reaches; with the input box's vx in [-0.2, 0.2] the verdict is the x hand computation.
    The pieces still tile G_s, vx range included."""
    start_lo, start_hi = np.array([[0.0, 0, -1, -1]]), np.array([[4.0, 3, 1, 1]])
    t_lo, t_hi = np.array([[2.0, 0, -0.25, -1]]), np.array([[3.5, 3, 0.25, 1]])
    stacked = [(w[None], b[None]) for w, b in translation_net([1.0, 0, 0, 0])]
    kw = dict(split_dims=(0,))
    (wide,) = refine_many(stacked, start_lo, start_hi, t_lo, t_hi, **kw)
    assert len(wide.reaching_lo) == 0
    i_lo, i_hi = np.array([[-5.0, 0, -0.2, -1]]), np.array([[5.0, 3, 0.2, 1]])
    (data,) = refine_many(stacked, start_lo, start_hi, t_lo, t_hi, input_lo=i_lo,
                          input_hi=i_hi, **kw)
    want_reach, want_miss = expected_1d(0.0, 4.0, 1.0, 2.0, 3.5)
    assert x_intervals(data.reaching_lo, data.reaching_hi) == want_reach
    assert x_intervals(data.nonreaching_lo, data.nonreaching_hi) == want_miss
    boxes.check_tiles(np.concatenate([data.reaching_lo, data.nonreaching_lo]),
                      np.concatenate([data.reaching_hi, data.nonreaching_hi]), start_lo[0],
                      start_hi[0])
    with pytest.raises(ValueError, match="input_lo/input_hi"):
        refine_many(stacked, start_lo, start_hi, t_lo, t_hi, input_lo=i_lo)
    with pytest.raises(ValueError, match="input_lo/input_hi"):
        refine_many(stacked, start_lo, start_hi, t_lo, t_hi, input_lo=i_lo[:, :3],
                    input_hi=i_hi[:, :3])


def test_split_dims_limit_the_bisection():
    """The x-only model's reaching part lies along x: with x allowed the analysis finds it as
    without the option; with only y allowed every half looks like its parent, so the boxes
    are halved down to the volume floor (depth 5: 2^-5 <= 0.05) and nothing reaches."""
    start_lo, start_hi = np.array([0.0, 0, -1, -1]), np.array([4.0, 3, 1, 1])
    t_lo, t_hi = np.array([2.0, 0, -1, -1]), np.array([3.5, 3, 1, 1])
    net = translation_net([1.0, 0, 0, 0], x_only=True)
    plain = refine(net, start_lo, start_hi, t_lo, t_hi)
    along_x = refine(net, start_lo, start_hi, t_lo, t_hi, split_dims=(0,))
    assert x_intervals(along_x.reaching_lo, along_x.reaching_hi) == x_intervals(
        plain.reaching_lo, plain.reaching_hi) == [(1.0, 2.5)]
    along_y = refine(net, start_lo, start_hi, t_lo, t_hi, split_dims=[1])
    assert len(along_y.reaching_lo) == 0 and along_y.depth == 5
    assert along_y.n_analysed == 2**6 - 1
    assert along_y.nonreaching_lo.tolist() == [start_lo.tolist()]  # merged back into G_s
    for bad in ((), (4,), (0, 0)):
        with pytest.raises(ValueError, match="split_dims"):
            refine(net, start_lo, start_hi, t_lo, t_hi, split_dims=bad)


def test_separation_rule_cuts_where_reaching_changes_not_where_the_box_is_widest():
    """F = s + (1, 0, 0, 0) from [0,2]x[0,4] towards x in [1.5, 3.5], one bisection allowed.
    Smear is gradient times width, so the wider y is cut: both halves look like their parent
    (c1 = 0.75) and nothing reaches. The separation rule compares both cuts' halves: along x
    their c1 are 0.5 and 1 (along y 0.75 and 0.75), so it cuts x and finds [1,2] reaching."""
    net = translation_net([1.0, 0, 0, 0])
    lo, hi = np.array([0.0, 0, 0, 0]), np.array([2.0, 4, 1, 1])
    t_lo, t_hi = np.array([1.5, 0, 0, 0]), np.array([3.5, 4, 1, 1])
    kw = dict(tau1=0.9, tau2=0.01, min_volume_ratio=0.5, method="ibp")
    smear = refine(net, lo, hi, t_lo, t_hi, **kw)
    assert len(smear.reaching_lo) == 0 and smear.nonreaching_lo.tolist() == [lo.tolist()]
    sep = refine(net, lo, hi, t_lo, t_hi, split_rule="separation", **kw)
    np.testing.assert_array_equal(sep.reaching_lo, [[1.0, 0, 0, 0]])
    np.testing.assert_array_equal(sep.reaching_hi, [[2.0, 4, 1, 1]])
    np.testing.assert_array_equal(sep.nonreaching_hi, [[1.0, 4, 1, 1]])
    assert sep.n_analysed == smear.n_analysed == 3  # the candidates' bounds are not counted
    # With one dimension allowed there is nothing to compare: the rules agree.
    one = [refine(net, lo, hi, t_lo, t_hi, split_dims=(1,), split_rule=r, **kw)
           for r in ("smear", "separation")]
    assert one[0].nonreaching_lo.tolist() == one[1].nonreaching_lo.tolist() == [lo.tolist()]
    with pytest.raises(ValueError, match="split_rule"):
        refine(net, lo, hi, t_lo, t_hi, split_rule="widest")


def test_merge_siblings_keeps_pieces_of_different_branches_apart():
    """F = x + 1 on x in [0, 4] towards x in [2, 3.5] (tau1 0.9, tau2 0.01): the bisection's
    leaves, left to right, are [0,1] no, [1,2] yes, [2,2.5] yes, [2.5,3] no, [3,4] no.
    ``merge="full"`` joins the neighbours with the same verdict; ``"siblings"`` joins only
    halves of one parent, and [1,2] / [2,2.5] or [2.5,3] / [3,4] are not siblings."""
    start_lo, start_hi = np.array([0.0, 0, 0, 0]), np.array([4.0, 1, 1, 1])
    t_lo, t_hi = np.array([2.0, 0, 0, 0]), np.array([3.5, 1, 1, 1])
    net = translation_net([1.0, 0, 0, 0])
    kw = dict(tau1=0.9, tau2=0.01, split_dims=(0,))
    full = refine(net, start_lo, start_hi, t_lo, t_hi, **kw)
    assert x_intervals(full.reaching_lo, full.reaching_hi) == [(1.0, 2.5)]
    assert x_intervals(full.nonreaching_lo, full.nonreaching_hi) == [(0.0, 1.0), (2.5, 4.0)]
    sib = refine(net, start_lo, start_hi, t_lo, t_hi, merge="siblings", **kw)
    assert x_intervals(sib.reaching_lo, sib.reaching_hi) == [(1.0, 2.0), (2.0, 2.5)]
    assert x_intervals(sib.nonreaching_lo, sib.nonreaching_hi) == [
        (0.0, 1.0), (2.5, 3.0), (3.0, 4.0)]
    boxes.check_tiles(np.concatenate([sib.reaching_lo, sib.nonreaching_lo]),
                      np.concatenate([sib.reaching_hi, sib.nonreaching_hi]), start_lo, start_hi)
    with pytest.raises(ValueError, match="merge"):
        refine(net, start_lo, start_hi, t_lo, t_hi, merge="one_pass")


def test_constant_outside_target_never_reaches():
    # The x-only model outputs y = 0.5, outside the target's y range [2, 3]: R misses G_d.
    res = refine(translation_net([1.0, 0, 0, 0], x_only=True), np.zeros(4), np.ones(4),
                 np.array([0.0, 2, 0, 0]), np.array([5.0, 3, 1, 1]))
    assert len(res.reaching_lo) == 0
    assert res.nonreaching_lo.tolist() == [[0.0] * 4] and res.n_analysed == 1


def test_all_or_nothing_gives_the_start_box_back():
    net = translation_net([0.5, 0, 0, 0])
    start_lo, start_hi = np.array([0.0, 0, 0, 0]), np.array([1.0, 1, 1, 1])
    res = refine(net, start_lo, start_hi, np.array([0.0, 0, 0, 0]), np.array([2.0, 1, 1, 1]))
    assert res.reaching_lo.tolist() == [start_lo.tolist()]
    assert res.reaching_hi.tolist() == [start_hi.tolist()]
    assert res.nonreaching_lo.shape == (0, 4) and (res.n_analysed, res.depth) == (1, 0)
    res = refine(net, start_lo, start_hi, np.array([5.0, 0, 0, 0]), np.array([6.0, 1, 1, 1]))
    assert res.reaching_lo.shape == (0, 4)
    assert res.nonreaching_lo.tolist() == [start_lo.tolist()]
    # F = 100 x: the box at x = 0 stays undecided (c1 < 1, c2 > 0) down to the smallest size,
    # the others miss; all pieces are non-reaching and merge back into G_s.
    net = translation_net([0.0, 0, 0, 0], x_only=True, scale=100.0)
    res = refine(net, start_lo, start_hi, np.array([0.0, 0, 0, 0]), np.array([1.0, 1, 1, 1]),
                 tau1=1.0, tau2=0.0)
    assert res.nonreaching_lo.tolist() == [start_lo.tolist()]
    assert res.reaching_lo.shape == (0, 4) and res.depth == 5


def test_degenerate_start_box_and_no_jobs():
    # G_s flat in y: never split along y, and the pieces still tile it.
    start_lo, start_hi = np.array([0.0, 1.0, 0, 0]), np.array([4.0, 1.0, 1, 1])
    res = refine(translation_net([1.0, 0, 0, 0]), start_lo, start_hi,
                 np.array([2.0, 0, 0, 0]), np.array([3.5, 2, 1, 1]))
    pieces_lo = np.concatenate([res.reaching_lo, res.nonreaching_lo])
    pieces_hi = np.concatenate([res.reaching_hi, res.nonreaching_hi])
    assert (pieces_lo[:, 1] == 1.0).all() and (pieces_hi[:, 1] == 1.0).all()
    boxes.check_tiles(pieces_lo, pieces_hi, start_lo, start_hi)
    assert res.reaching_lo[:, 0].tolist() == [1.0] and res.reaching_hi[:, 0].tolist() == [2.5]
    stacked = [(w[None], b[None]) for w, b in translation_net([1.0, 0, 0, 0])]
    empty = np.zeros((0, 4))
    assert refine_many([(w[:0], b[:0]) for w, b in stacked], empty, empty, empty, empty) == []


def random_case(seed, hidden=(8, 8)):
    key = jax.random.key(seed)
    params = MLP(hidden=hidden, out=D).init(key, jnp.zeros(3 * D))
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-1, 1, (2, D)), rng.uniform(-1, 1, (2, D))
    s_lo, s_hi = np.minimum(a[0], b[0]), np.maximum(a[0], b[0])
    t_lo, t_hi = np.minimum(a[1], b[1]), np.maximum(a[1], b[1])
    return params, s_lo.astype(np.float32), s_hi.astype(np.float32), t_lo, t_hi


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["crown", "ibp", "zonotope", "zonotope_box"]),
       st.sampled_from([0.05, 0.2]))
def test_pieces_tile_the_start_box_and_are_deterministic(seed, method, ratio):
    params, s_lo, s_hi, t_lo, t_hi = random_case(seed)
    # Widen the target so that the model's outputs straddle it (more splitting).
    res = refine(params, s_lo, s_hi, t_lo - 0.3, t_hi + 0.3, method=method,
                 min_volume_ratio=ratio, tau1=0.6, tau2=0.05)
    assert isinstance(res, RefineResult)
    all_lo = np.concatenate([res.reaching_lo, res.nonreaching_lo])
    all_hi = np.concatenate([res.reaching_hi, res.nonreaching_hi])
    boxes.check_tiles(all_lo, all_hi, s_lo, s_hi)
    assert all_lo.dtype == np.float32
    assert res.depth <= 5 and len(all_lo) <= 32 and res.n_analysed <= 63
    for lo, hi in ((res.reaching_lo, res.reaching_hi), (res.nonreaching_lo, res.nonreaching_hi)):
        order = np.lexsort(np.concatenate([lo, hi], 1).T[::-1])
        assert (order == np.arange(len(lo))).all()  # sorted: deterministic first box
    again = refine(params, s_lo, s_hi, t_lo - 0.3, t_hi + 0.3, method=method,
                   min_volume_ratio=ratio, tau1=0.6, tau2=0.05)
    for x, y in zip(res, again, strict=True):
        np.testing.assert_array_equal(x, y)


def test_refine_many_equals_one_job_at_a_time():
    cases = [random_case(s) for s in (3, 4, 5)]
    params = jax.tree.map(lambda *p: jnp.stack(p), *[c[0] for c in cases])
    args = [np.stack([c[i] for c in cases]) for i in range(1, 5)]
    args[2], args[3] = args[2] - 0.3, args[3] + 0.3
    many = refine_many(params, *args, tau1=0.6, tau2=0.05)
    assert len(many) == 3
    for j, case in enumerate(cases):
        one = refine(case[0], case[1], case[2], args[2][j], args[3][j], tau1=0.6, tau2=0.05)
        for x, y in zip(many[j], one, strict=True):
            np.testing.assert_array_equal(x, y)


def test_bad_arguments_raise_value_error_naming_them():
    net = translation_net([1.0, 0, 0, 0])
    lo, hi = np.zeros(4), np.ones(4)
    with pytest.raises(ValueError, match="method"):
        refine(net, lo, hi, lo, hi, method="deeppoly")
    with pytest.raises(ValueError, match="start_lo/start_hi: lo > hi"):
        refine(net, hi, lo, lo, hi)
    with pytest.raises(ValueError, match="target_lo/target_hi: NaN"):
        refine(net, lo, hi, lo, np.full(4, np.nan))
    with pytest.raises(ValueError, match="start_lo/target_lo"):
        refine(net, lo, hi, lo[:3], hi[:3])
    with pytest.raises(ValueError, match="input size 9"):
        refine(net, lo[:3], hi[:3], lo[:3], hi[:3])
    with pytest.raises(ValueError, match="min_volume_ratio"):
        refine(net, lo, hi, lo, hi, min_volume_ratio=0.0)
    with pytest.raises(ValueError, match="tau1"):
        refine(net, lo, hi, lo, hi, tau1=1.5)
    stacked = [(w[None], b[None]) for w, b in net]
    with pytest.raises(ValueError, match="2 jobs"):
        refine_many(stacked, np.zeros((2, 4)), np.ones((2, 4)), np.zeros((2, 4)), np.ones((2, 4)))


def test_reach_box_clips_bounds_that_overshoot_the_space():
    """F = (x + 1, y, 3 vx, 3 vy) from [0,1]x[0,3] (full velocities) towards [1,3]x[0,3]: the
    velocity bounds [-3, 3] put a third of R's width inside the target in each velocity
    dimension, so c1 = 1/9 and nothing reaches. Intersected with the state space (|v| <= 1)
    R lies inside the target: the whole start box reaches. A bound wholly outside the reach
    box lands on its nearest face."""
    d = 4
    keep = np.eye(d, 3 * d)
    layers = [(np.concatenate([keep, -keep], 0).T.astype(np.float32), np.zeros(2 * d, np.float32)),
              ((np.concatenate([np.eye(d), -np.eye(d)]) * np.array([1, 1, 3, 3])).astype(np.float32),
               np.array([1.0, 0, 0, 0], np.float32))]
    lo, hi = np.array([0.0, 0, -1, -1]), np.array([1.0, 3, 1, 1])
    t_lo, t_hi = np.array([1.0, 0, -1, -1]), np.array([3.0, 3, 1, 1])
    stacked = [(w[None], b[None]) for w, b in layers]
    args = (stacked, lo[None], hi[None], t_lo[None], t_hi[None])
    kw = dict(tau1=0.9, tau2=0.01, min_volume_ratio=0.25, method="ibp")
    plain = refine_many(*args, **kw)[0]
    assert len(plain.reaching_lo) == 0
    space = dict(reach_lo=np.array([[0.0, 0, -1, -1]]), reach_hi=np.array([[3.0, 3, 1, 1]]))
    clipped = refine_many(*args, **space, **kw)[0]
    np.testing.assert_array_equal(clipped.reaching_lo, lo[None])
    np.testing.assert_array_equal(clipped.reaching_hi, hi[None])
    # A reach box left of every prediction: R is moved onto x = 0.5, outside the target.
    left = dict(reach_lo=np.array([[0.0, 0, -1, -1]]), reach_hi=np.array([[0.5, 3, 1, 1]]))
    assert len(refine_many(*args, **left, **kw)[0].reaching_lo) == 0
    with pytest.raises(ValueError, match="reach_lo/reach_hi"):
        refine_many(*args, reach_lo=space["reach_lo"], **kw)
