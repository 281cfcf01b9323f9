"""What ``batch_invariant=True`` costs: epoch time with XLA's defaults and batch-invariant.

For each algorithm, the training driver's own jitted, seed-vmapped epoch
(:func:`gara_jax.train.compiled`, one device) is compiled twice, with ``batch_invariant`` off
(XLA's defaults: the one-device default) and on (on CPU: YNNPACK dot fusions off, see
:mod:`gara_jax.sharding`); compilation is timed apart. Both start from the same initial states,
run one warm-up epoch (which fills the replay buffers, so the timed epochs run every gradient
step) and then ``--epochs`` timed epochs each, interleaved (off, on, off, on, ...) so that a
change in the machine's load hits both alike; every epoch ends with ``block_until_ready``.
The greedy evaluation is part of the epoch function, as in ``train_many``. GARA's host step
is not run (it is the same for both; its bounds always compile with the option off).

Usage::

    python benchmarks/batch_invariance_cost.py                  # 20 seeds, default configs
    python benchmarks/batch_invariance_cost.py --algorithms handcrafted --seeds 8

Prints a markdown table and writes ``benchmarks/results/batch_invariance_cost.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from gara_jax import train as tr
from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script or loaded by path
from _common import load_average, machine_info, write_result  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "batch_invariance_cost.json"

CONFIGS = {
    "handcrafted": HandcraftedConfig,
    "gara": GaraConfig,
    "hiro_paper": HiroConfig.paper,
    "hiro": HiroConfig,
}


def bench(config, n_seeds: int, epochs: int) -> dict:
    """Compile, warm up and time the epoch with ``batch_invariant`` off and on."""
    loop = tr.init_loop(config, n_seeds, devices=1)
    platform = jax.devices()[0].platform
    variants = {}
    for invariant in (False, True):
        jitted = tr.compiled(config, 1, invariant).run.jitted(platform)
        states = jax.tree.map(jnp.copy, loop.states)  # the run donates its states
        t0 = time.perf_counter()
        run = jitted.lower(states, loop.keys, 0).compile()
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        states, _ = jax.block_until_ready(run(states, loop.keys, 0))
        variants[invariant] = {"run": run, "states": states, "compile_s": compile_s,
                               "warmup_s": time.perf_counter() - t0, "epoch_s": []}
    for epoch in range(1, epochs + 1):
        for invariant in (False, True):
            v = variants[invariant]
            t0 = time.perf_counter()
            v["states"], metrics = jax.block_until_ready(v["run"](v["states"], loop.keys, epoch))
            v["epoch_s"].append(time.perf_counter() - t0)
            v["train_success"] = float(jnp.mean(metrics["train_success"]))
    out = {}
    for invariant, v in variants.items():
        out["batch_invariant" if invariant else "default"] = {
            "compile_s": v["compile_s"], "warmup_epoch_s": v["warmup_s"],
            "epoch_s": v["epoch_s"], "median_epoch_s": statistics.median(v["epoch_s"]),
            "last_train_success": v["train_success"]}
    out["slowdown"] = out["batch_invariant"]["median_epoch_s"] / out["default"]["median_epoch_s"]
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algorithms", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--epochs", type=int, default=3, help="timed epochs per variant")
    parser.add_argument("--out", type=Path, default=RESULTS)
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    if args.seeds < 1 or args.epochs < 1:
        parser.error("--seeds and --epochs must be at least 1")
    result = {"machine": machine_info(), "seeds": args.seeds, "timed_epochs": args.epochs,
              "algorithms": {}}
    for name in args.algorithms:
        config = CONFIGS[name]()
        row = bench(config, args.seeds, args.epochs)
        row["steps_per_epoch"] = config.steps_per_epoch
        result["algorithms"][name] = row
        print(f"{name}: default {row['default']['median_epoch_s']:.2f} s, batch-invariant "
              f"{row['batch_invariant']['median_epoch_s']:.2f} s per epoch "
              f"({row['slowdown']:.2f}x)", flush=True)
    result["load_average_1min_at_end"] = load_average()
    print("\n| algorithm | steps/epoch | default (s/epoch) | batch-invariant (s/epoch) | "
          "ratio |\n|---|---:|---:|---:|---:|")
    for name, row in result["algorithms"].items():
        print(f"| {name} | {row['steps_per_epoch']:,} | {row['default']['median_epoch_s']:.2f} | "
              f"{row['batch_invariant']['median_epoch_s']:.2f} | {row['slowdown']:.2f}x |")
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
