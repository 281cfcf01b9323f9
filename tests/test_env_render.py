"""The NumPy rasteriser: what is drawn where."""

from __future__ import annotations

import numpy as np
import pytest

import envs
from envs.render import AGENT, EXIT, WALL, render_rgb

SIZE = 96


def pixel(img, params, x, y):
    """Colour at world point (x, y) (the same mapping as the renderer)."""
    n = float(params.n)
    margin = max(2, SIZE // 32)
    scale = (SIZE - 2 * margin) / n
    return tuple(img[int(margin + (n - y) * scale), int(margin + x * scale)])


@pytest.mark.parametrize("layout", envs.LAYOUTS)
def test_draws_walls_exit_and_agent(layout):
    _, params = envs.make(layout)
    img = render_rgb(params, [float(params.n) / 2, 0.2, 0.0, 0.0], size=SIZE)
    assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
    assert (img == EXIT).all(-1).sum() > 10
    assert (img == AGENT).all(-1).sum() > 4
    assert (img == WALL).all(-1).sum() > 10


def test_positions_of_the_u_maze_features():
    _, params = envs.make("u_maze")
    img = render_rgb(params, [0.3, 2.7, 0.0, 0.0], size=SIZE)
    assert pixel(img, params, 1.25, 1.0) == WALL  # inside the wall
    assert pixel(img, params, 2.8, 0.2) == EXIT  # exit square at (3, 0)
    assert pixel(img, params, 0.3, 2.7) == AGENT
    assert pixel(img, params, 2.0, 2.0) == (255, 255, 255)  # free floor
    moved = render_rgb(params, [2.0, 2.0, 0.0, 0.0], size=SIZE)
    assert pixel(moved, params, 2.0, 2.0) == AGENT and pixel(moved, params, 0.3, 2.7) != AGENT


def test_goal_boxes_use_only_xy_and_validate():
    _, params = envs.make("u_maze")
    obs = [0.0, 0.0, 0.0, 0.0]
    plain = render_rgb(params, obs, size=SIZE)
    lo = np.array([[0.0, 2.0, -1.0, -1.0], [1.5, 0.0, -1.0, -1.0]])
    hi = np.array([[1.0, 3.0, 1.0, 1.0], [3.0, 2.0, 1.0, 1.0]])
    boxed = render_rgb(params, obs, boxes=(lo, hi), size=SIZE)
    assert pixel(boxed, params, 0.5, 2.5) != pixel(plain, params, 0.5, 2.5)
    assert pixel(boxed, params, 2.0, 1.0) != pixel(plain, params, 2.0, 1.0)
    assert pixel(boxed, params, 0.5, 2.5) != pixel(boxed, params, 2.0, 1.0)  # by index
    assert pixel(boxed, params, 0.5, 1.0) == pixel(plain, params, 0.5, 1.0)  # outside
    with pytest.raises(ValueError, match="boxes"):
        render_rgb(params, obs, boxes=(lo, hi[:, :1]), size=SIZE)
    with pytest.raises(ValueError, match="size"):
        render_rgb(params, obs, size=8)
