"""The viewer application: ``python -m suture_gym.viewer --env ID [options]`` (``--help`` lists them).

It serves one env on a viser page (``http://127.0.0.1:8080`` by default; the simulation runs whether or not a
browser is connected) and steps it with a driver: a policy (``--policy expert | random | path/to/model.zip``,
the loaders of :mod:`suture_gym.baselines.evaluation`, a model with the VecNormalize statistics saved beside it) or the
teleoperator (``--policy teleop``, the default; :class:`~suture_gym.viewer.teleop.Teleop`; ``--spacemouse`` adds a
3D mouse). A teleoperation key pressed (or the 3D mouse deflected) while a policy drives takes over from it.

Page: the scene and read-outs of :class:`~suture_gym.render.live.LiveView`; *Controls*: pause, single step,
reset with a seed, speed (simulated seconds per wall-clock second; the simulator's own rate caps it), driver;
*View*: tissue opacity, each layer shown or hidden; *Teleoperation*: buttons for every key and the step sizes;
*Record*: record episodes and save them as a Minari dataset (:class:`~suture_gym.viewer.teleop.DemoRecorder`).
Keyboard (the page's hotkeys): the teleoperation keys of :data:`~suture_gym.viewer.teleop.KEYS`, R (proxy back to
the grip), space (pause / resume), enter (one step).

Every GUI callback calls a public method of :class:`ViewerApp` (:meth:`~ViewerApp.press`,
:meth:`~ViewerApp.set_paused`, :meth:`~ViewerApp.step_once`, :meth:`~ViewerApp.reset`, ...), under one lock shared
with the stepping loop, so a script (or a test) drives the viewer exactly as the page does.

It sits above the env layer, beside :mod:`suture_gym.baselines` (policies, Minari datasets), which it uses.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import suture_gym  # noqa: F401  (registers the ids)
from suture_gym.baselines.datasets import default_dataset_id
from suture_gym.baselines.evaluation import episode_end, make_policy, model_vecnormalize
from suture_gym.render.live import LAYERS, EpisodeStatus, LiveView
from suture_gym.viewer.teleop import KEYS, RESYNC_KEY, DemoRecorder, SpaceMouse, Teleop

#: The teleoperator as a driver (``--policy teleop``).
TELEOP = "teleop"
#: Seconds an ended episode stays on screen before a policy's next episode starts.
END_HOLD_S = 1.0


class ViewerApp:
    """One env on a viser page, stepped by a policy or the teleoperator (module docstring).

    Args:
        env_id: a registered id (``SutureGym/NeedleInsert-v3``, ...).
        config: env config (a YAML path or a mapping), as ``gym.make(env_id, config=...)``.
        policy: ``teleop``, ``expert``, ``random`` or the path of a saved SB3 model.
        action_mode: None (the config's) or ``wrench`` / ``pose_delta``.
        seed: env seed of the first episode (a policy's later episodes take the next seeds).
        host, port: where to serve the page (port 0: any free port).
        fps: most frames pushed to the page per second.
        speed: simulated seconds per wall-clock second to aim for; None: as fast as the simulator runs.

    :attr:`controls` holds the page's inputs (viser handles) by label; assigning one's ``value`` runs its callback
    as a change in the page does.
    """

    def __init__(self, env_id: str, config=None, policy: str = TELEOP, action_mode: str | None = None,
                 seed: int = 0, host: str = "127.0.0.1", port: int = 8080, fps: float = 30.0,
                 speed: float | None = 1.0) -> None:
        kwargs = {k: v for k, v in (("config", config), ("action_mode", action_mode)) if v is not None}
        self.env = gym.make(env_id, **kwargs)
        self.env_id = env_id
        unwrapped = self.env.unwrapped
        self.control_dt = unwrapped.sim.control_dt
        self.policy_name = policy
        self._policy = None
        if policy != TELEOP:
            self._policy = make_policy(policy, self.env, seed, model_vecnormalize(policy))
        self.driver = TELEOP if self._policy is None else "policy"
        self.teleop = Teleop(self.env)
        #: The attached 3D mouse (:meth:`attach_spacemouse`), polled before every step.
        self.spacemouse: SpaceMouse | None = None
        self.recorder = DemoRecorder()
        self.recording = False
        self._recorded_drivers: set[str] = set()
        self.paused = False
        self.speed: float | None = None
        self.set_speed(speed)
        self.view = LiveView(host, port, fps, unwrapped.config.action.max_force, label=f"suture_gym {env_id}")
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self.seed = seed
        self.steps = 0
        self.episode_return = 0.0
        self.info: dict = {}
        self.end: str | None = None
        self._ended_at = 0.0
        self._message = None
        self._gui()
        self.reset(seed)

    # ------------------------------------------------------------------------------------------------------
    # What the GUI calls
    # ------------------------------------------------------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """Start an episode with env seed ``seed`` (None: the next seed after the current one)."""
        with self._lock:
            self.seed = self.seed + 1 if seed is None else int(seed)
            self.controls["Seed"].value = self.seed
            obs, info = self.env.reset(seed=self.seed)
            self._obs = obs
            self.teleop.sync()
            if hasattr(self._policy, "reset"):
                self._policy.reset()
            if self.recording:
                self.recorder.start(self.seed, obs, info)
            self.steps, self.episode_return, self.info, self.end = 0, 0.0, info, None
            self.push(force=True)

    def step_once(self) -> dict | None:
        """One env step with the driver's action; returns its ``info`` (None when the episode has ended)."""
        with self._lock:
            if self.end is not None:
                return None
            if self.spacemouse is not None and self.spacemouse.poll(self.control_dt) and self.driver != TELEOP:
                self.set_driver(TELEOP)  # the 3D mouse takes over like a key, from where the grip is
                self.spacemouse.poll(self.control_dt)
            action = self.teleop.action() if self.driver == TELEOP else np.asarray(self._policy(self._obs))
            obs, reward, terminated, truncated, info = self.env.step(action)
            if self.recording:
                self.recorder.add(action, obs, reward, terminated, truncated, info)
                self._recorded_drivers.add(TELEOP if self.driver == TELEOP else self.policy_name)
            self._obs = obs
            self.steps += 1
            self.episode_return += float(reward)
            self.info = info
            if terminated or truncated:
                self.end = episode_end(info, terminated, truncated)
                self._ended_at = time.perf_counter()
            self.push(force=self.end is not None)
            return info

    def press(self, key: str) -> None:
        """A teleoperation key press (:data:`~suture_gym.viewer.teleop.KEYS` or R); a policy driving hands over
        to the teleoperator, its proxy starting on the grip."""
        with self._lock:
            if self.driver != TELEOP:
                self.set_driver(TELEOP)
            self.teleop.press(key)
            self.view.scene.update_proxy(self.teleop.position, self.teleop.quat)

    def attach_spacemouse(self, device=None) -> None:
        """Drive the proxy with a 3D mouse too (:class:`~suture_gym.viewer.teleop.SpaceMouse`; ``device``: an
        opened device, None: the first one attached). Deflecting it takes over from a policy, as a key does."""
        with self._lock:
            self.spacemouse = SpaceMouse(self.teleop, device)

    def set_driver(self, driver: str) -> None:
        """``teleop`` or ``policy`` (the ``--policy`` given) acts from the next step on."""
        with self._lock:
            if driver not in (TELEOP, "policy"):
                raise ValueError(f"driver must be {TELEOP!r} or 'policy', got {driver!r}")
            if driver == "policy" and self._policy is None:
                raise ValueError("no policy to drive: the viewer was started with --policy teleop")
            if driver == TELEOP and self.driver != TELEOP:
                self.teleop.sync()
            self.driver = driver
            self.controls["Driver"].value = self._driver_label()
            self.view.scene.update_proxy(self.teleop.position if driver == TELEOP else None, self.teleop.quat)

    def set_paused(self, paused: bool) -> None:
        """Pause or resume the stepping loop (:meth:`step_once` still steps)."""
        with self._lock:
            self.paused = bool(paused)
            self.controls["Paused"].value = self.paused
            self.push(force=True)

    def set_speed(self, speed: float | None) -> None:
        """Aim at ``speed`` simulated seconds per wall-clock second (> 0); None: as fast as possible."""
        if speed is not None and (isinstance(speed, bool) or not isinstance(speed, (int, float)) or not (
                0.0 < speed < float("inf"))):
            raise ValueError(f"speed must be a finite number > 0 (simulated s per wall-clock s) or None, got {speed!r}")
        self.speed = None if speed is None else float(speed)

    def set_recording(self, recording: bool) -> None:
        """Start recording (the episode restarts with its seed, so the recording begins at a reset) or stop (the
        running episode is kept, closed as truncated)."""
        with self._lock:
            recording = bool(recording)
            if recording == self.recording:
                return
            self.recording = recording
            self.controls["Record episodes"].value = recording
            if recording:
                self.reset(self.seed)
            else:
                self.recorder.finish()

    def save_demonstrations(self, dataset_id: str | None = None, root: str | Path | None = None) -> dict:
        """Write the recorded episodes as the Minari dataset ``dataset_id`` (default
        ``suture_gym/<Task>-v<k>/teleop-v0``) under ``root`` (default: Minari's datasets folder); recording goes
        on with the next reset. Returns :meth:`DemoRecorder.save`'s summary."""
        with self._lock:
            dataset_id = dataset_id or default_dataset_id(self.env_id, "teleop")
            drivers = ", ".join(sorted(self._recorded_drivers)) or TELEOP
            summary = self.recorder.save(self.env, dataset_id, root, algorithm_name=f"suture_gym.viewer ({drivers})")
            self._recorded_drivers = set()
            self._message = f"saved {summary['episodes']} episode(s), {summary['steps']} steps: {dataset_id}"
            self.push(force=True)
            return summary

    # ------------------------------------------------------------------------------------------------------
    # Loop
    # ------------------------------------------------------------------------------------------------------

    def push(self, force: bool = False) -> bool:
        """Show the current state on the page (rate-limited unless ``force``)."""
        with self._lock:
            unwrapped = self.env.unwrapped
            state = self.end or ("paused" if self.paused else "running")
            driver = TELEOP if self.driver == TELEOP else self.policy_name
            status = EpisodeStatus(self.seed, self.steps, unwrapped.sim.time, self.episode_return, state, driver)
            pushed = self.view.show(unwrapped.view_frame(), unwrapped.planned_arc_points(),
                                    unwrapped.sim.grip_pose()[0], self.info, status, force=force)
            if pushed:
                if self.driver == TELEOP:
                    self.view.scene.update_proxy(self.teleop.position, self.teleop.quat)
                recorded = f"recording: {self.recorder.steps} steps" if self.recording else "not recording"
                self._record_status.content = f"{recorded}  \n{self._message or ''}"
            return pushed

    def tick(self) -> bool:
        """One pass of the loop: a step unless paused or ended (a policy's ended episode is followed by the next
        seed's after :data:`END_HOLD_S`). Returns whether the env stepped."""
        with self._lock:
            if self.end is not None:
                if self.driver != TELEOP and not self.paused and time.perf_counter() - self._ended_at > END_HOLD_S:
                    self.reset()
                return False
            if self.paused:
                return False
            self.step_once()
            return True

    def run(self, max_steps: int | None = None, max_seconds: float | None = None) -> dict:
        """Step until :meth:`stop`, ``max_steps`` env steps or ``max_seconds`` of wall-clock time, pacing the steps
        to :attr:`speed`. Returns ``{steps, seconds, env_steps_per_s, frames, frames_per_s, push_ms}`` (frames
        pushed to the page, mean wall-clock time of one push)."""
        start = time.perf_counter()
        pushes0, push_s0 = self.view.pushes, self.view.push_seconds
        steps = 0
        next_at = start
        while not self._stop.is_set():
            now = time.perf_counter()
            if (max_steps is not None and steps >= max_steps) or (max_seconds is not None
                                                                  and now - start >= max_seconds):
                break
            if self.tick():
                steps += 1
                if self.speed is not None:
                    next_at = max(next_at + self.control_dt / self.speed, now - 0.1)
                    time.sleep(max(0.0, next_at - time.perf_counter()))
            else:
                time.sleep(0.01)
                next_at = time.perf_counter()
        seconds = time.perf_counter() - start
        frames = self.view.pushes - pushes0
        return {"steps": steps, "seconds": seconds, "env_steps_per_s": steps / seconds if seconds > 0 else 0.0,
                "frames": frames, "frames_per_s": frames / seconds if seconds > 0 else 0.0,
                "push_ms": 1e3 * (self.view.push_seconds - push_s0) / frames if frames else 0.0}

    def stop(self) -> None:
        """Make :meth:`run` return after its current step."""
        self._stop.set()

    def close(self) -> None:
        """Stop the page's server, release the 3D mouse and close the env."""
        self.stop()
        if self.spacemouse is not None:
            self.spacemouse.close()
        self.view.close()
        self.env.close()

    # ------------------------------------------------------------------------------------------------------
    # GUI
    # ------------------------------------------------------------------------------------------------------

    def _driver_label(self) -> str:
        return TELEOP if self.driver == TELEOP else f"policy: {self.policy_name}"

    def _gui(self) -> None:
        """Build the page's controls; each is kept in :attr:`controls` under its label."""
        gui = self.view.server.gui
        c = self.controls = {}

        def add(handle):
            c[handle.label] = handle
            return handle

        with gui.add_folder("Controls", order=-10):
            add(gui.add_checkbox("Paused", self.paused, hint="space")).on_update(
                lambda _: self.set_paused(c["Paused"].value))
            add(gui.add_button("Step", hint="one env step (enter)")).on_click(lambda _: self.step_once())
            add(gui.add_number("Seed", self.seed, step=1))
            add(gui.add_button("Reset")).on_click(lambda _: self.reset(int(c["Seed"].value)))
            add(gui.add_checkbox("As fast as possible", self.speed is None))
            add(gui.add_slider("Speed (x real time)", 0.05, 2.0, 0.05, self.speed or 1.0))
            for label in ("As fast as possible", "Speed (x real time)"):
                c[label].on_update(lambda _: self.set_speed(
                    None if c["As fast as possible"].value else float(c["Speed (x real time)"].value)))
            options = [TELEOP] if self._policy is None else [f"policy: {self.policy_name}", TELEOP]
            add(gui.add_dropdown("Driver", options, initial_value=self._driver_label())).on_update(
                lambda _: self.set_driver(TELEOP if c["Driver"].value == TELEOP else "policy"))
        with gui.add_folder("Teleoperation"):
            gui.add_markdown("Keys: D/A ±x, W/S ±y, E/Q ±z (move); L/J, I/K, O/U (turn about x, y, z); R: proxy to "
                             "the grip. The holder follows the proxy (axes) through the virtual coupling.")
            for kind, pairs in (("Move", (("A", "D"), ("S", "W"), ("Q", "E"))),
                                ("Turn", (("J", "L"), ("K", "I"), ("U", "O")))):
                for axis, (minus, plus) in zip("xyz", pairs, strict=True):
                    group = add(gui.add_button_group(f"{kind} {axis}", (f"− ({minus})", f"+ ({plus})")))
                    group.on_click(lambda event, minus=minus, plus=plus: self.press(
                        minus if event.target.value.startswith("−") else plus))
            add(gui.add_slider("Move step (mm)", 0.05, 2.0, 0.05, 1e3 * self.teleop.translation_step))
            add(gui.add_slider("Turn step (deg)", 0.5, 10.0, 0.5, float(np.degrees(self.teleop.rotation_step))))
            for label in ("Move step (mm)", "Turn step (deg)"):
                c[label].on_update(lambda _: self.teleop.set_steps(1e-3 * float(c["Move step (mm)"].value),
                                                                   float(np.radians(c["Turn step (deg)"].value))))
            add(gui.add_button("Proxy to grip (R)")).on_click(lambda _: self.press(RESYNC_KEY))
        with gui.add_folder("View", expand_by_default=False):
            add(gui.add_slider("Tissue opacity", 0.1, 1.0, 0.05, 0.8)).on_update(
                lambda _: self.view.scene.set_tissue_opacity(float(c["Tissue opacity"].value)))
            for layer in LAYERS:
                add(gui.add_checkbox(f"Show {layer.replace('_', ' ')}", True)).on_update(
                    lambda event, layer=layer: self.view.scene.set_visible(layer, event.target.value))
        with gui.add_folder("Record"):
            add(gui.add_checkbox("Record episodes", self.recording)).on_update(
                lambda _: self.set_recording(c["Record episodes"].value))
            add(gui.add_text("Dataset id", default_dataset_id(self.env_id, "teleop")))
            add(gui.add_button("Save as Minari dataset")).on_click(
                lambda _: self._save_from_gui(c["Dataset id"].value))
            self._record_status = gui.add_markdown("not recording")
        for key in (*KEYS, RESYNC_KEY):
            gui.add_command(f"Teleoperation key {key}", hotkey=key).on_trigger(lambda _, k=key: self.press(k))
        gui.add_command("Pause / resume", hotkey="space").on_trigger(lambda _: self.set_paused(not self.paused))
        gui.add_command("One step", hotkey="enter").on_trigger(lambda _: self.step_once())

    def _save_from_gui(self, dataset_id: str) -> None:
        try:
            self.save_demonstrations(dataset_id)
        except (ValueError, OSError, ImportError) as err:  # shown on the page: a callback has nowhere else to report
            self._message = f"not saved: {err}"
            self.push(force=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m suture_gym.viewer",
                                     description="Live 3D view of a SutureGym env in the browser (viser): policy "
                                                 "playback, teleoperation, demonstrations as Minari datasets.")
    parser.add_argument("--env", required=True, help="env id, e.g. SutureGym/NeedleInsert-v3")
    parser.add_argument("--config", default=None,
                        help="env config: a shipped config's name (suture_gym/configs/envs/) or a YAML path")
    parser.add_argument("--policy", default=TELEOP, help="teleop (default), expert, random or a saved model .zip")
    parser.add_argument("--action-mode", choices=("wrench", "pose_delta"), default=None,
                        help="override the config's action.mode")
    parser.add_argument("--seed", type=int, default=0, help="env seed of the first episode")
    parser.add_argument("--host", default="127.0.0.1", help="interface to serve on (0.0.0.0: every interface)")
    parser.add_argument("--port", type=int, default=8080, help="TCP port (0: any free port)")
    parser.add_argument("--fps", type=float, default=30.0, help="most frames pushed to the page per second")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="simulated seconds per wall-clock second to aim for (0: as fast as possible)")
    parser.add_argument("--steps", type=int, default=None, help="exit after this many env steps (default: never)")
    parser.add_argument("--paused", action="store_true", help="start paused")
    parser.add_argument("--spacemouse", action="store_true",
                        help="teleoperate with the first 3D mouse attached (pyspacemouse, the 'spacemouse' extra)")
    args = parser.parse_args(argv)
    if args.speed < 0:
        parser.error(f"--speed must be >= 0, got {args.speed}")
    app = ViewerApp(args.env, config=args.config, policy=args.policy, action_mode=args.action_mode, seed=args.seed,
                    host=args.host, port=args.port, fps=args.fps, speed=args.speed or None)
    try:
        app.set_paused(args.paused)
        if args.spacemouse:
            app.attach_spacemouse()
        print(f"suture_gym viewer: {args.env} at {app.view.url} (Ctrl-C to quit)", file=sys.stderr)
        summary = app.run(max_steps=args.steps)
    except KeyboardInterrupt:
        summary = None
    finally:
        app.close()
    if summary is not None:
        print(f"{summary['steps']} env steps in {summary['seconds']:.1f} s ({summary['env_steps_per_s']:.1f} steps/s), "
              f"{summary['frames']} frames pushed ({summary['frames_per_s']:.1f}/s, {summary['push_ms']:.2f} ms each)",
              file=sys.stderr)
    return 0
