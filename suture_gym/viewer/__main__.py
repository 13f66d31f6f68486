"""``python -m suture_gym.viewer``: see :mod:`suture_gym.viewer.app`."""

from suture_gym.viewer.app import main

raise SystemExit(main())
