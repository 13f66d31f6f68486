"""Test-wide set-up: a stable numba cache and two threads, fixed before any test imports numba."""

import os
from pathlib import Path

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))
os.environ.setdefault("NUMBA_NUM_THREADS", "2")


def import_script(monkeypatch, name: str):
    """The module of ``scripts/<name>.py``, imported as its command line would run it (the scripts' ``configure``
    sets the thread counts in ``os.environ``: they are set here first, so the test restores them)."""
    import importlib

    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "1")
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    return importlib.import_module(name)


def assert_fuzz_event_does_not_diverge(monkeypatch, event: dict) -> None:
    """Replay a divergence the fuzzer found (``scripts/fuzz.py --replay``; ``event`` without its ``kind``) and
    assert that it no longer diverges."""
    fuzz = import_script(monkeypatch, "fuzz")
    replayed = fuzz.replay({**event, "kind": "divergences"})
    kinds = {e["kind"] for e in replayed["events"]}
    assert not replayed["reproduced"] and "divergences" not in kinds, replayed
