"""Scripted expert for the SutureGym tasks, and demonstration recording.

:class:`ExpertPolicy` is the package's scripted surgeon, :class:`~suture_gym.baselines.surgeon.ScriptedSurgeon`
(turn the needle about its own centre along each planned stitch, pull the thread, carry the needle to the next
stitch), acting through the env's action space only, so it works in both ``wrench`` and ``pose_delta`` action
modes. Its default speeds are the task's (``SURGEON_TURN_RATE``, ``SURGEON_PULL_SPEED``). The env's start phases
follow the same motions (:mod:`suture_gym.tasks.surgeon`).

Recording: ``python -m suture_gym.baselines.expert --env ID --episodes N --out demos.npz`` writes the observations,
actions, rewards, tip forces and episode boundaries of N seeded expert episodes (see :func:`record`);
``--minari [DATASET_ID] [--root DIR]`` writes them as a Minari dataset instead (:func:`record_minari`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np

from suture_gym.baselines.datasets import RecordedEpisode
from suture_gym.baselines.surgeon import LIFT, TRANSIT_SPEED, WAYPOINT_TOLERANCE, ScriptedSurgeon
from suture_gym.sim.needle import needle_point_velocity
from suture_gym.sim.quat import quat_conj, quat_mul, quat_rotation_vector
from suture_gym.tasks.surgeon import PULL_DAMPING_PER_MAX_FORCE, swage_out_angle, thread_pull_wrench

#: :class:`FeedbackExpert`'s transit: the distance (m) within which the grip's commanded velocity shrinks in
#: proportion to what is left (height or horizontal distance), the horizontal distance (m) from the next approach
#: pose over which it glides down from :data:`~suture_gym.baselines.surgeon.LIFT` above it, and the rate (rad/s) and
#: the angle (rad) within which that rate shrinks in proportion, at which it turns the needle toward the
#: approach pose's orientation.
TRANSIT_SLOWDOWN = 0.005
TRANSIT_GLIDE = 0.005
TRANSIT_TURN_RATE = 1.0
TRANSIT_TURN_SLOWDOWN = 0.1


class ExpertPolicy(ScriptedSurgeon):
    """Scripted expert: a callable ``obs -> action`` (``(6,) float32`` in [-1, 1]) with :meth:`reset`; see
    :class:`~suture_gym.baselines.surgeon.ScriptedSurgeon` for the plan and the arguments (``env``, ``turn_rate``
    rad/s, ``pull_speed`` m/s)."""


class FeedbackExpert(ExpertPolicy):
    """The expert with its turn closed on the measured tip: an oracle that labels any state, for DAgger.

    :class:`ExpertPolicy` advances the commanded tip angle on a clock (``turn_rate`` rad/s), whatever the needle
    does; a learner that lags or leads the clock would be labelled with a command that depends on time it cannot
    observe. Here, while turning, the command is the needle lying on the planned circle with its tip ``lead`` rad
    ahead of the tip's measured angle about the circle's centre (the angle unwrapped next to the previous one),
    so the label is a function of the state: a needle off the circle is pulled back onto it, a needle behind
    is driven on from where it is. The turn ends, as the expert's, once the swage would be
    :data:`~suture_gym.tasks.surgeon.CLEARANCE` rad past the exit (measured within ``lead``).

    In ``wrench`` mode the pull is the start phases' (:func:`~suture_gym.tasks.surgeon.thread_pull_wrench`): a
    constant force along the expert's pull direction, damped, the orientation held at the turn's last pose by the
    softened coupling (``gain``). The expert's own pull servos the grip to a point ``pull_speed * dt`` ahead, a
    velocity loop so stiff that its labels flip between -1 and 1 with the grip's speed; a learner fitted to them
    pulled with their mean, about nothing (the full coupling's orientation hold flips the torque labels likewise).
    The transit between stitches (``wrench`` mode) is soft for the same reason, and a function of the state
    alone (the expert's waypoints depend on where its transit began): a velocity field
    (:meth:`transit_velocity`) that rises to :data:`~suture_gym.baselines.surgeon.LIFT` above the next approach pose,
    crosses at that height and glides down onto it, and turns the needle toward its orientation; the label is
    the damped force and torque toward those velocities, with the pull's damping and the softened coupling's
    angular damping, both scaled by ``gain``. It ends within
    :data:`~suture_gym.baselines.surgeon.WAYPOINT_TOLERANCE` of the approach pose.

    Args:
        env, turn_rate, pull_speed: as :class:`ExpertPolicy` (``turn_rate`` is unused while turning, but the
            transit and the first stitch's plan read it).
        lead: how far ahead of the measured tip the command leads, rad (> 0). The clock expert lags its own
            command by a median 0.013 rad in SutureThrow (95th percentile 0.017 rad), more inside the tissue;
            at 0.015 rad the feedback expert turns through NeedleInsert's tissue at half the clock's speed and
            runs out of time, at the default 0.02 rad it succeeds in 20/20 NeedleInsert-v3 episodes (391 steps
            on average, the clock expert 462) and 10/10 SutureThrow-v3 ones (977 steps, the clock expert about
            1,350).
        gain: the turn's command is the env's virtual coupling toward the commanded pose (``wrench`` mode) with
            its stiffnesses and dampings scaled by ``gain`` (in (0, 1]). At 1 the coupling saturates the torque
            at 0.008 rad of error and its damping alone at 0.67 rad/s: the label is the small difference of two
            large terms, so it swings with tiny changes of the state and a regression fits it poorly. A softer
            coupling with a longer lead gives smoother labels (0.25 and 0.06 rad: 2/2 SutureThrow-v3 episodes of
            about 410 steps; NeedleInsert-v3 in 150).
    """

    def __init__(self, env, turn_rate: float | None = None, pull_speed: float | None = None,
                 lead: float = 0.02, gain: float = 1.0) -> None:
        if not (math.isfinite(lead) and lead > 0.0):
            raise ValueError(f"lead must be a positive angle in rad, got {lead}")
        if not (math.isfinite(gain) and 0.0 < gain <= 1.0):
            raise ValueError(f"gain must lie in (0, 1], got {gain}")
        self.lead = float(lead)
        self.gain = float(gain)
        super().__init__(env, turn_rate, pull_speed)
        spring = self.env.sim.coupling_spring
        self.spring = dataclasses.replace(
            spring, linear_stiffness=gain * spring.linear_stiffness, linear_damping=gain * spring.linear_damping,
            angular_stiffness=gain * spring.angular_stiffness, angular_damping=gain * spring.angular_damping)

    def reset(self) -> None:
        super().reset()
        self.measured = 0.0

    def __call__(self, obs) -> np.ndarray:
        env = self.env
        sim = env.sim
        stitch = env.task.state.stitch
        if stitch != self.stitch:
            self._start_stitch(stitch)
            self.measured = self.angle
        wrench_mode = env.config.action.mode == "wrench"
        if self.phase == "transit" and wrench_mode:
            start, quat = sim.arc_grip_target(sim.arcs[self.stitch], self.angle)
            grip, _ = sim.grip_pose()
            if np.linalg.norm(start - grip) > WAYPOINT_TOLERANCE:
                return self._soft_transit(grip, start, quat)
            self.phase = "turn"
        if self.phase == "turn":
            arc = sim.arcs[self.stitch]
            tip = sim.tip_position() - arc.center
            raw = math.atan2(float(tip @ arc.v), float(tip @ arc.u))
            self.measured += (raw - self.measured + math.pi) % (2.0 * math.pi) - math.pi
            turn_end = swage_out_angle(arc, sim.model.needle.shape.arc_angle)
            if self.measured < turn_end - self.lead:
                self.angle = self.measured + self.lead
                target = sim.arc_grip_target(arc, self.angle)
                if not wrench_mode:
                    return env.action_toward(*target)
                return env.action_for_wrench(self.spring.wrench(sim.model.needle, sim.state.needle, *target))
            self.angle = turn_end
            self.phase = "pull"
        if self.phase != "pull" or not wrench_mode:
            return super().__call__(obs)
        arc = sim.arcs[self.stitch]
        _, hold = sim.arc_grip_target(arc, swage_out_angle(arc, sim.model.needle.shape.arc_angle))
        return env.action_for_wrench(thread_pull_wrench(sim, hold, self._pull_direction(self._planned_pull(
            self.stitch)), self.spring))

    @staticmethod
    def transit_velocity(grip: np.ndarray, start: np.ndarray) -> np.ndarray:
        """Commanded grip velocity (3,) m/s of the transit at grip position ``grip`` (3,) m toward the approach
        pose's grip position ``start`` (3,) m: up to :data:`~suture_gym.baselines.surgeon.LIFT` above ``start``
        (lower within :data:`TRANSIT_GLIDE` of it horizontally, reaching it at zero distance), across only once
        within :data:`TRANSIT_SLOWDOWN` of that height, each component at most
        :data:`~suture_gym.baselines.surgeon.TRANSIT_SPEED` and in proportion to what is left within
        :data:`TRANSIT_SLOWDOWN`."""
        across = start[:2] - grip[:2]
        distance = float(np.linalg.norm(across))
        rise = start[2] + LIFT * min(1.0, distance / TRANSIT_GLIDE) - grip[2]
        vertical = TRANSIT_SPEED * float(np.clip(rise / TRANSIT_SLOWDOWN, -1.0, 1.0))
        gate = float(np.clip(1.0 - rise / TRANSIT_SLOWDOWN, 0.0, 1.0))
        horizontal = TRANSIT_SPEED * gate * across / max(distance, TRANSIT_SLOWDOWN)
        return np.array([horizontal[0], horizontal[1], vertical])

    def _soft_transit(self, grip: np.ndarray, start: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """``wrench``-mode action of the transit at grip position ``grip`` (3,) m toward the approach pose
        ``start`` (3,) m, ``quat`` (4,) (see the class docstring)."""
        sim = self.env.sim
        needle, state = sim.model.needle, sim.state.needle
        velocity = needle_point_velocity(needle, state, needle.grip_pos_body)
        damping = self.gain * PULL_DAMPING_PER_MAX_FORCE * self.env.config.action.max_force
        turn = quat_rotation_vector(quat_mul(quat, quat_conj(state.body_quat)))
        omega = TRANSIT_TURN_RATE * turn / max(float(np.linalg.norm(turn)), TRANSIT_TURN_SLOWDOWN)
        force = damping * (self.transit_velocity(grip, start) - velocity)
        torque = self.spring.angular_damping * (omega - state.body_omega)
        return self.env.action_for_wrench(np.concatenate([force, torque]))


#: The experts :func:`expert_episodes` runs, by name.
EXPERTS = {"clock": ExpertPolicy, "feedback": FeedbackExpert}


def expert_episodes(env: gym.Env, episodes: int, seed: int = 0, progress: bool = False, expert: str = "clock",
                    action_noise: float = 0.0) -> Iterator[RecordedEpisode]:
    """Run a scripted expert on ``env`` for ``episodes`` episodes (env seeds ``seed, seed + 1, ...``), each until
    it terminates or is truncated; yields each as a :class:`~suture_gym.baselines.datasets.RecordedEpisode` once
    it ends.

    Args:
        expert: ``"clock"`` (:class:`ExpertPolicy`) or ``"feedback"`` (:class:`FeedbackExpert`, whose action is a
            function of the state, so a policy can be fitted to it).
        action_noise: standard deviation (action units, the box being ``[-1, 1]``) of Gaussian noise added to
            every action the expert chooses before the env executes it (clipped to the box), drawn from
            ``np.random.default_rng(env seed)``; the episode then records the executed action in ``actions``
            and the expert's own in ``expert_actions``. Demonstrations recorded this way show the expert correcting
            the small errors a learner makes (Laskey et al. 2017, "DART"); 0 executes the expert's action.
    """
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes <= 0:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if expert not in EXPERTS:
        raise ValueError(f"expert must be one of {sorted(EXPERTS)}, got {expert!r}")
    if not (math.isfinite(action_noise) and action_noise >= 0.0):
        raise ValueError(f"action_noise must be a finite standard deviation >= 0, got {action_noise!r}")
    policy = EXPERTS[expert](env.unwrapped)
    iterator = range(episodes)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"expert {env.spec.id if env.spec else ''}", unit="episode", file=sys.stderr)
    for k in iterator:
        obs, info = env.reset(seed=seed + k)
        policy.reset()
        noise = np.random.default_rng(seed + k)
        episode = RecordedEpisode(seed + k, obs, info)
        done = False
        while not done:
            chosen = np.asarray(policy(obs), dtype=np.float32)
            action = chosen
            if action_noise > 0.0:
                action = np.clip(chosen + action_noise * noise.standard_normal(chosen.shape), -1.0, 1.0)
                action = action.astype(np.float32)
            obs, reward, terminated, truncated, info = env.step(action)
            episode.actions.append(action)
            if action_noise > 0.0:
                episode.expert_actions.append(chosen)
            episode.observations.append(obs)
            episode.rewards.append(float(reward))
            episode.terminated.append(bool(terminated))
            episode.truncated.append(bool(truncated))
            episode.infos.append(info)
            done = terminated or truncated
        yield episode


def record(env_id: str, episodes: int, out: str | Path, seed: int = 0, env_kwargs: dict | None = None,
           progress: bool = True, expert: str = "clock", action_noise: float = 0.0) -> dict:
    """Run ``episodes`` expert episodes of ``env_id`` (env seeds ``seed, seed + 1, ...``; ``expert`` and
    ``action_noise`` as :func:`expert_episodes`) and save them to ``out``.

    The ``.npz`` holds, over all T steps concatenated: ``observations (T, D) float32`` (the observation each
    action was taken on; for Dict spaces one array per key, ``observations_<key>``), ``next_observations``
    likewise, ``actions (T, 6) float32``, ``rewards (T,) float64``, ``tip_forces (T,) float64`` (N),
    ``tissue_costs (T,) float64``, ``terminated (T,) bool``, ``truncated (T,) bool``, ``episode_starts (E,)
    int64`` (index of each episode's first step), ``episode_lengths (E,) int64``, ``episode_success (E,)
    bool``, ``episode_seeds (E,) int64``, and ``env_id``; with ``action_noise`` also ``expert_actions (T, 6)
    float32``, the expert's own actions. :func:`record_minari` writes the same episodes as a Minari dataset.

    Returns:
        ``{episodes, steps, success_rate, out}``.
    """
    import suture_gym  # noqa: F401  (registers the ids)

    env = gym.make(env_id, **(env_kwargs or {}))
    obs_rows: list = []
    next_rows: list = []
    columns: dict[str, list] = {k: [] for k in ("actions", "rewards", "tip_forces", "tissue_costs", "terminated",
                                                 "truncated")}
    starts, lengths, success, seeds, chosen = [], [], [], [], []
    for episode in expert_episodes(env, episodes, seed, progress, expert, action_noise):
        starts.append(len(columns["actions"]))
        seeds.append(episode.seed)
        obs_rows += [episode.reset_obs, *episode.observations[:-1]]
        next_rows += episode.observations
        columns["actions"] += episode.actions
        chosen += episode.expert_actions
        columns["rewards"] += episode.rewards
        columns["tip_forces"] += [float(i.get("tip_force", 0.0)) for i in episode.infos]
        columns["tissue_costs"] += [float(i.get("cost", 0.0)) for i in episode.infos]
        columns["terminated"] += episode.terminated
        columns["truncated"] += episode.truncated
        lengths.append(len(episode.actions))
        success.append(bool(episode.infos[-1].get("is_success", False)))
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
    if chosen:
        arrays["expert_actions"] = np.asarray(chosen, dtype=np.float32)
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


def record_minari(env_id: str, episodes: int, dataset_id: str | None = None, seed: int = 0,
                  env_kwargs: dict | None = None, root: str | Path | None = None, progress: bool = True,
                  author: str | None = None, author_email: str | None = None,
                  code_permalink: str | None = None, expert: str = "clock", action_noise: float = 0.0) -> dict:
    """Run ``episodes`` expert episodes of ``env_id`` (env seeds ``seed, seed + 1, ...``; ``expert`` and
    ``action_noise`` as :func:`expert_episodes`, the expert's own actions then stored as the info
    :data:`~suture_gym.baselines.datasets.EXPERT_ACTION_KEY`) and write them as the
    Minari dataset ``dataset_id`` (default :func:`suture_gym.baselines.datasets.default_dataset_id`) under
    :func:`suture_gym.baselines.datasets.datasets_root` ``(root)`` with
    :func:`suture_gym.baselines.datasets.write_minari`; needs ``pip install 'suture_gym[data]'``.

    Each episode holds Minari's ``observations`` (``T + 1``: the reset's, then each step's), ``actions (T, 6)``,
    ``rewards``, ``terminations``, ``truncations``, the infos of :data:`suture_gym.baselines.datasets.INFO_KEYS` (``T +
    1``), and its env seed; the dataset records the env spec (id, time limit, ``env_kwargs``, which must then be
    JSON data such as a config path), so ``dataset.recover_environment()`` rebuilds the env after
    ``import suture_gym``. ``author``, ``author_email`` and ``code_permalink`` go to the dataset's metadata
    (Minari warns about each one left out).

    Raises:
        ValueError: a dataset ``dataset_id`` already exists there (Minari never overwrites one).

    Returns:
        ``{episodes, steps, success_rate, dataset_id, root}``.
    """
    import minari  # noqa: F401  (fails before the episodes are run when Minari is missing)

    import suture_gym  # noqa: F401  (registers the ids)
    from suture_gym.baselines.datasets import INFO_KEYS, default_dataset_id, write_minari

    dataset_id = dataset_id or default_dataset_id(env_id)
    env = gym.make(env_id, **(env_kwargs or {}))
    recorded = list(expert_episodes(env, episodes, seed, progress, expert, action_noise))
    success = [bool(e.infos[-1].get("is_success", False)) for e in recorded]
    name = f"suture_gym.baselines.expert.{EXPERTS[expert].__name__}"
    noise = f", Gaussian action noise of std {action_noise:g}" if action_noise > 0.0 else ""
    folder = write_minari(
        dataset_id, recorded, env, root=root, algorithm_name=name, author=author,
        author_email=author_email, code_permalink=code_permalink,
        description=f"Scripted-expert ({name}{noise}) demonstrations of {env_id}, env "
                    f"seeds {seed}-{seed + episodes - 1}; per-step infos {sorted(INFO_KEYS)}")
    env.close()
    return {"episodes": episodes, "steps": sum(len(e.actions) for e in recorded),
            "success_rate": float(np.mean(success)), "dataset_id": dataset_id, "root": str(folder)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Record scripted-expert demonstrations to an .npz file or as a "
                                                 "Minari dataset.")
    parser.add_argument("--env", required=True, help="env id, e.g. SutureGym/NeedleInsert-v3")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0, help="env seed of the first episode")
    parser.add_argument("--config", default=None, help="env config (a shipped name or a YAML path)")
    parser.add_argument("--expert", choices=sorted(EXPERTS), default="clock",
                        help="the scripted expert: clock (ExpertPolicy) or feedback (FeedbackExpert)")
    parser.add_argument("--action-noise", type=float, default=0.0,
                        help="std of Gaussian noise added to the executed actions (the expert's are recorded too)")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", help="output .npz path")
    where.add_argument("--minari", nargs="?", const="", metavar="DATASET_ID",
                       help="write a Minari dataset (default id: suture_gym/<Task>-v<k>/expert-v0)")
    parser.add_argument("--root", default=None,
                        help="Minari datasets folder (default: $MINARI_DATASETS_PATH, else ~/.minari/datasets)")
    args = parser.parse_args(argv)
    env_kwargs = {"config": args.config} if args.config is not None else None
    if args.minari is None:
        if args.root is not None:
            parser.error("--root applies to --minari only")
        summary = record(args.env, args.episodes, args.out, seed=args.seed, env_kwargs=env_kwargs,
                         expert=args.expert, action_noise=args.action_noise)
        where_to = summary["out"]
    else:
        summary = record_minari(args.env, args.episodes, args.minari or None, seed=args.seed, root=args.root,
                                env_kwargs=env_kwargs, expert=args.expert, action_noise=args.action_noise)
        where_to = f"Minari dataset {summary['dataset_id']!r} in {summary['root']}"
    print(f"{summary['episodes']} episodes, {summary['steps']} steps, success rate "
          f"{summary['success_rate']:.2f} -> {where_to}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
