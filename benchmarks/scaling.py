"""How far one machine goes: agent steps/s and memory per seed against the seed count.

For each algorithm (Handcrafted, GARA, HIRO; the default configs) and each seed count, a fresh
subprocess (so that its peak resident memory is the size's own and an out-of-memory kill
ends only that size) runs the training driver's own jitted, seed-sharded epoch
(:func:`gara_jax.train.compiled`) on ``--devices`` devices:

1. ``init_loop``; the state's bytes (the agent-state pytree, all seeds) are counted;
2. a first epoch, which compiles (one compilation per device) and fills the replay buffers
   (learning starts within it); compilation is reported as its time minus a timed epoch's;
3. ``--epochs`` timed epochs, each with ``block_until_ready``; for GARA the host step after
   the timed epochs is timed apart;
4. the process's peak resident set size (``ru_maxrss``) is read at the end.

Epochs are shortened to ``--steps-per-epoch`` (default 1,000) and the learners start after
``steps_per_epoch / 2`` transitions (HIRO's high level after 100, its TD3 batch size), so the
timed epochs run every gradient step; everything else is the default
config (buffer sizes, networks), so memory is the real runs'. A size is not started when its
predicted need (state bytes from ``jax.eval_shape`` x ``--memory-factor``) exceeds
``--max-memory-gb`` (default: half the memory available at the start, since other jobs share
the machine); larger sizes of that algorithm are then skipped too.

``--device-counts 1 2 4`` also runs 8 seeds of every algorithm on 1, 2 and 4 devices (forced
CPU devices on a CPU: ``--xla_force_host_platform_device_count``), every count with
``batch_invariant=True``, and records the speed and whether the metrics are bitwise those of
the 1-device run; on a CPU the forced devices share the same cores, so this checks
correctness, not speedup.

Usage::

    python benchmarks/scaling.py                                # 1 20 128 512 1024 seeds
    python benchmarks/scaling.py --seeds 1 20 --algorithms handcrafted --device-counts
    # on a GPU machine (all its devices; larger counts, the real epoch length):
    python benchmarks/scaling.py --devices all --seeds 1 20 128 512 1024 4096 \\
        --steps-per-epoch 3000 --device-counts 1 2 4 8 --max-memory-gb 70

Prints a markdown table and writes ``benchmarks/results/scaling.json``. ``--dry-run`` checks
the arguments, prints the sizes it would run and those the memory rule would skip (state bytes
from shapes only) and exits without running or writing anything.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

RESULTS = Path(__file__).resolve().parent / "results" / "scaling.json"
ALGORITHMS = ("handcrafted", "gara", "hiro")
DEFAULT_STEPS = {"handcrafted": 1000, "gara": 1000, "hiro": 1000}


def make_config(name: str, steps_per_epoch: int):
    """The default config of ``name`` with shorter epochs and learning from half an epoch."""
    import dataclasses

    from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig

    base = {"handcrafted": HandcraftedConfig, "gara": GaraConfig, "hiro": HiroConfig}[name]()
    starts = max(1, steps_per_epoch // 2)
    low = dataclasses.replace(base.low, learning_starts=min(base.low.learning_starts, starts))
    changes = {"steps_per_epoch": steps_per_epoch, "low": low}
    if name == "hiro":  # the high level stores one transition per k steps
        high_starts = max(base.high.batch_size, min(base.high.learning_starts, starts // base.k))
        changes["high"] = dataclasses.replace(base.high, learning_starts=high_starts)
    return dataclasses.replace(base, **changes)


def state_bytes(tree) -> int:
    import jax

    return int(sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(tree)))


def predicted_state_bytes(name: str, steps_per_epoch: int, n_seeds: int) -> int:
    """Bytes of ``n_seeds`` agent states, from shapes only (nothing allocated)."""
    import jax

    from gara_jax.algorithms import make_algorithm

    alg = make_algorithm(make_config(name, steps_per_epoch))
    return state_bytes(jax.eval_shape(alg.init, jax.random.key(0))) * n_seeds


def peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def measure(name: str, n_seeds: int, steps_per_epoch: int, epochs: int, devices) -> dict:
    """One size, in this process (see the module docstring)."""
    import jax

    from gara_jax import train as tr

    config = make_config(name, steps_per_epoch)
    devices = None if devices == "all" else int(devices)
    comp = tr.compiled(config, devices)
    n_dev = comp.mesh.devices.size
    t0 = time.perf_counter()
    loop = jax.block_until_ready(tr.init_loop(config, n_seeds, devices=comp.mesh))
    init_s = time.perf_counter() - t0
    total_bytes = state_bytes(loop.states)
    states, keys = loop.states, loop.keys
    # Compile: the first call (on every device) compiles; time it apart from a warm epoch.
    t0 = time.perf_counter()
    states, _ = jax.block_until_ready(comp.run(states, keys, 0))
    first_epoch_s = time.perf_counter() - t0
    times = []
    for e in range(epochs):
        t0 = time.perf_counter()
        states, metrics = jax.block_until_ready(comp.run(states, keys, 1 + e))
        times.append(time.perf_counter() - t0)
    row = {
        "algorithm": name, "n_seeds": n_seeds, "devices": n_dev,
        "device_kind": str(comp.mesh.devices.flat[0].device_kind),
        "steps_per_epoch": steps_per_epoch, "timed_epochs": epochs,
        "init_s": init_s,
        # The first epoch's call compiles (once per device) and runs one epoch (with fewer
        # gradient steps: the buffers fill first), so compilation is at most the difference.
        "first_epoch_s": first_epoch_s, "compile_s": max(0.0, first_epoch_s - min(times)),
        "epoch_s": times, "epoch_s_min": min(times),
        "agent_steps_per_s": n_seeds * steps_per_epoch / min(times),
        "state_bytes": total_bytes, "state_bytes_per_seed": total_bytes / n_seeds,
    }
    if comp.alg.host_update is not None:
        t0 = time.perf_counter()
        states, info = comp.alg.host_update(states, 1 + epochs)
        jax.block_until_ready(states)
        row["host_step_s"] = time.perf_counter() - t0
        row["host_step_triggered"] = int(info["triggered"])
    row["peak_rss_bytes"] = peak_rss_bytes()
    row["peak_rss_bytes_per_seed"] = row["peak_rss_bytes"] / n_seeds
    row["low_loss_finite"] = bool(jax.numpy.isfinite(metrics["low_loss"]).all()) \
        if "low_loss" in metrics else None
    return row


def device_check(names, n_seeds: int, steps_per_epoch: dict, device_counts) -> list:
    """In this process (with enough devices): ``n_seeds`` seeds of each algorithm for two
    epochs on each device count; speed, and metrics bitwise equal to the 1-device run."""
    import jax
    import numpy as np

    from gara_jax import train as tr

    rows = []
    for name in names:
        config = make_config(name, steps_per_epoch[name])
        reference = None
        for n_dev in device_counts:
            t0 = time.perf_counter()
            res = tr.train_many(config, n_seeds, 2 * config.steps_per_epoch, devices=n_dev,
                                batch_invariant=True)
            wall = time.perf_counter() - t0
            leaves = [np.asarray(x) for x in jax.tree.leaves(jax.device_get(res.final.states))]
            if reference is None:
                reference = (res.metrics, leaves)
            same_metrics = all(np.array_equal(reference[0][k], res.metrics[k])
                               for k in res.metrics)
            same_states = all(np.array_equal(a, b) for a, b in zip(reference[1], leaves,
                                                                    strict=True))
            layout = jax.tree.leaves(res.final.states)[0].sharding
            rows.append({"algorithm": name, "n_seeds": n_seeds, "devices": n_dev,
                         "wall_s_two_epochs": wall,
                         "second_epoch_agent_steps_per_s": n_seeds * config.steps_per_epoch /
                         float(np.diff([0.0, res.first_epoch_s, res.wall_time_s])[-1]),
                         "bitwise_equal_to_1_device": bool(same_metrics and same_states),
                         "final_state_devices": len(layout.device_set)})
            print(f"devices {n_dev}: {name} {n_seeds} seeds, {wall:.1f} s, equal to 1 device: "
                  f"{rows[-1]['bitwise_equal_to_1_device']}", flush=True)
    return rows


def _worker(argv) -> int:
    job = json.loads(argv[0])
    if job["kind"] == "size":
        row = measure(job["algorithm"], job["n_seeds"], job["steps_per_epoch"], job["epochs"],
                      job["devices"])
        print("RESULT " + json.dumps(row), flush=True)
    else:
        rows = device_check(job["algorithms"], job["n_seeds"], job["steps_per_epoch"],
                            job["device_counts"])
        print("RESULT " + json.dumps(rows), flush=True)
    return 0


def _run_worker(job: dict, env: dict, timeout: float):
    """Run one job in a subprocess; ``(result or None, why)``."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(job)]
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, f"timed out after {timeout:.0f} s"
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):]), "ok"
    if proc.returncode < 0:
        return None, f"killed by signal {-proc.returncode} (out of memory?)"
    return None, f"exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}"


