"""Feasibility of benchmark cases and the physics oracle's commands: ``sim.feasibility`` asked per ``FaultCases``.

The computation itself (tension bounds, the torque-reach screen, the QP) lives in ``sim.feasibility`` so the control
path (``adaptation``) can use it without the benchmark; its names are also importable from here.
"""
from __future__ import annotations

from ..faults.bounds import FaultBounds
from ..sim.feasibility import (JAM_MODELS, MAX_SCREEN_NORMALS, feasible_tensions, outside_torque_reach,  # noqa: F401
                               tension_bounds)
from ..sim.model import MusculoskeletalModel
from ..sim.spring import SpringParams


def check_feasible(model: MusculoskeletalModel, cases, spring: SpringParams = SpringParams(),
                   jam_model: str = "one_sided", jammed_tension_in_torque: bool = True,
                   solver: str = "newton"):
    """(feasible (B,) bool, f_star (B, M) [N]) at each case's q_ref (``cases``: an ``evaluation.FaultCases``)."""
    return feasible_tensions(model, cases.q_ref, cases.faults, spring, jam_model, jammed_tension_in_torque, solver)


def oracle_commands(model: MusculoskeletalModel, cases, spring: SpringParams = SpringParams(), **kwargs):
    """(feasible, l_motor [m], f [N]) (B, M): a perfect command for every feasible case (NaN rows else).

    ``l_motor = l_geo(q_ref) - phi^-1(f*)`` within the motor-length bounds (``FaultBounds.motor_length_m``, the
    commands' own rule): a slack wire's banded motor at its band's lower end (f* = 0 there, any l_motor >= l_geo
    gives it), no motor above a jam's l_fixed or a band's hi. A yardstick for the evaluation: it should score
    E_cut = E_fix = E_weak = E_band = 0 and E_q, E_tau ~ 0.
    """
    feasible, f_star = check_feasible(model, cases, spring, **kwargs)
    l_geo, _, _ = model.kinematics(cases.q_ref)
    bounds = FaultBounds.from_faults(cases.faults, spring.f_max_n, spring)
    return feasible, bounds.motor_length_m(l_geo, f_star), f_star
