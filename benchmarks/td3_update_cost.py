"""Cost of HIRO's high-level TD3 update, the part that bounds HIRO's training throughput.

Times one vmapped critic step and one vmapped actor step (with its soft target update) of
``gara_jax.agents.td3`` with HIRO's settings (``HiroConfig().high``: 300-300 networks, batch
100; observations and goals of 4 numbers) for ``--seeds`` seeds, compile apart, after a warm-up
call, best of ``--repeats`` rounds with ``block_until_ready``. Also reports the floating-point
operations of one critic step (dense layers only: forward passes of the target actor and
twin target critics, forward and backward of the twin critics, backward counted as twice the
forward) and the rate they imply, set against this CPU's arithmetic peak: the rate of one large
float32 matrix product (the best this JAX build reaches here) and the theoretical peak, cores x
clock x FLOPs per cycle (``--flop-per-cycle``, default 64: two 512-bit FMA pipes per core,
16 float32 lanes each, 2 FLOPs per FMA, as on AMD Zen 5; the clock from ``/proc/cpuinfo``).
It also times the same per-seed steps run one seed after another (``lax.map``) instead of
vmapped, the other way to schedule the seeds' updates.

Usage::

    python benchmarks/td3_update_cost.py                 # 20 seeds, HIRO's sizes
    python benchmarks/td3_update_cost.py --hidden 64 64  # other widths, for comparison

Prints the numbers and writes ``benchmarks/results/td3_update_cost.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from gara_jax.agents.td3 import Batch, make_td3
from gara_jax.algorithms import HiroConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script or loaded by path
from _common import write_result  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "td3_update_cost.json"
DIM = 4  # U-maze state and relative goal


def mlp_macs(widths) -> int:
    return sum(a * b for a, b in zip(widths[:-1], widths[1:], strict=False))


def critic_step_flops(actor_hidden, critic_hidden, batch: int) -> int:
    """Dense-layer FLOPs of one critic step per seed (2 FLOPs per multiply-add)."""
    actor = mlp_macs((DIM, *actor_hidden, DIM))
    critic = mlp_macs((2 * DIM, *critic_hidden, 1))
    target = actor + 2 * critic  # target actor, twin target critics: forward only
    online = 3 * (2 * critic)  # twin critics: forward + backward (twice the forward)
    return 2 * batch * (target + online)


def time_best(fn, args, repeats: int, calls: int = 10) -> float:
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(fn(*args))
        best = min(best, (time.perf_counter() - start) / calls)
    return best


def cpu_mhz() -> float | None:
    """The clock ``/proc/cpuinfo`` reports (first core), ``None`` where there is none."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("cpu mhz"):
                return float(line.split(":")[1])
    except OSError:
        pass
    return None


def matmul_gflop_per_s(n: int, repeats: int) -> float:
    """Best rate of an ``n x n`` float32 matrix product (jitted, compile apart)."""
    a = jax.random.normal(jax.random.key(3), (n, n), jnp.float32)
    dot = jax.jit(jnp.dot)
    return 2 * n**3 / time_best(dot, (a, a), repeats, calls=3) / 1e9


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--hidden", type=int, nargs="+", default=None,
                        help="actor and critic hidden widths (default: HIRO's 300 300)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--matmul-size", type=int, default=2048)
    parser.add_argument("--flop-per-cycle", type=float, default=64.0,
                        help="float32 FLOPs per cycle per core (default 64: AMD Zen 5)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    if args.seeds < 1 or args.repeats < 1:
        parser.error("--seeds and --repeats must be >= 1")

    config = HiroConfig().high
    if args.hidden:
        config = dataclasses.replace(config, actor_hidden=tuple(args.hidden),
                                     critic_hidden=tuple(args.hidden))
    td3 = make_td3(config, DIM, DIM, -3.0, 3.0)
    n, b = args.seeds, config.batch_size
    states = jax.vmap(td3.init)(jax.random.split(jax.random.key(0), n))
    keys = jax.random.split(jax.random.key(1), n)
    data = jax.random.normal(jax.random.key(2), (4, n, b, DIM))
    batch = Batch(data[0], data[1], data[2, ..., 0], data[3], jnp.zeros((n, b), bool))

    critic = jax.jit(jax.vmap(td3.critic_update))
    actor = jax.jit(jax.vmap(td3.actor_update))
    start = time.perf_counter()
    critic.lower(states, batch, keys).compile()
    actor.lower(states, batch.obs).compile()
    compile_s = time.perf_counter() - start
    critic_s = time_best(critic, (states, batch, keys), args.repeats)
    actor_s = time_best(actor, (states, batch.obs), args.repeats)
    seq = jax.jit(lambda s, bt, k: jax.lax.map(lambda x: td3.critic_update(*x), (s, bt, k)))
    critic_map_s = time_best(seq, (states, batch, keys), args.repeats)
    flops = n * critic_step_flops(config.actor_hidden, config.critic_hidden, b)
    matmul = matmul_gflop_per_s(args.matmul_size, args.repeats)
    mhz = cpu_mhz()
    peak = None if mhz is None else os.cpu_count() * mhz * 1e-3 * args.flop_per_cycle
    result = {
        "seeds": n, "batch_size": b, "actor_hidden": config.actor_hidden,
        "critic_hidden": config.critic_hidden, "compile_s": compile_s,
        "critic_step_s": critic_s, "actor_step_s": actor_s,
        "mean_update_s_with_policy_delay": critic_s + actor_s / config.policy_delay,
        "critic_step_gflop": flops / 1e9, "critic_step_gflop_per_s": flops / critic_s / 1e9,
        "critic_step_seeds_in_sequence_s": critic_map_s,
        "matmul_size": args.matmul_size, "matmul_gflop_per_s": matmul,
        "cpu_mhz": mhz, "flop_per_cycle": args.flop_per_cycle,
        "theoretical_peak_gflop_per_s": peak,
        "critic_step_fraction_of_matmul": flops / critic_s / 1e9 / matmul,
        "critic_step_fraction_of_peak": None if peak is None else flops / critic_s / 1e9 / peak,
        "backend": jax.default_backend(), "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg(), "jax": jax.__version__,
    }
    print(f"TD3 {config.critic_hidden} batch {b}, {n} seeds: critic step {1e3 * critic_s:.1f} ms "
          f"({flops / 1e9:.2f} GFLOP, {flops / critic_s / 1e9:.0f} GFLOP/s), actor step "
          f"{1e3 * actor_s:.1f} ms, mean per high-level update "
          f"{1e3 * result['mean_update_s_with_policy_delay']:.1f} ms; seeds in sequence: "
          f"critic step {1e3 * critic_map_s:.1f} ms")
    print(f"{args.matmul_size}^2 float32 matmul: {matmul:.0f} GFLOP/s; theoretical peak "
          + ("unknown" if peak is None else f"{peak:.0f} GFLOP/s ({os.cpu_count()} cores x "
             f"{mhz:.0f} MHz x {args.flop_per_cycle:g})")
          + f"; the critic step reaches {100 * result['critic_step_fraction_of_matmul']:.0f}% "
            "of the matmul rate"
          + ("" if peak is None else
             f", {100 * result['critic_step_fraction_of_peak']:.0f}% of the peak"))
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
