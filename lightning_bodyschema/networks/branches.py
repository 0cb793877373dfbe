"""Two-branch muscle paths, their state and fit: where a wrap switches sides the length jumps; two polynomials and a
gate follow it.

``fit_branches`` gives every muscle whose one-polynomial residual has a heavy tail a second polynomial (same terms)
and a gate (a polynomial over the same joints, the highest total degree ``<= gate_degree`` with at most
``GATE_TERMS`` terms) whose sign picks the branch, from the samples alone, batched over muscles: labels two ways
(``_labels_by_residual``, ``_labels_by_gate``), both branches refitted, the gate a logistic regression of the labels,
the better labelling kept where it pays (``_fit_group``). A path's branch state: ``add_branches``; its evaluation:
``networks.snapshot.PathSnapshot`` (the second polynomials and gates are candidate rows).
"""
from __future__ import annotations

import contextlib

import torch

from .polynomial import group_system, muscle_degrees, solve_systems

ROUNDS = 3  # alternations of branch fits and reassignment
REFINE = 4  # refinement steps of each branch's final least squares
GATE_STEPS = 12  # Newton steps of the gate's logistic regression
GATE_TERMS = 60  # a gate's degree is the highest <= gate_degree with at most this many terms
BRANCH_RIDGE = 1e-15  # each branch's ridge, times the whole sample's diagonal (a branch may hold few samples; a
# larger ridge biases a polynomial fitted on part of the box, where the basis is far from orthogonal)
CANDIDATE_TAIL = 8.0  # a muscle is a candidate when its p99.9 residual exceeds this many medians
TAIL_FLOOR = 1e-3  # and this (in the units of y: a normalized length, this fraction of its spread)
HEAVY_TAIL = 10.0  # a residual beyond this many medians is a miss (_labels_by_gate)
SWING = 4.0  # a kept gated model's largest residual is at most this many times the one polynomial's
SAMPLES_PER_TERM = 3  # a kept branch's samples per term of its polynomial (fewer: it interpolates, and swings)
NEAR_FRACTION = 0.02  # the largest residuals of the one polynomial, next to a jump: the first gate's samples


def add_branches(path) -> None:
    """``path``'s branch state, none branched: ``coef_alt``, ``gate`` like its ``coef`` and ``branched (M,)``, and
    ``branched_index`` (not in the state dict: a shape known before a call, for torch.export), kept in step with
    ``branched`` by the fit and every state-dict load (``refresh_branches``)."""
    path.register_buffer("coef_alt", torch.zeros_like(path.coef))
    path.register_buffer("gate", torch.zeros_like(path.coef))
    path.register_buffer("branched", torch.zeros(len(path.coef), dtype=torch.bool))
    path.register_buffer("branched_index", torch.zeros(0, dtype=torch.long), persistent=False)
    path.register_load_state_dict_post_hook(lambda module, _: refresh_branches(module))


def refresh_branches(path) -> None:
    """``branched_index`` from ``branched`` (not on the meta device, where a skeleton holds no values)."""
    if not path.branched.is_meta:
        path.branched_index = torch.nonzero(path.branched).flatten()


