"""suture_gym: reinforcement-learning environments for soft-tissue suturing.

The physics lives in :mod:`suture_gym.sim` (XPBD tetrahedral tissue, a rigid curved needle and a
Cosserat suture thread); measurements against analytic references live in :mod:`suture_gym.measure`.
All quantities are SI: metres, kilograms, seconds, newtons.
"""

__version__ = "0.1.0"
