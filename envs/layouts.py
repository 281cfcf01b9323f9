"""The maze layouts of the reference implementation (SPEC.md section 1), as plain data.

Each layout is a dict of ``n``, ``walls`` (``[x_lo, x_hi, y_lo, y_hi]`` rows), ``start`` and
``exit``; everything else (exit half-width 0.5, reward 10, 300 steps) is shared.
"""

from __future__ import annotations

from types import MappingProxyType

LAYOUT_SPECS = MappingProxyType(
    {
        "u_maze": {
            "n": 3.0,
            "walls": ((1.0, 1.5, -1.0, 2.0),),
            "start": (0.0, 0.0),
            "exit": (3.0, 0.0),
        },
        "four_rooms": {
            "n": 3.0,
            "walls": (
                (1.0, 1.5, -1.0, 1.0),
                (1.0, 1.5, 2.0, 4.0),
                (-1.0, 0.5, 1.0, 1.5),
                (1.0, 1.5, 1.0, 1.5),
            ),
            "start": (0.0, 0.0),
            "exit": (3.0, 0.0),
        },
        "u_maze_6": {
            "n": 6.0,
            "walls": ((2.0, 4.0, -1.0, 4.0),),
            "start": (0.0, 0.0),
            "exit": (6.0, 0.0),
        },
        "big_u_maze": {
            "n": 6.0,
            "walls": (
                (1.0, 1.5, -1.0, 2.0),
                (4.0, 4.5, 1.0, 4.0),
                (-1.0, 7.0, 3.0, 4.0),
            ),
            "start": (0.0, 0.0),
            "exit": (6.0, 3.0),
        },
        "labyrinth": {
            "n": 6.0,
            "walls": (
                (1.0, 5.0, 0.5, 0.5),
                (1.0, 1.0, 0.5, 4.0),
                (3.0, 3.0, 2.5, 6.1),
                (5.0, 5.0, 0.5, 4.0),
            ),
            "start": (0.0, 0.0),
            "exit": (0.0, 6.0),
        },
    }
)

#: Valid layout names, in SPEC.md's order.
LAYOUTS: tuple[str, ...] = tuple(LAYOUT_SPECS)

#: Gymnasium id of each layout.
GYM_IDS = MappingProxyType(
    {
        "u_maze": "gara_jax/UMaze-v0",
        "four_rooms": "gara_jax/FourRooms-v0",
        "u_maze_6": "gara_jax/UMaze6-v0",
        "big_u_maze": "gara_jax/BigUMaze-v0",
        "labyrinth": "gara_jax/Labyrinth-v0",
    }
)


def layout_spec(name: str) -> dict:
    """The raw layout dict of ``name``; ``ValueError`` listing the valid names otherwise.

    Example:
        >>> layout_spec("u_maze")["exit"]
        (3.0, 0.0)
    """
    if name not in LAYOUT_SPECS:
        raise ValueError(f"unknown maze layout {name!r}; valid names: {', '.join(LAYOUTS)}")
    return dict(LAYOUT_SPECS[name])
