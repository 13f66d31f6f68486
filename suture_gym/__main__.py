"""``python -m suture_gym COMMAND [options]``: the command line of :mod:`suture_gym.cli`."""

import sys

from suture_gym.cli import main

if __name__ == "__main__":
    sys.exit(main())
