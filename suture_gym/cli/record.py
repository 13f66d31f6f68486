"""Record a video of each task, rendered by the env (``render_mode="rgb_array"``), driven by the scripted
expert (:class:`suture_gym.baselines.expert.ExpertPolicy`, the policy whose success rates docs/results.md
reports): the needle turned about its own centre along the planned arcs, then pulled to draw the thread through.

Usage::

    suture-gym record                      # all tasks -> docs/media/<task>.mp4
    suture-gym record --env SutureGym/NeedleInsert-v3 --out /tmp/videos --seconds 3 --speed 0.5

Prints one JSON line per video: path, frames, simulated seconds, size in bytes, success and the episode's
return. Frames are taken every ``--every`` env steps; the video plays at ``--speed`` times real time (fps =
speed / (every * env step)), so the default 5 ms env step and ``--every 8`` give 25 fps at real time. The
episode runs until it ends or ``--seconds`` of simulated time have passed; its last frame is held for a second.
The bottom-left gauges show the haptic reaction force on the instrument (against ``action.max_force``) and the
needle tip's contact force (against the puncture threshold).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import gymnasium as gym

import suture_gym.envs  # noqa: F401  (registers the ids)
from suture_gym.baselines.expert import ExpertPolicy
from suture_gym.envs import ENV_IDS
from suture_gym.render import write_video

#: Seconds the last image is held at the end of a video.
HOLD_SECONDS = 1.0


def expert_episode(env: gym.Env, seconds: float, every: int, seed: int, hold_frames: int):
    """Yield frames of one expert episode (and finally a dict summary through ``StopIteration.value``)."""
    obs, _ = env.reset(seed=seed)
    expert = ExpertPolicy(env)
    total, success = 0.0, False
    steps = int(math.ceil(seconds / env.unwrapped.sim.control_dt))
    k = 0
    for k in range(steps):
        if k % every == 0:
            yield env.render()
        obs, reward, terminated, truncated, info = env.step(expert(obs))
        total += float(reward)
        success = success or bool(info["is_success"])
        if terminated or truncated:
            break
    last = env.render()
    for _ in range(hold_frames):
        yield last
    return {"steps": k + 1, "seconds": (k + 1) * env.unwrapped.sim.control_dt, "return": total, "success": success}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="suture-gym record", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=list(ENV_IDS), help="env ids to record")
    parser.add_argument("--out", default="docs/media", help="output folder (default: docs/media of the current "
                                                            "directory)")
    parser.add_argument("--seconds", type=float, default=30.0, help="longest simulated time, s")
    parser.add_argument("--every", type=int, default=8, help="env steps per video frame")
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed, times real time")
    parser.add_argument("--size", default="480x360", help="frame size WIDTHxHEIGHT, pixels")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not (math.isfinite(args.speed) and args.speed > 0.0):
        parser.error(f"--speed must be a number > 0, got {args.speed}")
    if args.every < 1:
        parser.error(f"--every must be >= 1, got {args.every}")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size must be WIDTHxHEIGHT in pixels, e.g. 480x360, got {args.size!r}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for env_id in args.env:
        env = gym.make(env_id, render_mode="rgb_array", config={"render": {"width": width, "height": height}})
        task = env.unwrapped.config.task
        path = out / f"{task}.mp4"
        fps = args.speed / (args.every * env.unwrapped.sim.control_dt)
        frames = expert_episode(env, args.seconds, args.every, args.seed, round(HOLD_SECONDS * fps))
        summary = {}

        def collect(gen=frames, store=summary):
            store.update((yield from gen))

        count = write_video(collect(), path, fps=fps, quality=7.0)
        env.close()
        print(json.dumps({"env_id": env_id, "path": str(path), "frames": count, "fps": fps,
                          "bytes": path.stat().st_size, **summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
