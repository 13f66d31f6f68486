"""Memory stays flat over randomised episodes: every reset builds a new tissue (the episode's stiffness, puncture
force and wound gap), and nothing of the old ones may be kept beyond the bounded caches, including what the
sparse Cholesky factorisation of each tissue allocates outside Python."""

import ctypes
import gc
import sys

import numpy as np
import pytest

import suture_gym.sim.mesh as mesh_module
import suture_gym.sim.rest_system as rest_system
from suture_gym.envs import SutureEnv
from suture_gym.envs.simulation import CACHE_SIZE, PHASE_CACHE_SIZE, PHASE_STARTS
from suture_gym.sim.tissue_implicit import ImplicitTissue

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status, glibc")


def _live_kb() -> int:
    """Resident memory, KB, after a collection and handing glibc's free pages back (so heap fragmentation does
    not read as growth)."""
    gc.collect()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS"))


def test_randomised_episodes_keep_memory_and_caches_bounded():
    gc.collect()
    earlier = {id(o) for o in gc.get_objects() if isinstance(o, ImplicitTissue)}  # other tests' envs
    env = SutureEnv("needle_insert")
    zeros = np.zeros(6)
    for k in range(1000):
        env.reset(seed=k)
        env.sim.substep(zeros)  # the first solve with the episode's factorised tissue
        if k == 199:
            before = _live_kb()
    growth_kb = _live_kb() - before
    # 800 new tissues; each used to keep 8 bytes per dof of the factorisation's last right-hand side (6 KB here)
    assert growth_kb < 1024, f"resident memory grew {growth_kb} KB over 800 randomised episodes"
    assert len(env.sim._builds) <= CACHE_SIZE and len(PHASE_STARTS) <= PHASE_CACHE_SIZE
    assert len(rest_system._PATTERNS) <= rest_system._PATTERN_CACHE_SIZE
    assert len(mesh_module._SOUND_TOPOLOGIES) <= mesh_module.TOPOLOGY_CACHE_SIZE
    integrators = [o for o in gc.get_objects() if isinstance(o, ImplicitTissue) and id(o) not in earlier]
    assert len(integrators) <= CACHE_SIZE + 1  # the cached builds' states and the current one


def test_the_reset_memory_benchmark_reports_the_growth_of_each_id(monkeypatch):
    from suture_gym.measure import envs

    monkeypatch.setattr(envs, "MEMORY_EPISODES", 4)
    monkeypatch.setattr(envs, "MEMORY_SKIP", 2)
    monkeypatch.setattr(envs, "MEMORY_IDS", ("SutureGym/NeedleInsert-v3",))
    result = envs.bench_reset_memory()
    (entry,) = result["ids"]
    assert entry["env_id"] == "SutureGym/NeedleInsert-v3" and result["growth_mb_max"] == entry["growth_mb"]
    assert entry["kb_per_episode"] == pytest.approx(entry["growth_mb"] * 1024 / 2)


def test_releasing_the_solve_buffer_is_safe_before_and_after_solves():
    """cholespy crashes on a zero-column solve before any solve: the release is skipped then, and a zero-column
    rhs is refused by name."""
    import scipy.sparse as sp

    from suture_gym.sim.rest_system import SparseCholesky

    n = 30
    factor = SparseCholesky(sp.diags([np.full(n, 4.0), np.full(n - 1, -1.0), np.full(n - 1, -1.0)], [0, -1, 1]))
    factor.release_buffer()
    x = factor.solve(np.ones((n, 2)))
    factor.release_buffer()
    factor.release_buffer()
    np.testing.assert_allclose(factor.solve(np.ones((n, 2))), x)
    with pytest.raises(ValueError, match=r"at least one column, got shape \(30, 0\)"):
        factor.solve(np.empty((n, 0)))
