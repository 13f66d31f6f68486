"""Test-wide set-up: a stable numba cache and two threads, fixed before any test imports numba."""

import os
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))
os.environ.setdefault("NUMBA_NUM_THREADS", "2")
