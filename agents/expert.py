"""Scripted expert for the SutureGym tasks, and demonstration recording.

:class:`ExpertPolicy` reads privileged state through ``env.unwrapped`` (the planned arcs, the task's stitch
bookkeeping, the needle's grip pose) and acts as a surgeon does with a curved needle:

1. ``turn``: the needle is turned about its own centre along the current stitch's planned circle, the tip
   angle advancing ``turn_rate`` rad/s from the approach pose until the swage is ``clearance`` rad past the
   exit (:meth:`~suture_gym.envs.SutureEnv.scripted_action`, the env's wrench toward that pose).
2. ``pull``: the holder moves along the stitch's pull direction (the last stitch of a running suture's leans
   ahead, along the suture, :meth:`ExpertPolicy._planned_pull`) at ``pull_speed`` m/s, orientation held
   (:meth:`~suture_gym.envs.SutureEnv.action_toward`), until the task moves on to the next stitch. A component
   of the pull that would take the needle tip within ``WORKSPACE_INSET`` of the workspace's walls is dropped,
   so a long pull (the running suture's last, which tightens every stitch) slides along the wall instead of
   leaving the workspace.
3. ``transit`` (next stitch of a running suture): the holder rises ``lift`` m above where it is, crosses to
   ``lift`` above the next stitch's approach pose, descends to it, and step 1 starts again.

Every action comes from the env's own helpers, so the expert works in both ``wrench`` and ``pose_delta``
action modes. The start-phase script of :class:`~suture_gym.envs.simulation.Simulation` and the scripted
surgeon of :mod:`suture_gym.measure.envs` follow the same plan with their own fixed schedules.

Recording: ``python -m agents.expert --env ID --episodes N --out demos.npz`` writes the observations, actions,
rewards, tip forces and episode boundaries of N seeded expert episodes (see :func:`record`).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

#: Tip-angle advance while turning, rad/s, per task (the env's start-phase script turns at 1 rad/s). The
#: running suture turns faster: its three stitches (about 7 rad of turning each) must fit, with their transits
#: and the final tightening pull, into WoundClosure's 25 s time limit.
TURN_RATES = {"needle_insert": 1.0, "suture_throw": 1.0, "wound_closure": 2.0}
#: Holder speed while pulling the thread, m/s, per task (WoundClosure's faster for the same reason).
PULL_SPEEDS = {"needle_insert": 0.02, "suture_throw": 0.02, "wound_closure": 0.04}
#: How far past the exit the swage is turned before pulling, rad.
CLEARANCE = 0.3
#: Closest approach (m) of the needle tip to the workspace's walls that a pull may make.
WORKSPACE_INSET = 0.002
#: Height of the transit between stitches above the approach pose, m.
LIFT = 0.01
#: Holder speed during the transit, m/s.
TRANSIT_SPEED = 0.05
#: Distance (m) at which a transit waypoint counts as reached.
WAYPOINT_TOLERANCE = 1.0e-3


class ExpertPolicy:
    """Scripted surgeon: a callable ``obs -> action`` (``(6,) float32`` in [-1, 1]) with :meth:`reset`.

    Args:
        env: a SutureGym env (any wrappers; ``env.unwrapped`` must be a
            :class:`~suture_gym.envs.SutureEnv`). The observation passed to ``__call__`` is not read: the
            expert acts on the env's privileged state.
        turn_rate: tip-angle advance while turning, rad/s (> 0); default the task's :data:`TURN_RATES`.
        pull_speed: holder speed while pulling the thread, m/s (> 0); default the task's :data:`PULL_SPEEDS`.
    """

    def __init__(self, env: gym.Env, turn_rate: float | None = None, pull_speed: float | None = None) -> None:
        from suture_gym.envs import SutureEnv

        if not isinstance(env.unwrapped, SutureEnv):
            raise ValueError(f"env must be a SutureGym env, got {type(env.unwrapped).__name__}")
        task = env.unwrapped.task.NAME
        turn_rate = TURN_RATES[task] if turn_rate is None else turn_rate
        pull_speed = PULL_SPEEDS[task] if pull_speed is None else pull_speed
        if not (math.isfinite(turn_rate) and turn_rate > 0.0):
            raise ValueError(f"turn_rate must be a positive rad/s, got {turn_rate}")
        if not (math.isfinite(pull_speed) and pull_speed > 0.0):
            raise ValueError(f"pull_speed must be a positive m/s, got {pull_speed}")
        self.env = env.unwrapped
        self.turn_rate = float(turn_rate)
        self.pull_speed = float(pull_speed)
        self.reset()

    def reset(self) -> None:
        """Forget the episode; the next call plans from the env's state (call after ``env.reset``)."""
        self.phase = ""
        self.stitch = -1
        self.angle = 0.0
        self.waypoints: list[np.ndarray] = []

    def __call__(self, obs) -> np.ndarray:
        env = self.env
        sim = env.sim
        state = env.task.state
        if state.stitch != self.stitch:
            self._start_stitch(state.stitch)
        arc = sim.arcs[self.stitch]
        if self.phase == "transit":
            grip, _ = sim.grip_pose()
            _, quat = sim.arc_grip_target(arc, self.angle)
            target = self.waypoints[0]
            if np.linalg.norm(target - grip) <= WAYPOINT_TOLERANCE:
                self.waypoints.pop(0)
                if not self.waypoints:
                    self.phase = "turn"
                    return env.scripted_action(self.angle, self.stitch)
                target = self.waypoints[0]
            step = TRANSIT_SPEED * sim.control_dt
            offset = target - grip
            distance = max(float(np.linalg.norm(offset)), step)
            return env.action_toward(grip + offset * (step / distance), quat)
        turn_end = arc.exit_angle + sim.model.needle.shape.arc_angle + CLEARANCE
        if self.phase == "turn" and self.angle >= turn_end:
            self.phase = "pull"
        if self.phase == "turn":
            self.angle = min(turn_end, self.angle + self.turn_rate * sim.control_dt)
            return env.scripted_action(self.angle, self.stitch)
        grip, quat = sim.grip_pose()
        direction = self._pull_direction(self._planned_pull(self.stitch))
        return env.action_toward(grip + self.pull_speed * sim.control_dt * direction, quat)

    def _planned_pull(self, stitch: int) -> np.ndarray:
        """Unit direction (3,) in which to pull stitch ``stitch``'s thread: the arc's
        :attr:`~suture_gym.tasks.PlannedArc.pull_direction`; the last stitch of a running suture adds the
        direction in which the suture advanced (from the previous stitch's centre to this one's), which leads
        the long tightening pull away from the stitches into the free workspace beyond them."""
        arcs = self.env.sim.arcs
        direction = arcs[stitch].pull_direction
        if stitch > 0 and stitch == len(arcs) - 1:
            advance = arcs[stitch].center - arcs[stitch - 1].center
            direction = direction + advance / np.linalg.norm(advance)
        return direction / np.linalg.norm(direction)

    def _pull_direction(self, direction: np.ndarray) -> np.ndarray:
        """``direction`` (3,) less its components toward workspace walls that the tip is within
        :data:`WORKSPACE_INSET` of, rescaled to unit length (zero when nothing is left)."""
        tip = self.env.sim.tip_position()
        low, high = self.env.sim.workspace
        kept = np.where(((direction < 0.0) & (tip - low < WORKSPACE_INSET))
                        | ((direction > 0.0) & (high - tip < WORKSPACE_INSET)), 0.0, direction)
        norm = float(np.linalg.norm(kept))
        return kept / norm if norm > 0.0 else kept

    def _start_stitch(self, stitch: int) -> None:
        """Plan stitch ``stitch``: turn from the approach pose (the first one), else transit there first."""
        sim = self.env.sim
        arc = sim.arcs[stitch]
        self.angle = arc.entry_angle - self.env.config.plan.start_angle
        if self.stitch < 0:
            self.phase = "turn"
        else:
            grip, _ = sim.grip_pose()
            start, _ = sim.arc_grip_target(arc, self.angle)
            high = max(grip[2], start[2]) + LIFT
            self.waypoints = [np.array([grip[0], grip[1], high]), np.array([start[0], start[1], high]), start]
            self.phase = "transit"
        self.stitch = stitch


