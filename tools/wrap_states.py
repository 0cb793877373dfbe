#!/usr/bin/env python
"""Does fitting each muscle's length per wrapping state close the learned body's tail? An offline experiment.

    python tools/wrap_states.py --ckpt runs/myoarm/.../last.ckpt [--muscles TMAJ,BIClong,DELT1,TRIlong,PECM3,LAT3,SUP
                                | all] [--postures 2000] [--seed 1] [--samples 20000,40000,0] [--flag-share 0.01]
                                [--gate-degree 8] [--cell-gate-degree 4] [--margin-degree 8] [--json FILE]
    python tools/wrap_states.py --ckpt CKPT --adaptive-rounds 3 [--pool 3] [--budgets 80000,160000,320000]
                                [--cell-degree 14] [...]
    python tools/wrap_states.py --ckpt CKPT --blend-margin 0.1 [--budgets 80000] [--cell-degree 14] [...]

MuJoCo's length is smooth inside one wrapping state (``sim.wrapping.wrap_states``: which geoms a path wraps and on
which side). The checkpoint's train postures (its data module, rebuilt from the checkpoint; ``--cache-dir``) are
labelled by state, and for each of ``--muscles`` the length is fitted by least squares to MuJoCo's length:

* (i) one polynomial over every sample in the checkpoint's own whole-box basis for the muscle (its terms: the same
  degree and joint groups; the checkpoint's fit before branches and cells);
* (ii) one such polynomial per wrapping state, the state known (a perfect gate: the label);
* (iii) the same polynomials picked by a learned gate: a least-squares polynomial classifier of the labels of
  total degree ``--gate-degree`` over the joints the muscle crosses (one score per state, the largest wins);
* (c) one polynomial per cell of the checkpoint's layout (``networks.cells``: its cut joints in its pieces, the
  cell's local coordinates, the muscle's joint groups, total degree up to the checkpoint's cell degree), states
  mixed and nothing trimmed; (ii-c) one per cell and state, the state known; (iii-c) the same picked by the gate of
  (iii); (iii-cg) picked by a gate per cell (``CellGate``: a logistic regression of the cell's states, total degree
  ``--cell-gate-degree``), a state's polynomial used only inside the box of its samples (else the cell's);
  (iv-cm) picked by MuJoCo's own rule applied to regressed margins (``sim.wrapping.wrap_margins``: each wrapping
  geom's smooth signed quantities, [mm], fitted per cell by least squares over the joints they move with, total
  degree up to ``--margin-degree``; ``MarginFit``), each state's polynomial used wherever it is picked, as in (ii-c).

A fit with fewer samples than twice its terms keeps only its terms up to the highest total degree that has at most
half as many terms as samples. A gated fit flags the postures within ``|g| / |grad g| <= r`` [rad] of its gate's
boundary (``g``: the largest score less the second; (iv-cm): the nearest zero of a margin whose sign alone decides
the state), ``r`` the largest that flags at most ``--flag-share`` of
``--postures`` other random postures (``--seed`` + 1). Scored at ``--postures`` seeded uniform postures (``--seed``,
as ``tools/body_errors.py``): the worst of these muscles per posture (length [mm], moment arm [mm/rad] on the joints
it crosses), median / p90 / p99 / max, beside the checkpoint's own body on the same muscles and on every muscle (the
others kept as the checkpoint has them); gated fits also over the postures they do not flag; per muscle the length
p50 / p99 of each fit; (ii-c)'s p99 within and beyond ``NEAR_RAD`` of a true switch (along a joint the muscle
crosses); the gates' share of right states, and where the cell gates' and the margins' wrong answers lie (within
``MISGATE_RADII`` / ``MARGIN_RADII`` of a true switch); the margins' regression residual. Each ``--samples`` count
(0: every train sample) refits (ii) on the first that many train samples: the samples it needs. ``--json``: the
figures also to a file (written to a temporary name, then renamed). One torch thread.

``--adaptive-rounds N`` (> 0) runs only an adaptive-sampling experiment (``Adaptive``) instead, on fresh seeded
uniform postures rather than the checkpoint's train split: per budget of ``--budgets`` train samples, (ii-c) and
(iv-cm) fitted on that many uniform postures, and adaptively on half of them plus ``N`` rounds, each drawing
``--pool`` times as many fresh uniform postures as it adds, predicting MuJoCo's length there with the current
(ii-c) fit and adding those whose worst muscle it misses most; each fit scored as above (the worst of ``--muscles``
per held-out posture, (ii-c) and (iv-cm), and each muscle's p99), with the samples and each round's threshold.
``--cell-degree`` (every mode): each length polynomial's highest total degree in a cell instead of the checkpoint's.

``--blend-margin W`` (in (0, 0.5]) runs only a blend experiment (``Blend``) instead: per budget of ``--budgets`` fresh
seeded uniform train postures (as ``--adaptive-rounds``), the true state, (a) one polynomial per (cell, state); (b)
each fitted on its cell widened by ``W`` of the cell's width beyond every cut, used in its own cell; (c) those pieces
blended across each cut by a C1 partition of unity over [cut - w, cut + w]; (c) with the state from margins
regressed per cell (as (iv-cm), ``--margin-degree``); each scored as above (the worst of
``--muscles`` per held-out posture; length and moment arm), and within ``NEAR_RAD`` of a cut / beyond 0.1 rad.
"""
import argparse
import itertools
import json

import numpy as np
import torch

from lightning_bodyschema.apps.common import exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.basis import product_basis
from lightning_bodyschema.networks.cells import cell_coordinates
from lightning_bodyschema.sim.wrapping import states_from_margins, wrap_geoms, wrap_margins, wrap_states

DEFAULT_MUSCLES = "TMAJ,BIClong,DELT1,TRIlong,PECM3,LAT3,SUP"
CHUNK = 4000  # train rows per basis block; --samples counts are rounded up to it
RIDGE = 1e-10  # relative to the mean diagonal of each normal-equation matrix
CELL_DEGREE = 11  # a cell's highest total degree where the checkpoint has no cells on the muscle (its myoArm cells')
GATE_ROUNDS, GATE_RIDGE = 12, 1e-6  # a cell gate's Newton steps and ridge (per sample): separable data stays bounded
MISGATE_RADII = (0.005, 0.01, 0.02, 0.05)  # how far from a true switch the cell gates' wrong answers lie [rad]
MARGIN_RADII = (0.001, 0.005, 0.01)  # the same for the margins' gate [rad]
MARGIN_STEP = 1e-3  # [rad] a joint moves a margin when this step along it does (at MARGIN_PROBES train postures)
MARGIN_PROBES = 200
NEAR_RAD = 0.01  # a posture this near a true switch of a muscle's state (along a joint it crosses) is "near"
STATE_KEYS = 1000  # cell * STATE_KEYS + state: one key per (cell, wrapping state); codes stay below 3**6


def basis(x: torch.Tensor, exponents: torch.Tensor, slopes: bool = False):
    """``phi (B, P)`` (and ``dphi/dx (B, N, P)``) of terms ``exponents (P, N)`` at normalized postures ``x``."""
    return product_basis(x, exponents, max(1, int(exponents.max())), slopes)


def state_normal_equations(x, y, labels, exponents, states, marks):
    """Per state, ``phi^T phi`` and ``phi^T y`` and the count, summed over the train rows in blocks; a copy at each
    row count in ``marks`` (the first that many rows): ``{rows: (gram (K, P, P), rhs (K, P), counts (K,))}``."""
    k, p = len(states), len(exponents)
    gram, rhs, counts, out = torch.zeros(k, p, p, dtype=torch.float64), torch.zeros(k, p, dtype=torch.float64), \
        np.zeros(k, np.int64), {}
    for start in range(0, len(x), CHUNK):
        phi, rows = basis(x[start:start + CHUNK], exponents)[0], slice(start, start + CHUNK)
        for i, state in enumerate(states):
            at = torch.as_tensor(labels[rows] == state)
            gram[i] += phi[at].T @ phi[at]
            rhs[i] += phi[at].T @ y[rows][at]
            counts[i] += int(at.sum())
        if min(start + CHUNK, len(x)) in marks:
            out[min(start + CHUNK, len(x))] = (gram.clone(), rhs.clone(), counts.copy())
    return out


