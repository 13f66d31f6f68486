"""Shared start-up for the command-line scripts: thread limits and the numba cache, set before numba loads."""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def configure(threads: int | None = None) -> None:
    """Point numba's cache at ``<repo>/.numba_cache`` (unless set) and cap thread pools at ``threads``.

    Must run before numba or numpy are imported by the caller.
    """
    os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    if threads is not None:
        for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(threads)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