def record(env_id: str, episodes: int, out: str | Path, seed: int = 0, env_kwargs: dict | None = None,
           progress: bool = True) -> dict:
    """Run ``episodes`` expert episodes of ``env_id`` (env seeds ``seed, seed + 1, ...``) and save them to ``out``.

    The ``.npz`` holds, over all T steps concatenated: ``observations (T, D) float32`` (the observation each
    action was taken on; for Dict spaces one array per key, ``observations_<key>``), ``next_observations``
    likewise, ``actions (T, 6) float32``, ``rewards (T,) float64``, ``tip_forces (T,) float64`` (N),
    ``tissue_costs (T,) float64``, ``terminated (T,) bool``, ``truncated (T,) bool``, ``episode_starts (E,)
    int64`` (index of each episode's first step), ``episode_lengths (E,) int64``, ``episode_success (E,)
    bool``, ``episode_seeds (E,) int64``, and ``env_id``.

    Returns:
        ``{episodes, steps, success_rate, out}``.
    """
    import suture_gym  # noqa: F401  (registers the ids)

    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    env = gym.make(env_id, **(env_kwargs or {}))
    expert = ExpertPolicy(env)
    obs_rows: list = []
    next_rows: list = []
    columns: dict[str, list] = {k: [] for k in ("actions", "rewards", "tip_forces", "tissue_costs", "terminated",
                                                 "truncated")}
    starts, lengths, success, seeds = [], [], [], []
    iterator = range(episodes)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"expert {env_id}", unit="episode", file=sys.stderr)
    for k in iterator:
        obs, info = env.reset(seed=seed + k)
        expert.reset()
        starts.append(len(columns["actions"]))
        seeds.append(seed + k)
        done, length = False, 0
        while not done:
            action = expert(obs)
            next_obs, reward, terminated, truncated, info = env.step(action)
            obs_rows.append(obs)
            next_rows.append(next_obs)
            columns["actions"].append(action)
            columns["rewards"].append(float(reward))
            columns["tip_forces"].append(float(info.get("tip_force", 0.0)))
            columns["tissue_costs"].append(float(info.get("cost", 0.0)))
            columns["terminated"].append(bool(terminated))
            columns["truncated"].append(bool(truncated))
            obs = next_obs
            length += 1
            done = terminated or truncated
        lengths.append(length)
        success.append(bool(info.get("is_success", False)))
    env.close()
    arrays: dict[str, np.ndarray] = {
        "actions": np.asarray(columns["actions"], dtype=np.float32),
        "rewards": np.asarray(columns["rewards"], dtype=np.float64),
        "tip_forces": np.asarray(columns["tip_forces"], dtype=np.float64),
        "tissue_costs": np.asarray(columns["tissue_costs"], dtype=np.float64),
        "terminated": np.asarray(columns["terminated"], dtype=bool),
        "truncated": np.asarray(columns["truncated"], dtype=bool),
        "episode_starts": np.asarray(starts, dtype=np.int64),
        "episode_lengths": np.asarray(lengths, dtype=np.int64),
        "episode_success": np.asarray(success, dtype=bool),
        "episode_seeds": np.asarray(seeds, dtype=np.int64),
        "env_id": np.asarray(env_id),
    }
    if isinstance(obs_rows[0], dict):
        for key in obs_rows[0]:
            arrays[f"observations_{key}"] = np.asarray([o[key] for o in obs_rows], dtype=np.float32)
            arrays[f"next_observations_{key}"] = np.asarray([o[key] for o in next_rows], dtype=np.float32)
    else:
        arrays["observations"] = np.asarray(obs_rows, dtype=np.float32)
        arrays["next_observations"] = np.asarray(next_rows, dtype=np.float32)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    return {"episodes": episodes, "steps": int(arrays["actions"].shape[0]),
            "success_rate": float(np.mean(success)), "out": str(out)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Record scripted-expert demonstrations to an .npz file.")
    parser.add_argument("--env", required=True, help="env id, e.g. SutureGym/NeedleInsert-v0")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0, help="env seed of the first episode")
    parser.add_argument("--out", required=True, help="output .npz path")
    args = parser.parse_args(argv)
    summary = record(args.env, args.episodes, args.out, seed=args.seed)
    print(f"{summary['episodes']} episodes, {summary['steps']} steps, success rate "
          f"{summary['success_rate']:.2f} -> {summary['out']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
