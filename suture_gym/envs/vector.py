"""A natively batched :class:`gymnasium.vector.VectorEnv`: N simulators, stepped in parallel by worker processes.

:func:`make_vector_env` builds one from an env id (``gym.make_vec`` builds Gymnasium's ``SyncVectorEnv`` instead,
so that its ``wrappers`` argument works; see :mod:`suture_gym.envs.registry`). It holds N unwrapped
:class:`~suture_gym.envs.base.SutureEnv` (or :class:`~suture_gym.envs.base.SutureGoalEnv`) instances, batches
their observations into fresh arrays and enforces the time limit itself. Autoreset follows gymnasium's modes:
``NEXT_STEP`` (the default: the step after an episode ends resets that env and returns its first observation with
reward 0) or ``SAME_STEP`` (the env resets within the step that ended it; the last observation and info are in
``infos["final_obs"]`` and ``infos["final_info"]``, as SB3 expects).

Where the envs run (``workers``): ``workers=0`` keeps them in this process and steps them one after another;
``workers=k`` spreads them over k worker processes (contiguous blocks of about N / k envs), which step their
blocks at the same time while this process waits, so a step of N envs takes about the time of N / k steps on a
machine with k free cores. The default is one worker per env up to the cores this process may use
(:func:`default_workers`; none for one env). Workers start by ``forkserver`` (or ``spawn``), like
Stable-Baselines3's ``SubprocVecEnv``: a script that builds a vector env with workers must do so under
``if __name__ == "__main__":``. Each worker builds its own envs (the numba kernels load from the cache in each), and
receives the actions and returns the results through a pipe, so the envs are reachable only through
:meth:`SutureVectorEnv.call`, :meth:`~SutureVectorEnv.get_attr` and :meth:`~SutureVectorEnv.set_attr` (and
snapshots, rendering). Results are the same bit for bit in both modes. An exception in a worker is raised here,
with the worker's traceback as its cause.

Why processes and not threads: a step is Python (the task, the solver's orchestration, the sparse solves)
around numba kernels, so threads would scale only as far as the GIL is released, while processes do not depend
on where the time goes (measurements in docs/notes/environments.md). ``scripts/bench.py`` ``vector_env``
measures the processes' scaling.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from suture_gym.envs.base import EnvState
from suture_gym.envs.registry import MAX_EPISODE_STEPS, env_id_task, make_env


@dataclass(frozen=True)
class StepResult:
    """One env's share of a vector step (unbatched).

    Attributes:
        obs: the observation returned (after an autoreset in ``SAME_STEP`` mode, the new episode's first one).
        reward, terminated, truncated, info: the step's results (reward 0 and both flags False for the step
            that autoresets in ``NEXT_STEP`` mode; ``info`` is then the reset's).
        final_obs, final_info: the finished episode's last observation and info (``SAME_STEP`` mode, when
            the episode ended this step), else None.
    """

    obs: Any
    reward: float
    terminated: bool
    truncated: bool
    info: dict
    final_obs: Any
    final_info: dict | None


@dataclass(frozen=True)
class VectorEnvState:
    """Snapshot of a :class:`SutureVectorEnv`: each env's :class:`~suture_gym.envs.base.EnvState`, the
    steps taken in each episode and which envs reset on the next step (``NEXT_STEP`` mode)."""

    envs: tuple[EnvState, ...]
    elapsed: np.ndarray
    pending_reset: np.ndarray


def _advance(env, payload) -> tuple[StepResult, int, bool]:
    """One env's part of a vector step. ``payload`` is ``(action, pending_reset, elapsed, max_episode_steps,
    same_step)``; returns the :class:`StepResult` and the env's new ``elapsed`` and ``pending_reset``."""
    action, pending_reset, elapsed, max_episode_steps, same_step = payload
    if pending_reset:
        obs, info = env.reset()
        return StepResult(obs, 0.0, False, False, info, None, None), 0, False
    obs, reward, terminated, truncated, info = env.step(action)
    elapsed += 1
    if max_episode_steps is not None and elapsed >= max_episode_steps:
        truncated = True
    final_obs = final_info = None
    pending_reset = False
    if terminated or truncated:
        if same_step:
            final_obs, final_info = obs, info
            obs, info = env.reset()
            elapsed = 0
        else:
            pending_reset = True
    return StepResult(obs, float(reward), bool(terminated), bool(truncated), info, final_obs, final_info), elapsed, \
        pending_reset


