"""Static-equilibrium tensions by quadratic programming (paper section IV-A), and the healthy dataset.

For each posture q:  f = argmin ||f - f_ref||^2  s.t.  -G(q)^T f = tau_bias(q),  0 <= f <= f_max,
then ``l_motor = l_geo(q) - delta(f)`` (eq:muscle-elongation). Draws whose QP has no solution are
re-drawn and counted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import BodySchemaInputError
from ..solvers import EQUILIBRIUM_TOL_NM, FALLBACK_MAX_ITER, BoxQP, solve_box_qp
from ..status import Status
from .model import MusculoskeletalModel
from .spring import SpringParams, elongation_from_tension


@torch.inference_mode()  # arrays in and out: no tensor here needs autograd's version counters
def solve_equilibrium_qp(G, tau_bias, f_ref, *, f_hi_n, f_lo_n=0.0, solver: str = "newton",
                         max_iter: int = FALLBACK_MAX_ITER, num_threads: int = 1):
    """Tensions closest to ``f_ref`` that hold each posture in static equilibrium: ``solvers.solve_box_qp`` on
    arrays (the dataset's QP; the solvers' ``BoxQP`` with ``w = 0``).

    Args:
        G: (B, M, N) muscle Jacobians [m/rad]; tau_bias: (B, N) [N m]; f_ref: (B, M) [N].
        f_hi_n, f_lo_n: keyword only, scalars, (M,) or (B, M) tension bounds [N] (a per-case f_hi_n of 0 models a
            cut).
        solver: ``solve_box_qp``'s back-end: ``"newton"`` (the batched dual Newton, the torque-reach screen,
            proxsuite where they leave a case: fast, the same bytes in every process), ``"proxqp"`` (proxsuite on
            every case) or any qpsolvers solver name (one call per case).
        max_iter: proxsuite's iteration limit per posture; a posture with no solution runs to it.
        num_threads: proxsuite's threads (more than 1: its batch API).

    Returns:
        ``f (B, M)`` within the bounds, and ``ok (B,)``: the torque balanced, ``|-G^T f - tau_bias|`` below
        ``EQUILIBRIUM_TOL_NM`` on every joint.
    """
    solution = solve_box_qp(BoxQP.build(G, tau_bias, f_ref, f_lo_n, f_hi_n), solver, fallback_max_iter=max_iter,
                            num_threads=num_threads)
    return solution.f_n.cpu().numpy(), (solution.status == Status.OK.code).cpu().numpy()


@dataclass
class EquilibriumSamples:
    """Healthy samples in SI units: postures [rad], motor lengths [m], tensions [N]."""

    q: np.ndarray  # (n, N)
    l_motor: np.ndarray  # (n, M)
    f: np.ndarray  # (n, M)
    n_redrawn: int  # infeasible draws that were replaced

    @property
    def accepted_fraction(self) -> float:
        """Share of drawn postures that some tensions could hold (the rest were re-drawn)."""
        return len(self.q) / (len(self.q) + self.n_redrawn)


def _unholdable_message(model: MusculoskeletalModel, n_kept: int, n_drawn: int, spring: SpringParams,
                        shortfall_nm: np.ndarray) -> str:
    """The error when too few postures can be held: which joints the muscles fail to hold, and what to do."""
    median = np.median(shortfall_nm, axis=0) if len(shortfall_nm) else np.zeros(model.n_joints)
    worst = np.argsort(-median)
    names = [f"{model.joint_names[j]} ({median[j]:.3g} N m)" for j in worst if median[j] > EQUILIBRIUM_TOL_NM][:6]
    return (f"only {n_kept} of {n_drawn} postures ({100 * n_kept / max(n_drawn, 1):.2g} %) can be held in equilibrium "
            f"with f_max={spring.f_max_n} N: the muscles are too weak for this model's gravity at joints {names} (median torque shortfall of the "
            "unholdable draws): lock them (data.locked_joints: {name: rad}), narrow their range, or raise f_max_n")


def generate_equilibrium_samples(model: MusculoskeletalModel, n: int, seed: int,
                                 spring: SpringParams = SpringParams(), solver: str = "newton",
                                 max_draw_factor: int = 20, qp=None) -> EquilibriumSamples:
    """Draw ``n`` healthy equilibrium samples: uniform q in the joint range, uniform f_ref in [0, f_max].

    Postures no tension can hold are re-drawn; at most ``max_draw_factor * n`` postures are drawn (an
    accepted fraction of 1/max_draw_factor), past which the error names the joints the muscles fail to hold.
    qp: the tension solve, called as ``solve_equilibrium_qp`` (its default) is; ``sim.sampling`` passes one whose
    answers are the same bytes in every process.
    """
    if int(n) != n or n <= 0:
        raise BodySchemaInputError(f"dataset size n={n!r} must be a positive integer")
    rng = np.random.default_rng(seed)
    f_max = np.broadcast_to(np.asarray(spring.f_max_n, float), (model.n_muscles,))
    kept, n_drawn, shortfall = [], 0, []
    while sum(len(k[0]) for k in kept) < n:
        if n_drawn >= max_draw_factor * n:
            raise BodySchemaInputError(_unholdable_message(model, sum(len(k[0]) for k in kept), n_drawn, spring,
                                                           np.concatenate(shortfall)))
        batch = n - sum(len(k[0]) for k in kept)
        q = model.sample_q(rng, batch)
        f_ref = f_max * rng.random((batch, model.n_muscles))
        l_geo, G, tau_bias = model.kinematics(q)
        f, ok = (qp or solve_equilibrium_qp)(G, tau_bias, f_ref, f_hi_n=f_max, solver=solver)
        kept.append((q[ok], l_geo[ok] - elongation_from_tension(f[ok], spring), f[ok]))
        shortfall.append(np.abs(np.einsum("bmn,bm->bn", -G[~ok], f[~ok]) - tau_bias[~ok]))
        n_drawn += batch
    q, l_motor, f = (np.concatenate(parts)[:n] for parts in zip(*kept))
    return EquilibriumSamples(q=q, l_motor=l_motor, f=f, n_redrawn=n_drawn - n)
