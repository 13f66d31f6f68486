"""Render a picture of each anatomical scene kind with the project's renderer (``render_mode="rgb_array"``): the
scripted expert's needle just out at the far edge of its first stitch (env seed 0, no randomisation) on the
abdominal wall (WoundClosure config), the hand
(SutureThrow config) and a user's mesh (``scene.kind = mesh``: the hand's surface written as an OBJ and filled
by ``tetrahedralize_surface``, the incision given as points, as in ``docs/examples/mesh_suture_throw.yaml``).

Usage::

    python scripts/render_scenes.py                  # docs/media/scene_{abdominal_wall,hand,mesh}.png
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from _common import ROOT, configure

configure(threads=1)

import gymnasium as gym  # noqa: E402

import suture_gym.envs  # noqa: E402, F401
from suture_gym.baselines.expert import ExpertPolicy  # noqa: E402
from suture_gym.configs import ENV_DIR  # noqa: E402
from suture_gym.envs.config import read_yaml  # noqa: E402
from suture_gym.render import save_png  # noqa: E402
from suture_gym.sim.anatomy import hand_surface  # noqa: E402

CONFIGS = ENV_DIR
SCENES = {
    "abdominal_wall": ("SutureGym/WoundClosure-v3", CONFIGS / "abdominal_wall_wound_closure.yaml"),
    "hand": ("SutureGym/SutureThrow-v3", CONFIGS / "hand_suture_throw.yaml"),
    "mesh": ("SutureGym/SutureThrow-v3", ROOT / "docs" / "examples" / "mesh_suture_throw.yaml"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "docs" / "media"), help="output folder")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=400)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        hand_surface().export(Path(tmp) / "hand.obj")
        for name, (env_id, path) in SCENES.items():
            config = read_yaml(path)
            config.pop("randomization", None)
            if name == "mesh":
                config["scene"]["path"] = str(Path(tmp) / "hand.obj")
            config["render"] = {"width": args.width, "height": args.height}
            env = gym.make(env_id, config=config, render_mode="rgb_array")
            obs, _ = env.reset(seed=0)
            expert = ExpertPolicy(env)
            while not env.unwrapped.task.state.exited:
                obs, *_ = env.step(expert(obs))
            image = out / f"scene_{name}.png"
            save_png(env.render(), image)
            tissue = env.unwrapped.sim.model.tissue
            print(json.dumps({"scene": name, "path": str(image), "tets": tissue.tet_count,
                              "particles": tissue.particle_count}))
            env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
