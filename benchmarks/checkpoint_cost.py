"""Checkpoint size and write time per epoch: orbax (today's format) against the previous .npz.

For each algorithm (the default configs), ``--seeds`` seeds are trained for ``--epochs``
epochs with ``train_epochs`` (so the replay buffers hold what a run of that length holds),
then the loop state is written ``--repeats`` times as an orbax checkpoint
(:func:`gara_jax.checkpoint.save`, one step replacing the previous, as ``reproduce`` does every
epoch) and as the previous single ``.npz`` file (:func:`gara_jax.checkpoint.save_npz`), and
read back once. Sizes are the bytes on disk (``du``-style, allocated blocks) and the raw bytes
of the state pytree.

Usage::

    python benchmarks/checkpoint_cost.py                      # 20 seeds, 1 epoch each
    python benchmarks/checkpoint_cost.py --algorithms handcrafted --seeds 2

Prints a markdown table and writes ``benchmarks/results/checkpoint_cost.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

RESULTS = Path(__file__).resolve().parent / "results" / "checkpoint_cost.json"


def configs() -> dict:
    from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig

    return {"handcrafted": HandcraftedConfig(), "gara": GaraConfig(), "hiro": HiroConfig()}


def disk_bytes(path: Path) -> int:
    """Allocated bytes of a file or a directory tree."""
    paths = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_blocks * 512 for p in paths)


def bench(name, config, n_seeds: int, epochs: int, repeats: int, root: Path) -> dict:
    import jax

    from gara_jax import checkpoint
    from gara_jax import train as tr

    loop = None
    t0 = time.perf_counter()
    for out in tr.train_epochs(config, n_seeds, epochs * config.steps_per_epoch):
        loop = out.loop
    train_s = time.perf_counter() - t0
    loop = loop._replace(states=jax.block_until_ready(loop.states))
    raw = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(loop.states))
    orbax_dir, npz = root / f"{name}_orbax", root / f"{name}.npz"
    orbax_s, npz_s = [], []
    for r in range(repeats):
        t0 = time.perf_counter()
        checkpoint.save(orbax_dir, loop._replace(epoch=loop.epoch + r), {"epoch": r})
        orbax_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        checkpoint.save_npz(npz, loop, {"epoch": r})
        npz_s.append(time.perf_counter() - t0)
    template = tr.init_loop(config, n_seeds)
    t0 = time.perf_counter()
    back, _ = checkpoint.load(orbax_dir, template)
    jax.block_until_ready(back.states)
    load_s = time.perf_counter() - t0
    row = {"algorithm": name, "n_seeds": n_seeds, "epochs_trained": epochs,
           "env_steps_per_seed": epochs * config.steps_per_epoch, "train_s": train_s,
           "state_raw_bytes": raw,
           "orbax_disk_bytes": disk_bytes(orbax_dir), "orbax_write_s": orbax_s,
           "orbax_write_s_median": statistics.median(orbax_s), "orbax_load_s": load_s,
           "npz_disk_bytes": disk_bytes(npz), "npz_write_s": npz_s,
           "npz_write_s_median": statistics.median(npz_s), "load_average": os.getloadavg()}
    shutil.rmtree(orbax_dir)
    npz.unlink()
    return row


def table(rows) -> str:
    lines = ["| algorithm | seeds | state (GB, raw) | orbax on disk (GB) | orbax write (s) | "
             "orbax read (s) | .npz on disk (GB) | .npz write (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['algorithm']} | {r['n_seeds']} | {r['state_raw_bytes'] / 1e9:.3f} | "
            f"{r['orbax_disk_bytes'] / 1e9:.3f} | {r['orbax_write_s_median']:.2f} | "
            f"{r['orbax_load_s']:.2f} | {r['npz_disk_bytes'] / 1e9:.3f} | "
            f"{r['npz_write_s_median']:.2f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algorithms", nargs="+", default=list(configs()))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--epochs", type=int, default=1, help="epochs trained before saving")
    parser.add_argument("--repeats", type=int, default=3, help="writes timed per format")
    parser.add_argument("--dir", type=Path, default=None,
                        help="where to write (default: a temporary directory)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    from gara_jax import compile_cache

    compile_cache.add_argument(parser)
    args = parser.parse_args(argv)
    compile_cache.setup(args.no_compile_cache)

    from _common import machine_info

    cfgs = configs()
    rows = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for name in args.algorithms:
            rows.append(bench(name, cfgs[name], args.seeds, args.epochs, args.repeats,
                              Path(tmp)))
            r = rows[-1]
            print(f"{name:12s} orbax {r['orbax_disk_bytes'] / 1e9:.3f} GB in "
                  f"{r['orbax_write_s_median']:.2f} s, npz {r['npz_disk_bytes'] / 1e9:.3f} GB "
                  f"in {r['npz_write_s_median']:.2f} s (load {r['load_average'][0]:.1f})",
                  flush=True)
    print()
    print(table(rows))
    result = {"machine": machine_info(), "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2, default=float))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
