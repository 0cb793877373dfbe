#!/usr/bin/env python
"""How well per-muscle polynomials reach MuJoCo's myoArm muscle paths: least squares on exact lengths, held out.

    python tools/probe_paths.py [--degree 14] [--terms 500] [--train 40000] [--test 20000] [--seed 1]
                                [--branches 1|2] [--gate-degree 8] [--budget TERMS [--tolerance-mm MM]]
                                [--cells PIECES] [--muscles A,B,...] [--torque]

Draws ``--train + --test`` uniform postures of configs/myoarm.yaml's body (its locked joints), takes MuJoCo's exact
lengths and moment arms, fits ``networks.per_muscle.PerMusclePath`` (each muscle's polynomial over the joints it
crosses, the highest total degree ``<= --degree`` with at most ``--terms`` terms; ``--branches 2``: two polynomials
and a gate of degree ``--gate-degree`` where a path jumps; ``--budget``: the most terms over all muscles, what
``--terms`` leaves raising the lowest degrees first; with ``--tolerance-mm`` only in the muscles whose p99 after a
first fit at ``--terms`` exceeds it; ``--cells 2``: the muscles a smooth polynomial fits worst get a polynomial per
cell of their joints' box cut in two per joint, ``networks.cells``) on the first ``--train`` and prints,
on the rest: length error median and p99 [mm], moment-arm error on crossed pairs median and p99 [mm/rad], the
largest moment arm on uncrossed pairs, the muscles with p99 <= 0.1 mm, the worst muscles and those ``--muscles``
names (each with its degree, length median / p99 and moment-arm median / p99), the peak memory. ``--torque``: the
postures are those of an equilibrium dataset (configs/myoarm.yaml's spring; each posture's muscle tensions f), and a
degree-7 polynomial torque per joint is fitted (trimmed, as the fit does) on the first ``--train`` to ``-G^T f`` twice,
with the learned and with MuJoCo's moment arms, and scored against MuJoCo's tau_bias (median, % of the median
|tau_bias|), with the muscles whose moment-arm errors carry the most torque at the data's tensions. One torch thread.
"""
import argparse
import resource
import time

import numpy as np
import torch
import yaml