def _env(extra_flags: str = "") -> dict:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    if extra_flags:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {extra_flags}".strip()
    return env


def available_memory_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _write(path: Path, result: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2, default=float))


def table(rows) -> str:
    lines = ["| algorithm | seeds | devices | agent steps/s | epoch (s) | compile (s) | "
             "state per seed (MB) | peak RSS (GB) | peak RSS per seed (MB) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['algorithm']} | {r['n_seeds']} | - | {r['skipped']} | | | "
                         f"{r.get('state_bytes_per_seed', 0) / 1e6:.1f} | | |")
            continue
        fmt = lambda key, spec, r=r: format(r[key], spec) if key in r else "-"  # noqa: E731
        lines.append(
            f"| {r['algorithm']} | {r['n_seeds']} | {r['devices']} | "
            f"{r['agent_steps_per_s']:,.0f} | {fmt('epoch_s_min', '.2f')} | "
            f"{fmt('compile_s', '.1f')} | "
            f"{r['state_bytes_per_seed'] / 1e6:.1f} | {r['peak_rss_bytes'] / 1e9:.2f} | "
            f"{r['peak_rss_bytes_per_seed'] / 1e6:.1f} |")
    return "\n".join(lines)


def dry_run(args, steps: dict, limit: float) -> dict:
    """``--dry-run``: the sizes :func:`main` would run and skip, from shapes only."""
    plan = {"run": [], "skipped": [], "device_check": None, "out": str(args.out)}
    for name in args.algorithms:
        per_seed = predicted_state_bytes(name, steps[name], 1)
        for n in sorted(args.seeds):
            need = per_seed * n * args.memory_factor
            (plan["skipped"] if need > limit or any(
                s[0] == name for s in plan["skipped"]) else plan["run"]).append((name, n))
    if args.device_counts is not None:
        plan["device_check"] = {"n_seeds": 8, "device_counts": args.device_counts or [1, 2, 4]}
    print(f"scaling --dry-run (nothing run or written): memory limit {limit / 1e9:.1f} GB, "
          f"--devices {args.devices}, steps per epoch {steps}, {args.epochs} timed epoch(s)")
    print("  would run: " + ", ".join(f"{a} {n}" for a, n in plan["run"]))
    print("  would skip (memory): " + (", ".join(f"{a} {n}" for a, n in plan["skipped"])
                                        or "none"))
    if plan["device_check"]:
        print(f"  device check: 8 seeds on {plan['device_check']['device_counts']} devices")
    print(f"  would write {args.out}")
    return plan


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        return _worker(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS),
                        choices=ALGORITHMS)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 20, 128, 512, 1024])
    parser.add_argument("--steps-per-epoch", type=int, default=None,
                        help="environment steps per epoch (default 1000)")
    parser.add_argument("--epochs", type=int, default=1, help="timed epochs per size")
    parser.add_argument("--devices", default="1", help="devices per size: a count or 'all'")
    parser.add_argument("--max-memory-gb", type=float, default=None,
                        help="skip sizes predicted to need more (default: half of the "
                             "memory available at the start)")
    parser.add_argument("--memory-factor", type=float, default=1.5,
                        help="predicted need = state bytes x this")
    parser.add_argument("--timeout-s", type=float, default=900.0, help="per size")
    parser.add_argument("--device-counts", type=int, nargs="*", default=None,
                        help="also check 8 seeds on these device counts (forced CPU devices "
                             "on a CPU); with no value: 1 2 4")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of the existing JSON that this run does not measure")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--dry-run", action="store_true",
                        help="print the sizes that would run or be skipped and exit")
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    if args.devices != "all" and not (args.devices.isdigit() and int(args.devices) >= 1):
        parser.error(f"--devices: a count >= 1 or 'all', got {args.devices!r}")
    if any(n < 1 for n in [*args.seeds, *(args.device_counts or [])]) or args.epochs < 1 or (
            args.steps_per_epoch is not None and args.steps_per_epoch < 1):
        parser.error("--seeds, --device-counts, --epochs, --steps-per-epoch: must be >= 1")

    from _common import load_average, machine_info

    steps = {n: args.steps_per_epoch or DEFAULT_STEPS[n] for n in args.algorithms}
    available = available_memory_bytes()
    limit = (args.max_memory_gb * 1e9 if args.max_memory_gb is not None
             else (available or 16e9) / 2)
    if args.dry_run:
        return dry_run(args, steps, limit)
    result = {"machine": machine_info(), "memory_available_bytes_at_start": available,
              "memory_limit_bytes": limit, "memory_factor": args.memory_factor,
              "steps_per_epoch": steps, "rows": [], "device_check": None}
    print(f"memory available {available / 1e9 if available else float('nan'):.1f} GB, "
          f"limit {limit / 1e9:.1f} GB, load {load_average()}", flush=True)
    for name in args.algorithms:
        too_big = False
        for n in sorted(args.seeds):
            need = predicted_state_bytes(name, steps[name], n)
            if too_big or need * args.memory_factor > limit:
                too_big = True
                result["rows"].append({
                    "algorithm": name, "n_seeds": n, "state_bytes_per_seed": need / n,
                    "skipped": f"needs ~{need * args.memory_factor / 1e9:.1f} GB "
                               f"(> {limit / 1e9:.1f})"})
                print(f"{name:12s} seeds={n:5d}  skipped: {result['rows'][-1]['skipped']}")
                continue
            job = {"kind": "size", "algorithm": name, "n_seeds": n,
                   "steps_per_epoch": steps[name], "epochs": args.epochs,
                   "devices": args.devices}
            row, why = _run_worker(job, _env(), args.timeout_s)
            if row is None:
                too_big = True
                row = {"algorithm": name, "n_seeds": n, "state_bytes_per_seed": need / n,
                       "skipped": why}
            row["load_average"] = os.getloadavg()
            result["rows"].append(row)
            _write(args.out.with_suffix(".partial.json"), result)  # survives a later crash
            print(f"{name:12s} seeds={n:5d}  " + (
                f"{row['agent_steps_per_s']:10,.0f} steps/s  peak RSS "
                f"{row['peak_rss_bytes'] / 1e9:.2f} GB  load {row['load_average'][0]:.1f}"
                if "skipped" not in row else row["skipped"]), flush=True)
    if args.device_counts is not None:
        counts = args.device_counts or [1, 2, 4]
        job = {"kind": "devices", "algorithms": args.algorithms, "n_seeds": 8,
               "steps_per_epoch": steps, "device_counts": counts}
        flags = (f"--xla_force_host_platform_device_count={max(counts)}"
                 if args.devices != "all" else "")
        rows, why = _run_worker(job, _env(flags), args.timeout_s * 2)
        result["device_check"] = rows if rows is not None else {"failed": why}
    result["load_average_end"] = os.getloadavg()
    if args.merge and args.out.exists():
        old = json.loads(args.out.read_text())
        measured = {(r["algorithm"], r["n_seeds"]) for r in result["rows"]}
        kept = [r for r in old["rows"] if (r["algorithm"], r["n_seeds"]) not in measured]
        result["rows"] = sorted(kept + result["rows"], key=lambda r: (
            ALGORITHMS.index(r["algorithm"]), r["n_seeds"]))
        if result["device_check"] is None:
            result["device_check"] = old.get("device_check")
        result["earlier_runs"] = old.get("earlier_runs", []) + [
            {k: old.get(k) for k in ("memory_available_bytes_at_start", "memory_limit_bytes",
                                     "load_average_end")}]
    print()
    print(table(result["rows"]))
    if isinstance(result["device_check"], list):
        print("\n| algorithm | seeds | devices | 2 epochs wall (s) | bitwise = 1 device |")
        print("|---|---:|---:|---:|---|")
        for r in result["device_check"]:
            print(f"| {r['algorithm']} | {r['n_seeds']} | {r['devices']} | "
                  f"{r['wall_s_two_epochs']:.1f} | {r['bitwise_equal_to_1_device']} |")
    _write(args.out, result)
    args.out.with_suffix(".partial.json").unlink(missing_ok=True)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