def solve(gram: torch.Tensor, rhs: torch.Tensor, n: int, exponents: torch.Tensor) -> torch.Tensor:
    """Coefficients ``(P,)`` from one state's normal equations, on its terms up to the highest total degree with at
    most ``n / 2`` terms (module docstring); zero elsewhere."""
    total = exponents.sum(1)
    keep = total <= 0
    for degree in range(int(total.max()), -1, -1):
        keep = total <= degree
        if 2 * int(keep.sum()) <= n:
            break
    g = gram[keep][:, keep]
    g = g + RIDGE * float(g.diagonal().mean()) * torch.eye(len(g), dtype=g.dtype)
    coef = torch.zeros(len(exponents), dtype=torch.float64)
    coef[keep] = torch.linalg.solve(g, rhs[keep])
    return coef


def group_exponents(blocks, degree: int) -> torch.Tensor:
    """Every monomial of total degree <= ``degree`` whose joints all lie in one group of ``blocks (N,)`` (a group id
    per joint, -1: not crossed; the checkpoint's ``path_blocks`` row: lengths that add up over groups), as Legendre
    exponents ``(P, N)``, the constant first."""
    blocks, rows = np.asarray(blocks), {(0,) * len(blocks)}
    for group in sorted(set(blocks.tolist()) - {-1}):
        joints = np.flatnonzero(blocks == group)
        for e in itertools.product(range(degree + 1), repeat=len(joints)):
            if sum(e) <= degree:
                row = np.zeros(len(blocks), np.int64)
                row[joints] = e
                rows.add(tuple(row.tolist()))
    return torch.as_tensor(sorted(rows, key=lambda r: (sum(r), r)))


def gate_exponents(crossed: np.ndarray, degree: int) -> torch.Tensor:
    """Every monomial of total degree <= ``degree`` over the ``crossed (N,)`` joints, as Legendre exponents."""
    return group_exponents(np.where(crossed, 0, -1), degree)


def fit_gate(x, labels, states, exponents):
    """Least squares of one-hot state indicators ``(S, K)`` on the gate's basis: weights ``(P, K)``."""
    p = len(exponents)
    gram, rhs = torch.zeros(p, p, dtype=torch.float64), torch.zeros(p, len(states), dtype=torch.float64)
    onehot = torch.as_tensor(labels[:, None] == np.asarray(states)[None, :], dtype=torch.float64)
    for start in range(0, len(x), CHUNK):
        phi = basis(x[start:start + CHUNK], exponents)[0]
        gram += phi.T @ phi
        rhs += phi.T @ onehot[start:start + CHUNK]
    return torch.linalg.solve(gram + RIDGE * float(gram.diagonal().mean()) * torch.eye(p, dtype=gram.dtype), rhs)


def gate(x, weights, exponents, rad_per_unit):
    """The gate at ``x``: the state index ``(B,)`` and the distance estimate ``|g| / |grad g|`` [rad] ``(B,)``."""
    phi, dphi = basis(x, exponents, slopes=True)
    scores, slopes = phi @ weights, dphi @ weights  # (B, K), (B, N, K)
    if scores.shape[1] == 1:
        return torch.zeros(len(x), dtype=torch.long), torch.full((len(x),), float("inf"), dtype=torch.float64)
    return margin(scores, slopes, 1 / rad_per_unit)


class MuscleFit:
    """One muscle's fits (module docstring) in its checkpoint basis; lengths in mm, postures normalized."""

    def __init__(self, exponents, states, coef_all, coef_state, gate_weights, gate_terms):
        self.exponents, self.states, self.coef_all, self.coef_state = exponents, states, coef_all, coef_state
        self.gate_weights, self.gate_terms = gate_weights, gate_terms

    def predict(self, x, pick, rad_per_unit):
        """Length [mm] ``(B,)`` and moment arms [mm/rad] ``(B, N)`` with coefficients ``pick (B, P)``."""
        phi, dphi = basis(x, self.exponents, slopes=True)
        return (phi * pick).sum(1), (dphi * pick[:, None, :]).sum(2) / rad_per_unit[None, :]

    def pick(self, mode, x, labels, rad_per_unit, coef_state=None):
        """Coefficients per posture ``(B, P)`` for ``mode`` "all" / "state" / "gate" and the gate's distance."""
        coef_state = self.coef_state if coef_state is None else coef_state
        far = torch.full((len(x),), float("inf"), dtype=torch.float64)
        if mode == "all":
            return self.coef_all.expand(len(x), -1), far
        if mode == "state":  # a state the train samples never saw keeps the one polynomial
            table = torch.stack([self.coef_all] + list(coef_state))
            index = np.searchsorted(self.states, labels)
            known = (index < len(self.states)) & (np.asarray(self.states)[np.minimum(index, len(self.states) - 1)]
                                                   == labels)
            return table[torch.as_tensor(np.where(known, index + 1, 0))], far
        index, distance = gate(x, self.gate_weights, self.gate_terms, rad_per_unit)
        return torch.stack(list(coef_state))[index], distance


def fit_muscle(x, y, labels, exponents, crossed, gate_degree, marks):
    """``MuscleFit`` on every train row and, per mark, the per-state coefficients on its first rows."""
    states = np.unique(labels).tolist()
    sums = state_normal_equations(x, y, labels, exponents, states, set(marks) | {len(x)})
    gram, rhs, counts = sums[len(x)]
    coef_all = solve(gram.sum(0), rhs.sum(0), int(counts.sum()), exponents)
    coef_state = [solve(gram[i], rhs[i], int(counts[i]), exponents) for i in range(len(states))]
    gate_terms = gate_exponents(crossed, gate_degree)
    weights = fit_gate(x, labels, states, gate_terms)
    by_mark = {n: [solve(g[i], r[i], int(c[i]), exponents) for i in range(len(states))]
               for n, (g, r, c) in sums.items()}
    return MuscleFit(exponents, states, coef_all, coef_state, weights, gate_terms), by_mark, counts


def cell_keys(x: torch.Tensor, cut: np.ndarray, pieces: int):
    """The checkpoint's cells (``networks.cells``: each joint in ``cut (N,)`` cut in ``pieces``): the cell ``(B,)``,
    the cell's local coordinates ``z (B, N)`` (uncut joints as they are) and ``dz/dx (N,)``."""
    piece, local = cell_coordinates(x, pieces)
    joints = np.flatnonzero(cut)
    cell = sum((piece[:, j].numpy() * pieces ** i for i, j in enumerate(joints)), np.zeros(len(x), np.int64))
    z, dz_dx = x.clone(), torch.ones(x.shape[1], dtype=torch.float64)
    z[:, joints], dz_dx[joints] = local[:, joints], float(pieces)
    return np.asarray(cell, np.int64), z, dz_dx


class CellFit:
    """One polynomial per key (a cell, or a cell and a wrapping state) in the cell's coordinates, over the groups
    ``blocks`` of joints, of the highest total degree <= ``cap`` with at most half as many terms as samples."""

    def __init__(self, z, y, keys, blocks, cap):
        self.table, terms = {}, {d: group_exponents(blocks, d) for d in range(cap + 1)}
        for key in np.unique(keys):
            rows = torch.as_tensor(keys == key)
            fitting = [d for d in range(cap + 1) if 2 * len(terms[d]) <= int(rows.sum())]
            if not fitting:
                continue
            exponents = terms[max(fitting)]
            phi = basis(z[rows], exponents)[0]
            gram = phi.T @ phi
            gram += RIDGE * float(gram.diagonal().mean()) * torch.eye(len(gram), dtype=gram.dtype)
            box = (z[rows].amin(0), z[rows].amax(0))  # where this key's samples are
            self.table[int(key)] = (exponents, torch.linalg.solve(gram, phi.T @ y[rows]), box)

    def predict(self, z, keys, dz_dq, fallback, within_box: bool = False):
        """Length [mm] and moment arms [mm/rad] at ``z`` by key; keys without a fit keep ``fallback`` (l, G), and
        with ``within_box`` so do postures outside the box of their key's samples (a gate that picks a state where
        it has no sample would extrapolate that state's polynomial)."""
        l_hat, g_hat = fallback[0].clone(), fallback[1].clone()
        for key in np.unique(keys):
            if int(key) not in self.table:
                continue
            rows, (exponents, coef, (lo, hi)) = torch.as_tensor(keys == key), self.table[int(key)]
            if within_box:
                rows &= ((z >= lo) & (z <= hi)).all(1)
            phi, dphi = basis(z[rows], exponents, slopes=True)
            l_hat[rows], g_hat[rows] = phi @ coef, (dphi @ coef) * dz_dq[None, :]
        return l_hat, g_hat


