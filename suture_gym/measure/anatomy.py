"""Benchmarks of the seed paper's anatomical scenes with the full suturing load: ``paper_abdominal_wall`` and
``paper_hand`` (paper Table 1: 38 and 21 fps with a 30-node needle and a 200-node suture).

Each builds ``SutureGym/SutureThrow-v3`` on the scene and with the substep of its shipped config
(``configs/envs/abdominal_wall_suture_throw.yaml``: three substeps of 5/3 ms an env step;
``configs/envs/hand_suture_throw.yaml``: two of 2.5 ms) with a 200-node, 20 cm thread, drives the scripted surgeon
until the needle has come out at the far edge (through both wound faces), then times :data:`TIMED_STEPS` env steps
of the surgeon turning the needle out and pulling the thread through the wound (numba compilation and the drive
excluded; ``env_steps_per_s`` times ``env.step``, the scripted surgeon's own time per step, the driver's as a haptic
device's or a policy's would be, is ``surgeon_ms_median``). ``realtime_factor`` (``scripts/bench.py``) is simulated
seconds per wall second: the paper's figures are real time (factor 1) at 38 and 21 fps.
"""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np

import suture_gym.envs  # noqa: F401  (registers the ids)
from suture_gym.baselines.surgeon import ScriptedSurgeon
from suture_gym.measure.registry import benchmark
from suture_gym.sim.coupling import NODE_IN

TIMED_STEPS = 200
#: The paper's suture: 200 nodes (20 cm here, 1 mm segments).
SUTURE = {"node_count": 200, "length": 0.2}
#: The scenes of the shipped SutureThrow configs (configs/envs/): their ``scene`` and ``solver`` sections
#: (``tests/test_anatomy.py`` checks that they match).
SCENES = {
    "paper_abdominal_wall": {
        "scene": {"kind": "abdominal_wall", "size": (0.06, 0.04, 0.012), "grid": (14, 10, 6), "gap": 0.002,
                  "layer_thickness": (0.002, 0.006), "layer_stiffness": (1.0, 1.0, 0.5)},
        "solver": {"dt": 0.005 / 3, "substeps": 3},
    },
    "paper_hand": {
        "scene": {"kind": "hand", "cell_size": 0.0058, "gap": 0.0015},
        "solver": {"dt": 0.0025, "substeps": 2},
    },
}


def _bench_scene(sections: dict) -> dict:
    env = gym.make("SutureGym/SutureThrow-v3", config={**sections, "suture": SUTURE})
    unwrapped = env.unwrapped
    sim = unwrapped.sim
    surgeon = ScriptedSurgeon(env, turn_rate=2.0)
    obs, _ = env.reset(seed=0)
    drive = 0
    while not unwrapped.task.state.exited:
        obs, _, terminated, truncated, _ = env.step(surgeon(obs))
        drive += 1
        if terminated or truncated:
            raise RuntimeError(f"the scripted surgeon's stitch ended after {drive} steps before the far exit")
    sim.timings = {}
    wall = np.empty(TIMED_STEPS)
    solver = np.empty(TIMED_STEPS)
    driver = np.empty(TIMED_STEPS)
    for k in range(TIMED_STEPS):
        t0 = time.perf_counter()
        action = surgeon(obs)
        driver[k] = time.perf_counter() - t0
        before = sum(sim.timings.values())
        t0 = time.perf_counter()
        obs, _, terminated, truncated, _ = env.step(action)
        wall[k] = time.perf_counter() - t0
        solver[k] = sum(sim.timings.values()) - before
        if terminated or truncated:
            wall, solver, driver = wall[: k + 1], solver[: k + 1], driver[: k + 1]
            break
    timings = dict(sim.timings)
    total = sum(timings.values())
    model, state = sim.model, sim.state
    needle_nodes = model.needle.node_count
    result = {
        "tets": model.tissue.tet_count,
        "particles": model.tissue.particle_count,
        "strand_nodes": model.coupling.strand_node_count,
        "needle_nodes": needle_nodes,
        "suture_nodes": model.suture.node_count,
        "substep_ms": float(np.median(solver)) / sim.substeps * 1e3,
        "collision_fraction": timings.get("detect", 0.0) / total,
        "solver_fraction": timings.get("project", 0.0) / total,
        "env_steps_per_s": len(wall) / float(wall.sum()),
        "env_step_ms_median": float(np.median(wall)) * 1e3,
        "surgeon_ms_median": float(np.median(driver)) * 1e3,
        "substeps_per_env_step": sim.substeps,
        "dt_s": sim.dt,
        "timed_env_steps": len(wall),
        "drive_env_steps": drive,
        "paths": int(state.coupling.path_count),
        "suture_nodes_in_paths": int(np.count_nonzero(state.coupling.strand_status[needle_nodes:] == NODE_IN)),
        "diverged": bool(state.diverged),
        "tissue_integrator": unwrapped.config.solver.tissue_integrator,
        "scene_config": sections["scene"],
    }
    env.close()
    return result


for _name, _sections in SCENES.items():
    benchmark(_name)(lambda sections=_sections: _bench_scene(sections))
