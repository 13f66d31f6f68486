"""Benchmark the simulator (and, once they exist, the environments) on one CPU core.

Usage::

    suture-gym bench            # table on stdout
    suture-gym bench --json     # list of {scene, tets, particles, strand_nodes, substep_ms, ...}
    suture-gym bench --only paper_cube_tissue
    suture-gym bench --json --only vector_env cold_start   # parallel vector env; compile time from scratch

Times are medians over repeated substeps after a warm-up (numba compilation excluded). Every entry gains
``realtime_factor``, simulated seconds per wall-clock second (see :func:`realtime_factor`).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys

from tqdm import tqdm

from suture_gym.measure import BENCHMARKS, load_all


def realtime_factor(entry: dict) -> float | None:
    """Simulated seconds per wall-clock second of a benchmark entry (what an interactive or haptic user needs
    to be >= 1): ``env_steps_per_s * substeps_per_env_step * dt_s`` for an environment, ``dt_s / substep``
    (s) for a simulator scene; None for entries that simulate no time (renderer, collision queries) or do not
    state their substep (``dt_s``)."""
    if "dt_s" not in entry:
        return None
    if "env_steps_per_s" in entry and "substeps_per_env_step" in entry:
        return float(entry["env_steps_per_s"] * entry["substeps_per_env_step"] * entry["dt_s"])
    if "env_steps_per_s" not in entry and entry.get("substep_ms", 0.0) > 0.0:
        return float(entry["dt_s"] / (entry["substep_ms"] * 1e-3))
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="suture-gym bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run only these benchmarks")
    parser.add_argument("--list", action="store_true", help="list the registered benchmarks and exit")
    args = parser.parse_args(argv)

    load_all()
    if args.list:
        print("\n".join(BENCHMARKS))
        return 0
    names = args.only or list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; known: {sorted(BENCHMARKS)}")

    results = []
    bar = tqdm(names, desc="bench", unit="bench", file=sys.stderr, disable=None)
    for name in bar:
        bar.set_postfix_str(name)
        entry = {"scene": name, **BENCHMARKS[name]()}
        entry["realtime_factor"] = realtime_factor(entry)
        entry.setdefault("machine", f"{platform.processor() or platform.machine()}, 1 thread")
        results.append(entry)

    if args.json:
        print(json.dumps(results, indent=2))
    else:
        for r in results:
            fields = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items())
            print(fields)
    return 0


if __name__ == "__main__":
    sys.exit(main())
