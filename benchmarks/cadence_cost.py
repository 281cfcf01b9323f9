"""What GARA's per-episode cadence costs against the per-epoch host step.

``cadence="epoch"`` runs an epoch as one jitted call and the host step (trigger, forward model,
analysis) once after it; ``cadence="episode"`` (the reference presets, SPEC.md 3.9.3) runs it
as jitted segments, each taking every seed to the end of its current episode, with a host step
after each for the seeds whose episode ended. A seed whose episode ended idles until the
slowest seed's ends, so a segment's loop runs as long as its longest episode: the *idle
fraction* (loop iterations x seeds / agent steps - 1) is what the batch pays for that.

For each cadence, ``--seeds`` seeds of ``GaraConfig.reference(version=...)`` train for
``--steps`` steps through :func:`gara_jax.train.train_epochs`; the first epoch (which compiles)
is timed apart, the others give the steady-state seconds per epoch, the host step's share and
the segments. The two cadences take the same steps with the same keys but analyse at different
times, so after a few epochs their partitions (and their host steps' work) differ: the numbers
compare the cost of two faithful runs, not of one run twice.

Usage::

    python benchmarks/cadence_cost.py                       # 20 seeds x 15,000 steps
    python benchmarks/cadence_cost.py --seeds 2 --steps 6000 --version final

Prints a markdown table and writes ``benchmarks/results/cadence_cost.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

RESULTS = Path(__file__).resolve().parent / "results" / "cadence_cost.json"
CADENCES = ("epoch", "episode")


def bench(cadence: str, version: str, n_seeds: int, steps: int) -> dict:
    """Train one cadence and time it epoch by epoch."""
    import os

    from gara_jax import train as tr
    from gara_jax.algorithms import GaraConfig

    config = GaraConfig.reference(version=version, cadence=cadence)
    epoch_s, host_s, segments, iterations, episodes, analysed = [], [], [], [], [], 0
    t0 = time.perf_counter()
    for out in tr.train_epochs(config, n_seeds, steps):
        info = out.host_info or {}
        epoch_s.append(out.epoch_s)
        host_s.append(float(info.get("host_s", 0.0)))
        segments.append(int(info.get("segments", 0)))
        iterations.append(int(info.get("segment_iterations", 0)))
        episodes.append(int(sum(len(e) for e in out.episodes["length"])) if out.episodes else 0)
        analysed += int(info.get("analysed", 0))
    total = time.perf_counter() - t0
    spe = config.steps_per_epoch
    steady = epoch_s[1:] or epoch_s
    row = {"cadence": cadence, "version": version, "n_seeds": n_seeds,
           "epochs": len(epoch_s), "steps_per_seed": len(epoch_s) * spe, "total_s": total,
           "first_epoch_s": epoch_s[0], "epoch_s": epoch_s,
           "epoch_s_median_after_first": statistics.median(steady),
           "host_s_per_epoch_median_after_first": statistics.median(host_s[1:] or host_s),
           "host_s": host_s, "episodes": episodes, "analysed": analysed,
           "load_average_at_end": os.getloadavg()[0]}
    if cadence == "episode":
        row["segments_per_epoch_mean"] = statistics.mean(segments)
        # Loop iterations x seeds against the agent steps taken: the idle seeds' share.
        row["idle_fraction"] = sum(iterations) / (len(epoch_s) * spe) - 1.0
    return row


def table(rows) -> str:
    lines = ["| cadence | seeds | steps/seed | first epoch (s) | s/epoch after | host s/epoch "
             "| segments/epoch | idle fraction | total (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        seg = f"{r['segments_per_epoch_mean']:.1f}" if "segments_per_epoch_mean" in r else "-"
        idle = f"{r['idle_fraction']:.2f}" if "idle_fraction" in r else "-"
        lines.append(f"| {r['cadence']} | {r['n_seeds']} | {r['steps_per_seed']:,} | "
                     f"{r['first_epoch_s']:.1f} | {r['epoch_s_median_after_first']:.2f} | "
                     f"{r['host_s_per_epoch_median_after_first']:.2f} | {seg} | {idle} | "
                     f"{r['total_s']:.1f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--steps", type=int, default=15_000, help="steps per seed")
    parser.add_argument("--version", default="results", choices=("final", "results"))
    parser.add_argument("--cadences", nargs="+", default=list(CADENCES), choices=CADENCES)
    parser.add_argument("--out", type=Path, default=RESULTS)
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error("--seeds: must be >= 1")
    if args.steps < 1:
        parser.error("--steps: must be >= 1")
    compile_cache.setup(args.no_compile_cache)

    from _common import machine_info, write_result

    machine = machine_info()
    rows = []
    for cadence in args.cadences:
        rows.append(bench(cadence, args.version, args.seeds, args.steps))
        print(f"{cadence}: {rows[-1]['total_s']:.1f} s", flush=True)
    print()
    print(table(rows))
    result = {"machine": machine, "rows": rows}
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