def _reset(env, payload):
    seed, options = payload
    return env.reset(seed=seed, options=options)


def _call(env, payload):
    name, args, kwargs = payload
    attr = getattr(env, name)
    return attr(*args, **kwargs) if callable(attr) else attr


def _set_attr(env, payload) -> None:
    name, value = payload
    setattr(env, name, value)


#: What a vector env asks of one of its envs: name -> ``f(env, payload) -> result``.
_OPS: dict[str, Callable[[Any, Any], Any]] = {
    "advance": _advance,
    "reset": _reset,
    "call": _call,
    "set_attr": _set_attr,
    "get_state": lambda env, _: env.get_state(),
    "set_state": lambda env, state: env.set_state(state),
}


class _RemoteTraceback(Exception):
    """The traceback of an exception raised in a worker process (the cause of the exception raised here)."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text

    def __str__(self) -> str:
        return self.text


def _worker(conn, count: int, make_args: tuple) -> None:
    """A worker process: builds ``count`` envs with ``make_env(*make_args)``, then answers ``(op, [(index,
    payload), ...])`` requests with ``("ok", [result, ...])`` or ``("error", (exception, traceback))`` until
    ``("close", None)``."""
    envs: list = []
    try:
        envs = [make_env(*make_args) for _ in range(count)]
        conn.send(("ok", None))
        while True:
            op, items = conn.recv()
            if op == "close":
                break
            try:
                conn.send(("ok", [_OPS[op](envs[i], payload) for i, payload in items]))
            except Exception as exc:  # handed to the parent, which raises it
                conn.send(("error", _picklable(exc)))
    except KeyboardInterrupt:  # the parent is interrupted too and closes the pipes
        pass
    except Exception as exc:  # building the envs failed
        conn.send(("error", _picklable(exc)))
    finally:
        for env in envs:
            env.close()
        conn.close()


def _picklable(exc: Exception) -> tuple[Exception, str]:
    """``(exc, its traceback as text)``, ``exc`` replaced by a RuntimeError naming it if it does not survive a
    pickle round trip (the parent could not read it)."""
    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        exc = RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc, text


class _Workers:
    """``k`` worker processes holding contiguous blocks of the N envs (env ``i`` in block ``i * k // N``)."""

    def __init__(self, num_envs: int, workers: int, make_args: tuple, start_method: str | None) -> None:
        if start_method is None:
            start_method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
        context = multiprocessing.get_context(start_method)
        if start_method == "forkserver":
            context.set_forkserver_preload(["suture_gym.envs"])
        self.owner = [i * workers // num_envs for i in range(num_envs)]
        self.local = [self.owner[:i].count(self.owner[i]) for i in range(num_envs)]
        self.conns, self.processes = [], []
        for w in range(workers):
            parent, child = context.Pipe()
            process = context.Process(target=_worker, args=(child, self.owner.count(w), make_args), daemon=True,
                                      name=f"SutureVectorEnv worker {w}")
            process.start()
            child.close()
            self.conns.append(parent)
            self.processes.append(process)
        try:
            self._gather(range(workers))
        except BaseException:
            self.close()
            raise

    def apply(self, op: str, indices: list[int], payloads: list) -> list:
        """``_OPS[op](env_i, payload)`` for every ``i`` in ``indices``, in parallel over the workers; the results
        in the order of ``indices``."""
        jobs: dict[int, list] = {}
        for i, payload in zip(indices, payloads, strict=True):
            jobs.setdefault(self.owner[i], []).append((self.local[i], payload))
        for w, items in jobs.items():
            self.conns[w].send((op, items))
        answers = self._gather(jobs)
        position = {w: 0 for w in jobs}
        out = []
        for i in indices:
            w = self.owner[i]
            out.append(answers[w][position[w]])
            position[w] += 1
        return out

    def _gather(self, workers) -> dict[int, Any]:
        """Each listed worker's answer; raises the first error once all have answered (so the pipes stay in
        step)."""
        answers, error = {}, None
        for w in workers:
            try:
                status, payload = self.conns[w].recv()
            except EOFError:
                self.processes[w].join(1.0)
                status, payload = "error", (RuntimeError(
                    f"worker {w} (envs {self.owner.index(w)}-{len(self.owner) - 1 - self.owner[::-1].index(w)}) "
                    f"died (exit code {self.processes[w].exitcode}); a script that starts workers must do so under "
                    "`if __name__ == '__main__':` (or pass workers=0)"), "")
            if status == "error":
                error = error or payload
            else:
                answers[w] = payload
        if error is not None:
            exc, text = error
            raise exc from (_RemoteTraceback(text) if text else None)
        return answers

    def close(self) -> None:
        for conn, process in zip(self.conns, self.processes, strict=True):
            if process.is_alive():
                try:
                    conn.send(("close", None))
                except (BrokenPipeError, OSError):
                    pass
        for conn, process in zip(self.conns, self.processes, strict=True):
            process.join(5.0)
            if process.is_alive():
                process.terminate()
                process.join(1.0)
            conn.close()


class SutureVectorEnv(gym.vector.VectorEnv):
    """N suturing envs of one task, batched (module docstring).

    Args:
        task: a registered task name (``"needle_insert"``, ``"suture_throw"``, ``"wound_closure"``, ...).
        num_envs: N >= 1.
        config: as for :class:`~suture_gym.envs.base.SutureEnv` (shared by all N; with workers it must pickle,
            as a path, a mapping or an :class:`~suture_gym.envs.config.EnvConfig` do).
        render_mode: None or ``"rgb_array"`` (:meth:`render` returns one image per env).
        action_mode: as for :class:`~suture_gym.envs.base.SutureEnv`.
        goal_conditioned: batch :class:`~suture_gym.envs.base.SutureGoalEnv` instead.
        max_episode_steps: truncate episodes after this many steps (None: no limit); :func:`make_vector_env`
            passes the id's registered limit.
        autoreset_mode: :class:`gymnasium.vector.AutoresetMode` ``NEXT_STEP`` or ``SAME_STEP``.
        workers: worker processes stepping the envs in parallel, 0 <= workers <= N (0: the envs live in this
            process and step one after another); None: :func:`default_workers`.
        start_method: how workers start (``multiprocessing`` start method); None: ``forkserver`` where the
            platform has it, else ``spawn``.
    """

    def __init__(self, task: str = "needle_insert", num_envs: int = 1, config=None, render_mode: str | None = None,
                 action_mode: str | None = None, goal_conditioned: bool = False, max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, workers: int | None = None,
                 start_method: str | None = None) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1
        ):
            raise ValueError(f"max_episode_steps must be None or an integer >= 1, got {max_episode_steps!r}")
        mode = AutoresetMode(autoreset_mode)
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ValueError(f"autoreset_mode must be NEXT_STEP or SAME_STEP, got {mode!r}")
        if workers is None:
            workers = default_workers(num_envs)
        if isinstance(workers, bool) or not isinstance(workers, int) or not 0 <= workers <= num_envs:
            raise ValueError(f"workers must be an integer from 0 to num_envs = {num_envs}, got {workers!r}")
        if render_mode == "human":
            raise ValueError("render_mode='human' (a live view in the browser) is for one env, gym.make(id, "
                             "render_mode='human'); the vector env renders None or 'rgb_array'")
        make_args = (task, goal_conditioned, config, render_mode, action_mode)
        # One env here either way: the spaces and metadata come from it (and with workers, it checks the
        # arguments before any process starts).
        first = make_env(*make_args)
        self._envs: list | None = None
        self._workers: _Workers | None = None
        if workers == 0:
            self._envs = [first] + [make_env(*make_args) for _ in range(num_envs - 1)]
        else:
            first.close()
            self._workers = _Workers(num_envs, workers, make_args, start_method)
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.max_episode_steps = max_episode_steps
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.metadata = {**first.metadata, "autoreset_mode": mode}
        self._config = first.config
        self._elapsed = np.zeros(num_envs, dtype=np.int64)
        self._pending_reset = np.zeros(num_envs, dtype=np.bool_)

    @property
    def workers(self) -> int:
        """Worker processes stepping the envs (0: the envs live in this process)."""
        return 0 if self._workers is None else len(self._workers.processes)

    @property
    def envs(self) -> list:
        """The N envs, when they live in this process (``workers=0``); AttributeError otherwise."""
        if self._envs is None:
            raise AttributeError(f"the envs of a SutureVectorEnv with {self.workers} workers live in the worker "
                                 "processes; use call(), get_attr() or set_attr()")
        return self._envs

    @property
    def config(self):
        """The shared :class:`~suture_gym.envs.config.EnvConfig`."""
        return self._config

    def _apply(self, op: str, indices: list[int], payloads: list) -> list:
        """``_OPS[op](env_i, payload)`` for ``i`` in ``indices``: here in turn, or in parallel by the workers."""
        if self._workers is not None:
            return self._workers.apply(op, indices, payloads)
        return [_OPS[op](self._envs[i], payload) for i, payload in zip(indices, payloads, strict=True)]

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        """Reset the envs: ``seed`` int gives env ``i`` the seed ``seed + i``; a list gives one per env.

        ``options`` go to every env's reset, except ``reset_mask`` ((N,) bool), which resets only those envs
        (the others keep their state and return their last observation).
        """
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed must be None, an int or a list of {self.num_envs} seeds, got {len(seeds)}")
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, dtype=bool)))
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
            raise ValueError(f"options['reset_mask'] must be a ({self.num_envs},) bool array")
        results = self.reset_each(seeds, [options if m else None for m in mask])
        kept = [i for i, result in enumerate(results) if result is None]
        last = dict(zip(kept, self.get_attr("last_observation", indices=kept), strict=True)) if kept else {}
        infos: dict = {}
        observations = []
        for i, result in enumerate(results):
            if result is None:
                observations.append(last[i])
            else:
                observations.append(result[0])
                infos = self._add_info(infos, result[1], i)
        return self.batch(observations), infos

    def reset_each(self, seeds: list, options: list) -> list:
        """Reset env ``i`` with ``seeds[i]`` and ``options[i]`` unless ``options[i]`` is None; returns the
        ``(obs, info)`` of each reset env and None for the others."""
        if len(seeds) != self.num_envs or len(options) != self.num_envs:
            raise ValueError(f"seeds and options must hold {self.num_envs} entries, got {len(seeds)} and "
                             f"{len(options)}")
        indices = [i for i, opts in enumerate(options) if opts is not None]
        done = self._apply("reset", indices, [(seeds[i], options[i]) for i in indices])
        results: list = [None] * self.num_envs
        for i, result in zip(indices, done, strict=True):
            results[i] = result
            self._elapsed[i] = 0
            self._pending_reset[i] = False
        return results

    def step(self, actions):
        """Step every env with its row of ``actions`` (N, 6); see the module docstring for autoreset."""
        results = self.step_each(actions)
        rewards = np.array([r.reward for r in results], dtype=np.float64)
        terminations = np.array([r.terminated for r in results], dtype=np.bool_)
        truncations = np.array([r.truncated for r in results], dtype=np.bool_)
        infos: dict = {}
        for i, r in enumerate(results):
            if r.final_info is not None:
                infos = self._add_info(infos, {"final_obs": r.final_obs, "final_info": r.final_info}, i)
            infos = self._add_info(infos, r.info, i)
        return self.batch([r.obs for r in results]), rewards, terminations, truncations, infos

    def step_each(self, actions) -> list[StepResult]:
        """Step every env and apply the autoreset mode; one :class:`StepResult` per env, unbatched."""
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs, 6):
            raise ValueError(f"actions must have shape ({self.num_envs}, 6), got {actions.shape}")
        same_step = self.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        indices = list(range(self.num_envs))
        payloads = [(actions[i], bool(self._pending_reset[i]), int(self._elapsed[i]), self.max_episode_steps,
                     same_step) for i in indices]
        results = []
        for i, (result, elapsed, pending) in enumerate(self._apply("advance", indices, payloads)):
            self._elapsed[i] = elapsed
            self._pending_reset[i] = pending
            results.append(result)
        return results

    def render(self):
        """One ``(H, W, 3) uint8`` image per env (``render_mode="rgb_array"``), else None."""
        if self.render_mode is None:
            return None
        return self.call("render")

    def close_extras(self, **kwargs) -> None:
        if self._workers is not None:
            self._workers.close()
        else:
            for env in self._envs:
                env.close()

    def __del__(self) -> None:
        if getattr(self, "_workers", None) is not None and not getattr(self, "closed", True):
            try:
                self.close()
            except Exception:  # at interpreter exit the pipes may be gone; the daemon workers end with it
                pass

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        if isinstance(indices, (int, np.integer)):
            indices = [indices]
        indices = [int(i) for i in indices]
        bad = [i for i in indices if not 0 <= i < self.num_envs]
        if bad:
            raise ValueError(f"env indices must lie in [0, {self.num_envs}), got {bad}")
        return indices

    def call(self, name: str, *args, indices=None, **kwargs) -> tuple:
        """Call method ``name`` (or read attribute ``name``) of every env, or of the envs ``indices`` (an int or
        a list); returns their results."""
        indices = self._indices(indices)
        return tuple(self._apply("call", indices, [(name, args, kwargs)] * len(indices)))

    def get_attr(self, name: str, indices=None) -> tuple:
        """Attribute ``name`` of every env, or of the envs ``indices``."""
        indices = self._indices(indices)
        return tuple(self._apply("call", indices, [(name, (), {})] * len(indices))) if indices else ()

    def set_attr(self, name: str, values, indices=None) -> None:
        """Set attribute ``name`` of the envs ``indices`` (default all) to ``values[k]`` (a list, one per env), or
        of all of them to ``values``."""
        indices = self._indices(indices)
        if not isinstance(values, (list, tuple)):
            values = [values] * len(indices)
        if len(values) != len(indices):
            raise ValueError(f"values must hold {len(indices)} entries, got {len(values)}")
        self._apply("set_attr", indices, [(name, value) for value in values])

    def get_state(self) -> VectorEnvState:
        """Snapshot of every env and of the vector bookkeeping (restore with :meth:`set_state`)."""
        indices = list(range(self.num_envs))
        return VectorEnvState(tuple(self._apply("get_state", indices, [None] * self.num_envs)),
                              self._elapsed.copy(), self._pending_reset.copy())

    def set_state(self, state: VectorEnvState) -> None:
        """Restore a :meth:`get_state` snapshot."""
        if not isinstance(state, VectorEnvState) or len(state.envs) != self.num_envs:
            raise ValueError(f"state must be a VectorEnvState of {self.num_envs} envs")
        self._apply("set_state", list(range(self.num_envs)), list(state.envs))
        self._elapsed[:] = state.elapsed
        self._pending_reset[:] = state.pending_reset

    def batch(self, observations: list):
        """Fresh batched observation (array or dict of arrays) of N single observations."""
        out = create_empty_array(self.single_observation_space, self.num_envs)
        return concatenate(self.single_observation_space, observations, out)