from lightning_bodyschema.apps.common import exits_cleanly
from lightning_bodyschema.networks.path_config import PathConfig
from lightning_bodyschema.networks.per_muscle import PerMusclePath, degrees_within_tolerance


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name, default in (("degree", 14), ("terms", 500), ("train", 40000), ("test", 20000), ("seed", 1),
                          ("branches", 1), ("gate-degree", 8), ("budget", None), ("cells", 1)):
        parser.add_argument(f"--{name}", type=int, default=default)
    parser.add_argument("--tolerance-mm", type=float, default=None)
    parser.add_argument("--torque", action="store_true")
    parser.add_argument("--muscles", default="BIClong,TRIlong,SUP,DELT1,SUPSP,LAT1,LAT2,LAT3,TMAJ",
                        help="muscles to print (name prefixes, comma separated)")
    args = parser.parse_args(argv)
    if args.tolerance_mm is not None and args.budget is None:
        parser.error("--tolerance-mm needs --budget")
    torch.set_num_threads(1)
    from lightning_bodyschema.data.dataset import load_or_build_dataset
    from lightning_bodyschema.sim import MusculoskeletalModel
    from lightning_bodyschema.sim.spring import spring_for_model

    locks = yaml.safe_load(open("configs/myoarm.yaml"))["data"]["locked_joints"]
    body = MusculoskeletalModel("myo:myoarm", locked_joints=locks)
    if args.torque:
        data = load_or_build_dataset(body, args.train + args.test, args.seed, spring_for_model(body), progress=False)
        q, f = data["q"], torch.as_tensor(data["f"])
    else:
        q = body.sample_q(np.random.default_rng(args.seed), args.train + args.test)
    l_m, G, tau_bias = (torch.as_tensor(a) for a in body.kinematics(q))
    lo, hi = (torch.as_tensor(a) for a in body.q_range.T)
    q_n, half = 2 * (torch.as_tensor(q) - lo) / (hi - lo) - 1, (hi - lo) / 2
    mean, std = l_m[:args.train].mean(0), l_m[:args.train].std(0)
    start = time.perf_counter()
    x_train, y_train = q_n[:args.train], (l_m[:args.train] - mean) / std
    degrees = None if args.tolerance_mm is None else degrees_within_tolerance(
        body.crossing(), x_train, y_train, 1e3 * std, args.degree, args.terms, args.budget, args.tolerance_mm)
    path = PerMusclePath(body.crossing(), PathConfig(degree=args.degree, n_hidden=0, max_terms=args.terms,
                                                     branches=args.branches, gate_degree=args.gate_degree,
                                                     term_budget=args.budget, degrees=degrees, cells=args.cells))
    path.fit_polynomial(x_train, y_train)
    seconds = time.perf_counter() - start
    y, dy = path.with_jacobian(q_n[args.train:])
    length_mm = 1e3 * ((y * std + mean) - l_m[args.train:]).abs()
    arm_mm = 1e3 * (dy * (std[:, None] / half[None, :]) - G[args.train:]).abs()
    crossed = path.crossing
    per_muscle_p99 = torch.quantile(length_mm, 0.99, dim=0)
    pct = lambda a, p: float(np.percentile(a.numpy(), p))  # noqa: E731
    print(f"{path.coef.shape[1]} terms, least squares {seconds:.0f} s; length median {pct(length_mm, 50):.4f} mm, "
          f"p99 {pct(length_mm, 99):.3f} mm; moment arms (crossed) median {pct(arm_mm[:, crossed], 50):.4f} mm/rad, "
          f"p99 {pct(arm_mm[:, crossed], 99):.3f}; uncrossed largest {float(dy[:, ~crossed].abs().max()):.3g}; "
          f"{int((per_muscle_p99 <= 0.1).sum())} of {len(per_muscle_p99)} muscles with p99 <= 0.1 mm")
    names = body.muscle_names
    if args.branches == 2:
        branched = torch.nonzero(path.branched).flatten().tolist()
        print("two branches:", ", ".join(body.muscle_names[i] for i in branched))
    if args.cells > 1:
        print("cells (degree, fitted/all):", ", ".join(
            f"{names[i]} ({int(path.cell_degrees[i])}, {int(done.sum())}/{args.cells ** int(crossed[i].sum())})"
            for i, done in zip(path.cell_muscles.tolist(), path.cell_fitted)))
    worst = torch.argsort(per_muscle_p99, descending=True)[:8].tolist()
    shown = worst + [i for i, n in enumerate(names) if i not in worst and any(
        n.startswith(p + "_") or n == p for p in args.muscles.split(","))]
    degrees = (path.exponents.sum(1)[None, :] * path.term_mask).amax(1)
    for i in shown:
        arms = arm_mm[:, i][:, crossed[i]]
        print(f"  {names[i]}: crosses {int(crossed[i].sum())}, degree {int(degrees[i])} "
              f"({int(path.term_mask[i].sum())} terms), length median {float(length_mm[:, i].median()):.4f} mm, "
              f"p99 {float(per_muscle_p99[i]):.3f} mm; "
              f"arms median {pct(arms, 50):.4f}, p99 {pct(arms, 99):.3f} mm/rad")
    if args.torque:
        dy_all = path.with_jacobian(q_n)[1]
        torque_report(q_n, f, dy_all * (std[:, None] / half[None, :]), G, tau_bias, args.train, names)
    print(f"peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20:.1f} GB")


def torque_report(q_n, f, G_hat, G, tau_bias, n_train, names, degree=7):
    """Prints the polynomial torque's error against ``tau_bias`` on the postures after ``n_train``, fitted to
    ``-G_hat^T f`` and to ``-G^T f``, and the muscles whose ``(G_hat - G)^T f`` is the largest (median [N m])."""
    ref = tau_bias[n_train:].norm(dim=1).median()
    for name, arms in (("learned", G_hat), ("MuJoCo's", G)):
        torque = PerMusclePath(np.ones((q_n.shape[1],) * 2, bool), degree=degree, n_hidden=0)
        torque.fit_trimmed(q_n[:n_train], -torch.einsum("bmn,bm->bn", arms[:n_train], f[:n_train]))  # as the fit
        error = (torque(q_n[n_train:]) - tau_bias[n_train:]).norm(dim=1)
        print(f"torque fitted to -G^T f with {name} moment arms: median {100 * float(error.median() / ref):.2f} %, "
              f"p99 {100 * float(torch.quantile(error, 0.99) / ref):.1f} % of the median |tau_bias| "
              f"({float(ref):.2f} N m)")
    share = torch.einsum("bmn,bm->bmn", (G_hat - G)[n_train:], f[n_train:]).norm(dim=2).median(0).values
    print("moment-arm errors times tension, median [N m]: " + ", ".join(
        f"{names[i]} {float(share[i]):.3f}" for i in torch.argsort(share, descending=True)[:8].tolist()))


if __name__ == "__main__":
    main()
