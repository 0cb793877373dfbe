"""Independent joint coordinates of a model with joint couplings and locked joints.

MuJoCo writes both as ``<equality joint>`` constraints: ``joint1 - ref1 = a0 + a1 x + ... + a4 x^4`` with
``x = joint2 - ref2`` (a coupling: joint1 follows joint2), or ``joint1 - ref1 = a0`` without joint2 (a lock).
The pipeline works in the *free* joints only (neither following another nor locked): a posture is
``q (B, N)`` of the free joints, and ``full_q`` gives every joint of the model from it, so every
sampled posture lies exactly on the coupled manifold. ``tangent`` is ``E = d q_full / d q``; muscle
Jacobians become ``G = J_ten E`` and gravity ``E^T tau_bias`` (constraint forces do no work along the
manifold, so the equilibrium balances torques in these coordinates and the constraint forces are free).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import mujoco
import numpy as np

from ..errors import BodySchemaInputError

COUPLING_TOL_RAD = 1e-6  # a full posture given by the user may miss its couplings/locks by this much
_RANGE_GRID = 4001  # points per free joint range probed for dependents leaving their own range


def _horner(x: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """``coef[d, 0] + coef[d, 1] x[:, d] + ...`` at x (B, D), coefficients (D, K): numpy's ``polyval`` (the same
    operations, so the same numbers) for every coupling at once."""
    out = np.broadcast_to(coef[:, -1], x.shape).copy()
    for c in coef[:, -2::-1].T:
        out = out * x + c
    return out


@dataclass
class JointMap:
    """Free joints, locked joints and polynomial couplings of a compiled model (joint = qpos index)."""

    names: list[str]
    qpos0: np.ndarray  # (nq,) reference positions the equality polynomials are written around
    free: np.ndarray  # (N,) indices of the free joints
    locked: dict[int, float] = field(default_factory=dict)  # joint -> absolute value [rad or m]
    deps: list[tuple[int, int, np.ndarray]] = field(default_factory=list)  # (joint, follows, a0..a4)

    @classmethod
    def from_model(cls, m: mujoco.MjModel) -> "JointMap":
        names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}" for j in range(m.njnt)]
        locked, deps = {}, []
        for e in range(m.neq):
            if not m.eq_active0[e]:
                continue  # an inactive constraint does not hold
            label = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_EQUALITY, e) or f"#{e}"
            if int(m.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT):
                raise BodySchemaInputError(
                    f"equality constraint {label!r} is a {mujoco.mjtEq(int(m.eq_type[e])).name}; only <equality "
                    "joint> couplings and locks are supported (delete or deactivate the others)")
            j, k, coef = int(m.eq_obj1id[e]), int(m.eq_obj2id[e]), m.eq_data[e, :5].copy()
            if j in locked or any(d[0] == j for d in deps):
                raise BodySchemaInputError(f"joint {names[j]!r} is constrained twice (equality {label!r})")
            if k < 0:
                locked[j] = float(m.qpos0[j] + coef[0])
            else:
                deps.append((j, k, coef))
        dependent = {d[0] for d in deps}
        chained = [names[j] for j, k, _ in deps if k in dependent]
        if chained:
            raise BodySchemaInputError(f"joints {chained} follow a joint that itself follows another; only "
                                       "one level of <equality joint> coupling is supported")
        free = np.array([j for j in range(m.njnt) if j not in locked and j not in dependent], dtype=int)
        if free.size == 0:
            raise BodySchemaInputError("every joint is locked or coupled: the model has no free joint")
        return cls(names, m.qpos0[: m.njnt].copy(), free, locked, deps)

    @property
    def identity(self) -> bool:
        """True when every joint is free (no coupling, no lock): q is the model's qpos."""
        return not self.locked and not self.deps

    @property
    def free_names(self) -> list[str]:
        return [self.names[j] for j in self.free]

    def full_q(self, q: np.ndarray) -> np.ndarray:
        """Every joint (B, nq) from the free joints q (B, N): locks, then couplings (exactly on the manifold)."""
        if self.identity:
            return q
        full = np.tile(self.qpos0, (len(q), 1))
        full[:, self.free] = q
        for j, value in self.locked.items():
            full[:, j] = value
        if self.deps:  # every follower at once: a followed joint is free or locked, never a follower itself
            j, k, coef = self._dep_arrays
            full[:, j] = self.qpos0[j] + _horner(full[:, k] - self.qpos0[k], coef)
        return full

    def tangent(self, q: np.ndarray, full: np.ndarray | None = None) -> np.ndarray:
        """E = d full_q / d q (B, nq, N): 1 for a free joint, the polynomial's slope for its followers.
        ``full``: ``full_q(q)`` where the caller has it already."""
        batch, n_free = len(q), len(self.free)
        column = {j: c for c, j in enumerate(self.free)}
        e = np.zeros((batch, len(self.qpos0), n_free))
        e[:, self.free, np.arange(n_free)] = 1.0
        full = self.full_q(q) if full is None else full
        moving = [i for i, (_, k, _) in enumerate(self.deps) if k in column]  # a locked joint's followers stay
        if moving:
            j, k, coef = (a[moving] for a in self._dep_arrays)
            slope = coef[:, 1:] * np.arange(1, coef.shape[1])  # d/dx of a0 + a1 x + ... + a4 x^4
            e[:, j, [column[int(c)] for c in k]] = _horner(full[:, k] - self.qpos0[k], slope)
        return e

    def tangent_rate(self, q: np.ndarray, qdot: np.ndarray, full: np.ndarray | None = None) -> np.ndarray:
        """``dE/dt qdot`` (B, nq): the acceleration every joint has at velocity ``qdot`` (B, N) of the free joints
        and zero free acceleration, ``p''(x) xdot^2`` for a follower of x (0 for free and locked joints). With
        ``E qddot`` it is a follower's whole acceleration: the term that keeps a moving arm on the couplings."""
        out = np.zeros((len(q), len(self.qpos0)))
        column = {j: c for c, j in enumerate(self.free)}
        moving = [i for i, (_, k, _) in enumerate(self.deps) if k in column]
        if moving:
            j, k, coef = (a[moving] for a in self._dep_arrays)
            full = self.full_q(q) if full is None else full
            powers = np.arange(2, coef.shape[1])
            curvature = coef[:, 2:] * powers * (powers - 1)  # d2/dx2 of a0 + a1 x + ... + a4 x^4
            speed = qdot[:, [column[int(c)] for c in k]]
            out[:, j] = _horner(full[:, k] - self.qpos0[k], curvature) * speed ** 2
        return out

    @cached_property
    def _dep_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The couplings as arrays: followers (D,), followed joints (D,), coefficients a0..a4 (D, 5)."""
        return (np.array([d[0] for d in self.deps]), np.array([d[1] for d in self.deps]),
                np.array([d[2] for d in self.deps], float))

    def residual(self, full: np.ndarray) -> np.ndarray:
        """(B,) largest miss of the couplings and locks by full postures (B, nq) [rad or m]."""
        return np.abs(full - self.full_q(full[:, self.free])).max(axis=1)

    def reduce(self, full: np.ndarray, tol: float = COUPLING_TOL_RAD) -> np.ndarray:
        """Free joints (B, N) of full postures (B, nq), refusing postures off the couplings or locks."""
        miss = full - self.full_q(full[:, self.free])
        rows, joints = np.nonzero(np.abs(miss) > tol)
        if rows.size:
            b, j = int(rows[0]), int(joints[0])
            why = (f"locked at {self.locked[j]:.6g}" if j in self.locked else
                   f"coupled to {self.names[next(k for d, k, _ in self.deps if d == j)]!r}")
            raise BodySchemaInputError(
                f"q[{b}] of joint {self.names[j]!r} is {full[b, j]:.6g}, {miss[b, j]:+.3g} off its constraint "
                f"({why}; tolerance {tol:g}); {np.unique(rows).size} posture(s) off the couplings")
        return full[:, self.free]

    def free_range(self, jnt_range: np.ndarray) -> np.ndarray:
        """Ranges (N, 2) of the free joints, narrowed so that their followers stay inside their own ranges."""
        out = jnt_range[self.free].copy()
        for c, k in enumerate(self.free):
            followers = [(j, coef) for j, kk, coef in self.deps if kk == k]
            if not followers:
                continue
            grid = np.linspace(out[c, 0], out[c, 1], _RANGE_GRID)
            ok = np.ones(grid.shape, bool)
            for j, coef in followers:
                value = self.qpos0[j] + np.polynomial.polynomial.polyval(grid - self.qpos0[k], coef)
                ok &= (value >= jnt_range[j, 0] - 1e-12) & (value <= jnt_range[j, 1] + 1e-12)
            if not ok.any():
                raise BodySchemaInputError(f"no value of joint {self.names[k]!r} keeps its followers "
                                           f"{[self.names[j] for j, _ in followers]} inside their ranges")
            out[c] = grid[ok].min(), grid[ok].max()
        return out
