"""Does any physically valid command realize q_ref under the faults? (a QP on the true physics)

The one feasibility computation: ``BodySchema.adapt``'s physics check (``adaptation.physics``), the benchmark's
feasible subsets and the physics oracle (``evaluation.feasibility``) all ask it. It takes a robot with physics
(``kinematics``) and a ``faults.Faults`` batch, whose tension box at q_ref is ``faults.bounds.FaultBounds``'s (the
one the adapters and the exported package use).

At the fixed posture q_ref the unknowns are the tensions f (M,). A command (l_motor, f) with a perfect
score (E_cut = E_fix = E_tau = E_q = 0) exists iff some f satisfies

* static equilibrium      -G(q_ref)^T f = tau_bias(q_ref)
* healthy muscle i:        0 <= f_i <= f_max             (then l_motor_i = l_geo_i - phi^-1(f_i))
* ruptured muscle i:       f_i = 0
* jammed muscle j:         phi(d_j) <= f_j <= f_max,  d_j = max(0, l_geo_j(q_ref) - l_fixed_j)
* weakened muscle i:       f_max is its own f_max' (``cases.f_max``) in every bound above
* banded motor j:          phi(l_geo_j - hi_j) <= f_j <= phi(l_geo_j - lo_j)   (phi = 0 for a slack spring)

Why the jammed bound: the fault is ``l_motor_j <= l_fixed_j`` (paper eq. muscle-fix: the wire can
still be reeled in, not paid out). Any such motor length stretches the spring by
``delta_j = max(0, l_geo_j - l_motor_j) >= d_j``; phi is increasing, so f_j >= phi(d_j), and every
tension in [phi(d_j), f_max] is reached by reeling in to ``l_motor_j = l_geo_j - phi^-1(f_j)``.
When d_j > phi^-1(f_max) (~7 mm for the paper's spring) the arm would stretch the jammed muscle
past its maximum tension: no command exists, whatever the other muscles do.

``jam_model="immobile"`` instead treats the jammed motor as unable to move at all, so
f_j = phi(d_j) exactly (a stricter reading). ``jammed_tension_in_torque=False`` mirrors the paper's
literal E_tau, whose taut set excludes jammed muscles: then the other healthy muscles must hold the
arm alone (jammed tensions are dropped from the equilibrium, the d_j <= phi^-1(f_max) test remains).
Pair it with the same flag in ``ForwardSolverParams``: a command that is perfect under one torque
convention is not under the other (see ``evaluation.feasibility.oracle_commands``).

Why the band bound: the spring stretches by ``delta = l_geo - l_motor`` and f = phi(max(0, delta)) rises
with delta, so ``lo <= l_motor <= hi`` is ``l_geo - hi <= delta <= l_geo - lo``. A band wholly above
l_geo (the motor cannot reel in far enough to tighten the wire) allows only f = 0; a lower bound
above the upper one (band or jam against f_max') leaves no command at all.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from .. import solvers
from ..errors import BodySchemaInputError
from .._numpy import to_numpy
from ..faults.bounds import FaultBounds
from ..solvers import EQUILIBRIUM_TOL_NM, MAX_SCREEN_NORMALS  # EQUILIBRIUM_TOL_NM re-exported: evaluation.feasibility
from .equilibrium import solve_equilibrium_qp
from .spring import SpringParams

if TYPE_CHECKING:
    from ..faults.faults import Faults
    from .robot import RobotModel

JAM_MODELS = ("one_sided", "immobile")


def outside_torque_reach(G, tau_bias, lo, hi) -> np.ndarray:
    """(B,) True where no tension in [lo, hi] (B, M) holds the posture to EQUILIBRIUM_TOL_NM
    (``solvers.outside_torque_reach`` on arrays)."""
    args = (torch.as_tensor(x, dtype=torch.float64) for x in (G, tau_bias, lo, hi))
    return to_numpy(solvers.outside_torque_reach(*args, EQUILIBRIUM_TOL_NM))


def tension_bounds(l_geo, faults: "Faults", spring: SpringParams, jam_model: str = "one_sided",
                   jammed_tension_in_torque: bool = True):
    """Per-case tension bounds lo, hi (B, M) [N] at q_ref, the (B,) mask of cases whose jam (or band) lower
    bound exceeds the upper one (f_max, a weakened muscle's f_max', a band's), and f_need (B, M) = phi(d_j)
    on jammed muscles, raised to phi(l_geo - hi) on banded ones (0 elsewhere)."""
    if jam_model not in JAM_MODELS:
        raise BodySchemaInputError(f"jam_model={jam_model!r}; allowed: {list(JAM_MODELS)}")
    box_lo, hi = FaultBounds.from_faults(faults, spring.f_max_n, spring).tension_box(l_geo)
    lo, crossed = solvers.uncrossed_box(box_lo, hi)  # an absurd jam stretch overflows phi to inf: crossed, as it should
    f_need, fix = box_lo, faults.fix  # phi(d_j) on jammed muscles, raised to phi(l_geo - hi) on banded ones
    if jam_model == "immobile":
        hi = np.where(fix, lo, hi)
    if not jammed_tension_in_torque:
        lo, hi = np.where(fix, 0.0, lo), np.where(fix, 0.0, hi)
    return lo, hi, crossed, f_need


@torch.inference_mode()
def feasible_cases(model: "RobotModel", q_ref, faults: "Faults", spring: SpringParams = SpringParams()) -> np.ndarray:
    """(B,) bool: ``feasible_tensions(...)[0]`` (one-sided jams, jammed tensions in the torque), without solving for
    the tensions where the screen is exact (``solvers.screen_is_exact``): uncrossed bounds and a torque inside the zonotope
    of the tension box, to ``EQUILIBRIUM_TOL_NM`` (a torque within ``sqrt(N) EQUILIBRIUM_TOL_NM`` of its edge may
    read feasible where the QP's own residual test would just miss). The physics check asks only this."""
    if not solvers.screen_is_exact(model.n_muscles, model.n_joints):
        return feasible_tensions(model, q_ref, faults, spring)[0]
    l_geo, G, tau_bias = model.kinematics(q_ref)
    lo, hi, crossed, _ = tension_bounds(l_geo, faults, spring)
    return ~crossed & ~outside_torque_reach(G, tau_bias, lo, hi)


@torch.inference_mode()  # arrays in and out: no tensor here needs autograd's version counters
def feasible_tensions(model: "RobotModel", q_ref, faults: "Faults", spring: SpringParams = SpringParams(),
                      jam_model: str = "one_sided", jammed_tension_in_torque: bool = True, solver: str = "newton"):
    """(feasible (B,) bool, f_star (B, M) [N]): a perfect command's tensions at ``q_ref``, NaN rows if none exists.

    f_star is the tension vector closest to f_max/2 (the QP's f_ref) within the bounds above. With
    ``jammed_tension_in_torque=False`` its jammed entries are phi(d_j), the least tension that keeps
    the paper's r_fix at zero (that evaluation ignores them in the torque balance).
    """
    l_geo, G, tau_bias = model.kinematics(q_ref)
    lo, hi, crossed, f_need = tension_bounds(l_geo, faults, spring, jam_model, jammed_tension_in_torque)
    f_ref = np.broadcast_to(np.asarray(spring.f_max_n, float) / 2.0, lo.shape)
    f, ok = np.full(lo.shape, np.nan), np.zeros(len(lo), bool)
    run = np.flatnonzero(~crossed)  # the solver screens the torques out of reach itself (after its first steps)
    if run.size and solvers.screen_is_exact(*G.shape[1:]):
        # where every facet of the torque zonotope is enumerable the screen is exact and cheap: a hopeless case
        # then costs no Newton steps and no least squares
        run = run[~outside_torque_reach(G[run], tau_bias[run], lo[run], hi[run])]
    if run.size:
        f[run], ok[run] = solve_equilibrium_qp(G[run], tau_bias[run], f_ref[run], f_lo_n=lo[run], f_hi_n=hi[run],
                                               solver=solver)
    if not jammed_tension_in_torque:
        f = np.where(faults.fix, f_need, f)
    feasible = ok & ~crossed
    return feasible, np.where(feasible[:, None], f, np.nan)
