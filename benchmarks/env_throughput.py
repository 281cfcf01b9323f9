"""Maze environment throughput: ``jit(vmap(scan))`` over batch sizes vs plain Python loops.

The JAX rows run ``env.step_autoreset`` for ``--steps`` steps in every one of ``batch`` parallel
environments, with uniformly random actions drawn inside the jitted function (a counter-based
integer hash of a ``jax.random`` seed). Compile time is measured apart (``lower().compile()``),
then one warm-up call, then ``--repeats`` timed calls with ``block_until_ready``.

Baselines, one environment at a time with random actions and resets, the way the authors'
reference runs:

* ``envs.reference.ReferenceMaze``: the rules on Python floats;
* ``envs.reference.NumpyReferenceMaze``: the same rules on small NumPy arrays per step (the
  style of the authors' code; identical states, much slower in CPython).

Rows for ``point_u_maze`` (the brax-simulated U-maze, ``envs/point_maze.py``) follow, at
``--point-batches`` (1, 20 and 1024 by default) for ``--point-steps`` steps, measured the same
way in this process only (not in the pinned child: its question is XLA's thread split of the
kinematic step). Their speedup column still divides by the kinematic maze's plain loop.

Both are timed before and after the JAX rows (the machine may be shared and its load may
change). The speedup column divides by the best steps/s of the FASTEST plain loop, the stricter
baseline. A further row steps the jitted single-environment ``env.step`` from a Python loop (what
the Gymnasium adapter does).

By default the JAX rows are measured twice: in this process, with XLA's CPU thread pool on all
cores (what a user gets by default), and in a child process pinned to one core before JAX
starts (``os.sched_setaffinity``), where XLA runs every loop on that core. On a loaded 2-core
machine the second is often faster: XLA splits each loop of the step across the cores, and
every split waits for a core that other processes are using. ``--no-single-core`` skips it.

Usage:
    python benchmarks/env_throughput.py                       # full run
    python benchmarks/env_throughput.py --steps 256 --batches 1 1024 --loop-steps 20000  # quick
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.reference import NumpyReferenceMaze, ReferenceMaze

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script or loaded by path
from _common import load_average, machine_info, write_result  # noqa: E402


def random_actions(seed: jax.Array, t: jax.Array) -> jax.Array:
    """Uniform actions in {0, 1, 2, 3} from a counter-based integer hash of ``(seed, t)``.

    ``seed`` comes from ``jax.random``; the hash (the "lowbias32" finaliser) is a few integer
    ops, so that the measurement is dominated by the environment and not by random numbers.
    """
    x = seed + t.astype(jnp.uint32) * jnp.uint32(0x9E3779B9)
    x = (x ^ (x >> 16)) * jnp.uint32(0x7FEB352D)
    x = (x ^ (x >> 15)) * jnp.uint32(0x846CA68B)
    x = x ^ (x >> 16)
    return (x >> 30).astype(jnp.int32)


def make_rollout(env: envs.Maze, num_steps: int, unroll: int = 1):
    """``rollout(key, params) -> (total_reward, episodes_ended)`` over ``num_steps`` steps."""

    def rollout(key, params):
        key_seed, key_reset, key_step = jax.random.split(key, 3)
        seed = jax.random.bits(key_seed, (), jnp.uint32)
        _, state = env.reset(key_reset, params)

        def body(carry, t):
            state, total_reward, ended = carry
            action = random_actions(seed, t)
            _, state, reward, terminated, truncated, _ = env.step_autoreset(
                key_step, state, action, params
            )
            return (state, total_reward + reward, ended + (terminated | truncated)), None

        init = (state, jnp.zeros((), reward_dtype()), jnp.zeros((), jnp.int32))
        (_, total_reward, ended), _ = jax.lax.scan(
            body, init, jnp.arange(num_steps, dtype=jnp.int32), unroll=unroll
        )
        return total_reward, ended

    return rollout


def reward_dtype():
    return jnp.result_type(float)


class Stopwatch:
    """Collects wall-clock and process CPU seconds of each ``with`` block.

    CPU time is recorded too because this machine's cores may be shared: wall time then
    includes waiting for other processes, CPU time does not.
    """

    def __init__(self):
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def __enter__(self):
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall.append(time.perf_counter() - self._wall)
        self.cpu.append(time.process_time() - self._cpu)
        return False


def bench_jax(layout: str, batch: int, num_steps: int, repeats: int, seed: int) -> dict:
    """One ``jit(vmap(scan))`` row for any name of ``envs.ENV_NAMES``."""
    env, params = envs.make(layout)
    params = jax.device_put(params)
    run = jax.jit(jax.vmap(make_rollout(env, num_steps), in_axes=(0, None)))
    keys = jax.random.split(jax.random.key(seed), batch)
    start = time.perf_counter()
    compiled = run.lower(keys, params).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(keys, params))  # warm-up
    watch = Stopwatch()
    for _ in range(repeats):
        with watch:
            _, ended = jax.block_until_ready(compiled(keys, params))
    prefix = "" if layout in envs.LAYOUTS else f"{layout}: "
    return {
        "method": f"{prefix}jit(vmap(scan)) step_autoreset",
        "env": layout,
        "batch": batch,
        "steps_per_env": num_steps,
        "compile_s": compile_s,
        "times_s": watch.wall,
        "cpu_times_s": watch.cpu,
        "episodes_ended": int(np.asarray(ended).sum()),
        # Loops of the compiled program that XLA splits across threads (0 on one core).
        "xla_split_loops": _count_split_loops(compiled),
        "load_average_1min": load_average(),
    }


def _count_split_loops(compiled) -> int | None:
    try:
        return compiled.as_text().count("outer_dimension_partitions")
    except Exception:  # the text form is a debugging aid; never fail the benchmark over it
        return None


# (row name, class, divisor of --loop-steps: the NumPy loop is about 15x slower per step)
PLAIN_LOOPS = (
    ("plain Python loop (envs.reference, Python floats)", ReferenceMaze, 1),
    ("plain Python loop (envs.reference, NumPy arrays)", NumpyReferenceMaze, 10),
)


def bench_plain_loop(reference: type, layout: str, num_steps: int, repeats: int, seed: int) -> dict:
    env = reference.from_layout(layout)
    rng = random.Random(seed)
    watch, ended = Stopwatch(), 0
    for _ in range(repeats):
        env.reset()
        ended = 0
        with watch:
            for _ in range(num_steps):
                _, _, terminated, truncated = env.step(rng.randrange(4))
                if terminated or truncated:
                    env.reset()
                    ended += 1
    return {
        "batch": 1,
        "steps_per_env": num_steps,
        "compile_s": 0.0,
        "times_s": watch.wall,
        "cpu_times_s": watch.cpu,
        "episodes_ended": ended,
        "load_average_1min": load_average(),
    }


def bench_python_jit_loop(layout: str, num_steps: int, repeats: int, seed: int) -> dict:
    env, params = envs.make(layout)
    params = jax.device_put(params)
    step = jax.jit(env.step)
    key = jax.random.key(seed)
    rng = random.Random(seed)
    _, state = env.reset(key, params)
    start = time.perf_counter()
    jax.block_until_ready(step(key, state, jnp.int32(0), params))
    compile_s = time.perf_counter() - start
    watch = Stopwatch()
    for _ in range(repeats):
        _, state = env.reset(key, params)
        with watch:
            for _ in range(num_steps):
                _, state, _, terminated, truncated, _ = step(key, state, rng.randrange(4), params)
                if bool(terminated | truncated):  # a host sync per step, as a Python agent needs
                    _, state = env.reset(key, params)
    return {
        "method": "Python loop over jit(step)",
        "batch": 1,
        "steps_per_env": num_steps,
        "compile_s": compile_s,
        "times_s": watch.wall,
        "cpu_times_s": watch.cpu,
        "episodes_ended": None,
        "load_average_1min": load_average(),
    }


def summarise(row: dict, num_steps_total: int, baseline: float | None) -> dict:
    best = min(row["times_s"])
    median = statistics.median(row["times_s"])
    row["steps_per_s_best"] = num_steps_total / best
    row["steps_per_s_median"] = num_steps_total / median
    row["steps_per_cpu_s_best"] = num_steps_total / max(min(row["cpu_times_s"]), 1e-9)
    row["speedup_vs_plain_loop"] = None if baseline is None else row["steps_per_s_best"] / baseline
    return row


def markdown_table(rows: list[dict]) -> str:
    lines = [
        "| method | cores | batch | steps/env | compile (s) | env steps/s (best) "
        "| env steps/s (median) | x fastest plain loop |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        speedup = r["speedup_vs_plain_loop"]
        lines.append(
            f"| {r['method']} | {r['cores']} | {r['batch']} | {r['steps_per_env']} "
            f"| {r['compile_s']:.2f} | {r['steps_per_s_best']:,.0f} "
            f"| {r['steps_per_s_median']:,.0f} "
            f"| {'-' if speedup is None else f'{speedup:.1f}'} |"
        )
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="u_maze", choices=envs.LAYOUTS)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 20, 1024, 16384])
    parser.add_argument("--steps", type=int, default=2048, help="steps per environment")
    parser.add_argument(
        "--loop-steps",
        type=int,
        default=100_000,
        help="steps of the Python-floats plain loop per repeat (the NumPy loop takes a tenth)",
    )
    parser.add_argument(
        "--jit-loop-steps",
        type=int,
        default=5_000,
        help="steps of the Python loop over jit(step); 0 skips it",
    )
    parser.add_argument(
        "--point-batches",
        type=int,
        nargs="*",
        default=[1, 20, 1024],
        help="batch sizes of the point_u_maze rows; none skips them",
    )
    parser.add_argument(
        "--point-steps", type=int, default=256, help="steps per environment of point_u_maze"
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-single-core",
        action="store_true",
        help="skip the JAX rows measured in a child process pinned to one core",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).resolve().parent / "results" / "env_throughput.json",
    )
    # Internal: run the JAX rows only, pinned to this CPU, and print them as JSON.
    parser.add_argument("--jax-rows-on-cpu", type=int, default=None, help=argparse.SUPPRESS)
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    for name in ("steps", "loop_steps", "repeats", "point_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.jit_loop_steps < 0:
        parser.error("--jit-loop-steps must be >= 0")
    if any(b < 1 for b in args.batches + args.point_batches):
        parser.error("--batches must all be >= 1")
    return args


def jax_rows(args: argparse.Namespace, cores: str) -> list[dict]:
    rows = []
    for batch in args.batches:
        row = bench_jax(args.env, batch, args.steps, args.repeats, args.seed)
        row["cores"] = cores
        rows.append(row)
    return rows


def single_core_jax_rows(args: argparse.Namespace) -> list[dict] | str:
    """The JAX rows from a child process pinned to one CPU; a reason string if impossible."""
    if not hasattr(os, "sched_setaffinity"):
        return "os.sched_setaffinity is not available on this platform"
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return "this process already runs on a single CPU"
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--env", args.env,
        "--steps", str(args.steps),
        "--repeats", str(args.repeats),
        "--seed", str(args.seed),
        "--batches", *map(str, args.batches),
        "--jax-rows-on-cpu", str(cpus[-1]),
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        return f"the single-core child process failed:\n{done.stderr[-2000:]}"
    return json.loads(done.stdout.strip().splitlines()[-1])


def child_main(args: argparse.Namespace) -> None:
    # Before JAX creates its CPU client, so that XLA sizes its thread pool to this one CPU.
    os.sched_setaffinity(0, {args.jax_rows_on_cpu})
    rows = jax_rows(args, cores="1 (pinned)")
    print(json.dumps(rows))


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.jax_rows_on_cpu is not None:
        child_main(args)
        return {}
    info = machine_info()
    loop_steps = {name: max(1, args.loop_steps // div) for name, _, div in PLAIN_LOOPS}
    first_half = {
        name: bench_plain_loop(cls, args.env, loop_steps[name], args.repeats, args.seed)
        for name, cls, _ in PLAIN_LOOPS
    }

    cores = f"all ({len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'})"
    rows = []
    if args.jit_loop_steps:
        row = bench_python_jit_loop(args.env, args.jit_loop_steps, min(args.repeats, 3), args.seed)
        row["cores"] = cores
        rows.append(row)
    rows += jax_rows(args, cores)
    for batch in args.point_batches:
        row = bench_jax("point_u_maze", batch, args.point_steps, args.repeats, args.seed)
        row["cores"] = cores
        rows.append(row)
    single = None if args.no_single_core else single_core_jax_rows(args)
    if isinstance(single, list):
        rows += single
    elif isinstance(single, str):
        print(f"note: no single-core rows: {single}", file=sys.stderr)

    # The plain loops again, after the JAX rows: their best over both halves is the baseline.
    plain_rows = []
    for name, cls, _ in PLAIN_LOOPS:
        second = bench_plain_loop(cls, args.env, loop_steps[name], args.repeats, args.seed + 1)
        row = first_half[name]
        row["method"], row["cores"] = name, "1"
        row["times_s"] += second["times_s"]
        row["cpu_times_s"] += second["cpu_times_s"]
        row["load_average_1min"] = [row["load_average_1min"], second["load_average_1min"]]
        plain_rows.append(summarise(row, loop_steps[name], None))
    fastest = max(plain_rows, key=lambda r: r["steps_per_s_best"])
    baseline = fastest["steps_per_s_best"]
    for row in plain_rows:
        row["speedup_vs_plain_loop"] = row["steps_per_s_best"] / baseline
    for row in rows:
        summarise(row, row["batch"] * row["steps_per_env"], baseline)
    rows = plain_rows + rows

    info["load_average_1min_at_end"] = load_average()
    table = markdown_table(rows)
    print(
        f"Maze env throughput ({args.env}), {info['backend']} backend, {info['cpu_count']} CPUs, "
        f"jax {info['jax']}, {info['platform']}, load average (1 min) "
        f"{info['load_average_1min_at_start']:.2f} at start, "
        f"{info['load_average_1min_at_end']:.2f} at end"
    )
    print(table)
    print(
        f"x fastest plain loop = env steps/s (best) / {baseline:,.0f}, the best of the fastest "
        f"plain loop ({fastest['method']}) over {len(fastest['times_s'])} runs"
    )
    result = {
        "benchmark": "env_throughput",
        "env": args.env,
        "machine": info,
        "config": {k: (os.path.relpath(v) if isinstance(v, Path) else v)
                   for k, v in vars(args).items()},
        "baseline": {"method": fastest["method"], "steps_per_s": baseline},
        "results": rows,
        "table": table,
    }
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
