"""The learnability study (:mod:`suture_gym.baselines.study`) run from the checkout: one thread per pool and the
checkout's numba cache (``scripts/_common.py``). ``--help`` lists the options."""

import sys

from _common import configure

configure(threads=1)

from suture_gym.baselines.study import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
