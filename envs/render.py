"""Pure-NumPy rasteriser for the maze: bounds, walls, exit, agent and optional goal boxes."""

from __future__ import annotations

import numpy as np

FLOOR = (255, 255, 255)
OUTSIDE = (215, 215, 215)
WALL = (40, 40, 40)
BORDER = (0, 0, 0)
EXIT = (220, 30, 30)
AGENT = (30, 80, 220)
# Goal-box fills, cycled (tab10-like, without the exit's red).
BOX_COLOURS = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)
BOX_ALPHA = 0.35


def render_rgb(params, obs, boxes=None, size: int = 256, agent_radius=None) -> np.ndarray:
    """An ``[size, size, 3]`` uint8 picture of the maze with the agent at ``obs``.

    Args:
        params: :class:`envs.maze.EnvParams` (``n``, ``walls``, ``exit``, ``exit_half_width``).
        obs: ``(x, y, ...)``; only the position is drawn.
        boxes: optional ``(lo, hi)`` of goal boxes, each ``[G, >=2]``; the first two dims are
            taken as ``x, y``. Drawn as translucent fills with outlines, colour by index.
        size: side of the image in pixels.
        agent_radius: radius of the agent's disc in maze units (the point maze's ball);
            ``None`` draws a marker of ``size / 40`` pixels.

    Example:
        >>> import envs
        >>> _, params = envs.make("u_maze")
        >>> render_rgb(params, [0.0, 0.0, 0.0, 0.0], size=64).shape
        (64, 64, 3)
    """
    size = int(size)
    if size < 16:
        raise ValueError(f"size must be >= 16 pixels, got {size}")
    n = float(np.asarray(params.n))
    margin = max(2, size // 32)
    scale = (size - 2 * margin) / n
    img = np.empty((size, size, 3), np.float32)
    img[:] = OUTSIDE

    def span(a: float, b: float, flip: bool) -> tuple[int, int]:
        # World interval -> pixel interval, clipped to the maze, at least one pixel wide.
        a, b = min(max(a, 0.0), n), min(max(b, 0.0), n)
        if flip:  # rows grow downwards, y grows upwards
            a, b = n - b, n - a
        lo = int(np.floor(margin + a * scale))
        hi = max(lo + 1, int(np.ceil(margin + b * scale)))
        return lo, min(hi, size)

    def fill(x0, x1, y0, y1, colour, alpha=1.0):
        c0, c1 = span(x0, x1, flip=False)
        r0, r1 = span(y0, y1, flip=True)
        region = img[r0:r1, c0:c1]
        region[:] = (1 - alpha) * region + alpha * np.asarray(colour, np.float32)

    def outline(x0, x1, y0, y1, colour):
        c0, c1 = span(x0, x1, flip=False)
        r0, r1 = span(y0, y1, flip=True)
        img[r0:r1, c0] = img[r0:r1, c1 - 1] = colour
        img[r0, c0:c1] = img[r1 - 1, c0:c1] = colour

    fill(0.0, n, 0.0, n, FLOOR)
    if boxes is not None:
        lo, hi = (np.asarray(b, np.float64) for b in boxes)
        lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
        if lo.shape != hi.shape or lo.shape[-1] < 2:
            raise ValueError(f"boxes must be (lo, hi) of equal shape [G, >=2], got {lo.shape}")
        for i, (b_lo, b_hi) in enumerate(zip(lo, hi, strict=True)):
            colour = BOX_COLOURS[i % len(BOX_COLOURS)]
            fill(b_lo[0], b_hi[0], b_lo[1], b_hi[1], colour, BOX_ALPHA)
            outline(b_lo[0], b_hi[0], b_lo[1], b_hi[1], colour)

    ex, ey = np.asarray(params.exit, np.float64)
    hw = float(np.asarray(params.exit_half_width))
    fill(ex - hw, ex + hw, ey - hw, ey + hw, EXIT)
    for x_lo, x_hi, y_lo, y_hi in np.asarray(params.walls, np.float64).reshape(-1, 4):
        fill(x_lo, x_hi, y_lo, y_hi, WALL)
    outline(0.0, n, 0.0, n, BORDER)

    # The agent: a disc, clipped to the image.
    x, y = (float(v) for v in np.asarray(obs, np.float64)[:2])
    cx, cy = margin + x * scale, margin + (n - y) * scale
    radius = max(2.0, size / 40 if agent_radius is None else float(agent_radius) * scale)
    rows, cols = np.ogrid[:size, :size]
    img[(rows + 0.5 - cy) ** 2 + (cols + 0.5 - cx) ** 2 <= radius**2] = AGENT
    return img.astype(np.uint8)
