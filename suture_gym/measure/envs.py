"""Environment benchmarks (env steps per second of every registered id; of the batched vector env on 1, 2 and 4
envs, ``vector_env``; seconds from an empty numba cache to each task's first step, ``cold_start``; resident
memory growth over randomised episodes, ``reset_memory``) and two
end-to-end checks that the tasks can be done: the scripted surgeon's bite accuracy in NeedleInsert and its
thread pulled through in SutureThrow.

Each benchmark builds the env with its default config (``gym.make(id)``, so the registered wrappers are
timed too; ``env_NeedleInsert_rgb84`` and ``env_NeedleInsert_pointcloud`` with an 84 x 84 RGB image or a point
cloud as the observation, :data:`OBSERVATION_BENCHMARKS`), warms up (numba compilation excluded) and then
times env steps on one thread. Two workloads:

* ``env_steps_per_s``: uniformly random actions from a seeded action space, resetting whenever an episode
  ends (the resets' time included), the usual definition;
* ``env_steps_per_s_scripted``: the scripted surgeon (:class:`~suture_gym.baselines.surgeon.ScriptedSurgeon`)
  turning the needle along the planned arc at 2 rad/s and pulling the thread, so the needle is inside the
  tissue most of the time (path growth, node-path rows), the heavier case.

``substep_ms`` is the median over env steps of the solver time of the step divided by its substeps;
``collision_fraction`` and ``solver_fraction`` are the detection and projection shares of the solver time.
"""

from __future__ import annotations

import gc
import math
import os
import platform
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import suture_gym.envs  # registers the ids
from suture_gym.baselines.surgeon import ScriptedSurgeon
from suture_gym.envs import ENV_IDS
from suture_gym.envs.vector import SutureVectorEnv
from suture_gym.measure.registry import CheckResult, benchmark, check

WARMUP_STEPS = 50
#: Tip-angle advance of the scripted surgeon in the scripted benchmark, rad/s.
SCRIPTED_TURN_RATE = 2.0
TIMED_STEPS = 600


