"""The package as users install it: the wheel built from this checkout, installed in a fresh virtual environment
outside the checkout and run from another directory, reaches every id, the shipped configs, the viewer, the
training and the evaluation.

The fresh environment borrows this interpreter's installed dependencies through a ``.pth`` line (the test must
not download anything), so what it proves is that the wheel carries every module and data file it needs: nothing
of the checkout is on its path.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow

PLAY_EVERY_ID = """
import json, sys
import gymnasium as gym
import numpy as np
import suture_gym
from suture_gym.envs import ENV_IDS, GOAL_ENV_IDS
from suture_gym.configs import env_config_names

assert suture_gym.__file__.startswith(sys.prefix), suture_gym.__file__
played = {}
for env_id in [*ENV_IDS, *GOAL_ENV_IDS]:
    env = gym.make(env_id)
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(10):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert np.isfinite(reward)
        if terminated or truncated:
            env.reset()
    env.close()
    played[env_id] = 10
env = gym.make("SutureGym/NeedleInsert-v3", config="needle_insert_deterministic")
env.reset(seed=0)
env.close()
print(json.dumps({"played": played, "configs": env_config_names()}))
"""


def run(command: list[str], cwd: Path, env: dict, timeout: float = 900) -> subprocess.CompletedProcess:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{command} exited {result.returncode}:\n{result.stdout}\n{result.stderr}"
    return result


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(python, suture-gym, work folder, environment)`` of a fresh venv with the wheel installed."""
    build = tmp_path_factory.mktemp("wheel")
    source = tmp_path_factory.mktemp("source")
    # the files git knows of, so that no build folder or cache of the checkout can slip into the wheel
    listed = run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                 env=os.environ.copy()).stdout.split("\0")
    for name in filter(None, listed):
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, source / name)
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(build),
         str(source)], cwd=build, env=os.environ.copy())
    (wheel,) = build.glob("suture_gym-*.whl")
    venv = tmp_path_factory.mktemp("venv")
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=build, env=os.environ.copy())
    python = venv / "bin" / "python"
    site = Path(run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=build,
                    env=os.environ.copy()).stdout.strip())
    (site / "borrowed_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path_factory.mktemp("numba_cache"))
    run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q",
         str(wheel)], cwd=build, env=env)
    work = tmp_path_factory.mktemp("elsewhere")
    return python, venv / "bin" / "suture-gym", work, env


def test_the_wheel_holds_the_package_data_and_no_checkout_files(installed):
    python, _, work, env = installed
    listing = json.loads(run([str(python), "-c", (
        "import json, suture_gym, pathlib; root = pathlib.Path(suture_gym.__file__).parent; "
        "print(json.dumps(sorted(str(p.relative_to(root)) for p in root.rglob('*') if p.is_file() "
        "and '__pycache__' not in p.parts)))")], cwd=work, env=env).stdout)
    shipped = sorted(p.relative_to(ROOT / "suture_gym").as_posix() for p in (ROOT / "suture_gym" / "configs").rglob(
        "*.y*ml"))
    assert shipped and set(shipped) <= set(listing)
    assert {"baselines/expert.py", "cli/__init__.py", "viewer/app.py"} <= set(listing)
    assert not any(name.startswith(("tests", "scripts")) for name in listing)


def test_every_id_steps_from_the_installed_wheel(installed):
    python, _, work, env = installed
    summary = json.loads(run([str(python), "-c", PLAY_EVERY_ID], cwd=work, env=env).stdout)
    assert len(summary["played"]) == 6 and set(summary["played"].values()) == {10}
    assert "needle_insert_deterministic" in summary["configs"]


def test_the_command_line_trains_evaluates_and_views(installed):
    python, cli, work, env = installed
    assert "train" in run([str(cli), "--help"], cwd=work, env=env).stdout
    assert "hanging_bar" in run([str(python), "-m", "suture_gym", "validate", "--list"], cwd=work, env=env).stdout
    viewed = run([str(cli), "view", "--env", "SutureGym/NeedleInsert-v3", "--policy", "expert", "--steps", "20",
                  "--port", "0"], cwd=work, env=env)
    assert "20 env steps" in viewed.stderr
    trained = json.loads(run([str(cli), "train", "--algo", "ppo", "--env", "SutureGym/NeedleInsert-v3",
                              "--from-scratch", "--n-timesteps", "2048", "--eval-freq", "0", "--no-progress",
                              "--out", "runs"], cwd=work, env=env).stdout)
    model = Path(trained["model"])
    assert trained["timesteps"] >= 2048 and (work / model).is_file()
    evaluated = json.loads(run([str(cli), "evaluate", "--env", "SutureGym/NeedleInsert-v3", "--policy", str(model),
                                "--episodes", "2", "--json", "--no-progress"], cwd=work, env=env).stdout)
    assert evaluated["episodes"] == 2 and 0.0 <= evaluated["success_rate"] <= 1.0
