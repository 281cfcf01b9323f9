"""Fixed-capacity partitions: construction, locate, replacement, capacity, tiling checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gara_jax import boxes
from gara_jax.partition import (
    PAD_HI,
    PAD_LO,
    U_MAZE_HI,
    U_MAZE_LO,
    Partition,
    PartitionFullError,
    can_fit,
    check_tiling,
    gara_initial,
    handcrafted,
    locate,
    replace_box,
)


def test_spec_partitions_tile_the_u_maze():
    for p, n in ((handcrafted(), 6), (gara_initial(), 2)):
        assert int(p.count) == n
        check_tiling(p)
    lo, hi = handcrafted(max_goals=10).boxes()
    assert lo[2].tolist() == [1.0, 2.0, -1.0, -1.0] and hi[2].tolist() == [1.5, 3.0, 1.0, 1.0]
    lo, hi = gara_initial().boxes()
    assert lo.tolist() == [[0, 0, -1, -1], [1, 0, -1, -1]]
    assert hi.tolist() == [[1, 3, 1, 1], [3, 3, 1, 1]]


def test_gara_initial_general_domain():
    p = gara_initial(max_goals=4, state_lo=[0.0, 0.0], state_hi=[6.0, 6.0])
    assert p.boxes()[1][0].tolist() == [2.0, 6.0]
    check_tiling(p, [0.0, 0.0], [6.0, 6.0])
    p = gara_initial(max_goals=4, state_lo=[0.0, 0.0], state_hi=[6.0, 6.0], split_x=4.0)
    assert p.boxes()[1][0].tolist() == [4.0, 6.0]
    with pytest.raises(ValueError, match="split_x"):
        gara_initial(split_x=3.0)


def test_locate_first_box_wins_and_outside_is_minus_one():
    p = handcrafted(max_goals=8)
    states = jnp.array([
        [0.5, 1.0, 0.0, 0.0],   # box 0
        [1.0, 2.0, 0.0, 0.0],   # corner of boxes 0, 1, 2, 3: first wins
        [1.5, 2.5, 0.3, -0.3],  # face of 2 and 4
        [2.0, 1.0, 1.0, 1.0],   # box 5, velocity on the boundary
        [2.0, 1.0, 1.5, 0.0],   # velocity outside
        [-0.1, 1.0, 0.0, 0.0],  # x outside
        [PAD_LO, PAD_LO, PAD_LO, PAD_LO],  # would only be in a padding row, were it a box
    ])
    assert locate(p, states).tolist() == [0, 0, 2, 5, -1, -1, 0]
    assert locate(p, states[0]).shape == ()


def test_locate_jits_and_vmaps_over_partitions():
    # Two partitions of different sizes, stacked (same capacity).
    a, b = gara_initial(max_goals=6), handcrafted(max_goals=6)
    stacked = jax.tree.map(lambda x, y: jnp.stack([x, y]), a, b)
    s = jnp.array([[1.2, 2.5, 0.0, 0.0], [2.0, 0.5, 0.0, 0.0]])
    out = jax.jit(jax.vmap(locate, in_axes=(0, None)))(stacked, s)
    assert out.tolist() == [[1, 1], [2, 5]]


def test_locate_ignores_rows_past_count_even_if_not_padding():
    p = gara_initial(max_goals=4)
    p = p.replace(lo=p.lo.at[2].set(jnp.array([-9.0] * 4)), hi=p.hi.at[2].set(jnp.array([9.0] * 4)))
    assert locate(p, jnp.array([5.0, 5.0, 0.0, 0.0])).item() == -1


def test_replace_box_keeps_index_and_appends():
    p = gara_initial(max_goals=5)
    lo, hi = p.boxes()
    (la, ha), (lb, hb) = boxes.bisect(lo[1], hi[1], 1)
    p2, idx = replace_box(p, 1, np.stack([lb, la]), np.stack([hb, ha]))
    assert idx.tolist() == [1, 2] and int(p2.count) == 3
    assert np.asarray(p2.lo[1]).tolist() == np.asarray(lb).tolist()
    assert np.asarray(p2.lo[2]).tolist() == np.asarray(la).tolist()
    check_tiling(p2)
    assert p2.lo.dtype == p.lo.dtype and p2.count.dtype == jnp.int32
    # The original is unchanged (functional update).
    assert int(p.count) == 2


def test_capacity_is_reported_not_overwritten():
    p = gara_initial(max_goals=3)
    lo, hi = p.boxes()
    (la, ha), (lb, hb) = boxes.bisect(lo[0], hi[0], 0)
    (la1, ha1), (la2, ha2) = boxes.bisect(la, ha, 1)
    three_lo, three_hi = np.stack([la1, la2, lb]), np.stack([ha1, ha2, hb])
    assert can_fit(p, 1) and not can_fit(p, 2)
    with pytest.raises(PartitionFullError, match="max_goals"):
        replace_box(p, 0, three_lo, three_hi)
    assert issubclass(PartitionFullError, ValueError)
    p2, idx = replace_box(p, 0, np.stack([la, lb]), np.stack([ha, hb]))
    assert idx.tolist() == [0, 2] and not can_fit(p2, 1)
    check_tiling(p2)


def test_replace_box_rejects_bad_input():
    p = gara_initial(max_goals=4)
    lo, hi = p.boxes()
    with pytest.raises(ValueError, match="index"):
        replace_box(p, 2, lo[:1], hi[:1])
    with pytest.raises(ValueError, match="not inside"):
        replace_box(p, 0, lo[1:], hi[1:])
    with pytest.raises(ValueError, match="new boxes"):
        replace_box(p, 0, lo[:1, :3], hi[:1, :3])
    with pytest.raises(ValueError, match="lo > hi"):
        replace_box(p, 0, hi[:1], lo[:1])


def test_check_tiling_detects_overlap_gap_and_bad_padding():
    lo, hi = gara_initial().boxes()
    overlap = Partition.create(lo, hi + np.array([[0.5, 0, 0, 0], [0, 0, 0, 0]]), 4)
    with pytest.raises(ValueError, match="overlap"):
        check_tiling(overlap)
    with pytest.raises(ValueError, match="do not cover"):
        check_tiling(Partition.create(lo[:1], hi[:1], 4))
    p = gara_initial(max_goals=4)
    with pytest.raises(ValueError, match="padding"):
        check_tiling(p.replace(lo=p.lo.at[3, 0].set(0.0)))


def test_create_validates():
    with pytest.raises(PartitionFullError):
        Partition.create(np.zeros((3, 2)), np.ones((3, 2)), max_goals=2)
    with pytest.raises(ValueError, match="max_goals"):
        Partition.create(np.zeros((1, 2)), np.ones((1, 2)), max_goals=0)
    with pytest.raises(ValueError, match="lo > hi"):
        Partition.create(np.ones((1, 2)), np.zeros((1, 2)), max_goals=2)
    p = Partition.create(np.zeros((1, 2)), np.ones((1, 2)), max_goals=3)
    assert np.asarray(p.lo[1:]).tolist() == [[PAD_LO] * 2] * 2
    assert np.asarray(p.hi[1:]).tolist() == [[PAD_HI] * 2] * 2
    assert np.isfinite(np.asarray(p.lo)).all()


def test_u_maze_domain_constants():
    assert U_MAZE_LO == (0.0, 0.0, -1.0, -1.0) and U_MAZE_HI == (3.0, 3.0, 1.0, 1.0)


def test_a_ranked_partition_gives_a_shared_face_to_the_pieces_of_the_box_that_held_it():
    """GARA's left box [0, 1] x [0, 3] holds the face x = 1 it shares with the right box.
    Split it in two along y: appended, the upper piece (index 2) loses its part of the face
    to the right box (index 1); ranked, both pieces keep it."""
    pieces_lo = [[0.0, 0.0, -1, -1], [0.0, 1.5, -1, -1]]
    pieces_hi = [[1.0, 1.5, 1, 1], [1.0, 3.0, 1, 1]]
    face = jnp.array([[1.0, 1.0, 0.0, 0.0], [1.0, 2.5, 0.0, 0.0], [2.0, 2.5, 0.0, 0.0]])
    plain, idx = replace_box(gara_initial(max_goals=4), 0, pieces_lo, pieces_hi)
    assert idx.tolist() == [0, 2] and plain.rank is None
    assert locate(plain, face).tolist() == [0, 1, 1]
    ranked = gara_initial(max_goals=4).replace(rank=jnp.arange(4))
    ranked, idx = replace_box(ranked, 0, pieces_lo, pieces_hi)
    assert idx.tolist() == [0, 2] and ranked.rank.tolist() == [0, 2, 1, 3]
    assert locate(ranked, face).tolist() == [0, 2, 1]
    # Splitting the right box then keeps its pieces after the left ones.
    ranked, idx = replace_box(ranked, 1, [[1.0, 0, -1, -1], [2.0, 0, -1, -1]],
                              [[2.0, 3, 1, 1], [3.0, 3, 1, 1]])
    assert idx.tolist() == [1, 3] and ranked.rank.tolist() == [0, 2, 1, 3]
    assert locate(ranked, jnp.array([[2.0, 1.0, 0.0, 0.0]])).tolist() == [1]
    with pytest.raises(ValueError, match="rank"):
        Partition.create([[0.0]], [[1.0]], max_goals=2, rank=[0, 0])