@contextlib.contextmanager
def one_thread():
    """torch's CPU threads set to 1 inside, then restored (a context or a decorator): batched float64 LU solves of
    ``(2, 300, 300)`` and larger hang in torch 2.13's MKL with 2 threads ("Parameter 6 was incorrect on entry to
    DLASWP"); the fits' least squares run inside."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _scatter(order, values, n_terms):
    """``(M, K)`` per-muscle coefficients (in ``order``) as ``(M, P)`` over every term (padded entries hold 0 and
    may repeat a column: they are added)."""
    return torch.zeros(len(order), n_terms, dtype=values.dtype, device=values.device).scatter_add_(1, order, values)


def _subset_systems(phi_all, y, labels, order, valid, chunk):
    """Normal equations of each muscle's own terms on its labelled samples only: ``labels (S, M')`` bool,
    ``y (S, M')``; ``((M', K, K), (M', K))``. Each muscle's samples are gathered and padded (weight 0)."""
    counts = labels.sum(0)
    n = max(int(counts.max()), 1)
    idx = torch.argsort((~labels).to(torch.int8), dim=0, stable=True)[:n].T  # (M', n): labelled samples first
    used = torch.arange(n, device=y.device)[None, :] < counts[:, None]
    y_sub = torch.gather(y.T, 1, idx) * used
    m, k = order.shape
    system = torch.zeros(m, k, k, dtype=torch.float64, device=y.device)
    rhs = torch.zeros(m, k, dtype=torch.float64, device=y.device)
    step = max(1, chunk // m)
    for start in range(0, n, step):
        phi = phi_all[idx[:, start:start + step]]  # (M', c, P)
        phi = phi.gather(2, order[:, None, :].expand(-1, phi.shape[1], -1))
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


def fit_gate(phi_all, labels, gate_order, gate_valid, chunk, beta=None, steps=GATE_STEPS, weight=None,
             ridge=1e-6):
    """Logistic regression of ``labels (S, M')`` on each muscle's gate terms, each sample weighted by ``weight
    (S, M')`` (None: 1), ``steps`` Newton steps from ``beta`` (None: zeros): ``(M', Kg)`` coefficients whose
    ``phi @ beta > 0`` predicts True."""
    m, k = gate_order.shape
    beta = torch.zeros(m, k, dtype=torch.float64, device=phi_all.device) if beta is None else beta
    t = labels.to(torch.float64)
    weight = torch.ones_like(t) if weight is None else weight
    for _ in range(steps):
        hess = torch.zeros(m, k, k, dtype=torch.float64, device=phi_all.device)
        grad = torch.zeros(m, k, dtype=torch.float64, device=phi_all.device)
        for start in range(0, len(phi_all), chunk):
            phi = phi_all[start:start + chunk][:, gate_order] * gate_valid  # (c, M', Kg)
            p = torch.sigmoid(torch.einsum("smk,mk->sm", phi, beta))
            w = weight[start:start + chunk]
            hess += torch.einsum("smk,sm,sml->mkl", phi, w * p * (1 - p), phi)
            grad += torch.einsum("smk,sm->mk", phi, w * (t[start:start + chunk] - p))
        n = len(phi_all)
        hess = hess + ridge * n * torch.eye(k, dtype=torch.float64, device=phi_all.device)
        beta = beta + torch.linalg.solve(hess, (grad - ridge * n * beta).unsqueeze(-1)).squeeze(-1)
        beta = beta * gate_valid
    return beta


def _fit_pair(phi, y_m, labels, system, b, order_m, valid_m, ridge, chunk, refine=0):
    """Least squares of both branches of the muscles ``order_m`` describes: ``(coef_a, coef_b)``, each ``(M', P)``,
    ``coef_b`` on the samples ``labels (S, M')`` marks, ``coef_a`` on the others (the full normal equations
    ``system, b`` minus the smaller set's); ``refine`` steps of refinement from the samples' residuals recover the
    unregularized answer where the samples determine it (a branch's normal equations square its condition number)."""
    small, flip = _minority(labels)
    sys_s, rhs_s = _subset_systems(phi, y_m, small, order_m, valid_m, chunk)
    sys_b = torch.where(flip[:, None, None], system - sys_s, sys_s)
    systems = (system - sys_b, sys_b)
    rhs_b = torch.where(flip[:, None], b - rhs_s, rhs_s)
    scale = system.diagonal(dim1=1, dim2=2).mean(1, keepdim=True)  # the ridge of the whole sample, both branches
    n_terms = phi.shape[1]
    coefs = [_scatter(order_m, solve_systems(a, r, valid_m, ridge, scale), n_terms)
             for a, r in zip(systems, (b - rhs_b, rhs_b))]
    for _ in range(refine):  # per branch phi^T (y - phi coef) over its samples
        grads = [((y_m - phi @ coef.T) * mask).T @ phi for coef, mask in zip(coefs, (~labels, labels))]
        coefs = [c + _scatter(order_m, solve_systems(a, g.gather(1, order_m), valid_m, ridge, scale), n_terms)
                 for c, a, g in zip(coefs, systems, grads)]
    return coefs


def _gate_terms(path, muscles, order_m, valid_m, gate_degree):
    """Each muscle's gate terms: ``(order (M', Kg), valid (M', Kg))``, its terms of total degree at most its gate
    degree (a muscle's terms run by total degree, so they come first)."""
    degrees = muscle_degrees(path.crossing[muscles].cpu().numpy(), gate_degree, GATE_TERMS)
    gate_valid = valid_m & (path.exponents.sum(1)[order_m] <= torch.as_tensor(degrees, device=order_m.device)[:, None])
    k_gate = int(gate_valid.sum(1).max())
    return order_m[:, :k_gate], gate_valid[:, :k_gate]


def _labels_by_residual(phi, y_m, r_m, fit_pair):
    """Labels from the one polynomial's residual split in two clusters (Otsu), then ``ROUNDS`` times: both branches
    fitted on their labels, each sample to the branch that fits it better (a wrap switching at one angle)."""
    labels = _minority(otsu_labels(r_m))[0]
    for _ in range(ROUNDS):
        pred_a, pred_b = (phi @ coef.T for coef in fit_pair(labels))
        labels = _minority((y_m - pred_b).abs() < (y_m - pred_a).abs())[0]
    return labels


def _labels_by_gate(phi, y_m, r_m, fit_pair, gate_terms, chunk):
    """Labels from a gate first fitted to the sign of the one polynomial's largest residuals (next to a jump its
    sign tells the side), then ``ROUNDS`` times: both branches fitted on the gate's sides, a sample switched where
    its branch misses by more than ``HEAVY_TAIL`` times the median miss and the other branch fits better (far from
    the switch each branch is extrapolated, and there a slight miss says nothing), the gate refitted (a switching
    surface slanted across joints)."""
    near = (r_m.abs() >= torch.quantile(r_m.abs(), 1 - NEAR_FRACTION, dim=0)).to(torch.float64)
    beta = fit_gate(phi, r_m > 0, *gate_terms, chunk, weight=near / near.mean(0))
    for _ in range(ROUNDS):
        side = phi @ _scatter(gate_terms[0], beta, phi.shape[1]).T > 0
        miss_a, miss_b = ((y_m - phi @ coef.T).abs() for coef in fit_pair(side))
        own, other = torch.where(side, miss_b, miss_a), torch.where(side, miss_a, miss_b)
        labels = side ^ ((own > HEAVY_TAIL * own.median(0).values) & (other < own))
        beta = fit_gate(phi, labels, *gate_terms, chunk, beta, GATE_STEPS // ROUNDS)
    return labels


def fit_branches(path, x, y, gram, rhs, order, gate_degree, chunk=8192):
    """Two branches and a gate for every heavy-tailed muscle of a fitted ``PerMusclePath`` (module docstring):
    sets ``coef``, ``coef_alt``, ``gate`` and ``branched`` of those that gain, from every term's normal equations
    ``gram (P, P)``, ``rhs (P, M)`` and ``order (M, P)``, each muscle's terms first."""
    r = torch.cat([y[i:i + chunk] - path.basis(x[i:i + chunk])[0] @ path.coef.T for i in range(0, len(x), chunk)])
    tail = torch.quantile(r.abs(), 0.999, dim=0)
    tail = (tail > CANDIDATE_TAIL * r.abs().median(0).values) & (tail > TAIL_FLOOR)
    counts = path.term_mask.sum(1)
    for k in torch.unique(counts[tail]).tolist():  # a loop over groups of candidates with equal term counts
        _fit_group(path, x, y, r, gram, rhs, order, torch.nonzero(tail & (counts == k)).flatten(), gate_degree, chunk)


def _fit_group(path, x, y, r, gram, rhs, order, muscles, gate_degree, chunk):
    """``fit_branches`` for the candidate ``muscles``, whose polynomials have equal term counts (their systems are
    then not padded: one candidate with many terms does not make every other's solves as large)."""
    mask = path.term_mask[muscles]
    order_g = order[muscles, :int(mask.sum(1).max())]  # the candidates' own normal equations, padded
    valid_m, y_m, r_m = mask.gather(1, order_g), y[:, muscles], r[:, muscles]
    system, b = group_system(gram, rhs, muscles, order_g, valid_m)
    cols = torch.nonzero(mask.any(0)).flatten()  # the candidates' terms: the basis is kept for these only
    local = torch.zeros(len(mask.T), dtype=torch.long, device=cols.device).index_copy_(
        0, cols, torch.arange(len(cols), device=cols.device))  # term -> column of phi (padding: 0, masked)
    phi = torch.cat([path.basis(x[i:i + chunk])[0][:, cols] for i in range(0, len(x), chunk)])  # (S, C), once
    gate_order, gate_valid = _gate_terms(path, muscles, order_g, valid_m, gate_degree)
    order_m, gate_terms = local[order_g], (local[gate_order], gate_valid)
    pair = lambda labels, idx=slice(None), refine=0: _fit_pair(  # noqa: E731
        phi, y_m[:, idx], labels, system[idx], b[idx], order_m[idx], valid_m[idx], BRANCH_RIDGE, chunk, refine)
    labels = [_labels_by_residual(phi, y_m, r_m, pair), _labels_by_gate(phi, y_m, r_m, pair, gate_terms, chunk)]
    both = torch.cat([torch.arange(len(muscles), device=x.device)] * 2)  # the two candidates of every muscle, batched
    labels = torch.cat(labels, 1)
    coef_a, coef_b = pair(labels, both, REFINE)
    gate = _scatter(gate_terms[0][both], fit_gate(phi, labels, gate_terms[0][both], gate_terms[1][both], chunk),
                    phi.shape[1])
    pred_a, pred_b, g = (phi @ coef.T for coef in (coef_a, coef_b, gate))
    miss = (y_m[:, both] - torch.where(g > 0, pred_b, pred_a)).abs()
    p99, worst = torch.quantile(miss, 0.99, dim=0).view(2, -1), miss.amax(0).view(2, -1)
    pick = p99.argmin(0) * len(muscles) + torch.arange(len(muscles), device=p99.device)
    keep = p99.min(0).values * 2 <= torch.quantile(r_m.abs(), 0.99, dim=0)  # the branches halve the p99
    # and no branch swings away (a branch turned on away from its samples can swing by metres)
    keep &= worst.gather(0, p99.argmin(0)[None])[0] <= SWING * r_m.abs().amax(0)
    small = torch.minimum(labels.sum(0), len(labels) - labels.sum(0))[pick]  # and both are well determined
    keep &= small >= SAMPLES_PER_TERM * valid_m.sum(1)
    kept, pick = muscles[keep], pick[keep]
    for name, value in (("coef", coef_a), ("coef_alt", coef_b), ("gate", gate)):  # columns back to terms
        getattr(path, name)[kept] = torch.zeros_like(path.coef[kept]).index_copy_(1, cols, value[pick])
    path.branched[kept] = True