def _random_run(env: gym.Env, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Step ``env`` with seeded random actions; returns (per-step wall s, per-step solver s, total wall s)."""
    sim = env.unwrapped.sim
    env.action_space.seed(seed)
    env.reset(seed=seed)
    wall = np.empty(steps)
    solver = np.empty(steps)
    start = time.perf_counter()
    for k in range(steps):
        before = sum(sim.timings.values()) if sim.timings is not None else 0.0
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
        wall[k] = time.perf_counter() - t0
        solver[k] = (sum(sim.timings.values()) - before) if sim.timings is not None else 0.0
    return wall, solver, time.perf_counter() - start


def _scripted_run(env: gym.Env, steps: int, seed: int) -> float:
    """Wall time (s) of ``steps`` steps of the scripted surgeon (:class:`~suture_gym.baselines.surgeon.ScriptedSurgeon`,
    turning at :data:`SCRIPTED_TURN_RATE`), restarting each episode when it ends."""
    surgeon = ScriptedSurgeon(env, turn_rate=SCRIPTED_TURN_RATE)
    obs, _ = env.reset(seed=seed)
    start = time.perf_counter()
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(surgeon(obs))
        if terminated or truncated:
            obs, _ = env.reset()
            surgeon.reset()
    return time.perf_counter() - start


def _bench_env(env_id: str, config: dict | None = None) -> dict:
    env = gym.make(env_id, config=config)
    sim = env.unwrapped.sim
    _random_run(env, WARMUP_STEPS, seed=1)
    _scripted_run(env, WARMUP_STEPS, seed=1)
    sim.timings = {}
    wall, solver, total = _random_run(env, TIMED_STEPS, seed=0)
    timings = dict(sim.timings)
    sim.timings = None
    scripted = _scripted_run(env, TIMED_STEPS, seed=0)
    model = sim.model
    solver_total = sum(timings.values())
    env.close()
    return {
        "tets": model.tissue.tet_count,
        "particles": model.tissue.particle_count,
        "strand_nodes": model.coupling.strand_node_count,
        "substep_ms": float(np.median(solver)) / sim.substeps * 1e3,
        "substeps_per_s": sim.substeps / float(np.median(solver)),
        "collision_fraction": timings.get("detect", 0.0) / solver_total,
        "solver_fraction": timings.get("project", 0.0) / solver_total,
        "env_steps_per_s": TIMED_STEPS / total,
        "env_steps_per_s_scripted": TIMED_STEPS / scripted,
        "env_step_ms_median": float(np.median(wall)) * 1e3,
        "substeps_per_env_step": sim.substeps,
        "dt_s": sim.dt,
        "env_id": env_id,
        "workload": "seeded uniform random actions, resets included; scripted: the scripted surgeon at 2 rad/s",
        **({"config": config} if config else {}),
    }


#: The observation modes timed on NeedleInsert beside its state vector: ``env_NeedleInsert_<suffix>``.
OBSERVATION_BENCHMARKS = {
    "rgb84": {"observation": {"mode": "rgb", "camera": {"width": 84, "height": 84}}},
    "pointcloud": {"observation": {"mode": "point_cloud"}},
}


def _register_env_benchmarks() -> None:
    for env_id in ENV_IDS:
        name = "env_" + env_id.split("/")[1].split("-")[0]
        benchmark(name)(lambda env_id=env_id: _bench_env(env_id))
    for suffix, config in OBSERVATION_BENCHMARKS.items():
        benchmark(f"env_NeedleInsert_{suffix}")(
            lambda config=config: _bench_env("SutureGym/NeedleInsert-v3", config))


_register_env_benchmarks()


def _scripted_episode(env_id: str, turn_rate: float, pull_speed: float | None) -> dict:
    """Run the scripted surgeon (:class:`~suture_gym.baselines.surgeon.ScriptedSurgeon`) through one episode of
    ``env_id`` (seed 0, default config, wrench actions), turning at ``turn_rate`` rad/s and pulling at
    ``pull_speed`` m/s (None: the task's). Returns the recorded entry and exit errors (m), the thread pulled
    through (m) and the end flags."""
    env = gym.make(env_id)
    unwrapped = env.unwrapped
    sim = unwrapped.sim
    surgeon = ScriptedSurgeon(env, turn_rate=turn_rate, pull_speed=pull_speed)
    obs, _ = env.reset(seed=0)
    arc = sim.arcs[0]
    info, thread = {}, 0.0
    steps = 0
    while steps < env.spec.max_episode_steps:
        steps += 1
        obs, _, terminated, truncated, info = env.step(surgeon(obs))
        thread = max(thread, sim.thread_through())
        if terminated or truncated:
            break
    state = unwrapped.task.state
    result = {
        "entry_error_m": float(np.linalg.norm(state.entry_point - arc.entry)),
        "exit_error_m": float(np.linalg.norm(state.exit_point - arc.exit)),
        "thread_through_m": thread,
        "is_success": bool(info.get("is_success", False)),
        "diverged": bool(info.get("diverged", False)),
        "tear": bool(info.get("tear", False)),
        "env_steps": steps,
    }
    env.close()
    return result


def _scripted_settings(env_id: str, turn_rate: float, pull_speed: float | None) -> dict:
    from suture_gym.envs.config import config_to_dict

    unwrapped = gym.make(env_id).unwrapped
    speed = unwrapped.task.SURGEON_PULL_SPEED if pull_speed is None else pull_speed
    return {"env_id": env_id, "seed": 0, "turn_rate_rad_s": turn_rate, "pull_speed_m_s": speed,
            "surgeon": "suture_gym.baselines.surgeon.ScriptedSurgeon", "turn_end": "exit angle + needle arc + 0.3 rad",
            "config": config_to_dict(unwrapped.config)}


@check("env_needle_insert_scripted_accuracy")
def check_needle_insert_scripted_accuracy() -> CheckResult:
    """The scripted surgeon's bite in NeedleInsert: the larger of the entry and exit errors (material points
    against the planned markers) must be within the task's access tolerance, and the episode must succeed."""
    env_id, rate = "SutureGym/NeedleInsert-v3", 2.0
    run = _scripted_episode(env_id, rate, None)
    tolerance = gym.make(env_id).unwrapped.config.reward.access_tolerance
    measured = max(run["entry_error_m"], run["exit_error_m"])
    if not run["is_success"]:
        measured = math.inf
    return CheckResult("env_needle_insert_scripted_accuracy", measured, 0.0, tolerance, "m", "<=",
                       _scripted_settings(env_id, rate, None), run)


@check("env_suture_throw_scripted_thread")
def check_suture_throw_scripted_thread() -> CheckResult:
    """The scripted surgeon's stitch in SutureThrow: thread pulled through the far edge's exit (m), at least
    the task's target, with the episode successful (entry and exit within tolerance) and no divergence."""
    env_id, rate, speed = "SutureGym/SutureThrow-v3", 1.0, 0.02
    run = _scripted_episode(env_id, rate, speed)
    target = gym.make(env_id).unwrapped.config.plan.thread_target
    measured = run["thread_through_m"] if run["is_success"] and not run["diverged"] else -math.inf
    return CheckResult("env_suture_throw_scripted_thread", measured, target, 0.0, "m", ">=",
                       _scripted_settings(env_id, rate, speed), run)


#: Resets timed per start phase once its start is cached (the median is reported).
PHASE_RESETS = 3


def _reset_seconds(env: gym.Env, phase: str, seed: int) -> float:
    start = time.perf_counter()
    env.reset(seed=seed, options={"phase": phase})
    return time.perf_counter() - start


@benchmark("phase_reset")
def bench_phase_reset() -> dict:
    """Seconds to reset into each start phase of each task (``reset(options={"phase": ...})``): the first reset
    of a process (``first_s``: the scripted approach simulated on the nominal parameters, numba already
    compiled), then warm, the median of :data:`PHASE_RESETS` resets of a fresh env of the same config
    (``warm_s``, the cached start), both with the randomisation off, and of the id's default, randomised
    episodes (``warm_randomized_s``: each episode's parameters differ, so the start is carried over and
    settled; its first reset, which simulates, untimed)."""
    from suture_gym.envs.simulation import PHASE_STARTS

    phases = []
    nominal = {"randomization": {"enabled": False}}
    for env_id in ENV_IDS:
        for phase in gym.make(env_id).unwrapped.task_cls.PHASES:
            PHASE_STARTS.clear()
            entry = {"env_id": env_id, "phase": phase,
                     "first_s": _reset_seconds(gym.make(env_id, config=nominal), phase, seed=0)}
            warm = gym.make(env_id, config=nominal)
            entry["warm_s"] = float(np.median([_reset_seconds(warm, phase, seed=k) for k in range(PHASE_RESETS)]))
            env = gym.make(env_id)
            _reset_seconds(env, phase, seed=0)
            entry["warm_randomized_s"] = float(np.median(
                [_reset_seconds(env, phase, seed=k) for k in range(1, PHASE_RESETS + 1)]))
            phases.append(entry)
    return {
        "phases": phases,
        "warm_s_max": max(max(e["warm_s"], e["warm_randomized_s"]) for e in phases),
        "workload": "reset(options={'phase': p}); warm: fresh env of the nominal config after the first, and the "
                    "id's randomised episodes (new parameters each)",
    }



#: Randomised episodes of ``reset_memory`` per id, and the first ones left out of its growth (warm-up, caches).
MEMORY_EPISODES = 2000
MEMORY_SKIP = 200
#: The ids ``reset_memory`` measures.
MEMORY_IDS = ("SutureGym/NeedleInsert-v3", "SutureGym/WoundClosureGoal-v3")


def _resident_kb() -> int:
    """Resident memory of this process (``VmRSS`` of ``/proc/self/status``), KB."""
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS"))


@benchmark("reset_memory")
def bench_reset_memory() -> dict:
    """Resident memory growth over :data:`MEMORY_EPISODES` randomised episodes of each of :data:`MEMORY_IDS`
    (``gym.make(id)``, seeds 0, 1, ...; each episode a reset and one zero-action step, which solves with the
    episode's new tissue), after the first :data:`MEMORY_SKIP`: ``growth_mb`` and ``kb_per_episode`` per id
    (as the process sees it, heap fragmentation included). The acceptance bound is ``growth_mb_max < 2``."""
    results = []
    for env_id in MEMORY_IDS:
        env = gym.make(env_id)
        zero = np.zeros(6, np.float32)
        for k in range(MEMORY_EPISODES):
            env.reset(seed=k)
            env.step(zero)
            if k == MEMORY_SKIP - 1:
                gc.collect()
                before = _resident_kb()
        gc.collect()
        growth = _resident_kb() - before
        env.close()
        results.append({"env_id": env_id, "growth_mb": growth / 1024,
                        "kb_per_episode": growth / (MEMORY_EPISODES - MEMORY_SKIP)})
    return {
        "ids": results,
        "growth_mb_max": max(r["growth_mb"] for r in results),
        "workload": f"{MEMORY_EPISODES} randomised episodes per id (reset, one zero step), growth after the first "
                    f"{MEMORY_SKIP}",
    }


def _vector_rate(num_envs: int, workers: int, steps: int) -> float:
    """Env steps per second (all envs together) of a NeedleInsert :class:`SutureVectorEnv` of ``num_envs`` envs
    on ``workers`` worker processes, over ``steps`` vector steps of seeded random actions after a warm-up.

    The timed pass is rehearsed first, untimed, with the same seeds: the same episodes take the same code paths,
    so numba has compiled (or loaded from its cache) every kernel the timed pass calls. A fixed warm-up alone is
    not enough on an empty cache: a kernel first needed later in the pass (a puncture, a path) compiles inside
    the timing."""
    env = SutureVectorEnv("needle_insert", num_envs, max_episode_steps=300, workers=workers)
    for _pass in ("rehearsal", "timed"):
        env.action_space.seed(0)
        env.reset(seed=0)
        for _ in range(WARMUP_STEPS):
            env.step(env.action_space.sample())
        start = time.perf_counter()
        for _ in range(steps):
            env.step(env.action_space.sample())
        elapsed = time.perf_counter() - start
    env.close()
    return num_envs * steps / elapsed


@benchmark("vector_env")
def bench_vector_env() -> dict:
    """Env steps per second of :class:`~suture_gym.envs.vector.SutureVectorEnv` (NeedleInsert, random actions)
    with 1 env in this process and with 2 and 4 envs on one worker process per env up to the cores this process
    may use (:func:`~suture_gym.envs.vector.default_workers`), :data:`TIMED_STEPS` env steps each; and
    ``scaling_1_to_2``, the 2-env rate over the 1-env rate (2 on two free cores, at best). Wall-clock rates:
    other load on the machine (``load_average``, the 1-minute mean of runnable processes when it ended) lowers
    them and the scaling."""
    from suture_gym.envs.vector import default_workers

    rates = {}
    for n in (1, 2, 4):
        workers = default_workers(n)
        rates[n] = {"num_envs": n, "workers": workers,
                    "env_steps_per_s": _vector_rate(n, workers, max(TIMED_STEPS // n, 1))}
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "machine": f"{platform.processor() or platform.machine()}, {cores} cores, 1 thread per process",
        "env_id": "SutureGym/NeedleInsert-v3",
        "rates": list(rates.values()),
        "scaling_1_to_2": rates[2]["env_steps_per_s"] / rates[1]["env_steps_per_s"],
        "cores": cores,
        "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "workload": "seeded uniform random actions, NEXT_STEP autoreset, time limit 300; workers: processes",
    }


#: Run in a fresh interpreter by :func:`bench_cold_start`: imports suture_gym, then builds, resets and steps one
#: env of each registered flat id, printing a JSON line of seconds since its start after the import and after
#: each id's first step.
_COLD_START_CHILD = """
import time
t0 = time.perf_counter()
import json
import gymnasium as gym
import suture_gym
from suture_gym.envs import ENV_IDS
print(json.dumps({"event": "import", "t": time.perf_counter() - t0}), flush=True)
for env_id in ENV_IDS:
    env = gym.make(env_id)
    env.reset(seed=0)
    env.step(env.action_space.sample() * 0.0)
    env.close()
    print(json.dumps({"event": env_id, "t": time.perf_counter() - t0}), flush=True)
"""


def _cold_start_run(cache_dir: str) -> dict:
    """Seconds after the import and after each id's first step of one :data:`_COLD_START_CHILD` run with the
    numba cache ``cache_dir``, and the child's CPU seconds (user + system) under ``"cpu"``."""
    import json
    import resource
    import subprocess
    import sys

    root = str(Path(suture_gym.envs.__file__).resolve().parents[2])
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir, "NUMBA_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([sys.executable, "-c", _COLD_START_CHILD], env=env, capture_output=True, text=True,
                          check=True, timeout=3600)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {**{e["event"]: e["t"] for e in map(json.loads, done.stdout.splitlines())}, "cpu": cpu}


@benchmark("cold_start")
def bench_cold_start() -> dict:
    """Seconds from an empty numba cache to the first step of each task: a fresh interpreter with a new, empty
    ``NUMBA_CACHE_DIR`` imports suture_gym, then builds, resets and steps one env of each flat id in registration
    order (``first_step_s``: seconds since its start, so each id's figure includes the ids before it;
    ``added_s``: what each id added). Then a second interpreter on the now filled cache (``warm_first_step_s``):
    what every later start costs. One thread; compilation is CPU-bound, so other load on the machine
    (``load_average``) lengthens it; ``cpu_s`` and ``warm_cpu_s``, the CPU seconds (user + system) of each
    interpreter, depend on that load much less."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="suture_gym_cold_") as cache:
        cold = _cold_start_run(cache)
        warm = _cold_start_run(cache)
    ids = [k for k in cold if k not in ("import", "cpu")]
    added = {env_id: cold[env_id] - (cold[ids[k - 1]] if k else cold["import"]) for k, env_id in enumerate(ids)}
    return {
        "import_s": cold["import"],
        "first_step_s": {env_id: cold[env_id] for env_id in ids},
        "added_s": added,
        "total_s": cold[ids[-1]],
        "cpu_s": cold["cpu"],
        "warm_first_step_s": {env_id: warm[env_id] for env_id in ids},
        "warm_cpu_s": warm["cpu"],
        "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "workload": "fresh interpreter, empty NUMBA_CACHE_DIR, gym.make + reset + one zero action per flat id",
    }
