"""The command line: ``suture-gym COMMAND [options]`` (or ``python -m suture_gym COMMAND``).

=========  ==========================================================================================
train      train a Stable-Baselines3 or DAgger baseline (:mod:`suture_gym.cli.train`)
evaluate   evaluate random actions, the scripted expert or a saved model (:mod:`suture_gym.cli.evaluate`)
view       the live 3D viewer in the browser (:mod:`suture_gym.viewer.app`)
bench      benchmark the simulator and the envs (:mod:`suture_gym.cli.bench`)
validate   check the simulator against analytic references (:mod:`suture_gym.cli.validate`)
record     record a video of each task driven by the scripted expert (:mod:`suture_gym.cli.record`)
=========  ==========================================================================================

``suture-gym COMMAND --help`` lists a command's options. The environment variables that numba and the BLAS and
torch thread pools read (``NUMBA_CACHE_DIR``, ``OMP_NUM_THREADS`` ...) are honoured when set before the command
starts.
"""

from __future__ import annotations

import importlib
import sys

#: Command -> (module with a ``main(argv) -> int``, one-line description).
COMMANDS = {
    "train": ("suture_gym.cli.train", "train a Stable-Baselines3 or DAgger baseline"),
    "evaluate": ("suture_gym.cli.evaluate", "evaluate random actions, the scripted expert or a saved model"),
    "view": ("suture_gym.viewer.app", "the live 3D viewer in the browser"),
    "bench": ("suture_gym.cli.bench", "benchmark the simulator and the envs"),
    "validate": ("suture_gym.cli.validate", "check the simulator against analytic references"),
    "record": ("suture_gym.cli.record", "record a video of each task driven by the scripted expert"),
}


def usage() -> str:
    """The top-level help text."""
    width = max(map(len, COMMANDS))
    lines = [f"  {name:{width}s}  {text}" for name, (_, text) in COMMANDS.items()]
    return ("usage: suture-gym COMMAND [options]\n\ncommands:\n" + "\n".join(lines)
            + "\n\n'suture-gym COMMAND --help' lists a command's options.")


def main(argv: list[str] | None = None) -> int:
    """Run ``argv`` (default ``sys.argv[1:]``): its first item names the command, the rest are its options.
    Returns the command's exit status (2 for a missing or unknown command)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"suture-gym: unknown command {command!r}; the commands are {list(COMMANDS)}\n\n{usage()}",
              file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[command][0])
    return int(module.main(rest) or 0)
