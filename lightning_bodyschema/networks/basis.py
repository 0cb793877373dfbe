"""The Legendre product basis of the per-muscle polynomials (paths, gates, cells, the polynomial torque)."""
from __future__ import annotations

import torch


def legendre(x: torch.Tensor, degree: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Legendre polynomials ``P_0..P_degree`` of ``x (B, N)`` and their derivatives: two ``(B, N, degree + 1)``."""
    values, slopes = [torch.ones_like(x)], [torch.zeros_like(x)]
    if degree >= 1:
        values.append(x)
        slopes.append(torch.ones_like(x))
    for n in range(1, degree):  # (n+1) P_{n+1} = (2n+1) x P_n - n P_{n-1};  P'_{n+1} = P'_{n-1} + (2n+1) P_n
        values.append(((2 * n + 1) * x * values[n] - n * values[n - 1]) / (n + 1))
        slopes.append(slopes[n - 1] + (2 * n + 1) * values[n])
    return torch.stack(values, -1), torch.stack(slopes, -1)


def product_basis(x: torch.Tensor, exponents: torch.Tensor, degree: int, slopes: bool = False):
    """``phi (B, P)`` and, with ``slopes``, ``dphi/dx (B, N, P)``: per term ``exponents (P, N)``, the product over the
    joints of each joint's Legendre polynomial of that exponent (a loop over the N joints, batched over samples and
    terms); ``degree``: the largest exponent."""
    values, derivs = legendre(x, degree)
    factors = [values[:, j][:, exponents[:, j]] for j in range(x.shape[1])]  # N x (B, P)
    before = [torch.ones_like(factors[0])]  # prod_{i<j} factor_i
    for factor in factors[:-1]:
        before.append(before[-1] * factor)
    phi = before[-1] * factors[-1]
    if not slopes:
        return phi, None
    dphi, after = [], torch.ones_like(phi)  # after: prod_{i>j} factor_i
    for j in reversed(range(x.shape[1])):
        dphi.append(derivs[:, j][:, exponents[:, j]] * before[j] * after)
        after = after * factors[j]
    return phi, torch.stack(dphi[::-1], 1)