def default_workers(num_envs: int) -> int:
    """Workers for ``workers=None``: one per env up to the cores this process may use (``os.sched_getaffinity``
    where the platform has it), and none (the envs in this process) for one env or one core."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = min(num_envs, cores)
    return workers if workers > 1 else 0


def make_vector_env(env_id: str, num_envs: int = 1, **kwargs) -> SutureVectorEnv:
    """A :class:`SutureVectorEnv` of ``num_envs`` envs of the registered SutureGym id ``env_id`` (flat or
    goal-conditioned), truncating at the id's time limit unless ``max_episode_steps`` is given.

    Keyword arguments go to :class:`SutureVectorEnv` (``config``, ``render_mode``, ``action_mode``,
    ``max_episode_steps``, ``autoreset_mode``, ``workers``, ``start_method``); the id decides ``task`` and
    ``goal_conditioned``.

    Raises:
        ValueError: ``env_id`` is not a registered SutureGym id (the message lists them), or ``task`` /
            ``goal_conditioned`` were passed.
    """
    task, goal_conditioned = env_id_task(env_id)
    clash = sorted({"task", "goal_conditioned"} & set(kwargs))
    if clash:
        raise ValueError(f"make_vector_env takes the task from the env id {env_id!r}; do not pass {clash}")
    kwargs.setdefault("max_episode_steps", MAX_EPISODE_STEPS[task])
    return SutureVectorEnv(task, num_envs, goal_conditioned=goal_conditioned, **kwargs)