class CellGate:
    """A gate per cell: one-vs-rest logistic regressions (``GATE_ROUNDS`` Newton steps, ridge ``GATE_RIDGE``) of the
    cell's wrapping states on a polynomial of total degree <= ``degree`` in the cell's coordinates over the
    ``crossed`` joints; a cell whose samples are all in one state answers it everywhere. The distance to the gate's
    boundary ``|g| / |grad g|`` (``g``: the largest logit less the second) does not depend on the logits' scale."""

    def __init__(self, z, cells, labels, crossed, degree):
        self.table, terms = {}, {d: gate_exponents(crossed, d) for d in range(degree + 1)}
        for cell in np.unique(cells):
            rows = cells == cell
            states = np.unique(labels[rows])
            fitting = [d for d in range(1, degree + 1) if 4 * len(terms[d]) <= int(rows.sum())]
            if len(states) == 1 or not fitting:
                self.table[int(cell)] = (states[np.argmax([np.sum(labels[rows] == s) for s in states])], None, None)
                continue
            exponents = terms[max(fitting)]
            phi = basis(z[torch.as_tensor(rows)], exponents)[0]
            weights = torch.stack([logistic(phi, torch.as_tensor(labels[rows] == k, dtype=torch.float64))
                                   for k in states], 1)
            self.table[int(cell)] = (states, exponents, weights)

    def __call__(self, z, cells, dz_dq):
        """The gated state ``(B,)`` and the distance to the gate's boundary [rad] ``(B,)`` (inf: a one-state cell)."""
        state, distance = np.zeros(len(z), np.int64), np.full(len(z), np.inf)
        for cell in np.unique(cells):
            rows = cells == cell
            states, exponents, weights = self.table.get(int(cell), (np.array([0]), None, None))
            if weights is None:
                state[rows] = states
                continue
            phi, dphi = basis(z[torch.as_tensor(rows)], exponents, slopes=True)
            index, reach = margin(phi @ weights, dphi @ weights, dz_dq)
            state[rows], distance[rows] = states[index.numpy()], reach.numpy()
        return state, distance


