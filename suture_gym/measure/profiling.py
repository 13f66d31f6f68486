"""Names for numba's compiled code in a Linux ``perf`` profile (``scripts/perf_profile.py``).

``perf`` finds no symbols in code compiled at run time; it reads them from ``/tmp/perf-<pid>.map``, one line
``<start hex> <size hex> <name>`` per function. :func:`perf_map_entries` lists every function of every compiled
overload of the numba functions in ``suture_gym`` (their own code and what was inlined or linked into them), from
the addresses of their LLVM modules' functions. A numba cache keeps object code, not those modules: only functions
compiled in this process are listed (``scripts/perf_profile.py`` compiles into an empty cache for that reason).
"""

from __future__ import annotations

import os
import re
import sys

from numba.core.registry import CPUDispatcher


def readable_name(llvm_name: str) -> str:
    """The dotted Python name inside numba's mangled LLVM function name (``_ZN10suture_gym3sim4quat8quat_mulB3v5...``
    -> ``suture_gym.sim.quat.quat_mul``); other names unchanged."""
    if not llvm_name.startswith("_ZN"):
        return llvm_name
    parts, rest = [], llvm_name[3:]
    while (match := re.match(r"(\d+)", rest)) is not None:
        length = int(match.group(1))
        start = match.end()
        parts.append(rest[start : start + length])
        rest = rest[start + length :]
    return ".".join(parts) if parts else llvm_name


def perf_map_entries(prefix: str = "suture_gym") -> list[tuple[int, str]]:
    """``(address, name)`` of each function compiled in this process for the numba dispatchers of the modules whose
    name starts with ``prefix``, sorted by address, one name per address. ``name`` is ``<function> in
    <module>.<kernel>`` (:func:`readable_name`; a helper linked into several kernels appears once per kernel), or
    the bare name for code outside ``prefix`` (numba's runtime). Reads numba's ``CodeLibrary._final_module``, a
    private attribute (numba 0.68)."""
    entries: dict[int, str] = {}
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith(prefix):
            continue
        for attr, obj in list(vars(module).items()):
            if not isinstance(obj, CPUDispatcher) or obj.__module__ != module_name:
                continue
            short = f"{module_name.rsplit('.', 1)[-1]}.{attr}"
            for compiled in obj.overloads.values():
                library = compiled.library
                for function in library._final_module.functions:
                    if function.is_declaration:
                        continue
                    address = library.get_pointer_to_function(function.name)
                    if address:
                        name = readable_name(function.name)
                        # numba's runtime (NRT_incref, ...) is one copy that every kernel links: no kernel's name
                        entries.setdefault(int(address), f"{name} in {short}" if name.startswith(prefix) else name)
    return sorted(entries.items())


def write_perf_map(path: str | None = None, prefix: str = "suture_gym") -> tuple[str, int]:
    """Write :func:`perf_map_entries` as a perf map (default ``/tmp/perf-<pid>.map``); each function's size runs to
    the next entry (at most 1 MiB). Returns ``(path, number of entries)``."""
    path = path or f"/tmp/perf-{os.getpid()}.map"
    entries = perf_map_entries(prefix)
    with open(path, "w") as out:
        for k, (address, name) in enumerate(entries):
            size = entries[k + 1][0] - address if k + 1 < len(entries) else 4096
            out.write(f"{address:x} {max(1, min(size, 1 << 20)):x} {name}\n")
    return path, len(entries)
