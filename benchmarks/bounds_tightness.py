"""How tight IBP, CROWN and zonotope bounds are on the golden networks (not a timing).

Zonotopes with either ReLU transformer of :func:`gara_jax.reach.zonotope`: ``zonotope``
(DeepZ's) and ``zonotope_box`` (an unstable neuron replaced by its interval).

For each network of ``tests/data/bounds_reference.npz`` (the verification library's golden
cases, SPEC.md 5) and its input boxes, in float64: the median output width of each method, and
the fraction of outputs where the zonotope box is narrower than IBP's and than CROWN's. The
analysis of :func:`gara_jax.reach.refine` reads these widths: a looser box leaves more boxes
undecided, so more of them are bisected.

Usage (from the repository root):
    python benchmarks/bounds_tightness.py [--out benchmarks/results/bounds_tightness.json]
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import jax
import numpy as np

from gara_jax.reach import crown, ibp, zonotope

sys.path.insert(0, str(Path(__file__).resolve().parent))  # run as a script or loaded by path
from _common import machine_info, write_result  # noqa: E402

GOLDEN = Path(__file__).resolve().parents[1] / "tests" / "data" / "bounds_reference.npz"
METHODS = {"ibp": ibp, "crown": crown, "zonotope": zonotope,
           "zonotope_box": functools.partial(zonotope, relu="box")}


def tightness(path=GOLDEN) -> list[dict]:
    """One row per golden network: median widths per method and the zonotope's win rates."""
    data = np.load(path)
    rows = []
    with jax.enable_x64(True):
        for i in range(int(data["n_nets"])):
            arch = [int(a) for a in data[f"net{i}_arch"]]
            layers = [(data[f"net{i}_W{k}"], data[f"net{i}_b{k}"]) for k in range(len(arch) - 1)]
            lo, hi = data[f"net{i}_lo"], data[f"net{i}_hi"]
            width = {}
            for name, fn in METHODS.items():
                out_lo, out_hi = fn(layers, lo, hi)
                width[name] = np.asarray(out_hi - out_lo)
            rows.append({
                "net": "-".join(map(str, arch)), "boxes": int(lo.shape[0]),
                **{f"median_width_{m}": float(np.median(w)) for m, w in width.items()},
                "zonotope_narrower_than_ibp": float(
                    (width["zonotope"] < width["ibp"] - 1e-12).mean()),
                "zonotope_narrower_than_crown": float(
                    (width["zonotope"] < width["crown"] - 1e-12).mean()),
            })
    return rows


def table(rows) -> str:
    lines = ["| net | boxes | median width IBP | CROWN | zonotope | zonotope_box | zonotope "
             "narrower than IBP | than CROWN |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['net']} | {r['boxes']} | {r['median_width_ibp']:.3g} | "
                     f"{r['median_width_crown']:.3g} | {r['median_width_zonotope']:.3g} | "
                     f"{r['median_width_zonotope_box']:.3g} | "
                     f"{r['zonotope_narrower_than_ibp']:.0%} | "
                     f"{r['zonotope_narrower_than_crown']:.0%} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/bounds_tightness.json"))
    args = p.parse_args(argv)
    rows = tightness()
    print(table(rows))
    write_result(args.out, {"benchmark": "bounds_tightness", "machine": machine_info(),
                            "results": rows, "table": table(rows)})
    return rows


if __name__ == "__main__":
    main()
