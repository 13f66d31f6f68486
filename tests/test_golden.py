"""Golden trajectories: seeded episodes of every task, compared bit for bit against a stored reference.

Each case runs one env id through the public Gymnasium API (``gym.make``, ``reset``, ``step``) for a fixed
number of steps with the scripted expert or seeded random actions, resetting when an episode ends. Every
observation, reward, ``terminated``/``truncated`` flag and ``info`` value is serialised exactly (IEEE bytes for
floats, no rounding) into one SHA-256 per case. A refactoring that changes any bit of any trajectory changes the
digest.

Bit-identity holds on the machine type that wrote the reference: numba compiles for the host CPU and numpy
dispatches its kernels by CPU features, so a different CPU may round differently and, through the contact and
puncture thresholds, end up on a different trajectory. The reference records the CPU model, the CPU numba
compiles for and the library versions; on a machine that differs, the digests are not compared, and the test
compares the per-step rewards of the first :data:`PREFIX_STEPS` steps of each case within :data:`PREFIX_RTOL`
instead (still a real check of the physics and the task layer, before any threshold can branch differently).

Write the reference (only when a change of behaviour is intended, and say so in the commit):
``python tests/test_golden.py --write``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import platform
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from suture_gym.configs import ENV_DIR

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = Path(__file__).resolve().parent / "data" / "golden_trajectories.json"
CONFIGS = ENV_DIR
#: Steps compared with a tolerance when the reference comes from another machine type.
PREFIX_STEPS = 40
#: Relative tolerance of that comparison.
PREFIX_RTOL = 1.0e-6

#: (name, env id, config file or None, policy, env seed, steps)
CASES = (
    ("needle_insert_expert", "SutureGym/NeedleInsert-v3", None, "expert", 0, 480),
    ("needle_insert_random", "SutureGym/NeedleInsert-v3", None, "random", 1, 200),
    ("needle_insert_deterministic_expert", "SutureGym/NeedleInsert-v3", "needle_insert_deterministic.yaml", "expert", 7,
     300),
    ("needle_insert_pose_delta_random", "SutureGym/NeedleInsert-v3", "needle_insert_pose_delta.yaml", "random", 2, 120),
    ("suture_throw_expert", "SutureGym/SutureThrow-v3", None, "expert", 0, 400),
    ("suture_throw_random", "SutureGym/SutureThrow-v3", None, "random", 3, 200),
    ("wound_closure_expert", "SutureGym/WoundClosure-v3", None, "expert", 0, 400),
    ("wound_closure_random", "SutureGym/WoundClosure-v3", None, "random", 4, 200),
    ("needle_insert_goal_random", "SutureGym/NeedleInsertGoal-v3", None, "random", 5, 100),
)


def _feed(h, value) -> None:
    """Feed ``value`` into the hash ``h`` exactly and unambiguously (type-tagged)."""
    if isinstance(value, dict):
        h.update(b"D%d" % len(value))
        for key in sorted(value, key=str):
            _feed(h, str(key))
            _feed(h, value[key])
    elif isinstance(value, (list, tuple)):
        h.update(b"L%d" % len(value))
        for item in value:
            _feed(h, item)
    elif isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(b"A" + a.dtype.str.encode() + str(a.shape).encode())
        h.update(a.tobytes())
    elif isinstance(value, (bool, np.bool_)):
        h.update(b"B1" if value else b"B0")
    elif isinstance(value, (int, np.integer)):
        h.update(b"I" + str(int(value)).encode())
    elif isinstance(value, (float, np.floating)):
        h.update(b"F" + struct.pack("<d", float(value)))
    elif isinstance(value, str):
        h.update(b"S%d:" % len(value) + value.encode())
    elif value is None:
        h.update(b"N")
    else:
        raise TypeError(f"cannot hash a {type(value).__name__} in a golden trajectory")


def run_case(env_id: str, config: str | None, policy: str, seed: int, steps: int) -> tuple[str, list[float], int]:
    """Run one case; returns (SHA-256 hex digest, per-step rewards, number of episodes started)."""
    import gymnasium as gym

    import suture_gym.envs  # noqa: F401  (registers the ids)
    from suture_gym.baselines.expert import ExpertPolicy

    kwargs = {} if config is None else {"config": str(CONFIGS / config)}
    env = gym.make(env_id, **kwargs)
    h = hashlib.sha256()
    rng = np.random.default_rng(seed)
    expert = ExpertPolicy(env) if policy == "expert" else None
    obs, info = env.reset(seed=seed)
    _feed(h, (obs, info))
    episodes, rewards = 1, []
    for _ in range(steps):
        if expert is not None:
            action = expert(obs)
        else:
            action = rng.uniform(-1.0, 1.0, 6).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        _feed(h, (action, obs, reward, terminated, truncated, info))
        rewards.append(float(reward))
        if terminated or truncated:
            obs, info = env.reset()
            _feed(h, (obs, info))
            episodes += 1
            if expert is not None:
                expert.reset()
    env.close()
    return h.hexdigest(), rewards, episodes


def machine() -> dict:
    """What decides floating-point rounding here: CPU model and the numeric libraries' versions."""
    import llvmlite
    import llvmlite.binding
    import numba

    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        # the CPU numba compiles for: a virtual machine's model name ("AMD EPYC") hides the generation, whose
        # instruction set (AVX-512 or not, FMA) decides the rounding of the compiled kernels
        "host_cpu": llvmlite.binding.get_host_cpu_name(),
        "machine": platform.machine(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "llvmlite": llvmlite.__version__,
    }


