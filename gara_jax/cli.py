"""The ``gara-jax`` command line: one subcommand per job.

Adding a subcommand: write ``add_arguments(parser)`` and ``run(args) -> int`` functions and
register them with :func:`register` (at the bottom of this file, next to ``demo``). Keep heavy
imports inside ``run`` so that ``gara-jax --help`` stays fast.

Example:
    $ gara-jax demo --env u_maze --episodes 2000 --seed 0
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass

from gara_jax import compile_cache  # light: no JAX at import


@dataclass(frozen=True)
class Command:
    """A subcommand: its name, one-line help, argument setup and entry point."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


COMMANDS: dict[str, Command] = {}


def register(command: Command) -> Command:
    """Add a subcommand to ``gara-jax`` (names must be unique)."""
    if command.name in COMMANDS:
        raise ValueError(f"subcommand {command.name!r} is already registered")
    COMMANDS[command.name] = command
    return command


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="gara-jax",
        description="GARA (Goal Abstraction via Reachability Analysis) in JAX.",
    )
    from gara_jax import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS.values():
        sub_parser = sub.add_parser(command.name, help=command.help, description=command.help)
        command.add_arguments(sub_parser)
        compile_cache.add_argument(sub_parser)
        sub_parser.set_defaults(_run=command.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gara-jax`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        compile_cache.setup(args.no_compile_cache)
    except ValueError as err:
        print(f"gara-jax: error: {err}", file=sys.stderr)
        return 2
    return int(args._run(args) or 0)


# ----------------------------------------------------------------------------------------------
# gara-jax demo
# ----------------------------------------------------------------------------------------------

# SPEC.md section 1: U-maze, from the start, 300 steps (reference rules, 20,000 episodes each).
# SPEC.md section 1, per (layout, collision rules): success % and mean successful length (the
# final rules' figures come without lengths).
_REFERENCE_FIGURES = {("u_maze", "reference"): {0.0: (8.9, 206), 0.7: (61.0, 152)},
                      ("u_maze", "final"): {0.0: (14.9, None), 0.7: (71.2, None)}}


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {value}")
    return value


def _demo_arguments(parser: argparse.ArgumentParser) -> None:
    from envs.layouts import LAYOUTS  # light: plain data, no JAX

    parser.add_argument("--env", default="u_maze", choices=(*LAYOUTS, "point_u_maze"),
                        help="maze layout, or point_u_maze (the brax-simulated U-maze)")
    parser.add_argument(
        "--episodes", type=_positive_int, default=2000, help="episodes per policy (default 2000)"
    )
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed")
    parser.add_argument("--collision", default="reference", choices=("reference", "final"),
                        help="wall rules of a layout (SPEC.md 1; default reference)")
    parser.add_argument(
        "--sticky-prob",
        type=_probability,
        default=0.7,
        help="repeat probability of the sticky random policy (default 0.7)",
    )


def _demo(args: argparse.Namespace) -> int:
    import time

    import jax
    import numpy as np

    import envs
    from envs.maze import random_rollout

    env, params = envs.make(args.env, collision=args.collision)
    num_steps = int(params.max_steps)
    params = jax.device_put(params)
    rollouts = jax.jit(
        jax.vmap(random_rollout, in_axes=(None, None, 0, None, None)), static_argnums=(0, 3)
    )
    print(
        f"{args.env}: {args.episodes} episodes per policy, at most {num_steps} steps, "
        f"seed {args.seed} ({jax.default_backend()}, {jax.numpy.result_type(float)})"
    )
    key = jax.random.key(args.seed)
    keys = jax.random.split(key, args.episodes)
    start = time.perf_counter()
    # The sticky probability is a traced argument, so both policies share one compilation.
    compiled = rollouts.lower(env, params, keys, num_steps, 0.0).compile()
    print(f"compiled in {time.perf_counter() - start:.2f} s")
    print("| policy | success rate | mean successful length | env steps/s |")
    print("|---|---:|---:|---:|")
    policies = (
        ("uniform random", 0.0),
        (f"sticky random (p={args.sticky_prob:g})", args.sticky_prob),
    )
    for i, (name, sticky) in enumerate(policies):
        keys = jax.random.split(jax.random.fold_in(key, i), args.episodes)
        start = time.perf_counter()
        success, length = jax.block_until_ready(compiled(params, keys, sticky))
        run_s = time.perf_counter() - start
        success, length = np.asarray(success), np.asarray(length)
        rate = success.mean()
        stderr = np.sqrt(rate * (1 - rate) / len(success))
        mean_len = f"{length[success].mean():.1f}" if success.any() else "-"
        # Every episode is stepped for the full scan length, so that is what steps/s counts.
        steps_per_s = args.episodes * num_steps / run_s
        print(
            f"| {name} | {100 * rate:.1f}% ± {100 * stderr:.1f} | {mean_len} | {steps_per_s:,.0f} |"
        )
    reference = _REFERENCE_FIGURES.get((args.env, args.collision))
    if reference is not None:
        steps = lambda length: "" if length is None else f" ({length} steps)"
        rules = "" if args.collision == "reference" else f", {args.collision} rules"
        (u_rate, u_len), (s_rate, s_len) = reference[0.0], reference[0.7]
        print(
            f"Reference (SPEC.md{rules}): uniform {u_rate}%{steps(u_len)}, "
            f"sticky p=0.7 {s_rate}%{steps(s_len)}."
        )
    return 0


register(
    Command(
        "demo",
        "Roll out random and sticky-random policies on a maze and report "
        "success rate and throughput.",
        _demo_arguments,
        _demo,
    )
)


# ----------------------------------------------------------------------------------------------
# gara-jax reproduce
# ----------------------------------------------------------------------------------------------


def _reproduce_arguments(parser: argparse.ArgumentParser) -> None:
    from experiments import u_maze  # light: argparse and NumPy only at import

    u_maze.add_arguments(parser)


def _reproduce(args: argparse.Namespace) -> int:
    from experiments import u_maze

    return u_maze.run(args)


register(
    Command(
        "reproduce",
        "Reproduce the paper's U-maze study (GARA, GARA planning, GARA reference, Handcrafted, "
        "the paper's HIRO; --methods all adds published HIRO; 20 seeds x 120,000 steps) and "
        "write metrics, episodes, summary and figures.",
        _reproduce_arguments,
        _reproduce,
    )
)


if __name__ == "__main__":
    sys.exit(main())
