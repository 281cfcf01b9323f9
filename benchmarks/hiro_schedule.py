"""Wall time of published HIRO's training epochs under the two seed schedules.

Trains ``HiroConfig(seed_schedule=...)`` (``"sequential"``: the seeds' TD3 steps one after
another inside the vmapped epoch; ``"vmap"``: as batched operations) for ``--seeds`` seeds and
three ``--steps-per-epoch`` epochs each, and prints every epoch's wall time (the first includes
compilation) and the mean critic loss, so the two runs can be compared: the same algorithm, so
losses agree to rounding. Writes ``benchmarks/results/hiro_schedule.json``.

Usage::

    python benchmarks/hiro_schedule.py                 # 20 seeds, 1,500-step epochs
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gara_jax.algorithms import HiroConfig
from gara_jax.train import train_epochs

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script or loaded by path
from _common import load_average, machine_info, write_result  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "hiro_schedule.json"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--steps-per-epoch", type=int, default=1500)
    parser.add_argument("--out", type=Path, default=RESULTS)
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    result = {"machine": machine_info(), "seeds": args.seeds,
              "steps_per_epoch": args.steps_per_epoch, "schedules": {}}
    for schedule in ("sequential", "vmap"):
        cfg = HiroConfig(seed_schedule=schedule, steps_per_epoch=args.steps_per_epoch)
        times, losses = [], []
        for out in train_epochs(cfg, args.seeds, 3 * args.steps_per_epoch):
            times.append(out.epoch_s)
            losses.append(float(np.mean(out.metrics["critic_loss"])))
        result["schedules"][schedule] = {"epoch_s": times, "critic_loss": losses,
                                         "load_average_1min_at_end": load_average()}
        print(f"{schedule}: epoch s {[round(t, 1) for t in times]} (first includes compile), "
              f"critic loss {[round(x, 6) for x in losses]}", flush=True)
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