def _reference() -> dict:
    if not REFERENCE.exists():
        pytest.fail(f"no golden reference at {REFERENCE}; write it with `python tests/test_golden.py --write`")
    return json.loads(REFERENCE.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_golden_trajectory(case):
    name, env_id, config, policy, seed, steps = case
    ref = _reference()
    assert name in ref["cases"], f"case {name} missing from the reference; rewrite it"
    expected = ref["cases"][name]
    digest, rewards, episodes = run_case(env_id, config, policy, seed, steps)
    assert len(rewards) == len(expected["rewards"]) == steps
    if ref["machine"] == machine():
        assert episodes == expected["episodes"], f"{name}: {episodes} episodes, reference {expected['episodes']}"
        first = next((i for i, (a, b) in enumerate(zip(rewards, expected["rewards"], strict=True)) if a != b), None)
        assert digest == expected["sha256"], (
            f"{name}: trajectory differs from the reference (first differing reward at step {first})"
        )
    else:
        np.testing.assert_allclose(
            rewards[:PREFIX_STEPS], expected["rewards"][:PREFIX_STEPS], rtol=PREFIX_RTOL, atol=1e-12,
            err_msg=f"{name}: rewards differ from the reference (written on {ref['machine']})",
        )


def test_hash_is_exact_and_type_tagged():
    """The serialisation tells apart values a rounding or a type change would confuse."""

    def digest(value) -> str:
        h = hashlib.sha256()
        _feed(h, value)
        return h.hexdigest()

    assert digest(1.0) != digest(math.nextafter(1.0, 2.0))
    assert digest(np.float32(1.0)) == digest(1.0)
    assert digest(np.zeros(3, np.float32)) != digest(np.zeros(3, np.float64))
    assert digest(True) != digest(1)
    assert digest({"a": 1.0}) != digest({"b": 1.0})
    assert digest(["ab", "c"]) != digest(["a", "bc"])
    with pytest.raises(TypeError, match="object"):
        digest(object())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="write the reference file")
    args = parser.parse_args()
    out = {"machine": machine(), "cases": {}}
    for name, env_id, config, policy, seed, steps in CASES:
        digest, rewards, episodes = run_case(env_id, config, policy, seed, steps)
        out["cases"][name] = {"sha256": digest, "episodes": episodes, "rewards": rewards}
        print(f"{name}: {digest[:16]} ({episodes} episode(s), return {math.fsum(rewards):.6g})", flush=True)
    if args.write:
        REFERENCE.parent.mkdir(exist_ok=True)
        REFERENCE.write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {REFERENCE}")


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
