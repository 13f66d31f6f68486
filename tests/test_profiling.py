"""The perf map that names numba's compiled code for ``scripts/perf_profile.py``."""

import os
import subprocess
import sys

from suture_gym.measure.profiling import name_at, readable_name, sample_stack_tops

_CHILD = """
import sys
import numpy as np
from suture_gym.sim.quat import quat_mul
from suture_gym.measure.profiling import write_perf_map
quat_mul(np.ones(4), np.ones(4))
compiled = quat_mul.overloads[quat_mul.signatures[0]]
entry = compiled.library.get_pointer_to_function(compiled.fndesc.mangled_name)
path, count = write_perf_map(sys.argv[1])
print(entry, count)
"""


def test_readable_name_unmangles_numba_names_and_keeps_others():
    assert readable_name("_ZN10suture_gym3sim4quat8quat_mulB3v52B38c8tJTIeFIjxB2IKSgI4CrvQ") == (
        "suture_gym.sim.quat.quat_mul"
    )
    assert readable_name("NRT_incref") == "NRT_incref"


def test_perf_map_names_a_kernel_compiled_in_the_process(tmp_path):
    """In a fresh interpreter with an empty numba cache: the map lists the compiled quat_mul at its entry point, in
    ascending address order, each line ``<hex start> <hex size> <name>``."""
    out = tmp_path / "perf.map"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-c", _CHILD, str(out)], env=env, capture_output=True, text=True,
                          timeout=300, check=True)  # fmt: skip
    entry, count = (int(v) for v in done.stdout.split())
    lines = out.read_text().splitlines()
    assert len(lines) == count > 0
    starts = [int(line.split()[0], 16) for line in lines]
    assert starts == sorted(starts)
    named = {int(line.split()[0], 16): line.split(maxsplit=2)[2] for line in lines}
    assert named[entry] == "suture_gym.sim.quat.quat_mul in quat.quat_mul"
    assert all(int(line.split()[1], 16) > 0 for line in lines)


def test_no_script_shadows_a_standard_library_module():
    """A script runs with ``scripts/`` first on ``sys.path``: a ``scripts/profile.py`` once replaced the standard
    ``profile`` module for every script, and torch's ``import cProfile`` broke training."""
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[1] / "scripts"
    clashes = sorted(p.stem for p in scripts.glob("*.py") if p.stem in sys.stdlib_module_names)
    assert clashes == []


def _dump_sample(ip: int, stack_top: int, stack_offset: int = 0xE0) -> str:
    """One sample as ``perf report -D`` prints it: the raw event in hex rows of 16 bytes (the stack copy's 8-byte
    size at ``stack_offset``, then the copy), then the decoded header line and the stack copy's place."""
    raw = bytes(stack_offset) + (64).to_bytes(8, "little") + stack_top.to_bytes(8, "little") + bytes(56)
    rows = []
    for start in range(0, len(raw), 16):
        chunk = raw[start : start + 16]
        hexes = "".join(f"{b:02x} " for b in chunk)
        rows.append(f".  {start:04x}:  {hexes:<48} {'.' * len(chunk)}")
    return "\n".join(
        [f"0x2c220@/tmp/perf.data [0x{len(raw):x}]: event: 9", ".", f". ... raw event: size {len(raw)} bytes", *rows,
         "", f"77345580688805 0x2c220 [0x138]: PERF_RECORD_SAMPLE(IP, 0x2): 30685/30685: 0x{ip:x} period: 1 addr: 0",
         "... FP chain: nr:0", f"... ustack: size 64, offset 0x{stack_offset:x}", " ... thread: python:30685", ""]
    )  # fmt: skip


def test_stack_tops_read_the_word_at_the_stack_pointer_and_name_its_caller():
    """Two samples in a leaf and one elsewhere: each sample's first stack word is read past the copy's size field,
    and :func:`name_at` places it in the function that holds it (none past the last function's end)."""
    dump = "\n".join(
        [_dump_sample(0x7000, 0x1010), _dump_sample(0x7004, 0x2008, stack_offset=0xF0), _dump_sample(0x1020, 0x9)]
    )
    dump += "\n0x2c358@/tmp/perf.data [0x10]: event: 3\n. ... raw event: size 16 bytes\n"  # a record without a stack
    tops = sample_stack_tops(dump)
    assert tops == [(0x7000, 0x1010), (0x7004, 0x2008), (0x1020, 0x9)]
    entries = [(0x1000, "kernel_a"), (0x2000, "kernel_b"), (0x7000, "NRT_incref")]
    assert [name_at(entries, word) for ip, word in tops if name_at(entries, ip) == "NRT_incref"] == [
        "kernel_a",
        "kernel_b",
    ]
    assert name_at(entries, 0x9) is None
    assert name_at(entries, 0x7000 + 4096) is None
