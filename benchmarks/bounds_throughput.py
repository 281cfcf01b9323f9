"""Bound throughput (IBP, CROWN, zonotopes) on forward-model-shaped MLPs, and the wall time of refinements.

Throughput rows: boxes per second of ``gara_jax.reach.ibp`` / ``crown`` / ``zonotope`` (the public functions,
``validate=False``, float32) on MLPs 12-8-8-4 and 12-32-32-4 with Glorot weights and random
input boxes (every dimension has width), for each batch size. Compilation is timed apart
(``lower().compile()`` of the jitted core); then one warm-up call, then ``--repeats`` rounds of
calls, each call followed by ``block_until_ready``; the best and the median round are reported,
with the process CPU time per call (on a loaded machine wall time rises, CPU time much less)
and the process's voluntary context switches per call (a thread waiting for another).

``--dispatch sync`` turns JAX's asynchronous CPU dispatch off
(``jax_cpu_enable_async_dispatch=False``, set before the backend starts): the call then runs
on the calling thread instead of being handed to a worker thread and waited for.
``--callers N`` runs the timed loop in N Python threads at once (the rows then give the
aggregate boxes/s of the process): one call uses one core, so this shows what a second
concurrent caller (e.g. a second refinement) adds on a multi-core CPU.

Refinement rows: wall time of ``refine`` (one job) and ``refine_many`` (``--jobs`` jobs in one
call) on (a) a hand-set forward model (``F(s, G) = s + (1, 0, 0, 0)`` through ReLUs) and (b) a
forward model 12-8-8-4 quickly trained on synthetic k-step U-maze-like transitions; from the
first GARA goal ``[0,1]x[0,3]`` towards the second ``[1,3]x[0,3]`` (for (a): ``[1.5,3]x[0,3]``,
so that the start box splits), full velocity ranges; the ``--jobs`` jobs slide the target along
x. "first" includes compiling, "warm" is the best of ``--repeats`` later calls.

Floor rows: what a jitted call costs before any layer, for each batch: a jitted function that
takes IBP's two ``[B, 12]`` inputs and returns their sum and difference (IBP's own first step),
next to the same two operations in NumPy, with the context switches per jitted call: from some
size on XLA splits such a loop over the CPU's threads, and on a VM the hand-offs can cost more
than the arithmetic (``ibp`` works on chunks of boxes and avoids the split at batch 4096).

Usage (from the repository root, with the package installed or ``PYTHONPATH=.``):
    python benchmarks/bounds_throughput.py                          # full run
    python benchmarks/bounds_throughput.py --batches 64 4096 --repeats 3   # quick
    python benchmarks/bounds_throughput.py --dispatch sync --no-refine \
        --out benchmarks/results/bounds_throughput_sync.json
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from gara_jax.networks import MLP, mlp_layers
from gara_jax.partition import gara_initial
from gara_jax.reach import crown, ibp, refine, refine_many, zonotope
from gara_jax.reach.crown import _crown_jit
from gara_jax.reach.ibp import _ibp_jit
from gara_jax.reach.zonotope import _zonotope_jit

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script or loaded by path
from _common import load_average, machine_info, write_result  # noqa: E402

ARCHS = {"12-8-8-4": (8, 8), "12-32-32-4": (32, 32)}
METHODS = {"ibp": (ibp, _ibp_jit), "crown": (crown, _crown_jit),
           "zonotope": (zonotope, _zonotope_jit)}


def random_layers(hidden, seed):
    params = MLP(hidden=hidden, out=4).init(jax.random.key(seed), jnp.zeros(12))
    return tuple((jnp.asarray(w), jnp.asarray(b)) for w, b in mlp_layers(params))


def random_boxes(batch, seed):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1, 3, size=(batch, 12)).astype(np.float32)
    radius = rng.uniform(0, 0.5, size=(batch, 12)).astype(np.float32)
    return jnp.asarray(centre - radius), jnp.asarray(centre + radius)


def time_rounds(fn, calls: int, repeats: int, callers: int = 1):
    """Per call, for each round of ``calls`` blocked calls in each of ``callers`` threads:
    wall seconds, process CPU seconds, and the round's voluntary context switches."""

    def loop(_):
        for _ in range(calls):
            jax.block_until_ready(fn())

    wall, cpu, switches = [], [], []
    with ThreadPoolExecutor(callers) as pool:
        for _ in range(repeats):
            s0 = resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw
            w0, c0 = time.perf_counter(), time.process_time()
            if callers == 1:
                loop(0)
            else:
                list(pool.map(loop, range(callers)))
            n = calls * callers
            wall.append((time.perf_counter() - w0) / n)
            cpu.append((time.process_time() - c0) / n)
            switches.append((resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw - s0) / n)
    return wall, cpu, switches


