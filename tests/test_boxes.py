"""Box algebra: membership, volume, intersection, coverage, bisection, merging, tiling checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gara_jax import boxes

SETTINGS = settings(max_examples=40, deadline=None)


@st.composite
def box_arrays(draw, n=4, d=3):
    """``n`` random boxes over ``d`` dims on a coarse grid (so faces and degeneracies occur)."""
    a = np.array(draw(st.lists(st.integers(-4, 4), min_size=n * d, max_size=n * d)), float)
    b = np.array(draw(st.lists(st.integers(-4, 4), min_size=n * d, max_size=n * d)), float)
    a, b = a.reshape(n, d) / 2, b.reshape(n, d) / 2
    return np.minimum(a, b), np.maximum(a, b)


def test_contains_is_closed_and_batched():
    lo, hi = jnp.zeros(2), jnp.ones(2)
    x = jnp.array([[0.0, 1.0], [0.5, 0.5], [1.0 + 1e-6, 0.5], [-1e-6, 0.0]])
    assert boxes.contains(lo, hi, x).tolist() == [True, True, False, False]
    # Batch of boxes against one point.
    los = jnp.array([[0.0, 0.0], [2.0, 2.0]])
    his = jnp.array([[1.0, 1.0], [3.0, 3.0]])
    assert boxes.contains(los, his, jnp.array([2.0, 3.0])).tolist() == [False, True]


def test_volume_and_empty_intersection():
    assert float(boxes.volume(jnp.array([0.0, 1.0, 2.0]), jnp.array([2.0, 2.0, 5.0]))) == 6.0
    lo, hi = boxes.intersect(jnp.array([0.0, 0.0]), jnp.array([1.0, 1.0]),
                             jnp.array([2.0, 0.0]), jnp.array([3.0, 1.0]))
    assert float(boxes.volume(lo, hi)) == 0.0
    # An empty intersection contains nothing, not even the would-be face points.
    assert not bool(boxes.contains(lo, hi, jnp.array([1.5, 0.5])))
    assert not bool(boxes.contains(lo, hi, jnp.array([2.0, 0.5])))


@SETTINGS
@given(box_arrays(n=2))
def test_intersection_is_the_set_intersection(pair):
    lo, hi = pair
    ilo, ihi = boxes.intersect(lo[0], hi[0], lo[1], hi[1])
    # Sample points on the grid: membership of the intersection = membership of both.
    grid = np.stack(np.meshgrid(*[np.arange(-4, 5) / 2] * 3, indexing="ij"), -1).reshape(-1, 3)
    both = boxes.contains(lo[0], hi[0], grid) & boxes.contains(lo[1], hi[1], grid)
    assert (np.asarray(boxes.contains(ilo, ihi, grid)) == np.asarray(both)).all()
    assert float(boxes.volume(ilo, ihi)) <= float(boxes.volume(lo[0], hi[0])) + 1e-12


def test_coverage_hand_examples():
    # R = [0,2] x {5}, T = [1,5] x [0,9]: only x counts; overlap 1 of R's 2 and of T's 4.
    c1, c2 = boxes.coverage(jnp.array([0.0, 5.0]), jnp.array([2.0, 5.0]),
                            jnp.array([1.0, 0.0]), jnp.array([5.0, 9.0]))
    assert (float(c1), float(c2)) == (0.5, 0.25)
    # The same R with its point coordinate outside T: R and T are disjoint.
    c1, c2 = boxes.coverage(jnp.array([0.0, 10.0]), jnp.array([2.0, 10.0]),
                            jnp.array([1.0, 0.0]), jnp.array([5.0, 9.0]))
    assert (float(c1), float(c2)) == (0.0, 0.0)
    # R inside T: c1 = 1; T inside R: c2 = 1.
    c1, c2 = boxes.coverage(jnp.array([1.0, 1.0]), jnp.array([2.0, 2.0]),
                            jnp.zeros(2), jnp.full(2, 4.0))
    assert (float(c1), float(c2)) == (1.0, 1.0 / 16)
    c1, c2 = boxes.coverage(jnp.zeros(2), jnp.full(2, 4.0),
                            jnp.array([1.0, 1.0]), jnp.array([2.0, 2.0]))
    assert (float(c1), float(c2)) == (1.0 / 16, 1.0)
    # A point R: 1 inside T, 0 outside. T degenerate where R is wide: c2 = 0, no NaN.
    assert [float(c) for c in boxes.coverage(jnp.ones(2), jnp.ones(2), jnp.zeros(2),
                                             jnp.full(2, 2.0))] == [1.0, 1.0]
    assert [float(c) for c in boxes.coverage(jnp.full(2, 3.0), jnp.full(2, 3.0), jnp.zeros(2),
                                             jnp.full(2, 2.0))] == [0.0, 0.0]
    c1, c2 = boxes.coverage(jnp.zeros(2), jnp.full(2, 2.0), jnp.array([0.0, 1.0]),
                            jnp.array([2.0, 1.0]))
    assert float(c2) == 0.0 and not np.isnan(float(c1))


@SETTINGS
@given(box_arrays(n=2))
def test_coverage_ratios_are_fractions(pair):
    lo, hi = pair
    c1, c2 = boxes.coverage(lo[0], hi[0], lo[1], hi[1])
    for c in (float(c1), float(c2)):
        assert 0.0 <= c <= 1.0 + 1e-12


def test_bisect_halves_tile_the_box():
    lo = jnp.array([[0.0, -1.0], [2.0, 2.0]])
    hi = jnp.array([[4.0, 1.0], [3.0, 6.0]])
    (la, ha), (lb, hb) = boxes.bisect(lo, hi, jnp.array([0, 1]))
    assert ha.tolist() == [[2.0, 1.0], [3.0, 4.0]]
    assert lb.tolist() == [[2.0, -1.0], [2.0, 4.0]]
    np.testing.assert_allclose(boxes.volume(la, ha) + boxes.volume(lb, hb), boxes.volume(lo, hi))
    for i in range(2):
        boxes.check_tiles(np.stack([la[i], lb[i]]), np.stack([ha[i], hb[i]]), lo[i], hi[i])
    # jit/vmap-able with a traced dimension.
    out = jax.jit(jax.vmap(boxes.bisect))(lo, hi, jnp.array([1, 0]))
    assert out[0][1].tolist() == [[4.0, 0.0], [2.5, 6.0]]


def _grid_boxes(cuts):
    """All cells of a grid given cut points per dimension: a tiling of the bounding box."""
    cells = np.stack(np.meshgrid(*[np.arange(len(c) - 1) for c in cuts], indexing="ij"), -1)
    cells = cells.reshape(-1, len(cuts))
    lo = np.stack([np.asarray(c)[cells[:, d]] for d, c in enumerate(cuts)], -1)
    hi = np.stack([np.asarray(c)[cells[:, d] + 1] for d, c in enumerate(cuts)], -1)
    return lo.astype(float), hi.astype(float)


def test_merge_adjacent_full_grid_becomes_one_box():
    lo, hi = _grid_boxes([[0, 1, 3], [0, 2, 3, 4], [-1, 1]])
    mlo, mhi = boxes.merge_adjacent(lo, hi)
    assert mlo.tolist() == [[0.0, 0.0, -1.0]] and mhi.tolist() == [[3.0, 4.0, 1.0]]


@SETTINGS
@given(st.lists(st.booleans(), min_size=12, max_size=12))
def test_merge_adjacent_keeps_the_covered_set(keep):
    lo, hi = _grid_boxes([[0, 1, 2, 4], [0, 1, 3, 4, 5]])  # 12 cells
    keep = np.array(keep)
    mlo, mhi = boxes.merge_adjacent(lo[keep], hi[keep])
    assert len(mlo) <= keep.sum()
    # Same set: every kept cell's centre is covered exactly once, dropped cells not at all.
    centres = (lo + hi) / 2
    hits = np.asarray(boxes.contains(mlo[None], mhi[None], centres[:, None])).sum(-1) \
        if len(mlo) else np.zeros(len(lo))
    assert (hits == keep).all()
    if len(mlo):
        np.testing.assert_allclose(np.prod(mhi - mlo, -1).sum(), np.prod(hi - lo, -1)[keep].sum())


def test_merge_adjacent_empty_and_no_merge():
    lo, hi = boxes.merge_adjacent(np.zeros((0, 2)), np.zeros((0, 2)))
    assert lo.shape == (0, 2)
    # Touching along a face but with different extents: no merge.
    lo, hi = boxes.merge_adjacent(np.array([[0.0, 0.0], [1.0, 0.0]]),
                                  np.array([[1.0, 1.0], [2.0, 2.0]]))
    assert len(lo) == 2


def test_validate_boxes_errors_name_the_argument():
    with pytest.raises(ValueError, match="goal: lo > hi"):
        boxes.validate_boxes([0.0, 2.0], [1.0, 1.0], "goal")
    with pytest.raises(ValueError, match="goal: NaN"):
        boxes.validate_boxes([0.0, np.nan], [1.0, 1.0], "goal")
    with pytest.raises(ValueError, match="goal: lo and hi have different shapes"):
        boxes.validate_boxes([0.0], [1.0, 1.0], "goal")
    lo, hi = boxes.validate_boxes([0, 0], [1, 1])
    assert lo.dtype == np.float64


def test_check_tiles_detects_overlap_gap_and_escape():
    lo, hi = _grid_boxes([[0, 1, 2], [0, 1]])
    boxes.check_tiles(lo, hi, [0, 0], [2, 1])
    with pytest.raises(ValueError, match="overlap"):
        boxes.check_tiles(np.array([[0.0, 0.0], [0.5, 0.0]]), np.array([[1.0, 1.0], [2.0, 1.0]]),
                          [0, 0], [2, 1])
    with pytest.raises(ValueError, match="do not cover"):
        boxes.check_tiles(lo[:1], hi[:1], [0, 0], [2, 1])
    with pytest.raises(ValueError, match="leaves the domain"):
        boxes.check_tiles(lo, hi + 0.5, [0, 0], [2, 1])
    # Exact: a sliver of 1e-12 missing is caught.
    with pytest.raises(ValueError, match="do not cover"):
        boxes.check_tiles(np.array([[0.0, 0.0], [1.0 + 1e-12, 0.0]]),
                          np.array([[1.0, 1.0], [2.0, 1.0]]), [0, 0], [2, 1])
