"""Record a short video of each task, rendered by the env (``render_mode="rgb_array"``), driven by the scripted
surgeon (:meth:`suture_gym.envs.SutureEnv.scripted_action`): the needle turned about its own centre along the
planned arcs, then pulled to draw the thread through.

Usage::

    python scripts/record_video.py                      # all tasks -> docs/media/<task>.mp4
    python scripts/record_video.py --env SutureGym/NeedleInsert-v0 --out /tmp/videos --seconds 3

Prints one JSON line per video: path, frames, simulated seconds, size in bytes, success and the episode's
return. Frames are taken every ``--every`` env steps; the video plays at real time (fps = 1 / (every * env
step)), so the default 5 ms env step and ``--every 8`` give 25 fps.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from _common import ROOT, configure

configure(threads=1)

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import suture_gym.envs  # noqa: E402, F401  (registers the ids)
from suture_gym.envs import ENV_IDS  # noqa: E402
from suture_gym.render import write_video  # noqa: E402

#: Tip-angle advance of the scripted surgeon per task, rad/s (a thread anchored by its tail, as in wound_closure,
#: needs the slower turn to stay stable; see the report on the coupling's robustness).
TURN_RATE = {"needle_insert": 2.0, "suture_throw": 1.0, "wound_closure": 1.0}
#: Frames the last image is held at the end of a video.
HOLD_FRAMES = 12
#: Pull speed once the needle is out, m/s.
PULL_SPEED = 0.02


def scripted_episode(env: gym.Env, seconds: float, every: int, seed: int):
    """Yield frames of one scripted episode (and finally a dict summary through ``StopIteration.value``)."""
    unwrapped = env.unwrapped
    sim = unwrapped.sim
    env.reset(seed=seed)
    total, success, steps = 0.0, False, int(math.ceil(seconds / sim.control_dt))
    stitch = 0
    angle = sim.arcs[0].entry_angle - unwrapped.config.plan.start_angle
    needle_arc = sim.model.needle.shape.arc_angle
    k = 0
    for k in range(steps):
        if k % every == 0:
            yield env.render()
        state = unwrapped.task.state
        if state.stitch != stitch:  # next stitch: start again before its entry
            stitch = state.stitch
            angle = sim.arcs[stitch].entry_angle - unwrapped.config.plan.start_angle
        arc = sim.arcs[stitch]
        if angle < arc.exit_angle + needle_arc + 0.3:
            angle += TURN_RATE[unwrapped.config.task] * sim.control_dt
            action = unwrapped.scripted_action(angle)
        else:
            action = _pull_action(unwrapped, arc)
        _, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        success = success or bool(info["is_success"])
        if terminated or truncated:
            break
    last = env.render()
    for _ in range(HOLD_FRAMES):
        yield last
    return {"steps": k + 1, "return": total, "success": success}


def _pull_action(unwrapped, arc) -> np.ndarray:
    """Hold the needle's orientation and move the grip along the stitch's pull direction (back across the wound
    and up); the action's force limit bounds the thread tension."""
    grip, quat = unwrapped.sim.grip_pose()
    return unwrapped.action_toward(grip + PULL_SPEED * unwrapped.sim.control_dt * arc.pull_direction, quat)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=list(ENV_IDS), help="env ids to record")
    parser.add_argument("--out", default=str(ROOT / "docs" / "media"), help="output folder")
    parser.add_argument("--seconds", type=float, default=None, help="simulated seconds (default per task)")
    parser.add_argument("--every", type=int, default=8, help="env steps per video frame")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    default_seconds = {"needle_insert": 1.5, "suture_throw": 7.5, "wound_closure": 25.0}
    for env_id in args.env:
        env = gym.make(env_id, render_mode="rgb_array")
        task = env.unwrapped.config.task
        seconds = args.seconds or default_seconds[task]
        path = out / f"{task}.mp4"
        frames = scripted_episode(env, seconds, args.every, args.seed)
        summary = {}

        def collect(gen=frames, store=summary):
            store.update((yield from gen))

        fps = 1.0 / (args.every * env.unwrapped.sim.control_dt)
        count = write_video(collect(), path, fps=fps, quality=7.0)
        env.close()
        print(json.dumps({"env_id": env_id, "path": str(path), "frames": count, "fps": fps,
                          "bytes": path.stat().st_size, **summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