def logistic(phi: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Weights ``(P,)`` of a ridge logistic regression of ``target (S,)`` in {0, 1} on ``phi (S, P)`` (Newton)."""
    w = torch.zeros(phi.shape[1], dtype=torch.float64)
    ridge = GATE_RIDGE * len(phi) * torch.eye(phi.shape[1], dtype=torch.float64)
    for _ in range(GATE_ROUNDS):
        p = torch.sigmoid(phi @ w)
        hessian = phi.T @ (phi * (p * (1 - p))[:, None]) + ridge
        w = w + torch.linalg.solve(hessian, phi.T @ (target - p) - ridge @ w)
    return w


def margin(scores: torch.Tensor, slopes: torch.Tensor, dz_dq: torch.Tensor):
    """The winning column of ``scores (B, K)`` and ``|g| / |grad_q g|`` [rad], ``g`` its lead over the second;
    ``slopes (B, N, K)`` d scores / d z, ``dz_dq (N,)``."""
    top2, rows = torch.topk(scores, 2, dim=1).indices, torch.arange(len(scores))
    g = scores[rows, top2[:, 0]] - scores[rows, top2[:, 1]]
    grad = (slopes[rows, :, top2[:, 0]] - slopes[rows, :, top2[:, 1]]) * dz_dq[None, :]
    return top2[:, 0], g.abs() / grad.norm(dim=1).clamp_min(1e-300)


def percentiles(a: np.ndarray) -> list:
    return [float(np.percentile(a, p)) for p in (50, 90, 99, 100)]


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--muscles", default=DEFAULT_MUSCLES, help="names (comma-separated) or all")
    parser.add_argument("--postures", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--samples", default="20000,40000,0", help="train-sample counts for (ii); 0: all")
    parser.add_argument("--gate-degree", type=int, default=8)
    parser.add_argument("--cell-gate-degree", type=int, default=4)
    parser.add_argument("--flag-share", type=float, default=0.01)
    parser.add_argument("--margin-degree", type=int, default=8, help="(iv-cm): a margin's highest cell degree")
    parser.add_argument("--cell-degree", type=int, default=0,
                        help="a length's highest cell degree (0: the checkpoint's); a fit still keeps at most half "
                             "as many terms as samples")
    parser.add_argument("--cache-dir", default="runs/cache")
    parser.add_argument("--adaptive-rounds", type=int, default=0,
                        help="> 0: only the adaptive-sampling experiment (class Adaptive), in this many rounds")
    parser.add_argument("--pool", type=int, default=3,
                        help="an adaptive round draws this many fresh uniform postures per posture it adds")
    parser.add_argument("--budgets", default="80000,160000,320000", help="train samples per adaptive run")
    parser.add_argument("--blend-margin", type=float, default=0.0,
                        help="> 0: only the blend experiment (class Blend): each piece widened by this share of "
                             "its cell beyond every cut, blended across the cuts; in (0, 0.5]")
    parser.add_argument("--json", default=None, help="also write the figures to this file")
    args = parser.parse_args(argv)
    if not 0.0 <= args.blend_margin <= 0.5 or (args.blend_margin and args.adaptive_rounds):
        raise BodySchemaInputError(f"--blend-margin {args.blend_margin}: expected a share of the cell in (0, 0.5] "
                                   "(0: off), not with --adaptive-rounds")
    if not all(part.strip().isdigit() for part in args.samples.split(",")):
        raise BodySchemaInputError(f"--samples {args.samples!r}: expected train-sample counts >= 0, comma-separated")
    if args.postures < 100 or min(args.gate_degree, args.margin_degree) < 1 or not 0.0 <= args.flag_share < 1.0 \
            or args.cell_degree < 0:
        raise BodySchemaInputError(f"--postures {args.postures} / --gate-degree {args.gate_degree} / --margin-degree "
                                   f"{args.margin_degree} / --flag-share {args.flag_share} / --cell-degree "
                                   f"{args.cell_degree}: expected >= 100 / >= 1 / >= 1 / in [0, 1) / >= 0")
    if args.adaptive_rounds < 0 or args.pool < 1 or not all(b.strip().isdigit() and int(b) >= 2 * args.adaptive_rounds
                                                            for b in args.budgets.split(",")):
        raise BodySchemaInputError(f"--adaptive-rounds {args.adaptive_rounds} / --pool {args.pool} / --budgets "
                                   f"{args.budgets!r}: expected >= 0 / >= 1 / counts >= twice the rounds, "
                                   "comma-separated")
    torch.set_num_threads(1)
    experiment = (run_blend, blend_table) if args.blend_margin else (run_adaptive, adaptive_table) \
        if args.adaptive_rounds else (run, table)
    result = experiment[0](args)
    if args.json is not None:
        write_json(result, args.json)
    print(experiment[1](result))


def write_json(result: dict, path: str) -> None:
    import os
    with open(path + ".tmp", "w") as f:  # a temporary name, then renamed: never a half-written file
        json.dump(result, f, indent=1)
    os.replace(path + ".tmp", path)


def table(result: dict) -> str:
    """The figures as markdown: one row per fit, the worst muscle per posture over these muscles and over all."""
    fmt = lambda values: " / ".join(f"{v:.3g}" for v in values)  # noqa: E731
    lines = ["states (code: train samples): " + "; ".join(f"{m} {dict(zip(s['codes'], s['train_samples']))}"
                                                         for m, s in result["states"].items()), "",
             f"| fit | postures | {', '.join(result['muscles'])}: worst length p50 / p90 / p99 / max [mm] | worst "
             "moment arm p50 / p90 / p99 / max [mm/rad] | every muscle: worst length p50 / p90 / p99 / max [mm] | "
             "> 0.1 mm |", "|---|---|---|---|---|---|"]
    labels = dict(ROWS)
    labels.update({f"{k}, unflagged": f"{labels[k]}, outside the flag band ({100 * f['flagged_share']:.3g} % "
                   f"flagged, r = {1e3 * f['radius_rad']:.3g} mrad)" for k, f in result["flags"].items()})
    for key, r in result["rows"].items():
        label = labels.get(key, f"(ii) on the first {key[3:]} train samples")
        lines.append(f"| {label} | {r['postures']} | {fmt(r['these_length_mm'])} | {fmt(r['these_arm_mm_per_rad'])} "
                     f"| {fmt(r['all_length_mm'])} | {100 * r['bad_share_all']:.3g} % |")
    lines += ["", "per muscle, length p50 / p99 [mm]: | " + " | ".join(result["muscles"]) + " |"]
    for key, r in result["rows"].items():
        lines.append(f"| {key} | " + " | ".join(fmt(v) for v in r["per_muscle_length_p50_p99_mm"].values()) + " |")
    lines.append("(ii-c) per muscle, length p99 [mm] within / beyond {:g} rad of a true switch (share within): ".format(
        NEAR_RAD) + ", ".join(f"{m} {fmt([v for v in nf if v is not None])} ({100 * result['near_switch_share'][m]:.3g} %)"
                               for m, nf in result["ii-c_near_far_p99_mm"].items()))
    for key, label in (("cell_gate_wrong_near_switch", "gate per cell"), ("margin_gate_wrong_near_switch", "margins")):
        wrong = result[key]
        lines.append(f"{label}, wrong answers ({sum(wrong['postures'])} muscle-postures): share within " + ", ".join(
            f"{1e3 * r:g}" for r in wrong["radii_rad"]) + " mrad of a true switch along a joint: " + ", ".join(
            "-" if v is None else f"{100 * v:.3g} %" for v in wrong["share_within"]))
    lines.append("margins, regression residual p99 (largest over a muscle's margins) [mm]: " + ", ".join(
        f"{m} {v:.3g}" for m, v in result["margin_residual_p99_mm"].items()))
    for key, label in (("gate_accuracy", "whole-box gate"), ("cell_gate_accuracy", "gate per cell"),
                       ("margin_gate_accuracy", "margins")):
        lines.append(f"{label}, share of postures in the right state: " + ", ".join(
            f"{m} {100 * a:.3g} %" for m, a in result[key].items()))
    return "\n".join(lines)


def load(args):
    """The checkpoint's schema, its muscles' names and the indices of ``--muscles``."""
    from lightning_bodyschema.schemas.loading import load_schema

    schema = load_schema(args.ckpt).eval()
    names = [n.removesuffix("_tendon") for n in schema.robot_model.muscle_names]
    wanted = names if args.muscles == "all" else [m.strip().removesuffix("_tendon") for m in args.muscles.split(",")
                                                  if m.strip()]
    unknown = [m for m in wanted if m not in names]
    if unknown or not hasattr(schema.length_net, "exponents"):
        raise BodySchemaInputError(f"--muscles {unknown}: not muscles of this body ({names}), or the checkpoint's "
                                   f"path is not per_muscle")
    return schema, names, [names.index(m) for m in wanted]


def run_adaptive(args) -> dict:
    schema, names, muscles = load(args)
    return Adaptive(args, schema, muscles).run([names[m] for m in muscles])


def adaptive_table(result: dict) -> str:
    """The adaptive experiment as markdown: one row per budget and round."""
    fmt = lambda values: " / ".join(f"{v:.3g}" for v in values)  # noqa: E731
    muscles = result["muscles"]
    lines = [f"| budget | fit | train samples | (ii-c) true state: worst length p50 / p90 / p99 / max [mm] | worst "
             f"moment arm p99 [mm/rad] | (iv-cm) regressed margins: worst length p50 / p90 / p99 / max [mm] | "
             f"(ii-c) per muscle p99 [mm] ({', '.join(muscles)}) | next round: added of pool, threshold [mm] |",
             "|---|---|---|---|---|---|---|---|"]
    for budget, runs in result["budgets"].items():
        for name, row in [("uniform", runs["uniform"])] + [(f"round {r}", row) for r, row in
                                                            enumerate(runs["adaptive"])]:
            step = row.get("next")
            lines.append(f"| {budget} | {name} | {row['samples']} | {fmt(row['ii-c']['length_mm'])} | "
                         f"{row['ii-c']['arm_mm_per_rad'][2]:.3g} | {fmt(row['iv-cm']['length_mm'])} | "
                         f"{fmt(row['ii-c']['muscle_p99_mm'])} | "
                         + (f"{step['added']} of {step['pool']}, {step['threshold_mm']:.3g} |" if step else "|"))
    return "\n".join(lines)


def run(args) -> dict:
    from lightning_bodyschema.schemas.loading import load_datamodule

    schema, names, muscles = load(args)
    model, path, norm = schema.robot_model, schema.length_net, schema.normalizer
    q_train = np.asarray(load_datamodule(args.ckpt, cache_dir=args.cache_dir).splits["train"][0], np.float64)
    q_eval = model.sample_q(np.random.default_rng(args.seed), args.postures)
    q_flag = model.sample_q(np.random.default_rng(args.seed + 1), args.postures)
    encode = lambda q: norm.encode_q(torch.as_tensor(q, dtype=torch.float64))  # noqa: E731
    rad_per_unit = 0.5 * (norm.q_hi - norm.q_lo).to(torch.float64)  # dq/dx of the normalized postures
    marks = sorted({min(-(-(int(n) or len(q_train)) // CHUNK) * CHUNK, len(q_train)) for n in args.samples.split(",")})
    data = {"train": (encode(q_train), wrap_states(model, q_train)[:, muscles]),
            "eval": (encode(q_eval), wrap_states(model, q_eval)[:, muscles]),
            "flag": (encode(q_flag), None)}
    margins_train = 1e3 * wrap_margins(model, q_train)[:, muscles]  # [mm]: (T, K, J, 5)
    margin_eval_mm = 1e3 * wrap_margins(model, q_eval)[:, muscles]
    l_train_mm = torch.as_tensor(1e3 * model.kinematics(q_train)[0][:, muscles])
    l_eval, g_eval, _ = model.kinematics(q_eval)
    crossed = np.abs(g_eval).max(0) > 1e-12
    preds, counts, states = {}, [], []
    for col, m in enumerate(muscles):
        exponents = path.exponents[path.term_mask[m].cpu()].cpu()
        fit, mark_coefs, n_state = fit_muscle(data["train"][0], l_train_mm[:, col], data["train"][1][:, col],
                                              exponents, crossed[m], args.gate_degree, marks)
        groups, cut, pieces, cap = cell_layout(schema, crossed, m, args.cell_degree)
        for mode, value in predict_muscle(fit, mark_coefs, data, col, l_train_mm[:, col], groups, cut,
                                          pieces, cap, rad_per_unit, crossed[m],
                                          args.cell_gate_degree,
                                          (margins_train[:, col], margin_joints(model, q_train, m), args.margin_degree,
                                           margin_eval_mm[:, col])).items():
            preds.setdefault(mode, []).append(value)
        counts.append(n_state), states.append(fit.states)
    truth = (1e3 * l_eval, 1e3 * g_eval, crossed)
    result = score(args, schema, names, muscles, preds, truth, counts, states, marks)
    near = near_switch(model, q_eval, data["eval"][1], muscles, crossed)
    wrong = np.stack([~p[0].numpy() for p in preds["cell_gate_right"]], 1)
    result["cell_gate_wrong_near_switch"] = {"radii_rad": list(MISGATE_RADII), "postures": wrong.sum(0).tolist(),
                                             "share_within": [float(np.mean(near_switch(model, q_eval, data["eval"][1],
                                                                                        muscles, crossed, r)[wrong]))
                                                              if wrong.any() else None for r in MISGATE_RADII]}
    wrong_m = np.stack([~p[0].numpy() for p in preds["margin_gate_right"]], 1)
    result["margin_gate_wrong_near_switch"] = {
        "radii_rad": list(MARGIN_RADII), "postures": wrong_m.sum(0).tolist(),
        "share_within": [float(np.mean(near_switch(model, q_eval, data["eval"][1], muscles, crossed, r)[wrong_m]))
                         if wrong_m.any() else None for r in MARGIN_RADII]}
    result["near_switch_share"] = {names[m]: float(near[:, i].mean()) for i, m in enumerate(muscles)}
    result["ii-c_near_far_p99_mm"] = {names[m]: [float(np.percentile(e[near[:, i]], 99)) if near[:, i].any() else None,
                                                 float(np.percentile(e[~near[:, i]], 99))]
                                      for i, (m, e) in enumerate(zip(muscles, result.pop("_ii-c_errors").T))}
    return result


def cell_layout(schema, crossed: np.ndarray, m: int, degree: int = 0):
    """Muscle ``m``'s cells as the checkpoint has them: its joint groups ``(N,)``, cut joints ``(N,)``, pieces per
    cut joint and highest cell degree (``degree`` where > 0, else the checkpoint's; ``CELL_DEGREE`` where the
    checkpoint has no cells on it)."""
    path, blocks = schema.length_net, schema.hparams.get("path_blocks")
    groups = np.where(crossed[m], 0, -1) if blocks is None else np.asarray(blocks[m])
    cut = np.asarray(path.cell_cut[m]) if path.pieces > 1 else crossed[m]
    cap = int(path.cell_degrees[m]) if path.pieces > 1 and int(path.cell_degrees[m]) else CELL_DEGREE
    return groups, cut, max(path.pieces, 2), degree or cap


def near_switch(model, q: np.ndarray, labels: np.ndarray, muscles, crossed, reach: float = None) -> np.ndarray:
    """``(B, K)`` bool: a muscle's state differs ``reach`` [rad] (``NEAR_RAD``) away along some joint it crosses
    (either way)."""
    near, reach = np.zeros(labels.shape, bool), NEAR_RAD if reach is None else reach
    for joint in range(q.shape[1]):
        for step in (-reach, reach):
            moved = q.copy()
            moved[:, joint] = np.clip(moved[:, joint] + step, *model.q_range[joint])
            near |= (wrap_states(model, moved)[:, muscles] != labels) & crossed[muscles, joint][None, :]
    return near


def predict_muscle(fit, mark_coefs, data, col, y_train, groups, cut, pieces, cap, rad_per_unit, crossed,
                   gate_degree, margin_data) -> dict:
    """One muscle's predictions at the eval postures, ``{fit name: (l_mm (B,), G (B, N) [mm/rad], distance (B,))}``:
    the whole-box fits (i)-(iii), (ii) per train-sample count, and the same in the checkpoint's cells."""
    (x, labels), (x_train, labels_train) = data["eval"], data["train"]
    far = torch.full((len(x),), float("inf"), dtype=torch.float64)
    out = {}
    for mode, name in (("all", "i"), ("state", "ii"), ("gate", "iii")):
        pick, distance = fit.pick(mode, x, labels[:, col], rad_per_unit)
        out[name] = (*fit.predict(x, pick, rad_per_unit), distance)
    for n, coef_state in mark_coefs.items():
        out[f"ii@{n}"] = (*fit.predict(x, fit.pick("state", x, labels[:, col], rad_per_unit, coef_state)[0],
                                       rad_per_unit), far)
    cell_train, z_train, dz_dx = cell_keys(x_train, cut, pieces)
    cell, z, _ = cell_keys(x, cut, pieces)
    dz_dq = dz_dx / rad_per_unit
    cells = CellFit(z_train, y_train, cell_train, groups, cap).predict(z, cell, dz_dq, out["i"][:2])
    out["c"] = (*cells, far)
    per_state = CellFit(z_train, y_train, cell_train * STATE_KEYS + labels_train[:, col], groups, cap)
    out["ii-c"] = (*per_state.predict(z, cell * STATE_KEYS + labels[:, col], dz_dq, cells), far)
    index, distance = gate(x, fit.gate_weights, fit.gate_terms, rad_per_unit)
    gated = np.asarray(fit.states)[index.numpy()]
    out["iii-c"] = (*per_state.predict(z, cell * STATE_KEYS + gated, dz_dq, cells), distance)
    cell_gate = CellGate(z_train, cell_train, labels_train[:, col], crossed, gate_degree)
    gated_c, distance_c = cell_gate(z, cell, dz_dq)
    out["iii-cg"] = (*per_state.predict(z, cell * STATE_KEYS + gated_c, dz_dq, cells, within_box=True),
                     torch.as_tensor(distance_c))
    out["gate_right"] = (torch.as_tensor(gated == labels[:, col]), None, far)
    out["cell_gate_right"] = (torch.as_tensor(gated_c == labels[:, col]), None, far)
    x_flag = data["flag"][0]
    flag_cell, z_flag, _ = cell_keys(x_flag, cut, pieces)
    margins_train, moving, degree, margins_true = margin_data
    margin_fit = MarginFit(z_train, cell_train, margins_train, moving, degree)
    code_m, distance_m, residual = margin_fit(z, cell, dz_dq, margins_true)
    out["iv-cm"] = (*per_state.predict(z, cell * STATE_KEYS + code_m, dz_dq, cells),  # as (ii-c): a rule, not a guess
                    torch.as_tensor(distance_m))
    out["margin_gate_right"] = (torch.as_tensor(code_m == labels[:, col]), residual, far)
    out["reach"] = (gate(x_flag, fit.gate_weights, fit.gate_terms, rad_per_unit)[1],
                    torch.as_tensor(cell_gate(z_flag, flag_cell, dz_dq)[1]),
                    torch.as_tensor(margin_fit(z_flag, flag_cell, dz_dq)[1]))
    return out


def margin_joints(model, q: np.ndarray, muscle: int) -> np.ndarray:
    """``(J, N)`` bool: the joints each of the muscle's wrapping geoms' margins move with (``MARGIN_STEP`` along the
    joint at the first ``MARGIN_PROBES`` postures ``q``): the sites and the geom ride on these joints only."""
    probe = q[:MARGIN_PROBES]
    base = wrap_margins(model, probe)[:, muscle]
    moved = []
    for joint in range(q.shape[1]):
        step = probe.copy()
        step[:, joint] += MARGIN_STEP
        change = np.abs(np.nan_to_num(wrap_margins(model, step)[:, muscle] - base, posinf=0.0, neginf=0.0))
        moved.append(change.max((0, 2)) > 1e-12)  # [m]; a still margin changes by rounding only
    return np.stack(moved, 1)


class MarginFit:
    """(iv-cm): each wrapping geom's margins (``sim.wrapping.MARGINS``, [mm]) regressed per cell by least squares
    (``CellFit``: a polynomial in the cell's coordinates over the joints the margin moves with, total degree up to
    ``degree``); the state is MuJoCo's rule applied to the regressed margins (``states_from_margins``), and the
    distance to its switch ``min |m| / |grad m|`` [rad] over the margins whose sign alone would change the state."""

    def __init__(self, z, cells, margins_mm, moving, degree):
        self.shape, self.fits = margins_mm.shape[1:], {}
        for j, k in itertools.product(range(self.shape[0]), range(self.shape[1])):
            y = margins_mm[:, j, k]
            if np.isfinite(y).all() and moving[j].any():
                self.fits[j, k] = CellFit(z, torch.as_tensor(y), cells, np.where(moving[j], 0, -1), degree)
            elif np.isfinite(y).all():  # a geom riding with both its sites: its margins are constants
                self.fits[j, k] = float(np.mean(y))

    def __call__(self, z, cells, dz_dq, truth_mm=None):
        """The state ``(B,)``, the distance ``(B,)`` [rad] and, given the true margins ``(B, J, 9)`` [mm], the p99 of
        the regression's largest residual over the margins [mm] (else None)."""
        value = np.full((len(z), *self.shape), np.nan)
        slope = np.zeros((len(z), *self.shape, z.shape[1]))
        for (j, k), fit in self.fits.items():
            if isinstance(fit, float):
                value[:, j, k] = fit
                continue
            fallback = (torch.zeros(len(z), dtype=torch.float64), torch.zeros(len(z), z.shape[1], dtype=torch.float64))
            v, g = fit.predict(z, cells, dz_dq, fallback)
            value[:, j, k], slope[:, j, k] = v.numpy(), g.numpy()
        state = states_from_margins(value[:, None])[:, 0]
        reach = np.full(len(z), np.inf)
        for j, k in self.fits:
            flipped = value.copy()
            flipped[:, j, k] = -flipped[:, j, k]
            changes = states_from_margins(flipped[:, None])[:, 0] != state
            distance = np.abs(value[:, j, k]) / np.maximum(np.linalg.norm(slope[:, j, k], axis=1), 1e-300)
            reach = np.where(changes, np.minimum(reach, distance), reach)
        residual = None
        if truth_mm is not None:
            error = np.nan_to_num(np.abs(value - truth_mm), nan=0.0, posinf=0.0)
            residual = float(np.percentile(error.max((1, 2)), 99))
        return state, reach, residual

TRUTH_CHUNK = 10000  # postures whose MuJoCo truth is computed at once (the Jacobian is (B, tendons, dofs))


def truth_at(model, q: np.ndarray, muscles, margins: bool = True):
    """MuJoCo at postures ``q (B, N)``, in chunks: lengths [mm] ``(B, K)``, wrapping states ``(B, K)`` and (with
    ``margins``) ``wrap_margins`` [mm] ``(B, K, J, 9)``, else None."""
    width = max(len(wrap_geoms(model)[m]) for m in muscles)  # the margins' geoms: these muscles' only
    parts = [(1e3 * model.kinematics(q[s:s + TRUTH_CHUNK])[0][:, muscles],
              wrap_states(model, q[s:s + TRUTH_CHUNK])[:, muscles],
              1e3 * wrap_margins(model, q[s:s + TRUTH_CHUNK])[:, muscles, :width] if margins else None)
             for s in range(0, len(q), TRUTH_CHUNK)]
    return tuple(None if p[0] is None else np.concatenate(p) for p in zip(*parts))


class StateCellFit:
    """One muscle's (ii-c) (a polynomial per cell and wrapping state, the cell's all-state polynomial where a
    state has none) and (iv-cm) (the state from its margins regressed per cell) on one train set."""

    def __init__(self, x, l_mm, labels, margins_mm, layout, moving, margin_degree):
        groups, self.cut, self.pieces, cap = layout
        cell, z, _ = cell_keys(x, self.cut, self.pieces)
        y = torch.as_tensor(l_mm)
        self.cells = CellFit(z, y, cell, groups, cap)
        self.per_state = CellFit(z, y, cell * STATE_KEYS + labels, groups, cap)
        self.margins = MarginFit(z, cell, margins_mm, moving, margin_degree)

    def __call__(self, x, labels, fallback, rad_per_unit, margins: bool = True) -> dict:
        """``{"ii-c": (l_mm, G), "iv-cm": (l_mm, G), "right": (B,) bool}`` at ``x``; ``fallback`` (l, G) where a
        cell has no fit; without ``margins`` (ii-c) only."""
        cell, z, dz_dx = cell_keys(x, self.cut, self.pieces)
        dz_dq = dz_dx / rad_per_unit
        mixed = self.cells.predict(z, cell, dz_dq, fallback)
        out = {"ii-c": self.per_state.predict(z, cell * STATE_KEYS + labels, dz_dq, mixed)}
        if margins:
            code = self.margins(z, cell, dz_dq)[0]
            out["iv-cm"] = self.per_state.predict(z, cell * STATE_KEYS + code, dz_dq, mixed)
            out["right"] = code == labels
        return out


class Adaptive:
    """``--adaptive-rounds``: per budget ``B`` (train samples), (ii-c) and (iv-cm) fitted on ``B`` uniform postures
    and, adaptively, on ``B / 2`` of them, then ``--adaptive-rounds`` rounds that each draw ``--pool`` times as many
    fresh uniform postures as they add, predict MuJoCo's length there with the current per-state fit (the true
    state: the data generator knows it), and add the ``B / (2 rounds)`` postures whose worst muscle misses most;
    every fit scored at the held-out postures (``--seed``)."""

    def __init__(self, args, schema, muscles):
        self.args, self.schema, self.muscles, model = args, schema, muscles, schema.robot_model
        norm = schema.normalizer
        self.encode = lambda q: norm.encode_q(torch.as_tensor(q, dtype=torch.float64))  # noqa: E731
        self.rad_per_unit = 0.5 * (norm.q_hi - norm.q_lo).to(torch.float64)
        self.q_eval = model.sample_q(np.random.default_rng(args.seed), args.postures)
        l_eval, g_eval, _ = model.kinematics(self.q_eval)
        self.crossed = np.abs(g_eval).max(0) > 1e-12
        self.truth = (1e3 * l_eval[:, muscles], 1e3 * g_eval[:, muscles],
                      wrap_states(model, self.q_eval)[:, muscles])
        self.q_stream = model.sample_q(np.random.default_rng([args.seed, 2]), max(self.budgets))
        self.stream = truth_at(model, self.q_stream, muscles)
        self.layouts = [cell_layout(schema, self.crossed, m, args.cell_degree) for m in muscles]
        self.moving = [margin_joints(model, self.q_stream, m) for m in muscles]

    @property
    def budgets(self) -> list:
        return [int(b) for b in self.args.budgets.split(",")]

    def checkpoint(self, q: np.ndarray):
        """The checkpoint's (l [mm], G [mm/rad]) per muscle at ``q``: where a cell has no fit."""
        l_ck, g_ck, _ = self.schema.body_si(torch.as_tensor(q))
        return [(torch.as_tensor(1e3 * l_ck[:, m]), torch.as_tensor(1e3 * g_ck[:, m])) for m in self.muscles]

    def fit(self, q, truth) -> list:
        l_mm, labels, margins_mm = truth
        x = self.encode(q)
        return [StateCellFit(x, l_mm[:, k], labels[:, k], margins_mm[:, k], self.layouts[k], self.moving[k],
                             self.args.margin_degree) for k in range(len(self.muscles))]

    def score(self, fits, samples: int) -> dict:
        """The worst of these muscles per held-out posture for (ii-c) and (iv-cm), and each muscle's p99 [mm]."""
        l_mm, g_mm, labels = self.truth
        x, out = self.encode(self.q_eval), {"samples": samples}
        preds = [f(x, labels[:, k], fb, self.rad_per_unit) for k, (f, fb) in
                 enumerate(zip(fits, self.checkpoint(self.q_eval)))]
        crossed = self.crossed[self.muscles]
        for key in ("ii-c", "iv-cm"):
            lengths = np.stack([np.abs(p[key][0].numpy() - l_mm[:, k]) for k, p in enumerate(preds)], 1)
            arms = np.stack([np.where(crossed[k], np.abs(p[key][1].numpy() - g_mm[:, k]), 0).max(1)
                             for k, p in enumerate(preds)], 1)
            out[key] = {"length_mm": percentiles(lengths.max(1)), "arm_mm_per_rad": percentiles(arms.max(1)),
                        "muscle_p99_mm": [float(np.percentile(e, 99)) for e in lengths.T]}
        out["state_right"] = [float(p["right"].mean()) for p in preds]
        return out

    def pick(self, fits, q_pool, count: int):
        """The ``count`` pool postures whose worst muscle the (ii-c) fits miss most, and that worst muscle."""
        l_mm, labels, _ = truth_at(self.schema.robot_model, q_pool, self.muscles, margins=False)
        x = self.encode(q_pool)
        miss = np.stack([np.abs(f(x, labels[:, k], fb, self.rad_per_unit, margins=False)["ii-c"][0].numpy()
                                - l_mm[:, k]) for k, (f, fb) in enumerate(zip(fits, self.checkpoint(q_pool)))], 1)
        top = np.argsort(-miss.max(1))[:count]
        return top, miss[top].argmax(1), float(miss.max(1)[top[-1]])

    def run(self, names) -> dict:
        out, uniform, rounds = {"muscles": names, "budgets": {}}, {}, self.args.adaptive_rounds

        def fitted(n: int):  # uniform fits on the stream's first n postures, shared by the budgets
            if n not in uniform:
                fits = self.fit(self.q_stream[:n], tuple(t[:n] for t in self.stream))
                uniform[n] = (fits, self.score(fits, n))
            return uniform[n]

        for i, budget in enumerate(self.budgets):
            half = budget // 2
            (fits, row), add = fitted(half), (budget - half) // rounds
            rows, q, truth = [dict(row)], self.q_stream[:half], tuple(t[:half] for t in self.stream)
            for r in range(rounds):
                if r:
                    fits = self.fit(q, truth)
                    rows.append(self.score(fits, len(q)))
                q_pool = self.schema.robot_model.sample_q(np.random.default_rng([self.args.seed, 3, i, r]),
                                                          self.args.pool * add)
                top, worst, threshold = self.pick(fits, q_pool, add)
                new = truth_at(self.schema.robot_model, q_pool[top], self.muscles)
                q, truth = np.vstack([q, q_pool[top]]), tuple(np.concatenate(p) for p in zip(truth, new))
                rows[-1]["next"] = {"added": int(add), "pool": len(q_pool), "threshold_mm": threshold,
                                    "worst_muscle_share": np.bincount(worst, minlength=len(self.muscles)).tolist()}
            rows.append(self.score(self.fit(q, truth), len(q)))
            out["budgets"][budget] = {"uniform": fitted(budget)[1], "adaptive": rows}
        return out


def smoothstep(t: torch.Tensor):
    """``3 t^2 - 2 t^3`` and its slope at ``t`` clamped to [0, 1]: C1, 0 and 1 at the ends with zero slope."""
    t = t.clamp(0.0, 1.0)
    return t * t * (3 - 2 * t), 6 * t * (1 - t)


class Blend:
    """``--blend-margin W``: (a) one polynomial per cell and wrapping state (the true state) on its cell's samples;
    (b) each fitted on its cell widened by ``W`` of the cell's width beyond every cut (a neighbour's samples, in this
    cell's coordinates rescaled onto [-1, 1]; corners included), used in its own cell; (c) the same pieces blended:
    along each cut joint a smoothstep over [cut - w, cut + w] mixes the two neighbours' pieces (tensor product over
    the cut joints: up to ``2^k`` pieces, weights summing to 1); its moment arms include the weights' slope times
    the pieces' differences. A neighbour (cell, state) without a fit counts as the posture's own piece."""

    def __init__(self, layout, width: float):
        self.groups, self.cut, self.pieces, self.cap = layout
        self.joints, self.w = np.flatnonzero(self.cut), 2.0 * width  # the margin in local units (a cell is 2 wide)

    def shifted(self, z: torch.Tensor, cell: np.ndarray, move: tuple):
        """Each posture seen from the neighbour across its nearest cut along the joints where ``move`` is 1:
        that cell ``(B,)`` (-1: no neighbour there, or farther than ``w`` from the cut) and its coordinates."""
        z2, cell2 = z.clone(), cell.copy()
        for i, (j, m) in enumerate(zip(self.joints, move)):
            if not m:
                continue
            side = np.where(z[:, j].numpy() > 0, 1, -1)
            piece = (cell // self.pieces ** i) % self.pieces + side
            ok = (piece >= 0) & (piece < self.pieces) & (1 - np.abs(z[:, j].numpy()) <= self.w)
            cell2 = np.where(ok & (cell2 >= 0), cell2 + side * self.pieces ** i, -1)
            z2[:, j] = z[:, j] - 2.0 * torch.as_tensor(side, dtype=z.dtype)
        return cell2, z2

    def moves(self):
        return list(itertools.product((0, 1), repeat=len(self.joints)))

    def widened(self, z: torch.Tensor) -> torch.Tensor:
        """A widened cell's coordinates: [-1 - w, 1 + w] mapped onto [-1, 1] along the cut joints (Legendre terms
        of degree 11 grow ~1e3-fold at 1.5: the normal equations would lose the cell's interior)."""
        out = z.clone()
        out[:, self.joints] = z[:, self.joints] / (1 + self.w)
        return out

    def fit(self, x, y, labels):
        """(a) and (b) on train postures ``x`` (normalized), lengths ``y`` [mm] and true states ``labels``."""
        cell, z, _ = cell_keys(x, self.cut, self.pieces)
        plain = CellFit(z, y, cell * STATE_KEYS + labels, self.groups, self.cap)
        parts = [self.shifted(z, cell, move) for move in self.moves()]
        keep = [c >= 0 for c, _ in parts]
        keys = np.concatenate([(c * STATE_KEYS + labels)[k] for (c, _), k in zip(parts, keep)])
        wide = CellFit(self.widened(torch.cat([zz[k] for (_, zz), k in zip(parts, keep)])),
                       torch.cat([y[k] for k in keep]), keys, self.groups, self.cap)
        return plain, wide

    def predict(self, fits, x, labels, fallback, rad_per_unit):
        """``{"a", "b", "c": (l_mm (B,), G (B, N) [mm/rad])}`` at ``x`` with the true states ``labels``."""
        (plain, wide), (cell, z, dz_dx) = fits, cell_keys(x, self.cut, self.pieces)
        dz_dq = dz_dx / rad_per_unit
        dw_dq = self.widened(dz_dq[None])[0]
        out = {"a": plain.predict(z, cell * STATE_KEYS + labels, dz_dq, fallback),
               "b": wide.predict(self.widened(z), cell * STATE_KEYS + labels, dw_dq, fallback)}
        a, slope = [], []  # the neighbour's weight along each cut joint and its slope d a / d q_j
        for i, j in enumerate(self.joints):
            piece = (cell // self.pieces ** i) % self.pieces
            side = np.where(z[:, j].numpy() > 0, 1, -1)
            inside = torch.as_tensor((piece + side >= 0) & (piece + side < self.pieces), dtype=z.dtype)
            s, ds = smoothstep((self.w - (1 - z[:, j].abs())) / (2 * self.w))
            a.append(s * inside)  # 0.5 at the cut: the two pieces weigh the same there
            slope.append(ds * inside * torch.as_tensor(side, dtype=z.dtype) / (2 * self.w) * dz_dq[j])
        l_mix, g_mix = torch.zeros_like(out["b"][0]), torch.zeros_like(out["b"][1])
        for move in self.moves():
            cell2, z2 = self.shifted(z, cell, move)
            keys = np.where(cell2 >= 0, cell2 * STATE_KEYS + labels, -1)  # -1: no neighbour, the own piece
            l_p, g_p = wide.predict(self.widened(z2), keys, dw_dq, out["b"])
            factors = [a[i] if m else 1 - a[i] for i, m in enumerate(move)]
            weight = torch.stack(factors).prod(0)
            l_mix += weight * l_p
            g_mix += weight[:, None] * g_p
            for i, (j, m) in enumerate(zip(self.joints, move)):  # the weight's slope along joint j
                others = torch.stack([f for k, f in enumerate(factors) if k != i] or [torch.ones_like(weight)]).prod(0)
                g_mix[:, j] += (slope[i] if m else -slope[i]) * others * l_p
        out["c"] = (l_mix, g_mix)
        return out

    def margin_state(self, x, margins_mm, moving, degree, x_eval, rad_per_unit) -> np.ndarray:
        """The state ``(B,)`` at ``x_eval`` from margins regressed per (plain) cell on train postures ``x``
        (``MarginFit``, as (iv-cm))."""
        cell, z, dz_dx = cell_keys(x, self.cut, self.pieces)
        cell_eval, z_eval, _ = cell_keys(x_eval, self.cut, self.pieces)
        return MarginFit(z, cell, margins_mm, moving, degree)(z_eval, cell_eval, dz_dx / rad_per_unit)[0]

    def cut_distance_rad(self, x, rad_per_unit) -> np.ndarray:
        """``(B,)`` [rad] to the nearest inner cut along a cut joint (a box edge is not a cut)."""
        cell, z, _ = cell_keys(x, self.cut, self.pieces)
        best = np.full(len(x), np.inf)
        for i, j in enumerate(self.joints):
            piece = (cell // self.pieces ** i) % self.pieces
            side = np.where(z[:, j].numpy() > 0, 1, -1)
            inner = (piece + side >= 0) & (piece + side < self.pieces)
            d = (1 - np.abs(z[:, j].numpy())) * float(rad_per_unit[j]) / self.pieces
            best = np.where(inner, np.minimum(best, d), best)
        return best


def run_blend(args) -> dict:
    """The three fits of ``Blend`` per budget of ``--budgets`` uniform train postures (seed ``[--seed, 2]``, as
    ``Adaptive``), scored at the ``--postures`` held-out ones (``--seed``): the worst of ``--muscles`` per posture."""
    schema, names, muscles = load(args)
    model, norm = schema.robot_model, schema.normalizer
    encode = lambda q: norm.encode_q(torch.as_tensor(q, dtype=torch.float64))  # noqa: E731
    rad_per_unit = 0.5 * (norm.q_hi - norm.q_lo).to(torch.float64)
    q_eval = model.sample_q(np.random.default_rng(args.seed), args.postures)
    l_eval, g_eval, _ = model.kinematics(q_eval)
    crossed = np.abs(g_eval).max(0) > 1e-12
    labels_eval, x_eval = wrap_states(model, q_eval)[:, muscles], encode(q_eval)
    budgets = [int(b) for b in args.budgets.split(",")]
    q_train = model.sample_q(np.random.default_rng([args.seed, 2]), max(budgets))
    l_train, labels_train, margins_train = truth_at(model, q_train, muscles)
    moving = [margin_joints(model, q_train, m) for m in muscles]
    l_ck, g_ck, _ = schema.body_si(torch.as_tensor(q_eval))
    blends = [Blend(cell_layout(schema, crossed, m, args.cell_degree), args.blend_margin) for m in muscles]
    near = np.min([b.cut_distance_rad(x_eval, rad_per_unit) for b in blends], 0)
    out = {"muscles": [names[m] for m in muscles], "blend_margin": args.blend_margin, "budgets": {}}
    for n in budgets:
        x = encode(q_train[:n])
        preds = []
        for k, (b, m) in enumerate(zip(blends, muscles)):
            fits, fallback = b.fit(x, torch.as_tensor(l_train[:n, k]), labels_train[:n, k]), (
                torch.as_tensor(1e3 * l_ck[:, m]), torch.as_tensor(1e3 * g_ck[:, m]))
            code = b.margin_state(x, margins_train[:n, k], moving[k], args.margin_degree, x_eval, rad_per_unit)
            preds.append(b.predict(fits, x_eval, labels_eval[:, k], fallback, rad_per_unit))
            preds[-1]["c-m"] = b.predict(fits, x_eval, code, fallback, rad_per_unit)["c"]
        rows = {}
        for key in ("a", "b", "c", "c-m"):
            lengths = np.stack([np.abs(p[key][0].numpy() - 1e3 * l_eval[:, m]) for p, m in zip(preds, muscles)], 1)
            arms = np.stack([np.where(crossed[m], np.abs(p[key][1].numpy() - 1e3 * g_eval[:, m]), 0).max(1)
                             for p, m in zip(preds, muscles)], 1)
            worst = lengths.max(1)
            rows[key] = {"length_mm": percentiles(worst), "arm_mm_per_rad": percentiles(arms.max(1)),
                         "near_far_p99_mm": [float(np.percentile(worst[near <= NEAR_RAD], 99)),
                                             float(np.percentile(worst[near > 0.1], 99))],
                         "muscle_p99_mm": [float(np.percentile(e, 99)) for e in lengths.T]}
        out["budgets"][n] = rows
    out["near_far_postures"] = [int((near <= NEAR_RAD).sum()), int((near > 0.1).sum())]
    return out


def blend_table(result: dict) -> str:
    """The blend experiment as markdown: one row per budget and fit."""
    fmt = lambda values: " / ".join(f"{v:.3g}" for v in values)  # noqa: E731
    labels = {"a": "(a) per (cell, state)", "b": "(b) widened, own cell", "c": "(c) widened + blend",
              "c-m": "(c) with the state from regressed margins"}
    lines = [f"| train samples | fit (margin {result['blend_margin']:g}) | worst length p50 / p90 / p99 / max [mm] | "
             f"worst moment arm p99 [mm/rad] | worst p99 within {1e3 * NEAR_RAD:g} mrad of a cut / beyond 0.1 rad "
             f"({' / '.join(map(str, result['near_far_postures']))} postures) | per muscle p99 "
             f"({', '.join(result['muscles'])}) |", "|---|---|---|---|---|---|"]
    for n, rows in result["budgets"].items():
        lines += [f"| {n} | {labels[k]} | {fmt(r['length_mm'])} | {r['arm_mm_per_rad'][2]:.3g} | "
                  f"{fmt(r['near_far_p99_mm'])} | {fmt(r['muscle_p99_mm'])} |" for k, r in rows.items()]
    return "\n".join(lines)


ROWS = (("checkpoint", "the checkpoint's body"), ("i", "(i) one polynomial over every sample"),
        ("ii", "(ii) one polynomial per wrapping state, perfect gate"),
        ("iii", "(iii) the same, learned gate"), ("c", "(c) the checkpoint's cells, one polynomial per cell"),
        ("ii-c", "(ii-c) per wrapping state in each cell, perfect gate"), ("iii-c", "(iii-c) the same, learned gate"),
        ("iii-cg", "(iii-cg) the same, a logistic gate per cell"),
        ("iv-cm", "(iv-cm) the same, the state from margins regressed per cell"))


def score(args, schema, names, muscles, preds, truth, counts, states, marks) -> dict:
    """Every figure of the module docstring, as a dict."""
    l_mm, g_mm, crossed = truth
    q_eval = schema.robot_model.sample_q(np.random.default_rng(args.seed), args.postures)
    l_ck, g_ck, _ = schema.body_si(torch.as_tensor(q_eval))
    preds["checkpoint"] = [(torch.as_tensor(1e3 * l_ck[:, m]), torch.as_tensor(1e3 * g_ck[:, m]), None)
                           for m in muscles]
    others = [m for m in range(len(names)) if m not in muscles]
    rest_l = np.abs(1e3 * l_ck[:, others] - l_mm[:, others]).max(1, initial=0.0)
    rest_g = np.where(crossed[others][None], np.abs(1e3 * g_ck[:, others] - g_mm[:, others]), 0).max((1, 2),
                                                                                                     initial=0.0)

    def errors(key):
        lengths = np.stack([np.abs(p[0].numpy() - l_mm[:, m]) for p, m in zip(preds[key], muscles)], 1)
        arms = np.stack([np.where(crossed[m], np.abs(p[1].numpy() - g_mm[:, m]), 0).max(1)
                         for p, m in zip(preds[key], muscles)], 1)
        return lengths, arms

    def row(key, keep=None):
        lengths, arms = errors(key)
        keep = np.ones(len(lengths), bool) if keep is None else keep
        worst_l, worst_g = lengths.max(1)[keep], arms.max(1)[keep]
        all_l = np.maximum(worst_l, rest_l[keep])
        return {"these_length_mm": percentiles(worst_l), "these_arm_mm_per_rad": percentiles(worst_g),
                "all_length_mm": percentiles(all_l), "all_arm_mm_per_rad": percentiles(np.maximum(worst_g, rest_g[keep])),
                "bad_share_all": float(np.mean(all_l > 0.1)), "postures": int(keep.sum()),
                "per_muscle_length_p50_p99_mm": {names[m]: [float(np.percentile(lengths[keep, i], p)) for p in (50, 99)]
                                                 for i, m in enumerate(muscles)}}

    nearest = lambda i, key: np.min(np.stack([p[i].numpy() for p in preds[key]], 1), 1)  # noqa: E731
    out = {"muscles": [names[m] for m in muscles],
           "states": {names[m]: {"codes": s, "train_samples": c.tolist()} for m, s, c in zip(muscles, states, counts)},
           "gate_accuracy": {names[m]: float(p[0].float().mean()) for m, p in zip(muscles, preds["gate_right"])},
           "cell_gate_accuracy": {names[m]: float(p[0].float().mean())
                                  for m, p in zip(muscles, preds["cell_gate_right"])}, "rows": {}, "flags": {}}
    out["margin_gate_accuracy"] = {names[m]: float(p[0].float().mean())
                                   for m, p in zip(muscles, preds["margin_gate_right"])}
    out["margin_residual_p99_mm"] = {names[m]: p[1] for m, p in zip(muscles, preds["margin_gate_right"])}
    for key, reach in (("iii", 0), ("iii-c", 0), ("iii-cg", 1), ("iv-cm", 2)):
        radius = float(np.quantile(nearest(reach, "reach"), args.flag_share)) if args.flag_share > 0 else 0.0
        flagged = nearest(2, key) <= radius
        out["flags"][key] = {"radius_rad": radius, "flagged_share": float(flagged.mean())}
        out["rows"][f"{key}, unflagged"] = row(key, ~flagged)
    out["rows"] = {**{key: row(key) for key, _ in ROWS}, **out["rows"]}
    out["_ii-c_errors"] = errors("ii-c")[0]
    out["rows"].update({f"ii@{n}": row(f"ii@{n}") for n in marks})
    return out


if __name__ == "__main__":
    main()
