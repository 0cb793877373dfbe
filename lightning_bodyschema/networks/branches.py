"""Two-branch muscle paths: where a wrap switches sides the length jumps; two polynomials and a gate follow it.

MuJoCo's wrapping picks a side of each wrap object, and a muscle's length jumps where the side switches: the path
is piecewise smooth. A smooth polynomial rings around such a jump. ``fit_branches`` gives every muscle whose
residual after the one-polynomial fit has a heavy tail a second polynomial (same terms) and a gate, a polynomial of
total degree ``<= gate_degree`` over the same joints whose sign picks the branch, all fitted from the samples alone
(no branch label needed), batched over muscles:

The gate's total degree is the highest ``<= gate_degree`` with at most ``GATE_TERMS`` terms.

1. the first labels split each muscle's signed residual into two clusters (Otsu's threshold);
2. alternating: each branch's polynomial is refitted by least squares on its samples (the majority branch's normal
   equations are the full ones minus the minority's), and each sample goes to the branch that fits it better;
3. the gate is a logistic regression of those labels (Newton steps, a ridge keeps it finite on separable data);
4. a muscle keeps its branches only where the gated model's p99 train residual is at most half the single fit's.

The length at a posture is the active branch's polynomial and the moment arm its exact derivative: local, one-sided
at the jump. Plain PyTorch, no Lightning.
"""
from __future__ import annotations

import torch

from .degrees import muscle_degrees

ROUNDS = 4  # alternations of branch fits and reassignment
REFINE = 4  # refinement steps of each branch's least squares
GATE_STEPS = 12  # Newton steps of the gate's logistic regression
GATE_TERMS = 200  # a gate's degree is the highest <= gate_degree with at most this many terms
BRANCH_RIDGE = 1e-15  # each branch's ridge, times the whole sample's diagonal (a branch may hold few samples; a
# larger ridge biases a polynomial fitted on part of the box, where the basis is far from orthogonal)
CANDIDATE_TAIL = 5.0  # a muscle is a candidate when its p99.9 residual exceeds this many medians
TAIL_FLOOR = 1e-3  # and this (in the units of y: a normalized length, this fraction of its spread)
HEAVY_TAIL = 10.0  # a residual beyond this many medians is a miss (_reassign)
NEAR_FRACTION = 0.02  # the largest residuals of the one polynomial, next to a jump: the first gate's samples


def solve_systems(system, b, valid, ridge, scale=None, refine=2):
    """Each muscle's ridge-regularized normal equations ``(M, K, K) x = (M, K)``, padded terms (``~valid``) 0; the
    ridge is ``ridge`` times ``scale (M, 1)`` (default: the mean of the system's diagonal). ``refine`` steps of
    iterative refinement (a polynomial fitted on part of the box has an ill-conditioned system)."""
    if scale is None:
        scale = system.diagonal(dim1=1, dim2=2).mean(1, keepdim=True).clamp_min(1e-300)
    system = system + torch.diag_embed(torch.where(valid, ridge * scale, torch.ones_like(scale)))
    b = (b * valid).unsqueeze(-1)
    lu, pivots = torch.linalg.lu_factor(system)
    x = torch.linalg.lu_solve(lu, pivots, b)
    for _ in range(refine):
        x = x + torch.linalg.lu_solve(lu, pivots, b - system @ x)
    return x.squeeze(-1) * valid


def _scatter(order, values, n_terms):
    """``(M, K)`` per-muscle coefficients (in ``order``) as ``(M, P)`` over every term."""
    return torch.zeros(len(order), n_terms, dtype=values.dtype, device=values.device).scatter_(1, order, values)


def _predict(path, x, coefs, chunk):
    """``phi(x) @ coef.T`` for every ``coef (M', P)`` in ``coefs``: a list of ``(S, M')``."""
    out = [[] for _ in coefs]
    for start in range(0, len(x), chunk):
        phi = path.basis(x[start:start + chunk])[0]
        for i, coef in enumerate(coefs):
            out[i].append(phi @ coef.T)
    return [torch.cat(o) for o in out]


