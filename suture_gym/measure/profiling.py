"""Names for numba's compiled code in a Linux ``perf`` profile (``scripts/perf_profile.py``).

``perf`` finds no symbols in code compiled at run time; it reads them from ``/tmp/perf-<pid>.map``, one line
``<start hex> <size hex> <name>`` per function. :func:`perf_map_entries` lists every function of every compiled
overload of the numba functions in ``suture_gym`` (their own code and what was inlined or linked into them), from
the addresses of their LLVM modules' functions. A numba cache keeps object code, not those modules: only functions
compiled in this process are listed (``scripts/perf_profile.py`` compiles into an empty cache for that reason).
"""

from __future__ import annotations

import bisect
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


def sample_stack_tops(dump: str) -> list[tuple[int, int]]:
    """``(ip, top)`` of each sample in ``perf report -D`` output of a recording made with ``--call-graph dwarf,N``:
    the sampled instruction address and the first 8 bytes (little-endian) of the user stack copied with it, the
    word at the stack pointer. For a leaf function that keeps no stack frame, such as numba's ``NRT_incref`` and
    ``NRT_decref``, that word is its return address, inside the caller: compiled code has no unwind tables, so
    ``perf`` itself cannot name the caller. Samples without a stack copy are skipped."""
    tops = []
    for block in re.split(r"\n(?=0x[0-9a-f]+@\S+ \[0x[0-9a-f]+\]: event: 9\b)", dump):
        head = re.search(r"PERF_RECORD_SAMPLE\([^)]*\): \d+/\d+: 0x([0-9a-f]+)", block)
        stack = re.search(r"ustack: size (\d+), offset 0x([0-9a-f]+)", block)
        if head is None or stack is None or int(stack.group(1)) < 8:
            continue
        raw = bytearray()
        for line in block.splitlines():
            row = re.match(r"\.\s+[0-9a-f]{4}:\s+((?:[0-9a-f]{2} )+)", line)
            if row is not None:
                raw += bytes.fromhex(row.group(1).replace(" ", ""))
        start = int(stack.group(2), 16) + 8  # the offset points at the copy's 8-byte size field
        if len(raw) >= start + 8:
            tops.append((int(head.group(1), 16), int.from_bytes(raw[start : start + 8], "little")))
    return tops


def name_at(entries: list[tuple[int, str]], address: int, limit: int = 1 << 20) -> str | None:
    """The name of the :func:`perf_map_entries` function holding ``address`` (it runs to the next entry, at most
    ``limit`` bytes), or ``None``."""
    k = bisect.bisect_right([start for start, _ in entries], address) - 1
    if k < 0:
        return None
    end = entries[k + 1][0] if k + 1 < len(entries) else entries[k][0] + 4096
    return entries[k][1] if address < min(end, entries[k][0] + limit) else None
