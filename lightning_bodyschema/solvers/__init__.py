"""Box QPs on muscle tensions: one problem (``BoxQP``), one solution (``Solution``), one entry (``solve_box_qp``).

torch (float64, any device); numpy only at proxsuite's boundary (``backends``). No Lightning, no schemas, no faults.

* ``newton``: the batched dual semismooth Newton, exportable with an iteration cap (a ``torch.while_loop``);
* ``least_squares``: the box least squares (the answer of a case without a solution);
* ``torque_reach``: the screen that proves a torque out of a box's reach;
* ``backends``: proxsuite (the fallback and the reference) and qpsolvers;
* ``solve``: ``solve_box_qp(problem, solver)``, the back-end chosen by name (the Newton then the fallbacks, by
  default).
"""
from .backends import proxsuite_solve, qpsolvers_solve
from .least_squares import LS_REG, box_least_squares, least_squares_weight
from .newton import NEWTON_MAX_ITER, NEWTON_TOL_NM, NewtonResult, dual_newton
from .problem import BoxQP, Solution, uncrossed_box
from .solve import EQUILIBRIUM_TOL_NM, FALLBACK_MAX_ITER, solve_box_qp
from .torque_reach import MAX_SCREEN_NORMALS, outside_torque_reach, residual_direction, screen_is_exact

__all__ = ["BoxQP", "Solution", "solve_box_qp", "dual_newton", "NewtonResult", "box_least_squares",
           "least_squares_weight", "outside_torque_reach", "residual_direction", "proxsuite_solve", "qpsolvers_solve",
           "uncrossed_box", "EQUILIBRIUM_TOL_NM", "FALLBACK_MAX_ITER", "LS_REG", "MAX_SCREEN_NORMALS",
           "screen_is_exact", "NEWTON_MAX_ITER", "NEWTON_TOL_NM"]
