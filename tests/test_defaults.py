"""One default per physical parameter: the env config's sections are the simulator's dataclasses, and where an
env section keeps a default of its own it is the simulator's times the documented force scale."""

from dataclasses import fields

import pytest

from suture_gym.envs.config import (
    ActionConfig,
    CouplingConfig,
    NeedleConfig,
    SolverConfig,
    SutureConfig,
    TissueConfig,
)
from suture_gym.envs.config.physics import FORCE_SCALE
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.model import TissueMaterial
from suture_gym.sim.needle import NeedleShape, VirtualCoupling
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.scenes import PAPER_COUPLING, PAPER_SOLVER, PAPER_TISSUE
from suture_gym.sim.solver import Solver

#: Env fields whose default is not the simulator's, and why: the holder is FORCE_SCALE x the simulator's (its
#: forces are), and ``node_count = 0`` is the env's "no thread" (a thread needs at least two nodes).
SCALED = {"holder_mass", "holder_inertia"}
ENV_ONLY_MEANING = {"node_count"}


@pytest.mark.parametrize("env_cls, sim_cls", [(TissueConfig, TissueMaterial), (NeedleConfig, NeedleShape),
                                              (SutureConfig, SutureParams), (CouplingConfig, CouplingParams),
                                              (SolverConfig, Solver)])
def test_env_sections_keep_the_simulators_defaults_field_by_field(env_cls, sim_cls):
    env, sim = env_cls(), sim_cls()
    for f in fields(sim_cls):
        if f.name in SCALED:
            assert getattr(env, f.name) == pytest.approx(FORCE_SCALE * getattr(sim, f.name), rel=1e-12), f.name
        elif f.name in ENV_ONLY_MEANING and env_cls is SutureConfig:
            assert env.node_count == 0 and sim.node_count >= 2
        else:
            assert getattr(env, f.name) == getattr(sim, f.name), f"{env_cls.__name__}.{f.name}"


def test_the_virtual_coupling_gains_are_the_simulators_times_the_force_scale():
    action, sim = ActionConfig(), VirtualCoupling()
    for name in ("linear_stiffness", "linear_damping", "angular_stiffness", "angular_damping"):
        assert getattr(action, f"coupling_{name}") == pytest.approx(FORCE_SCALE * getattr(sim, name), rel=1e-12)


def test_the_solver_defaults_to_the_environments_integrator():
    assert Solver().tissue_integrator == SolverConfig().tissue_integrator == "quasi_newton"
    assert Solver().iterations == SolverConfig().iterations == 2


def test_the_papers_scale_is_named_once_and_differs_from_the_defaults():
    assert PAPER_TISSUE.youngs_modulus == 1.0e3 and TissueMaterial().youngs_modulus == 3.0e5
    assert PAPER_COUPLING.puncture_force == 0.015 and CouplingParams().puncture_force == 0.5
    assert PAPER_SOLVER.tissue_integrator == "xpbd"
