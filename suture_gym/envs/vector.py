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

Worker faults: every reply of a worker is awaited at most ``worker_timeout`` seconds (None: forever), and a worker
that exits (a crash, a signal such as SIGKILL from the out-of-memory killer) is seen at once. Either raises
:class:`WorkerError`, naming the worker, its envs, its exit code or signal (or that it did not answer, and its
process state, e.g. stopped) and the last request sent to it (a step's actions); the worker is killed, and every
later request to it raises too. With ``restart_workers=True`` a step instead starts a new worker in its place, resets
its envs with seeds derived from their last reset's (:meth:`SutureVectorEnv.restart_seed`) and reports the
interrupted episodes as truncated with ``info["worker_restarted"] = True`` (and ``info["worker_error"]``, the
message), so a long run loses those episodes, not the run; a reset is retried once on the new worker; any other
request (``call``, snapshots) restarts the worker and raises the error.

Why processes and not threads: a step is Python (the task, the solver's orchestration, the sparse solves)
around numba kernels, so threads would scale only as far as the GIL is released, while processes do not depend
on where the time goes (measurements in docs/notes/environments.md). ``scripts/bench.py`` ``vector_env``
measures the processes' scaling.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import pickle
import signal
import time
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import wait
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


#: Default seconds a worker may take to answer one request (``worker_timeout``): above the slowest legitimate
#: reply, a first step on a cold numba cache (about a minute of compilation per worker, longer with workers sharing
#: cores) or a first reset into a later start phase (tens of seconds to minutes).
WORKER_TIMEOUT = 300.0


class WorkerError(RuntimeError):
    """A worker process of a :class:`SutureVectorEnv` died or did not answer within ``worker_timeout``.

    Attributes:
        worker: the worker's number (0 to ``workers - 1``).
        env_indices: the envs it held.
        exitcode: its exit code (negative: ``-signal``), or None while it was alive (a timeout).
        signal: the name of the signal that ended it (``"SIGKILL"``), or None.
        request: what it was last asked (the op, and for a step the actions of its envs).
    """

    def __init__(self, message: str, worker: int, env_indices: tuple[int, ...], exitcode: int | None,
                 signal: str | None, request: str) -> None:
        super().__init__(message)
        self.worker = worker
        self.env_indices = env_indices
        self.exitcode = exitcode
        self.signal = signal
        self.request = request

    def __reduce__(self):
        return type(self), (str(self), self.worker, self.env_indices, self.exitcode, self.signal, self.request)


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


def _signal_name(exitcode: int | None) -> str | None:
    """The name of the signal that ended a process with ``exitcode`` (negative: killed by ``-exitcode``)."""
    if exitcode is None or exitcode >= 0:
        return None
    try:
        return signal.Signals(-exitcode).name
    except ValueError:
        return f"signal {-exitcode}"


def _process_state(pid: int | None) -> str | None:
    """The ``State:`` line of ``/proc/<pid>/status`` (``"T (stopped)"``), or None where there is none."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("State:"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def _describe(op: str, indices: list[int], payloads: list) -> str:
    """The request ``op`` with ``payloads`` for the envs ``indices``, for an error message (a step's actions)."""
    if op == "advance":
        shown = []
        for i, payload in zip(indices, payloads, strict=True):
            action = np.asarray(payload[0])
            shown.append(f"env {i}: {np.round(action, 4).tolist() if action.dtype.kind in 'iuf' else action!r}")
        return "step with actions " + "; ".join(shown)
    if op == "call":
        return f"call {payloads[0][0]!r}" if payloads else "call"
    return op


class _Workers:
    """``k`` worker processes holding contiguous blocks of the N envs (env ``i`` in block ``i * k // N``).

    Every reply is awaited at most ``timeout`` seconds (None: forever); a worker that dies or times out raises
    :class:`WorkerError` and is killed; :meth:`restart` replaces it.
    """

    def __init__(self, num_envs: int, workers: int, make_args: tuple, start_method: str | None,
                 timeout: float | None) -> None:
        if start_method is None:
            start_method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
        self.context = multiprocessing.get_context(start_method)
        if start_method == "forkserver":
            self.context.set_forkserver_preload(["suture_gym.envs"])
        self.make_args = make_args
        self.timeout = timeout
        self.owner = [i * workers // num_envs for i in range(num_envs)]
        self.local = [self.owner[:i].count(self.owner[i]) for i in range(num_envs)]
        self.conns: list = [None] * workers
        self.processes: list = [None] * workers
        #: The last request sent to each worker, described for error messages.
        self.requests: list[str] = ["start (building its envs)"] * workers
        #: The error of each worker that failed and was not restarted (its later requests raise it again).
        self.failed: dict[int, WorkerError] = {}
        for w in range(workers):
            self._spawn(w)
        try:
            self.raise_for(*self._gather(range(workers))[1:])
        except BaseException:
            self.close()
            raise

    def envs_of(self, w: int) -> tuple[int, ...]:
        """The env indices worker ``w`` holds."""
        return tuple(i for i, owner in enumerate(self.owner) if owner == w)

    def _spawn(self, w: int) -> None:
        parent, child = self.context.Pipe()
        process = self.context.Process(target=_worker, args=(child, self.owner.count(w), self.make_args),
                                       daemon=True, name=f"SutureVectorEnv worker {w}")
        process.start()
        child.close()
        self.conns[w], self.processes[w] = parent, process
        self.requests[w] = "start (building its envs)"

    def restart(self, w: int) -> None:
        """Kill worker ``w`` if it still runs and start a new one in its place, with freshly built envs (not yet
        reset); WorkerError if the new one fails to start."""
        self._kill(w)
        self.failed.pop(w, None)
        self._spawn(w)
        self.raise_for(*self._gather([w])[1:])

    def apply(self, op: str, indices: list[int], payloads: list) -> list:
        """``_OPS[op](env_i, payload)`` for every ``i`` in ``indices``, in parallel over the workers; the results
        in the order of ``indices``. Raises the first :class:`WorkerError` (or an env's exception) once every
        worker asked has answered or failed."""
        results, failed, error = self.apply_partial(op, indices, payloads)
        self.raise_for(failed, error)
        return results

    def apply_partial(self, op: str, indices: list[int], payloads: list) -> tuple[list, dict[int, WorkerError],
                                                                                   tuple | None]:
        """As :meth:`apply`, without raising: ``(results, failed, error)``, ``results`` None for the envs of the
        workers in ``failed`` (worker -> its :class:`WorkerError`), ``error`` the first ``(exception,
        traceback)`` an env raised (then ``results`` are incomplete), else None."""
        jobs: dict[int, list] = {}
        for i, payload in zip(indices, payloads, strict=True):
            jobs.setdefault(self.owner[i], []).append((self.local[i], payload))
        failed: dict[int, WorkerError] = {}
        for w in jobs:
            if w in self.failed:
                earlier = self.failed[w]
                failed[w] = WorkerError(f"{earlier} (an earlier request found this; the worker is gone)", w,
                                        earlier.env_indices, earlier.exitcode, earlier.signal, earlier.request)
        asked = []
        for w, items in jobs.items():
            if w in failed:
                continue
            mine = [(i, p) for i, p in zip(indices, payloads, strict=True) if self.owner[i] == w]
            self.requests[w] = _describe(op, [i for i, _ in mine], [p for _, p in mine])
            try:
                self.conns[w].send((op, items))
            except (BrokenPipeError, ConnectionResetError, EOFError, OSError):
                failed[w] = self._dead(w)
                continue
            asked.append(w)
        answers, more, error = self._gather(asked)
        failed.update(more)
        position = {w: 0 for w in jobs}
        out = []
        for i in indices:
            w = self.owner[i]
            if w in answers:
                out.append(answers[w][position[w]])
                position[w] += 1
            else:
                out.append(None)
        return out, failed, error

    def _gather(self, workers) -> tuple[dict[int, Any], dict[int, WorkerError], tuple | None]:
        """Each listed worker's answer, waiting until all have answered, died or run out of time:
        ``(answers, failed, error)`` (see :meth:`apply_partial`)."""
        answers: dict[int, Any] = {}
        failed: dict[int, WorkerError] = {}
        error = None
        pending = set(workers)
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while pending:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            handles = {self.conns[w]: w for w in pending}
            handles.update({self.processes[w].sentinel: w for w in pending})
            ready = wait(list(handles), timeout=left)
            if not ready:
                for w in sorted(pending):
                    failed[w] = self._timed_out(w)
                break
            for w in sorted({handles[h] for h in ready}):
                try:
                    if not self.conns[w].poll():  # its sentinel: the process ended without answering
                        raise EOFError
                    status, payload = self.conns[w].recv()
                except (EOFError, ConnectionResetError, OSError):
                    failed[w] = self._dead(w)
                else:
                    if status == "error":
                        error = error or payload
                    else:
                        answers[w] = payload
                pending.discard(w)
        return answers, failed, error

    def raise_for(self, failed: dict[int, WorkerError], error: tuple | None) -> None:
        """Raise the :class:`WorkerError` of the lowest failed worker, else the env exception ``error`` (with the
        worker's traceback as its cause), if any."""
        if failed:
            raise failed[min(failed)]
        if error is not None:
            exc, text = error
            raise exc from (_RemoteTraceback(text) if text else None)

    def _name(self, w: int) -> str:
        envs = self.envs_of(w)
        span = f"env {envs[0]}" if len(envs) == 1 else f"envs {envs[0]}-{envs[-1]}"
        return f"SutureVectorEnv worker {w} ({span}, pid {self.processes[w].pid})"

    def _dead(self, w: int) -> WorkerError:
        """The error of worker ``w``, which exited; it is marked failed."""
        process = self.processes[w]
        process.join(1.0)
        code = process.exitcode
        name = _signal_name(code)
        request = self.requests[w]
        if name is not None:
            how = f"was killed by {name} (exit code {code})"
        else:
            how = f"exited with exit code {code}"
            if request.startswith("start") and code:
                how += ("; a script that starts workers must do so under `if __name__ == '__main__':` (or pass "
                        "workers=0)")
        error = WorkerError(f"{self._name(w)} {how}; the last request sent to it: {request}", w, self.envs_of(w),
                            code, name, request)
        self._kill(w)
        self.failed[w] = error
        return error

    def _timed_out(self, w: int) -> WorkerError:
        """The error of worker ``w``, which did not answer in time; it is killed and marked failed."""
        state = _process_state(self.processes[w].pid)
        request = self.requests[w]
        error = WorkerError(
            f"{self._name(w)} did not answer within worker_timeout = {self.timeout:g} s"
            f"{f' (process state: {state})' if state else ''} and was killed; the last request sent to it: {request}",
            w, self.envs_of(w), None, None, request)
        self._kill(w)
        self.failed[w] = error
        return error

    def _kill(self, w: int) -> None:
        """End worker ``w`` now (SIGKILL: a stopped process ends too) and close its pipe."""
        process, conn = self.processes[w], self.conns[w]
        if process.is_alive():
            process.kill()
        process.join(5.0)
        conn.close()

    def close(self) -> None:
        for w, (conn, process) in enumerate(zip(self.conns, self.processes, strict=True)):
            if process is not None and process.is_alive() and w not in self.failed:
                try:
                    conn.send(("close", None))
                except (BrokenPipeError, OSError):
                    pass
        for conn, process in zip(self.conns, self.processes, strict=True):
            if process is None:
                continue
            process.join(5.0)
            if process.is_alive():
                process.kill()
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
        worker_timeout: seconds a worker may take to answer one request (a step, a reset, a call) before
            :class:`WorkerError`; None waits forever. Default :data:`WORKER_TIMEOUT`.
        restart_workers: replace a worker that died or timed out during a step or reset and carry on (the
            module docstring); False raises :class:`WorkerError`. Without workers neither has any effect.
    """

    def __init__(self, task: str = "needle_insert", num_envs: int = 1, config=None, render_mode: str | None = None,
                 action_mode: str | None = None, goal_conditioned: bool = False, max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, workers: int | None = None,
                 start_method: str | None = None, worker_timeout: float | None = WORKER_TIMEOUT,
                 restart_workers: bool = False) -> None:
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
        if worker_timeout is not None and (
            isinstance(worker_timeout, bool) or not isinstance(worker_timeout, (int, float))
            or not (math.isfinite(worker_timeout) and worker_timeout > 0)
        ):
            raise ValueError(f"worker_timeout must be None or a finite number of seconds > 0, got {worker_timeout!r}")
        if not isinstance(restart_workers, bool):
            raise ValueError(f"restart_workers must be True or False, got {restart_workers!r}")
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
            self._workers = _Workers(num_envs, workers, make_args, start_method,
                                     None if worker_timeout is None else float(worker_timeout))
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
        self.worker_timeout = worker_timeout
        self.restart_workers = restart_workers
        #: How many times each env's worker was restarted under it.
        self.restarts = np.zeros(num_envs, dtype=np.int64)
        self._seeds: list[int | None] = [None] * num_envs  # each env's last reset seed
        self._last_obs: list = [None] * num_envs  # each env's last observation returned
        # (obs, info) of envs reset on a restarted worker in NEXT_STEP mode, returned by their next step
        self._restarted: dict[int, tuple] = {}
        # envs whose worker was restarted during a request other than a step: their next step truncates them
        self._interrupted: dict[int, WorkerError] = {}

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
        """``_OPS[op](env_i, payload)`` for ``i`` in ``indices``: here in turn, or in parallel by the workers.
        With ``restart_workers``, a worker that fails is restarted (its envs truncated at the next step) before
        its :class:`WorkerError` is raised."""
        if self._workers is None:
            return [_OPS[op](self._envs[i], payload) for i, payload in zip(indices, payloads, strict=True)]
        if not self.restart_workers:
            return self._workers.apply(op, indices, payloads)
        results, failed, error = self._workers.apply_partial(op, indices, payloads)
        if failed or error is not None:
            self._fail(failed, error)
        return results

    def _fail(self, failed: dict[int, WorkerError], error: tuple | None) -> None:
        """Restart the ``failed`` workers, reset their envs (truncated at their next step), then raise (the first
        worker's error, else the env exception ``error``)."""
        for w, fault in failed.items():
            self._restart(w, fault)
            envs = list(self._workers.envs_of(w))
            self._workers.apply("reset", envs, [(self.restart_seed(i), None) for i in envs])
            self._interrupted.update(dict.fromkeys(envs, fault))
        self._workers.raise_for(failed, error)

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
        payloads = [(seeds[i], options[i]) for i in indices]
        if self._workers is None or not self.restart_workers:
            done = self._apply("reset", indices, payloads)
        else:
            done, failed, error = self._workers.apply_partial("reset", indices, payloads)
            if error is not None:
                self._fail(failed, error)
            for w, fault in failed.items():
                self._restart(w, fault)
                mine = [k for k, i in enumerate(indices) if self._workers.owner[i] == w]
                again = self._workers.apply("reset", [indices[k] for k in mine], [payloads[k] for k in mine])
                for k, (obs, info) in zip(mine, again, strict=True):
                    done[k] = (obs, {**info, "worker_restarted": True, "worker_error": str(fault)})
        results: list = [None] * self.num_envs
        for i, result in zip(indices, done, strict=True):
            results[i] = result
            self._elapsed[i] = 0
            self._pending_reset[i] = False
            self._seeds[i] = seeds[i]
            self._last_obs[i] = result[0]
            self._restarted.pop(i, None)
            self._interrupted.pop(i, None)
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
        results: list = [None] * self.num_envs
        for i, (obs, info) in self._restarted.items():  # reset on a restarted worker: the autoreset step
            results[i] = StepResult(obs, 0.0, False, False, info, None, None)
            self._elapsed[i] = 0
            self._pending_reset[i] = False
        self._restarted = {}
        interrupted, self._interrupted = self._interrupted, {}
        indices = [i for i in range(self.num_envs) if results[i] is None and i not in interrupted]
        payloads = [(actions[i], bool(self._pending_reset[i]), int(self._elapsed[i]), self.max_episode_steps,
                     same_step) for i in indices]
        if self._workers is None or not self.restart_workers:
            done, failed = self._apply("advance", indices, payloads), {}
        else:
            done, failed, error = self._workers.apply_partial("advance", indices, payloads)
            if error is not None:
                self._fail(failed, error)
        for i, answer in zip(indices, done, strict=True):
            if answer is not None:
                results[i], self._elapsed[i], self._pending_reset[i] = answer
        for w, fault in failed.items():
            self._restart(w, fault)
            self._truncate(list(self._workers.envs_of(w)), fault, results, same_step)
        for fault in {id(f): f for f in interrupted.values()}.values():
            self._truncate([i for i, f in interrupted.items() if f is fault], fault, results, same_step)
        for i, result in enumerate(results):
            self._last_obs[i] = result.obs
        return results

    def restart_seed(self, index: int) -> int | None:
        """The seed env ``index`` is reset with after its worker's restart number ``restarts[index]``: drawn
        from ``np.random.SeedSequence([last reset seed, index, restarts])`` (an int below 2**31), or None when
        its last reset had no seed."""
        seed = self._seeds[index]
        if seed is None:
            return None
        sequence = np.random.SeedSequence([int(seed), int(index), int(self.restarts[index])])
        return int(sequence.generate_state(1)[0] >> 1)

    def _restart(self, w: int, fault: WorkerError) -> None:
        """Start a new worker ``w`` in place of the one that raised ``fault`` (warning about it)."""
        warnings.warn(f"{fault}; restarting it (restart_workers=True)", RuntimeWarning, stacklevel=4)
        self._workers.restart(w)
        for i in self._workers.envs_of(w):
            self.restarts[i] += 1
            self._restarted.pop(i, None)
            self._interrupted.pop(i, None)

    def _truncate(self, envs: list[int], fault: WorkerError, results: list, same_step: bool) -> None:
        """Fill ``results`` for ``envs``, whose worker raised ``fault`` and was restarted: each is reset with its
        :meth:`restart_seed` and its episode truncated, its final observation the last one returned; with
        ``SAME_STEP`` the step returns the new episode's first observation, with ``NEXT_STEP`` the next step
        does."""
        reset = self._workers.apply("reset", envs, [(self.restart_seed(i), None) for i in envs])
        flags = {"worker_restarted": True, "worker_error": str(fault)}
        for i, (obs, info) in zip(envs, reset, strict=True):
            last = self._last_obs[i] if self._last_obs[i] is not None else obs
            self._elapsed[i] = 0
            self._pending_reset[i] = False
            if same_step:
                results[i] = StepResult(obs, 0.0, False, True, {**info, **flags}, last, dict(flags))
            else:
                results[i] = StepResult(last, 0.0, False, True, dict(flags), None, None)
                self._restarted[i] = (obs, {**info, **flags})

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
    ``max_episode_steps``, ``autoreset_mode``, ``workers``, ``start_method``, ``worker_timeout``,
    ``restart_workers``); the id decides ``task`` and ``goal_conditioned``.

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
