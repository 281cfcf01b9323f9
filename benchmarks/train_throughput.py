"""Training throughput: agent steps per second (env step + all learning) per algorithm.

For each algorithm (GARA, GARA with the planner, Handcrafted, and HIRO when
``gara_jax.algorithms.hiro`` exists) and each seed count, one jitted ``vmap(train_epoch)`` with
the SPEC defaults (3,000-step epochs, learning from 3,000 stored transitions) is compiled
(timed apart), warmed up with one epoch (which also fills the replay buffers, so the timed
epochs include every gradient step), then timed over ``--epochs`` epochs with
``block_until_ready``. The greedy evaluation (run once per epoch by ``train_many``) is timed
apart, and so is GARA's host step (``host_update`` on the states after the timed epochs, timed
twice: the first call compiles the forward-model fit and the bounds).

``--reproduction`` also times the whole paper reproduction, ``train_many`` for 20 seeds x
120,000 steps per method, compilation, evaluation and refinement included.

Usage::

    python benchmarks/train_throughput.py                  # 1, 20, 128 seeds
    python benchmarks/train_throughput.py --seeds 20 --algorithms handcrafted
    python benchmarks/train_throughput.py --reproduction
    python benchmarks/train_throughput.py --seeds 20 --dry-run   # the plan only

Prints a markdown table and writes ``benchmarks/results/train_throughput.json``. ``--dry-run``
checks the arguments, builds the configs, prints what would be measured and exits without
measuring or writing.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

from gara_jax.algorithms import GaraConfig, HandcraftedConfig, make_algorithm

RESULTS = Path(__file__).resolve().parent / "results" / "train_throughput.json"


def configs() -> dict:
    out = {"gara": GaraConfig(), "gara_planning": GaraConfig(planning=True),
           "handcrafted": HandcraftedConfig()}
    try:
        from gara_jax.algorithms import HiroConfig
    except (ImportError, AttributeError):
        return out
    out["hiro"] = HiroConfig()
    return out


def machine_info() -> dict:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return {
        "cpu": cpu,
        "logical_cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }


def _block(tree):
    return jax.block_until_ready(tree)


def bench_one(config, n_seeds: int, epochs: int) -> dict:
    """Compile, warm up and time ``vmap(train_epoch)`` (and the evaluation) for ``n_seeds``."""
    alg = make_algorithm(config)
    keys = jax.random.split(jax.random.key(0), n_seeds)
    states = _block(jax.jit(jax.vmap(alg.init))(keys))
    epoch_fn = jax.jit(jax.vmap(alg.train_epoch), donate_argnums=0)
    eval_fn = jax.jit(jax.vmap(alg.evaluate))

    t0 = time.perf_counter()
    epoch = epoch_fn.lower(states, keys).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    evaluate = eval_fn.lower(states, keys).compile()
    eval_compile_s = time.perf_counter() - t0

    states, _ = _block(epoch(states, jax.random.split(jax.random.key(1), n_seeds)))  # warm-up
    times, cpu = [], []
    for e in range(epochs):
        k = jax.random.split(jax.random.key(2 + e), n_seeds)
        t0, c0 = time.perf_counter(), time.process_time()
        states, metrics = _block(epoch(states, k))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    _block(evaluate(states, keys))
    t0 = time.perf_counter()
    _block(evaluate(states, keys))
    eval_s = time.perf_counter() - t0

    epoch_s = statistics.median(times)
    row = {
        "n_seeds": n_seeds,
        "steps_per_epoch": config.steps_per_epoch,
        "compile_s": compile_s,
        "eval_compile_s": eval_compile_s,
        "epoch_s_median": epoch_s,
        "epoch_s_all": times,
        "agent_steps_per_s": n_seeds * config.steps_per_epoch / epoch_s,
        # Process CPU time (all threads): less sensitive than wall time to other processes
        # sharing the machine.
        "epoch_cpu_s_median": statistics.median(cpu),
        "agent_steps_per_cpu_s": n_seeds * config.steps_per_epoch / statistics.median(cpu),
        "eval_s": eval_s,
        "eval_episodes_per_seed": config.eval_episodes,
    }
    if alg.host_update is not None:
        # The first call compiles the forward-model fit and the bounds; time a second one too.
        t0 = time.perf_counter()
        _, info = alg.host_update(states, epochs)
        row["host_update_first_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, info = alg.host_update(states, epochs)
        row["host_update_s"] = time.perf_counter() - t0
        row["host_update_jobs"] = int(info["triggered"])
        row["host_update_fit_s"] = float(info["fit_s"])
        row["host_update_refine_s"] = float(info["refine_s"])
    return row


def reproduction(algorithms, n_seeds=20, total_steps=120_000) -> dict:
    """Wall time of full ``train_many`` runs (compile, eval and refinement included)."""
    from gara_jax.train import train_many

    out = {}
    for name, config in algorithms.items():
        res = train_many(config, n_seeds, total_steps)
        out[name] = {
            "n_seeds": n_seeds, "total_steps": total_steps, "wall_time_s": res.wall_time_s,
            "first_epoch_s": res.first_epoch_s, "host_time_s": res.host_time_s,
            "final_eval_success_mean": float(res.metrics["eval_success"][:, -1].mean()),
            "final_n_goals_mean": float(res.metrics["n_goals"][:, -1].mean()),
        }
        print(f"reproduction {name}: {res.wall_time_s:.1f}s "
              f"(first epoch {res.first_epoch_s:.1f}s, host {res.host_time_s:.1f}s)", flush=True)
    return out


def table(rows) -> str:
    lines = ["| algorithm | seeds | agent steps/s | steps per CPU-s | epoch (s) | compile (s) | "
             "eval (s) | host step (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        host = f"{r['host_update_s']:.2f} ({r['host_update_jobs']} jobs)" \
            if "host_update_s" in r else "-"
        lines.append(
            f"| {r['algorithm']} | {r['n_seeds']} | {r['agent_steps_per_s']:,.0f} | "
            f"{r['agent_steps_per_cpu_s']:,.0f} | "
            f"{r['epoch_s_median']:.2f} | {r['compile_s'] + r['eval_compile_s']:.1f} | "
            f"{r['eval_s']:.2f} | {host} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 20, 128])
    parser.add_argument("--algorithms", nargs="+", default=None,
                        help="subset of gara, gara_planning, handcrafted, hiro")
    parser.add_argument("--epochs", type=int, default=2, help="timed epochs per measurement")
    parser.add_argument("--reproduction", action="store_true",
                        help="also time 20 seeds x 120,000 steps per method with train_many")
    parser.add_argument("--max-epoch-s", type=float, default=60.0,
                        help="skip an algorithm's larger seed counts once one of its epochs "
                             "took longer than this (seconds)")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of the existing JSON that this run does not measure")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--dry-run", action="store_true",
                        help="print what would be measured and exit (nothing run or written)")
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    if any(n < 1 for n in args.seeds) or args.epochs < 1:
        parser.error("--seeds and --epochs: must be >= 1")

    algorithms = configs()
    if args.algorithms:
        unknown = set(args.algorithms) - set(algorithms)
        if unknown:
            parser.error(f"unknown or unavailable algorithms: {sorted(unknown)}")
        algorithms = {k: v for k, v in algorithms.items() if k in args.algorithms}
    if args.dry_run:
        plan = {"algorithms": list(algorithms), "seeds": sorted(args.seeds),
                "timed_epochs": args.epochs,
                "steps_per_epoch": {k: v.steps_per_epoch for k, v in algorithms.items()},
                "reproduction": args.reproduction, "out": str(args.out)}
        print("train_throughput --dry-run (nothing measured or written): "
              f"{', '.join(plan['algorithms'])} x seeds {plan['seeds']}, one compiling and one "
              f"warm-up epoch, then {args.epochs} timed epoch(s) of "
              f"{', '.join(f'{k} {v:,}' for k, v in plan['steps_per_epoch'].items())} steps"
              f"{'; then the 20-seed x 120,000-step reproduction' if args.reproduction else ''}"
              f"; would write {args.out}")
        return plan
    load_start = os.getloadavg()
    rows, skipped = [], []
    for name, config in algorithms.items():
        for n in sorted(args.seeds):
            if any(r["algorithm"] == name and r["epoch_s_median"] > args.max_epoch_s
                   for r in rows):
                skipped.append({"algorithm": name, "n_seeds": n})
                print(f"{name:14s} seeds={n:4d}  skipped (slower than --max-epoch-s)")
                continue
            row = {"algorithm": name, **bench_one(config, n, args.epochs),
                   "load_average": os.getloadavg(),
                   "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S")}
            rows.append(row)
            print(f"{name:14s} seeds={n:4d}  {row['agent_steps_per_s']:10,.0f} steps/s  "
                  f"compile {row['compile_s']:.1f}s", flush=True)
    if args.merge and args.out.exists():
        measured = {(r["algorithm"], r["n_seeds"]) for r in rows}
        kept = [r for r in json.loads(args.out.read_text())["rows"]
                if (r["algorithm"], r["n_seeds"]) not in measured]
        order = list(configs())
        rows = sorted(kept + rows, key=lambda r: (order.index(r["algorithm"])
                                                  if r["algorithm"] in order else 99,
                                                  r["n_seeds"]))
    result = {"machine": machine_info(), "load_average_start": load_start,
              "load_average_end": os.getloadavg(), "rows": rows, "skipped": skipped}
    if args.reproduction:
        result["reproduction"] = reproduction(algorithms)
    print()
    print(table(rows))
    for sk in skipped:
        print(f"(skipped: {sk['algorithm']} with {sk['n_seeds']} seeds)")
    if "reproduction" in result:
        total = sum(r["wall_time_s"] for r in result["reproduction"].values())
        print(f"\nreproduction (20 seeds x 120,000 steps, all methods): {total:.0f} s")
    print(f"\nload average (1, 5, 15 min): start {load_start}, end {result['load_average_end']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2, default=float))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
