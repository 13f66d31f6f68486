"""The perf map that names numba's compiled code for ``scripts/perf_profile.py``."""

import os
import subprocess
import sys

from suture_gym.measure.profiling import readable_name

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
