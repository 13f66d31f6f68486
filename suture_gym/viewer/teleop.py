"""Teleoperation (keyboard and on-screen buttons) and the recording of teleoperated episodes.

:class:`Teleop` holds a *proxy*, the pose a haptic device's handle would have: keys move it in steps, and every
env step the needle holder is pulled toward it through the env's own virtual coupling
(:meth:`~suture_gym.envs.base.SutureEnv.action_toward`). In ``wrench`` mode the action is the coupling's wrench
on the grip point (N, N m, clipped to the action box), as an impedance-type haptic device commands; in
``pose_delta`` mode it is the change of the holder target toward the proxy (at most ``action.max_translation`` m
and ``action.max_rotation`` rad per step and component). Either way the action is what the env records, so a
recorded episode replays in the same action mode.

Keys (:data:`KEYS`, world frame, z up): D/A +x/-x, W/S +y/-y, E/Q +z/-z move the proxy by the translation
step; L/J, I/K, O/U turn it about +x/-x, +y/-y, +z/-z through the grip point by the rotation step; R puts the
proxy back on the grip (drops what the holder has not followed). A 3D mouse (:class:`SpaceMouse`, pyspacemouse)
moves the proxy continuously instead.

:class:`DemoRecorder` buffers teleoperated episodes and writes them as a Minari dataset in the format of
:mod:`suture_gym.baselines.datasets` (the scripted expert's), which
:func:`suture_gym.baselines.imitation.load_minari_demos` reads for behaviour cloning.
"""

from __future__ import annotations

import math

import numpy as np

from suture_gym.sim.quat import quat_from_rotation_vector, quat_mul, quat_normalize

#: Key -> (component, sign): components 0-2 move the proxy along world x, y, z, 3-5 turn it about them.
KEYS: dict[str, tuple[int, int]] = {
    "D": (0, 1), "A": (0, -1), "W": (1, 1), "S": (1, -1), "E": (2, 1), "Q": (2, -1),
    "L": (3, 1), "J": (3, -1), "I": (4, 1), "K": (4, -1), "O": (5, 1), "U": (5, -1),
}
#: Key that puts the proxy back on the grip.
RESYNC_KEY = "R"


def _step(name: str, value, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not (
            0.0 < value <= high):
        raise ValueError(f"{name} must be a finite number in (0, {high}], got {value!r}")
    return float(value)


class Teleop:
    """Keyboard teleoperation of one env through a proxy pose (module docstring).

    Args:
        env: a SutureGym env (wrapped or not).
        translation_step: proxy move per key press, m (at most 1 cm).
        rotation_step: proxy turn per key press, rad (at most 0.5).

    Call :meth:`sync` after every ``reset`` (the proxy starts on the grip), then :meth:`press` for key presses
    and :meth:`action` once per env step.
    """

    def __init__(self, env, translation_step: float = 5.0e-4, rotation_step: float = 0.05) -> None:
        self.env = env.unwrapped
        self.translation_step = _step("translation_step", translation_step, 0.01)
        self.rotation_step = _step("rotation_step", rotation_step, 0.5)
        self.position = np.zeros(3)
        self.quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.presses = 0

    def set_steps(self, translation_step: float, rotation_step: float) -> None:
        """Change the per-press translation (m) and rotation (rad) steps."""
        self.translation_step = _step("translation_step", translation_step, 0.01)
        self.rotation_step = _step("rotation_step", rotation_step, 0.5)

    def sync(self) -> None:
        """Put the proxy on the needle's current grip pose."""
        self.position, self.quat = self.env.sim.grip_pose()

    def press(self, key: str) -> None:
        """Act on one key press (:data:`KEYS`, or :data:`RESYNC_KEY`); case-insensitive."""
        k = str(key).upper()
        if k == RESYNC_KEY:
            self.sync()
        elif k in KEYS:
            component, sign = KEYS[k]
            delta = np.zeros(6)
            delta[component] = sign * (self.translation_step if component < 3 else self.rotation_step)
            self.nudge(delta[:3], delta[3:])
        else:
            raise ValueError(f"unknown teleoperation key {key!r}; keys: {sorted(KEYS)} and {RESYNC_KEY!r}")
        self.presses += 1

    def nudge(self, translation: np.ndarray, rotation: np.ndarray) -> None:
        """Move the proxy by ``translation`` (3,) m and turn it by the rotation vector ``rotation`` (3,) rad
        (world frame, about the proxy's own point)."""
        t = np.asarray(translation, dtype=np.float64)
        r = np.asarray(rotation, dtype=np.float64)
        if t.shape != (3,) or r.shape != (3,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(r))):
            raise ValueError(f"translation and rotation must be finite (3,) vectors, got {t!r} and {r!r}")
        self.position = self.position + t
        self.quat = quat_normalize(quat_mul(quat_from_rotation_vector(r), self.quat))

    def action(self) -> np.ndarray:
        """``(6,) float32`` action in [-1, 1] pulling the holder toward the proxy (module docstring)."""
        return self.env.action_toward(self.position, self.quat)