def _subset_systems(path, x, y, labels, order, valid, chunk):
    """Normal equations of each muscle's own terms on its labelled samples only: ``labels (S, M')`` bool,
    ``y (S, M')``; ``((M', K, K), (M', K))``. Each muscle's samples are gathered and padded (weight 0)."""
    counts = labels.sum(0)
    n = max(int(counts.max()), 1)
    idx = torch.argsort((~labels).to(torch.int8), dim=0, stable=True)[:n].T  # (M', n): labelled samples first
    used = torch.arange(n, device=x.device)[None, :] < counts[:, None]
    y_sub = torch.gather(y.T, 1, idx) * used
    m, k = order.shape
    system = torch.zeros(m, k, k, dtype=torch.float64, device=x.device)
    rhs = torch.zeros(m, k, dtype=torch.float64, device=x.device)
    step = max(1, chunk // m)
    for start in range(0, n, step):
        xi = x[idx[:, start:start + step]]  # (M', c, N)
        phi = path.basis(xi.reshape(-1, x.shape[1]))[0].reshape(m, xi.shape[1], -1)
        phi = phi.gather(2, order[:, None, :].expand(-1, xi.shape[1], -1))
        phi = phi * used[:, start:start + step, None] * valid[:, None, :]
        system += phi.transpose(1, 2) @ phi
        rhs += (phi.transpose(1, 2) @ y_sub[:, start:start + step, None])[..., 0]
    return system, rhs


def otsu_labels(r: torch.Tensor) -> torch.Tensor:
    """``(S, M)`` bool: per column, the samples above the threshold that best splits ``r`` into two clusters
    (largest between-cluster variance)."""
    values = torch.sort(r, 0).values
    s = len(r)
    n_low = torch.arange(1, s, dtype=r.dtype, device=r.device)[:, None]
    low = values.cumsum(0)[:-1]
    mean_low, mean_high = low / n_low, (values.sum(0) - low) / (s - n_low)
    between = n_low * (s - n_low) * (mean_low - mean_high).pow(2)
    split = between.argmax(0)
    threshold = 0.5 * (values.gather(0, split[None]) + values.gather(0, split[None] + 1))
    return r > threshold


def _minority(labels):
    """Labels flipped per column so that True marks the smaller branch, and the flip ``(M',)``."""
    flip = labels.sum(0) * 2 > len(labels)
    return labels ^ flip, flip


def fit_gate(path, x, labels, gate_order, gate_valid, chunk, beta=None, steps=GATE_STEPS, weight=None,
             ridge=1e-6):
    """Logistic regression of ``labels (S, M')`` on each muscle's gate terms, each sample weighted by ``weight
    (S, M')`` (None: 1), ``steps`` Newton steps from ``beta`` (None: zeros): ``(M', Kg)`` coefficients whose
    ``phi @ beta > 0`` predicts True."""
    m, k = gate_order.shape
    beta = torch.zeros(m, k, dtype=torch.float64, device=x.device) if beta is None else beta
    t = labels.to(torch.float64)
    weight = torch.ones_like(t) if weight is None else weight
    for _ in range(steps):
        hess = torch.zeros(m, k, k, dtype=torch.float64, device=x.device)
        grad = torch.zeros(m, k, dtype=torch.float64, device=x.device)
        for start in range(0, len(x), chunk):
            phi = path.basis(x[start:start + chunk])[0][:, gate_order] * gate_valid  # (c, M', Kg)
            p = torch.sigmoid(torch.einsum("smk,mk->sm", phi, beta))
            w = weight[start:start + chunk]
            hess += torch.einsum("smk,sm,sml->mkl", phi, w * p * (1 - p), phi)
            grad += torch.einsum("smk,sm->mk", phi, w * (t[start:start + chunk] - p))
        hess = hess + ridge * len(x) * torch.eye(k, dtype=torch.float64, device=x.device)
        beta = beta + torch.linalg.solve(hess, (grad - ridge * len(x) * beta).unsqueeze(-1)).squeeze(-1)
        beta = beta * gate_valid
    return beta


def _fit_pair(path, x, y_m, labels, system, b, order_m, valid_m, ridge, chunk):
    """Least squares of both branches of the muscles ``order_m`` describes: ``(coef_a, coef_b)``, each ``(M', P)``,
    ``coef_b`` on the samples ``labels (S, M')`` marks, ``coef_a`` on the others (the full normal equations
    ``system, b`` minus those of the smaller set, which alone are summed). A branch's normal equations square the
    condition number of its basis on part of the box; ``REFINE`` steps of refinement with residuals taken from the
    samples recover the unregularized least-squares answer where the samples determine it (the ridge only keeps each
    solve finite)."""
    small, flip = _minority(labels)
    sys_s, rhs_s = _subset_systems(path, x, y_m, small, order_m, valid_m, chunk)
    sys_b = torch.where(flip[:, None, None], system - sys_s, sys_s)
    systems = (system - sys_b, sys_b)
    rhs_b = torch.where(flip[:, None], b - rhs_s, rhs_s)
    scale = system.diagonal(dim1=1, dim2=2).mean(1, keepdim=True)  # the ridge of the whole sample, both branches
    n_terms = path.coef.shape[1]
    coefs = [_scatter(order_m, solve_systems(a, r, valid_m, ridge, scale), n_terms)
             for a, r in zip(systems, (b - rhs_b, rhs_b))]
    for _ in range(REFINE):
        grads = _gradients(path, x, y_m, labels, coefs, chunk)
        coefs = [c + _scatter(order_m, solve_systems(a, g.gather(1, order_m), valid_m, ridge, scale), n_terms)
                 for c, a, g in zip(coefs, systems, grads)]
    return coefs


def _gradients(path, x, y_m, labels, coefs, chunk):
    """``phi^T (y - phi coef)`` over each branch's samples (``~labels``, then ``labels``): two ``(M', P)``."""
    grads = [torch.zeros_like(c) for c in coefs]
    for start in range(0, len(x), chunk):
        phi, y, side = path.basis(x[start:start + chunk])[0], y_m[start:start + chunk], labels[start:start + chunk]
        for grad, coef, mask in zip(grads, coefs, (~side, side)):
            grad += ((y - phi @ coef.T) * mask).T @ phi
    return grads


def _reassign(y, pred_a, pred_b, side):
    """New labels ``(S, M')``: the gate's ``side``, switched where its branch misses by more than ``HEAVY_TAIL``
    times its median miss and the other branch fits better (far from the switch each branch is extrapolated and
    its slight misses say nothing)."""
    miss_b, miss_a = (y - pred_b).abs(), (y - pred_a).abs()
    own, other = torch.where(side, miss_b, miss_a), torch.where(side, miss_a, miss_b)
    return side ^ ((own > HEAVY_TAIL * own.median(0).values) & (other < own))


def _gate_terms(path, muscles, order_m, valid_m, gate_degree):
    """Each muscle's gate terms: ``(order (M', Kg), valid (M', Kg))``, its terms of total degree at most its gate
    degree (a muscle's terms run by total degree, so they come first)."""
    degrees = muscle_degrees(path.crossing[muscles].cpu().numpy(), gate_degree, GATE_TERMS)
    gate_valid = valid_m & (path.exponents.sum(1)[order_m] <= torch.as_tensor(degrees, device=order_m.device)[:, None])
    k_gate = int(gate_valid.sum(1).max())
    return order_m[:, :k_gate], gate_valid[:, :k_gate]


def fit_branches(path, x, y, system, b, order, valid, gate_degree, chunk=8192):
    """Two branches and a gate for every heavy-tailed muscle of a fitted ``PerMusclePath`` (module docstring):
    sets ``coef``, ``coef_alt``, ``gate`` and ``branched`` of those that gain. ``system, b, order, valid`` are the
    one-polynomial fit's padded normal equations (``PerMusclePath.fit_polynomial``)."""
    r = y - _predict(path, x, [path.coef], chunk)[0]
    tail = torch.quantile(r.abs(), 0.999, dim=0)
    tail = (tail > CANDIDATE_TAIL * r.abs().median(0).values) & (tail > TAIL_FLOOR)
    muscles = torch.nonzero(tail).flatten()
    if len(muscles) == 0:
        return
    ridge = BRANCH_RIDGE
    order_m, valid_m, y_m, system, b = order[muscles], valid[muscles], y[:, muscles], system[muscles], b[muscles]
    gate_order, gate_valid = _gate_terms(path, muscles, order_m, valid_m, gate_degree)
    r_m = r[:, muscles]  # in the tail next to a jump its sign tells the side: the first gate's labels
    near = (r_m.abs() >= torch.quantile(r_m.abs(), 1 - NEAR_FRACTION, dim=0)).to(torch.float64)
    beta = fit_gate(path, x, r_m > 0, gate_order, gate_valid, chunk, weight=near / near.mean(0))
    for _ in range(ROUNDS):  # each branch fits its side of the gate, each sample goes to the better, a new gate
        side = _predict(path, x, [_scatter(gate_order, beta, path.coef.shape[1])], chunk)[0] > 0
        coef_a, coef_b = _fit_pair(path, x, y_m, side, system, b, order_m, valid_m, ridge, chunk)
        pred_a, pred_b = _predict(path, x, [coef_a, coef_b], chunk)
        labels = _reassign(y_m, pred_a, pred_b, side)
        beta = fit_gate(path, x, labels, gate_order, gate_valid, chunk, beta, GATE_STEPS // ROUNDS)
    coef_a, coef_b = _fit_pair(path, x, y_m, labels, system, b, order_m, valid_m, ridge, chunk)
    gate = _scatter(gate_order, fit_gate(path, x, labels, gate_order, gate_valid, chunk, beta), path.coef.shape[1])
    pred_a, pred_b, g = _predict(path, x, [coef_a, coef_b, gate], chunk)
    gated = torch.where(g > 0, pred_b, pred_a)
    keep = torch.quantile((y_m - gated).abs(), 0.99, dim=0) * 2 <= torch.quantile(r[:, muscles].abs(), 0.99, dim=0)
    kept = muscles[keep]
    path.coef[kept] = coef_a[keep]
    path.coef_alt[kept] = coef_b[keep]
    path.gate[kept] = gate[keep]
    path.branched[kept] = True
