#!/usr/bin/env python
"""WEAK and BAND rows for RESULTS.md: the paper Diff schema on 40 + 40 new-fault cases (test split, seed 0).

    python tools/results_new_faults.py [CKPT]   # default: runs/paper/diff-10000 from tools/reproduce_paper.py

WEAK: one random muscle per case limited to half its healthy tension; BAND: one random motor confined to
[healthy - 4 mm, healthy - 2 mm]. Prints a Markdown table (phys reading, medians): the unadapted command, the
default adaptation, and a stronger guidance (``n_guide=4, lr=1.0``).
"""
import glob, sys
import numpy as np, torch
torch.set_num_threads(1)
from lightning_bodyschema.schemas import load_schema, load_datamodule
from lightning_bodyschema.evaluation import FaultCases, run_fault_benchmark
ck = sys.argv[1] if len(sys.argv) > 1 else sorted(glob.glob(
    "runs/paper/diff-10000/lightning_logs/version_*/checkpoints/epoch=9999-*.ckpt"))[-1]
s = load_schema(ck); dm = load_datamodule(ck)
q, x = dm.splits["val"]; q = q.numpy(); M = s.n_muscles
rng = np.random.default_rng(0)
pick = rng.choice(len(q), 80, replace=False)
q_ref = q[pick]
l_plain, f_plain = s.infer(q_ref)
mus = rng.integers(0, M, 80)
rows = np.arange(80)
f_max = np.full((80, M), np.nan); l_band = np.full((80, M, 2), np.nan)
f_max[rows[:40], mus[:40]] = 0.5 * f_plain[rows[:40], mus[:40]]          # WEAK: half the healthy tension
lo = l_plain[rows[40:], mus[40:]] - 0.004; hi = l_plain[rows[40:], mus[40:]] - 0.002   # BAND: 2-4 mm shorter
l_band[rows[40:], mus[40:], 0], l_band[rows[40:], mus[40:], 1] = lo, hi
none = np.zeros((80, M), bool)
cases = FaultCases(q_ref, none, none.copy(), np.full((80, M), np.nan), np.array(["WEAK"] * 40 + ["BAND"] * 40),
                   f_max=f_max, l_band=l_band)
# the default guidance, and a stronger one (4 guidance steps per timestep, lr 1.0) for hard one-sided bands
STRONG = {"n_guide": 4, "lr": 1.0}
runs = {label: run_fault_benchmark(s.robot_model, s.spring, cases, s.infer,
                                   lambda qq, ff, o=opts: s.adapt(qq, ff, check_physics=False, **o), settle_check=True)
        for label, opts in (("default", {}), ("strong", STRONG))}
print("| condition | subset | n | command | E_weak [N] | E_band [mm] | E_tau [N m] | E_q [rad] | E_q_phys [rad] |")
print("|---|---|---|---|---|---|---|---|---|")
for cond in ("WEAK", "BAND"):
    for subset in ("all", "feasible"):
        for kind, r, name in (("unadapted", runs["default"], "unadapted"), ("adapted", runs["default"], "adapted"),
                              ("adapted", runs["strong"], "adapted, n_guide=4, lr=1.0")):
            mask = np.ones(80, bool) if subset == "all" else r.feasible["phys"]
            sel = (cases.cond == cond) & mask
            m = r.metrics[kind]["phys"]
            med = lambda a, k=1: f"{k*np.nanmedian(a[sel]):.3g}" if np.isfinite(a[sel]).any() else "—"
            print(f"| {cond} | {subset} | {sel.sum()} | {name} | {med(m['E_weak'])} | {med(m['E_band'], 1e3)} | "
                  f"{med(m['E_tau'])} | {med(m['E_q'])} | {med(m['E_q_phys'])} "
                  f"({int(m['settle_unsettled'][sel].sum())} not at rest, left out) |")