class SpaceMouse:
    """A 3D mouse moving a :class:`Teleop`'s proxy (``pip install 'suture_gym[spacemouse]'``: pyspacemouse 2, which
    needs the system's hidapi library, Debian ``libhidapi-hidraw0``).

    Each :meth:`poll` reads the device's deflection (x, y, z, roll, pitch, yaw in [-1, 1], right-handed with z up:
    pyspacemouse's ``HID_Z_UP`` convention, the scene's frame) and moves the proxy at ``speed`` m/s and turns it
    at ``turn_rate`` rad/s per unit deflection over ``dt`` (simulated) seconds; deflections below ``deadband``
    count as 0.

    Args:
        teleop: the proxy's owner.
        device: an opened device with ``read()`` and ``close()`` (None: open the first one attached;
            RuntimeError from pyspacemouse when there is none).
        speed: proxy speed at full deflection, m/s (a surgeon's hand: 2 cm/s).
        turn_rate: proxy turn rate at full deflection, rad/s.
        deadband: deflection treated as rest, in [0, 1).
    """

    def __init__(self, teleop: Teleop, device=None, speed: float = 0.02, turn_rate: float = 1.0,
                 deadband: float = 0.05) -> None:
        self.teleop = teleop
        self.speed = _step("speed", speed, 1.0)
        self.turn_rate = _step("turn_rate", turn_rate, 10.0)
        if isinstance(deadband, bool) or not isinstance(deadband, (int, float)) or not 0.0 <= deadband < 1.0:
            raise ValueError(f"deadband must be a number in [0, 1), got {deadband!r}")
        self.deadband = float(deadband)
        if device is None:
            try:
                import pyspacemouse
            except ImportError as err:
                raise ImportError("a 3D mouse needs pyspacemouse: pip install 'suture_gym[spacemouse]'") from err
            device = pyspacemouse.open(axis_convention=pyspacemouse.AxisConvention.HID_Z_UP)
        self.device = device

    def poll(self, dt: float) -> bool:
        """Read the device and move the proxy for ``dt`` s; returns whether it was deflected."""
        state = self.device.read()
        d = np.array([state.x, state.y, state.z, state.roll, state.pitch, state.yaw], dtype=np.float64)
        d[np.abs(d) < self.deadband] = 0.0
        if not np.any(d):
            return False
        self.teleop.nudge(d[:3] * self.speed * dt, d[3:] * self.turn_rate * dt)
        return True

    def close(self) -> None:
        """Release the device."""
        self.device.close()


class DemoRecorder:
    """Teleoperated episodes, buffered step by step and written as a Minari dataset.

    :meth:`start` at each reset, :meth:`add` after each step; :meth:`save` writes every episode recorded so far
    (an episode still running is closed first, its last step marked truncated) with
    :func:`suture_gym.baselines.datasets.write_minari` and empties the buffer. Needs the repository's ``agents`` package
    and Minari (``pip install 'suture_gym[data]'``).
    """

    def __init__(self) -> None:
        self.episodes: list = []
        self._current = None

    @property
    def steps(self) -> int:
        """Steps recorded in finished episodes and the running one."""
        running = len(self._current.actions) if self._current is not None else 0
        return running + sum(len(e.actions) for e in self.episodes)

    def start(self, seed: int | None, obs, info: dict) -> None:
        """Begin an episode at a reset with env seed ``seed`` (closing the running one)."""
        from suture_gym.baselines.datasets import RecordedEpisode

        self.finish()
        self._current = RecordedEpisode(seed=-1 if seed is None else int(seed), reset_obs=obs, reset_info=info)

    def add(self, action: np.ndarray, obs, reward: float, terminated: bool, truncated: bool, info: dict) -> None:
        """Record one step; an episode that ends here is closed."""
        if self._current is None:
            raise RuntimeError("DemoRecorder.add before start: call start() at the reset")
        e = self._current
        e.actions.append(np.asarray(action, dtype=np.float32).copy())
        e.observations.append(obs)
        e.rewards.append(float(reward))
        e.terminated.append(bool(terminated))
        e.truncated.append(bool(truncated))
        e.infos.append(info)
        if terminated or truncated:
            self.finish()

    def finish(self) -> None:
        """Close the running episode (kept if it has a step; a last step that did not end it is marked
        truncated: the demonstrator stopped there)."""
        e, self._current = self._current, None
        if e is None or not e.actions:
            return
        if not (e.terminated[-1] or e.truncated[-1]):
            e.truncated[-1] = True
        self.episodes.append(e)

    def save(self, env, dataset_id: str, root=None, algorithm_name: str = "suture_gym.viewer (teleop)") -> dict:
        """Write the recorded episodes as the Minari dataset ``dataset_id`` under ``root`` (see
        :func:`suture_gym.baselines.datasets.datasets_root`) for the env ``env`` (made by ``gym.make``, for its spec);
        ``algorithm_name`` names who acted in the dataset's metadata.

        Raises:
            ValueError: nothing recorded, or the dataset exists already.

        Returns:
            ``{episodes, steps, dataset_id, root}``.
        """
        from suture_gym.baselines.datasets import write_minari

        self.finish()
        if not self.episodes:
            raise ValueError("no teleoperated step recorded: nothing to save")
        steps = sum(len(e.actions) for e in self.episodes)
        folder = write_minari(dataset_id, self.episodes, env, root=root, algorithm_name=algorithm_name,
                              description=f"Demonstrations of {env.spec.id if env.spec else env} recorded in the "
                                          f"suture_gym viewer ({algorithm_name})")
        summary = {"episodes": len(self.episodes), "steps": steps, "dataset_id": dataset_id, "root": str(folder)}
        self.episodes = []
        return summary
