"""One box-QP problem and one solution type for every tension QP of the package.

Per case (``G (M, N)`` [m/rad], ``tau (N,)`` [N m], tensions ``f (M,)`` [N])::

    min_f  1/2 ||f - f_ref||^2 + 1/(2 w) ||G^T f + tau||^2    s.t.  lo <= f <= hi       w > 0: least squares
    min_f  1/2 ||f - f_ref||^2   s.t.  G^T f + tau = 0,  lo <= f <= hi                  w = 0: equilibrium

(the equilibrium ``-G^T f = tau``: the torque the muscles balance). Every field is a float64 tensor on one device.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from .._arrays import minimum
from ..errors import BodySchemaInputError


class BoxQP(NamedTuple):
    """A batch of the module docstring's problems, validated (``BoxQP.build``).

    ``G (B, M, N)`` [m/rad], ``tau_nm (B, N)``, ``f_ref_n, lo_n, hi_n (B, M)`` [N] (+-inf where unbounded),
    ``w_m2 (B,)`` [m^2] (0: the equilibrium QP); ``crossed (B,)`` bool: some ``lo > hi`` in the given bounds (no
    tension meets them; ``lo_n`` is then lowered to ``hi_n`` so the box is never empty); ``bad_input (B,)`` bool:
    a non-finite G, tau or f_ref, or a NaN bound (the row is not solved)."""

    G: torch.Tensor
    tau_nm: torch.Tensor
    f_ref_n: torch.Tensor
    lo_n: torch.Tensor
    hi_n: torch.Tensor
    w_m2: torch.Tensor
    crossed: torch.Tensor
    bad_input: torch.Tensor

    @classmethod
    def build(cls, G, tau_nm, f_ref_n, lo_n, hi_n, w_m2=0.0, device=None) -> "BoxQP":
        """The problem from tensors or arrays: ``f_ref_n, lo_n, hi_n`` a scalar, ``(M,)`` or ``(B, M)``; ``w_m2`` a
        scalar or ``(B,)``, finite and >= 0. On ``device`` (default: G's). Raises ``BodySchemaInputError`` naming
        the first field of the wrong shape."""
        on_host = _host_fields(G, tau_nm, f_ref_n, lo_n, hi_n, w_m2, device)
        if on_host is not None:
            return cls(*on_host)
        G = _tensor("G", G, device)
        if G.dim() != 3:
            raise BodySchemaInputError(f"G has shape {tuple(G.shape)}; allowed: (B, M, N)")
        batch, m, n = G.shape
        tau = _shaped("tau_nm", tau_nm, (batch, n), G.device)
        f_ref, lo, hi = (_shaped(name, x, (batch, m), G.device)
                         for name, x in (("f_ref_n", f_ref_n), ("lo_n", lo_n), ("hi_n", hi_n)))
        w = _weight(w_m2, batch, G.device)
        finite = torch.isfinite(torch.cat([G.flatten(1), tau, f_ref], 1)).all(1)
        bad = ~(finite & ((lo < np.inf) & (hi > -np.inf)).all(1))  # NaN bounds compare False
        lo, crossed = uncrossed_box(lo, hi)
        return cls(G, tau, f_ref, lo, hi, w, crossed & ~bad, bad)

    @property
    def batch(self) -> int:
        return self.G.shape[0]

    def take(self, idx: torch.Tensor) -> "BoxQP":
        """The cases ``idx`` (indices or a (B,) mask)."""
        return BoxQP(*(x[idx] for x in self))

    def with_weight(self, w_m2: torch.Tensor) -> "BoxQP":
        """The same cases as least-squares problems of weight ``w_m2 (B,)``."""
        return self._replace(w_m2=w_m2)

    def balance_residual_nm(self, f_n: torch.Tensor) -> torch.Tensor:
        """``max_j |G^T f + tau|`` per case (B,) [N m]: how far ``f`` is from balancing the torque."""
        return ((self.G.transpose(1, 2) @ f_n.unsqueeze(-1)).squeeze(-1) + self.tau_nm).abs().amax(1)


class Solution(NamedTuple):
    """``f_n (B, M)`` [N] float64 on the problem's device, within the box (NaN rows where the input was bad);
    ``status (B,)`` int32 codes of ``lightning_bodyschema.status.Status``; ``iterations (B,)`` int32: the dual
    Newton's steps (0 where another back-end solved the case); ``problem``: the ``BoxQP`` it solves, so that the
    residuals below are the solution's own (qpsolvers' ``Solution`` style). ``certificate (B, N)``: on an
    equilibrium case ``INFEASIBLE`` in an uncrossed box, the unit direction u that proves it (Farkas:
    ``separation_gap_nm`` along u exceeds ``sqrt(N)`` times the equilibrium tolerance, so every tension in the box
    leaves some joint's residual above that tolerance); NaN on every other case (a crossed box is its own proof)."""

    f_n: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    problem: BoxQP
    certificate: torch.Tensor | None = None

    def balance_residual_nm(self) -> torch.Tensor:
        """``max_j |G^T f + tau|`` per case (B,) [N m]: the equilibrium's residual (0 to the tolerance on an ``ok``
        equilibrium case; what a least-squares case leaves unbalanced)."""
        return self.problem.balance_residual_nm(self.f_n)

    def box_residual_n(self) -> torch.Tensor:
        """``max_m`` of how far ``f`` lies outside ``[lo, hi]`` per case (B,) [N]: 0 on every solved row."""
        outside = torch.maximum(self.problem.lo_n - self.f_n, self.f_n - self.problem.hi_n)
        return outside.clamp_min(0.0).amax(1)


def uncrossed_box(lo, hi):
    """``(lo', crossed)``: the crossed-box rule of every tension QP. ``crossed (B,)`` where some ``lo > hi`` in the
    bounds ``lo, hi (B, M)`` (no tension meets them), and ``lo' = min(lo, hi)`` so the box is never empty and a solver
    stays well posed (the caller keeps ``crossed``). numpy arrays or torch tensors (``_arrays``)."""
    return minimum(lo, hi), (lo > hi).any(1)


def separation_gap_nm(G, tau, lo, hi, normals) -> torch.Tensor:
    """(B, K) ``u . tau - max_f u . (-G^T f)`` over the box ``lo <= f <= hi`` (B, M) for the unit directions ``u =
    normals (B, K, N)``: where it is positive, u separates tau from the torque zonotope {-G^T f} and every f in the box
    leaves ``|u . (G^T f + tau)| >= gap`` (some joint's residual ``>= gap / sqrt(N)``). An unbounded side along
    ``c = -G u`` gives the gap -inf (no proof)."""
    reach = -(G @ normals.transpose(1, 2)).transpose(1, 2)  # (B, K, M): c_m per direction
    zero = torch.zeros((), dtype=G.dtype, device=G.device)  # an infinite bound along c_m = 0 adds nothing
    support = torch.where(reach > 0, hi.unsqueeze(1) * reach,
                          torch.where(reach < 0, lo.unsqueeze(1) * reach, zero)).sum(-1)
    return (normals @ tau.unsqueeze(-1)).squeeze(-1) - support


def _weight(w_m2, batch: int, device) -> torch.Tensor:
    """``w_m2`` (a number or (B,)) as a (B,) float64 tensor, or the error naming a value that is negative or not
    finite (a number is checked on the host: no tensor operations for the common scalar)."""
    if isinstance(w_m2, (int, float)):
        if not (math.isfinite(w_m2) and w_m2 >= 0):
            raise BodySchemaInputError(f"w_m2 has {float(w_m2)!r}; allowed: finite numbers >= 0")
        return torch.full((batch,), float(w_m2), dtype=torch.float64, device=device)
    w = _shaped("w_m2", w_m2, (batch,), device)
    if not bool(((w >= 0) & torch.isfinite(w)).all()):
        raise BodySchemaInputError(f"w_m2 has {w[~((w >= 0) & torch.isfinite(w))][0].item()!r}; allowed: "
                                   "finite numbers >= 0")
    return w


def _host_fields(G, tau_nm, f_ref_n, lo_n, hi_n, w_m2, device):
    """``BoxQP.build``'s fields from float64 numpy arrays of the full shapes on the CPU (a controller's few cases):
    the same checks and rule in numpy (a few times cheaper per operation than torch at batch 1), then tensors that
    share the arrays' memory, as ``_tensor`` makes them; None for any other input (``build`` checks it in torch)."""
    arrays = (G, tau_nm, f_ref_n, lo_n, hi_n)
    if getattr(device, "type", device) not in (None, "cpu") or not isinstance(w_m2, (int, float)) or not all(
            isinstance(a, np.ndarray) and a.dtype == np.float64 for a in arrays) or G.ndim != 3:
        return None
    batch, m, n = G.shape
    if tau_nm.shape != (batch, n) or any(a.shape != (batch, m) for a in arrays[2:]):
        return None
    G, tau, f_ref, lo, hi = (a if a.flags.writeable and (a is G or a.flags.c_contiguous) else np.array(a)
                             for a in arrays)  # torch warns on read-only arrays (broadcasts)
    finite = np.isfinite(np.concatenate([G.reshape(batch, -1), tau, f_ref], 1)).all(1)
    bad = ~(finite & ((lo < np.inf) & (hi > -np.inf)).all(1))  # NaN bounds compare False
    lo, crossed = uncrossed_box(lo, hi)
    fields = (G, tau, f_ref, lo, hi)
    return (*(torch.from_numpy(a) for a in fields), _weight(w_m2, batch, device), torch.from_numpy(crossed & ~bad),
            torch.from_numpy(bad))


def _tensor(name: str, x, device) -> torch.Tensor:
    try:
        if isinstance(x, np.ndarray) and not x.flags.writeable:  # torch warns on read-only arrays (broadcasts)
            x = np.array(x, dtype=np.float64)
        if isinstance(x, np.ndarray) and x.dtype == np.float64 and getattr(device, "type", device) in (None, "cpu"):
            return torch.from_numpy(x)  # what as_tensor returns (shared memory), without its two dispatches
        return torch.as_tensor(x, dtype=torch.float64, device=device)
    except (TypeError, ValueError, RuntimeError) as error:
        raise BodySchemaInputError(f"{name} is not numeric ({error}); allowed: arrays or tensors of numbers") from None


def _shaped(name: str, x, shape: tuple, device) -> torch.Tensor:
    """``x`` as a float64 tensor broadcast to ``shape`` (a contiguous copy), or the error naming it."""
    t = _tensor(name, x, device)
    if t.shape == shape and t.is_contiguous():  # what expand and contiguous return, without their dispatch
        return t
    try:
        return t.expand(shape).contiguous() if t.dim() <= len(shape) else _wrong(name, t, shape)
    except RuntimeError:
        return _wrong(name, t, shape)


def _wrong(name: str, t: torch.Tensor, shape: tuple):
    raise BodySchemaInputError(f"{name} has shape {tuple(t.shape)}; allowed: a shape that broadcasts to {shape}")
