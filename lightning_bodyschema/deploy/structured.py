"""``StructuredAdapterModule``: the structured schema's prepared adapter as a tensor-only module (``deploy.module``'s
signature and outputs), for ``torch.export``.

Per case, as ``StructuredSchema.solve_si`` and ``faults.qp.fault_command`` do: the learned body at the posture
(lengths ``l_geo``, moment arms ``G``, the torque ``tau``: a per-muscle body's frozen ``BodySnapshot``, what
``body_si`` evaluates, else ``schema.body``), the faults' tension box through the
spring (``FaultBounds.tension_box``), the tensions closest to ``f_ref`` (half of each muscle's f_max) that balance
``tau`` inside the box by the batched dual Newton of ``solvers.newton`` with an iteration cap (``fixed_iterations``:
traceable; the graph stops once every case has settled), then ``l_motor = l_geo - delta(f)`` and the shared safe
command. A case whose box crosses, or whose Newton does not settle within the cap (a torque the box cannot
balance), is ``infeasible_learned`` with a NaN row, as in Python.
"""
from __future__ import annotations

import torch

from ..errors import BodySchemaInputError
from ..faults.qp import learned_body_status
from ..solvers.newton import NEWTON_TOL_NM, dual_newton
from ..solvers.problem import uncrossed_box
from ..status import Status
from .module import PackageModule

# the most Newton steps the package runs: the Python adapter stops a case when it settles (a holdable posture takes
# a handful of steps with the exact line search) and hands the few it has not settled to proxsuite
PACKAGE_NEWTON_ITER = 12


class StructuredAdapterModule(PackageModule):
    """The tensor-only adapter of a trained ``StructuredSchema`` (module docstring); ``max_iter``: the most Newton
    steps a call runs. The ``seed`` input must be 0 (the structured schema draws nothing)."""

    kind = "structured"

    def __init__(self, schema, max_iter: int = PACKAGE_NEWTON_ITER):
        from ..schemas import StructuredSchema

        if not isinstance(schema, StructuredSchema):
            raise BodySchemaInputError(f"StructuredAdapterModule exports the structured schema; got "
                                       f"{type(schema).__name__}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, int) or not 1 <= max_iter <= 1000:
            raise BodySchemaInputError(f"max_iter={max_iter!r}: Newton steps per case, an int in 1..1000")
        super().__init__(schema, [0])
        self.schema, self.max_iter, self.dtype = schema, max_iter, schema.dtype
        self.snapshot = schema.body_snapshot() if schema.snapshot_covers() else None

    def body(self, q):
        """The learned body ``(l_geo, G, tau)`` at postures ``q (B, N)`` [rad]: the frozen ``BodySnapshot`` where it
        covers the body (``body_si``'s arithmetic), else ``schema.body`` at the normalized postures; the same numbers
        either way, every posture at once (exported, the batch size stays symbolic)."""
        return self.schema.body(self.normalized_q(q, self.dtype)) if self.snapshot is None else self.snapshot(q)

    def forward(self, q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed):
        bad, q, bounds = self.faults(q_ref, cut, jam, l_fixed_m, f_weak_n, band_lo_m, band_hi_m, seed)
        l_geo, G, tau = (t.to(torch.float64) for t in self.body(q))
        box_lo, box_hi = bounds.tension_box(l_geo)
        box_lo, crossed = uncrossed_box(box_lo, box_hi)  # crossed: no tension meets the bounds
        f_ref = (0.5 * self.f_max_n).expand_as(box_lo)
        newton = dual_newton(G, tau, f_ref, box_lo, box_hi, 0.0, NEWTON_TOL_NM, self.max_iter, fixed_iterations=True)
        held = newton.converged & ~crossed
        x = torch.where(held[:, None], torch.cat([bounds.motor_length_m(l_geo, newton.f), newton.f], 1), float("nan"))
        l_motor, f, status = self.safe(x, bounds, bad)
        status = learned_body_status(torch.where(~held & ~bad, Status.INFEASIBLE.code, status))
        return l_motor, f, status.to(torch.int32)
