"""Worker processes for evaluations and DAgger's rollouts: one spawned pool, one thread per worker.

Spawned, not forked: numba and torch keep threads and locks a fork would copy half-held. Each worker runs on one
numba, BLAS and torch thread (the environment variables are inherited, torch is set in the worker), so N workers
use N cores and a worker's arithmetic does not depend on how many threads the parent had.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

THREAD_VARIABLES = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def worker_pool(workers: int, initializer: Callable[..., None], initargs: tuple) -> ProcessPoolExecutor:
    """A spawned pool of ``workers`` processes, each on one thread, each running ``initializer(*initargs)`` once
    (after setting torch to one thread, when torch is installed)."""
    for var in THREAD_VARIABLES:
        os.environ.setdefault(var, "1")
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start,
                               initargs=(initializer, initargs))  # fmt: skip


def _start(initializer: Callable[..., None], initargs: tuple) -> None:
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    initializer(*initargs)