def bench_bounds(arch: str, method: str, batch: int, repeats: int, seed: int,
                 callers: int = 1) -> dict:
    layers = random_layers(ARCHS[arch], seed)
    lo, hi = random_boxes(batch, seed + 1)
    public, core = METHODS[method]
    start = time.perf_counter()
    core.lower(layers, lo, hi).compile()
    compile_s = time.perf_counter() - start
    fn = lambda: public(layers, lo, hi, validate=False)  # noqa: E731
    jax.block_until_ready(fn())  # warm-up (and the jit cache's own compile)
    calls = max(1, min(200, int(2e5 // batch)))
    wall, cpu, switches = time_rounds(fn, calls, repeats, callers)
    return {
        "arch": arch, "method": method, "batch": batch, "compile_s": compile_s,
        "callers": callers, "calls_per_round": calls, "wall_s_per_call": wall,
        "cpu_s_per_call": cpu, "context_switches_per_call": statistics.median(switches),
        "boxes_per_s_best": batch / min(wall),
        "boxes_per_s_median": batch / statistics.median(wall),
        "boxes_per_cpu_s_best": batch / min(cpu),
    }


def bench_floor(batch: int, repeats: int, seed: int) -> dict:
    """Seconds per call of IBP's first step alone, jitted XLA against NumPy (see docstring)."""
    lo, hi = random_boxes(batch, seed + 1)
    first_step = jax.jit(lambda lo, hi: (lo + hi, hi - lo))
    lo_np, hi_np = np.asarray(lo), np.asarray(hi)
    calls = max(1, min(500, int(5e5 // batch)))
    jax.block_until_ready(first_step(lo, hi))
    xla, _, switches = time_rounds(lambda: first_step(lo, hi), calls, repeats)
    numpy, _, _ = time_rounds(lambda: (lo_np + hi_np, hi_np - lo_np), calls, repeats)
    return {"batch": batch, "xla_s_per_call_best": min(xla), "numpy_s_per_call_best": min(numpy),
            "xla_ceiling_boxes_per_s": batch / min(xla),
            "xla_context_switches_per_call": statistics.median(switches)}


def translation_model():
    """``F(s, G) = s + (1, 0, 0, 0)`` exactly, as relu(s) - relu(-s) + shift."""
    eye = np.eye(4, 12)
    return [(np.concatenate([eye, -eye], 0).T.astype(np.float32), np.zeros(8, np.float32)),
            (np.concatenate([np.eye(4), -np.eye(4)], 0).astype(np.float32),
             np.array([1.0, 0, 0, 0], np.float32))]


def trained_model(seed: int, steps: int = 300):
    """A 12-8-8-4 forward model fitted for a few hundred Adam steps to synthetic k-step
    transitions: position moves by 5 velocities (clipped to the maze), velocity decays."""
    rng = np.random.default_rng(seed)
    s = rng.uniform([0, 0, -1, -1], [3, 3, 1, 1], size=(4096, 4)).astype(np.float32)
    goal_lo = rng.uniform([0, 0, -1, -1], [2, 2, 0, 0], size=(4096, 4)).astype(np.float32)
    goal = np.concatenate([goal_lo, goal_lo + 1.0], 1)
    nxt = np.concatenate([np.clip(s[:, :2] + 0.5 * s[:, 2:], 0, 3), 0.5 * s[:, 2:]], 1)
    x, y = jnp.asarray(np.concatenate([s, goal], 1)), jnp.asarray(nxt)
    net = MLP(hidden=(8, 8), out=4)
    params = net.init(jax.random.key(seed), x[:1])
    opt = optax.adam(0.005)

    @jax.jit
    def step(params, state):
        loss, grads = jax.value_and_grad(lambda p: jnp.mean((net.apply(p, x) - y) ** 2))(params)
        updates, state = opt.update(grads, state)
        return optax.apply_updates(params, updates), state, loss

    state = opt.init(params)
    for _ in range(steps):
        params, state, loss = step(params, state)
    return params, float(loss)


def first_and_warm(fn, repeats: int):
    """``fn()``'s result, the first call's seconds (compiling) and ``repeats`` later calls'."""
    start = time.perf_counter()
    result = fn()
    first = time.perf_counter() - start
    warm = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        warm.append(time.perf_counter() - start)
    return result, first, warm


def bench_refine(name: str, model, method: str, jobs: int, repeats: int,
                 target_x_lo: float = 1.0) -> list[dict]:
    lo, hi = (np.array(a) for a in gara_initial().boxes())
    lo[1, 0] = target_x_lo
    args = (lo[0], hi[0], lo[1], hi[1])
    rows = []
    res, first, warm = first_and_warm(lambda: refine(model, *args, method=method), repeats)
    rows.append({
        "model": name, "method": method, "jobs": 1, "first_call_s": first, "warm_s": warm,
        "n_analysed": res.n_analysed, "depth": res.depth,
        "pieces": [len(res.reaching_lo), len(res.nonreaching_lo)]})
    layers = model if isinstance(model, list) else mlp_layers(model)
    stacked = [(jnp.stack([jnp.asarray(w)] * jobs), jnp.stack([jnp.asarray(b)] * jobs))
               for w, b in layers]
    # Different targets per job: the target box slides along x.
    shift = np.linspace(0, 1, jobs)[:, None] * np.array([1.0, 0, 0, 0])
    many = (np.repeat(lo[:1], jobs, 0), np.repeat(hi[:1], jobs, 0),
            np.repeat(lo[1:], jobs, 0) - shift, np.repeat(hi[1:], jobs, 0) - shift)
    results, first, warm = first_and_warm(
        lambda: refine_many(stacked, *many, method=method), repeats)
    rows.append({
        "model": name, "method": method, "jobs": jobs, "first_call_s": first, "warm_s": warm,
        "n_analysed": sum(r.n_analysed for r in results), "depth": max(r.depth for r in results),
        "pieces": [sum(len(r.reaching_lo) for r in results),
                   sum(len(r.nonreaching_lo) for r in results)]})
    return rows


def bounds_table(rows: list[dict]) -> str:
    lines = ["| net | method | batch | compile (s) | boxes/s (best) | boxes/s (median) "
             "| boxes per CPU-s | context switches per call |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['arch']} | {r['method']} | {r['batch']} | {r['compile_s']:.2f} "
            f"| {r['boxes_per_s_best']:.3g} | {r['boxes_per_s_median']:.3g} "
            f"| {r['boxes_per_cpu_s_best']:.3g} | {r['context_switches_per_call']:.1f} |")
    return "\n".join(lines)


def refine_table(rows: list[dict]) -> str:
    lines = ["| model | method | jobs | first call (s) | warm (s, best) | boxes analysed "
             "| depth | pieces (reach/miss) |", "|---|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(
            f"| {r['model']} | {r['method']} | {r['jobs']} | {r['first_call_s']:.2f} "
            f"| {min(r['warm_s']):.4f} | {r['n_analysed']} | {r['depth']} "
            f"| {r['pieces'][0]}/{r['pieces'][1]} |")
    return "\n".join(lines)


def set_dispatch(mode: str) -> None:
    """Choose JAX's CPU dispatch; it is read when the CPU backend starts, so this must come
    before the first computation (machine_info() starts it)."""
    asynchronous = mode == "async"
    if jax.config.values["jax_cpu_enable_async_dispatch"] == asynchronous:
        return
    from jax._src import xla_bridge  # no public way to ask whether the backend has started

    if getattr(xla_bridge, "backends_are_initialized", lambda: False)():
        raise SystemExit(f"--dispatch {mode}: JAX's CPU backend has already started in this "
                         "process; run the benchmark in a fresh process")
    jax.config.update("jax_cpu_enable_async_dispatch", asynchronous)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--archs", nargs="+", default=list(ARCHS), choices=list(ARCHS))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 4096, 65536])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=16, help="jobs in the refine_many rows")
    parser.add_argument("--no-refine", action="store_true", help="skip the refinement rows")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dispatch", choices=("async", "sync"), default="async",
                        help="JAX's CPU dispatch (async is JAX's default; see the docstring)")
    parser.add_argument("--callers", type=int, default=1,
                        help="threads running the throughput loop at once")
    parser.add_argument(
        "--out", type=Path,
        default=Path(__file__).resolve().parent / "results" / "bounds_throughput.json")
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)
    if (args.repeats < 1 or args.jobs < 1 or args.callers < 1
            or any(b < 1 for b in args.batches)):
        parser.error("--repeats, --jobs, --callers and --batches must be >= 1")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    set_dispatch(args.dispatch)
    info = machine_info()
    rows = []
    for arch in args.archs:
        for method in args.methods:
            for batch in args.batches:
                rows.append(bench_bounds(arch, method, batch, args.repeats, args.seed,
                                         args.callers))
                print(f"  {arch} {method} {batch}: {rows[-1]['boxes_per_s_best']:.3g} boxes/s",
                      file=sys.stderr, flush=True)
    floor_rows = [bench_floor(batch, args.repeats, args.seed) for batch in args.batches]
    refine_rows = []
    trained_loss = None
    if not args.no_refine:
        params, trained_loss = trained_model(args.seed)
        # The translation reaches x in [1.5, 3] from x in [0.5, 1]: a split at depth 1.
        for name, model, x_lo in (("hand-set translation", translation_model(), 1.5),
                                  ("trained 12-8-8-4", params, 1.0)):
            for method in args.methods:
                refine_rows += bench_refine(name, model, method, args.jobs, args.repeats, x_lo)
    info["load_average_1min_at_end"] = load_average()
    table = bounds_table(rows)
    print(f"Bound throughput (float32), {info['backend']} backend, {info['cpu_count']} CPUs, "
          f"jax {info['jax']}, {args.dispatch} dispatch, {args.callers} caller(s), "
          f"load average {info['load_average_1min_at_start']:.1f} at start")
    print(table)
    print("\nFloor: IBP's first step alone, (lo + hi, hi - lo) on [B, 12] float32")
    for r in floor_rows:
        print(f"  batch {r['batch']}: jitted {1e6 * r['xla_s_per_call_best']:.1f} us "
              f"(ceiling {r['xla_ceiling_boxes_per_s']:.3g} boxes/s, "
              f"{r['xla_context_switches_per_call']:.1f} context switches per call), "
              f"NumPy {1e6 * r['numpy_s_per_call_best']:.1f} us")
    rtable = refine_table(refine_rows) if refine_rows else ""
    if rtable:
        print(f"\nRefinement wall time (trained model's final MSE {trained_loss:.4f})")
        print(rtable)
    result = {
        "benchmark": "bounds_throughput",
        "machine": info,
        "config": {k: (os.path.relpath(v) if isinstance(v, Path) else v)
                   for k, v in vars(args).items()},
        "results": rows,
        "floor": floor_rows,
        "refine": refine_rows,
        "trained_model_mse": trained_loss,
        "table": table,
        "refine_table": rtable,
    }
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
