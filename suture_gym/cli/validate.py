"""Validate the simulator against analytic references.

Usage::

    suture-gym validate            # table on stdout
    suture-gym validate --json     # list of {name, measured, reference, tolerance, passed, ...}
    suture-gym validate --only hanging_bar cantilever
    suture-gym validate --list

Exits with status 1 if any selected check fails, 2 on a bad argument.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from tqdm import tqdm

from suture_gym.measure import CHECKS, load_all


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="suture-gym validate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run only these checks")
    parser.add_argument("--list", action="store_true", help="list the registered checks and exit")
    args = parser.parse_args(argv)

    load_all()
    if args.list:
        print("\n".join(CHECKS))
        return 0
    names = args.only or list(CHECKS)
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        parser.error(f"unknown check(s) {unknown}; known: {sorted(CHECKS)}")

    results = []
    bar = tqdm(names, desc="validate", unit="check", file=sys.stderr, disable=None)
    for name in bar:
        bar.set_postfix_str(name)
        t0 = time.perf_counter()
        result = CHECKS[name]().to_dict()
        result["wall_s"] = round(time.perf_counter() - t0, 2)
        results.append(result)

    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(f"{'check':28s} {'measured':>12s} {'reference':>12s} {'tolerance':>10s}  unit  result")
        for r in results:
            verdict = "PASS" if r["passed"] else "FAIL"
            print(
                f"{r['name']:28s} {r['measured']:12.5g} {r['reference']:12.5g} {r['tolerance']:10.3g}"
                f"  {r['unit']:4s}  {verdict}"
            )
    return 0 if all(r["passed"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
