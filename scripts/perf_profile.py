"""Profile one benchmark of ``scripts/bench.py`` with Linux ``perf``, numba's compiled functions named.

Usage::

    python scripts/perf_profile.py paper_abdominal_wall              # the 30 costliest symbols
    python scripts/perf_profile.py paper_cube --top 50 --out runs/cube.perf
    python scripts/perf_profile.py paper_cube --callers NRT_incref NRT_decref   # who calls them, and how often

The benchmark runs twice in this process: once to compile everything, then under ``perf record`` attached to the
process. A perf map (:mod:`suture_gym.measure.profiling`) then names the compiled code, so the report shows
kernels and the helpers linked into them (``suture_gym.sim.rod_linalg.factor_block in
rod_linalg.solve_block_tridiagonal``) beside numba's runtime
(``NRT_incref``, ``NRT_MemInfo_alloc_aligned``) and the interpreter. The map needs code compiled in this process,
so numba compiles into an empty temporary cache (a minute or two; ``NUMBA_CACHE_DIR`` is ignored).

``--callers`` names the callers of leaf functions such as numba's reference counting: compiled code has no unwind
tables, so perf's call graphs stop at it; the recording then keeps the top 64 bytes of the stack with each sample,
whose first word is a frameless leaf's return address (:func:`suture_gym.measure.profiling.sample_stack_tops`).

Needs ``perf`` (linux-tools) with permission to attach to one's own processes
(``/proc/sys/kernel/perf_event_paranoid`` <= 2).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile

from _common import configure

CACHE = tempfile.mkdtemp(prefix="suture_gym_profile_numba_")
os.environ["NUMBA_CACHE_DIR"] = CACHE
configure(threads=1)

from suture_gym.measure import BENCHMARKS, load_all  # noqa: E402
from suture_gym.measure.profiling import name_at, perf_map_entries, sample_stack_tops, write_perf_map  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("benchmark", help="a name of scripts/bench.py --list")
    parser.add_argument("--top", type=int, default=30, help="symbols to print (default 30)")
    parser.add_argument("--out", default=None, help="keep the perf data here (default: a temporary file)")
    parser.add_argument("--callers", nargs="+", default=None, metavar="SYMBOL",
                        help="count who calls these frameless leaf functions (NRT_incref NRT_decref)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.top < 1:
        parser.error(f"--top must be >= 1, got {args.top}")
    if shutil.which("perf") is None:
        parser.error("perf is not installed (Debian/Ubuntu: the linux-tools or linux-perf package)")
    load_all()
    if args.benchmark not in BENCHMARKS:
        parser.error(f"unknown benchmark {args.benchmark!r}; known: {sorted(BENCHMARKS)}")

    out = os.path.abspath(args.out) if args.out else os.path.join(CACHE, "perf.data")
    try:
        print(f"compiling ({args.benchmark}, first run) ...", file=sys.stderr)
        BENCHMARKS[args.benchmark]()
        stack = ["--call-graph", "dwarf,64"] if args.callers else []
        record = subprocess.Popen(["perf", "record", "-q", "-F", "2000", *stack, "-p", str(os.getpid()), "-o", out],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
        print(f"profiling ({args.benchmark}, second run) ...", file=sys.stderr)
        try:
            BENCHMARKS[args.benchmark]()
        finally:
            record.send_signal(signal.SIGINT)
            _, err = record.communicate()
        if record.returncode not in (0, -signal.SIGINT):
            print(f"perf record failed ({record.returncode}): {err.decode(errors='replace').strip()}", file=sys.stderr)
            return 1
        path, count = write_perf_map()
        kept = f"; data: {out}" if args.out else ""
        print(f"perf map: {path} ({count} functions){kept}", file=sys.stderr)
        command = ["perf", "report", "-i", out, "--stdio", "--no-children", "--sort", "symbol", "-g", "none"]
        report = subprocess.run(command, capture_output=True, text=True, check=True)
        lines = [line for line in report.stdout.splitlines() if line.strip() and not line.startswith("#")]
        print("\n".join(line.rstrip()[:160] for line in lines[: args.top]))
        if args.callers:
            _print_callers(out, set(args.callers), args.top)
    finally:  # the compiled code and, without --out, the perf data
        shutil.rmtree(CACHE, ignore_errors=True)
    return 0


def _print_callers(data: str, leaves: set[str], top: int) -> None:
    """The callers of the samples in ``leaves``, by share of all samples, from the stack tops of ``data``."""
    dump = subprocess.run(["perf", "report", "-D", "-i", data], capture_output=True, text=True, check=True).stdout
    entries = perf_map_entries()
    tops = sample_stack_tops(dump)
    counts: dict[str, int] = {}
    for ip, word in tops:
        if name_at(entries, ip) in leaves:
            caller = name_at(entries, word) or "(not compiled code: a frame, or another caller)"
            counts[caller] = counts.get(caller, 0) + 1
    total = max(len(tops), 1)
    print(f"\ncallers of {', '.join(sorted(leaves))}: {sum(counts.values()) / total:.2%} of {len(tops)} samples")
    for caller, n in sorted(counts.items(), key=lambda item: -item[1])[:top]:
        print(f"    {n / total:7.2%}  {caller[:140]}")


if __name__ == "__main__":
    sys.exit(main())
