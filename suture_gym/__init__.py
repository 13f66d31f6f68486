"""suture_gym: reinforcement-learning environments for soft-tissue suturing.

The physics lives in :mod:`suture_gym.sim` (XPBD tetrahedral tissue, a rigid curved needle and a
Cosserat suture thread); measurements against analytic references live in :mod:`suture_gym.measure`.
All quantities are SI: metres, kilograms, seconds, newtons. Importing the package registers the environments
(``SutureGym/NeedleInsert-v3``, ``SutureGym/SutureThrow-v3``, ``SutureGym/WoundClosure-v3`` and their
goal-conditioned ``...Goal`` variants); see :mod:`suture_gym.envs`.
"""

__version__ = "0.1.0"

from suture_gym import envs as envs  # noqa: E402  (registers the SutureGym/* Gymnasium ids)
