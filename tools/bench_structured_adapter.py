#!/usr/bin/env python
"""The structured schema's command QPs on the true myoArm body: the per-case loop against the batched solve.

    python tools/bench_structured_adapter.py [--batch 4000] [--old-cases 200] [--repeats 5] [--threads 1]
                                             [--baseline cd50b84] [--ckpt CKPT] [--singles 50]

Builds configs/myoarm.yaml's body (its locked joints), draws postures with ``model.sample_q`` and, per case, one cut
and one jammed muscle (the jam's motor length is the healthy command's at another posture, as the binding protocol
draws it); then times ``faults.qp.fault_command`` on the true l_geo, G and tau_bias: today's (``solvers.solve_box_qp``
on every case at once) and ``--baseline``'s (that git revision's faults/qp.py: one proxsuite QP per
case, least squares one per case), at batch 1 and ``--batch``, in ms per case (medians of ``--repeats``; the baseline
on the first ``--old-cases`` cases, its least squares costing up to a second per case). Prints the share of cases
whose bounds cross or whose torque the box cannot balance and what each kind costs, and how many cases the
equilibrium QP would still solve past ``QP_MAX_ITER`` (at 200 iterations). With ``--ckpt`` (a trained
StructuredSchema, loaded with weights_only) also the prepared adapter ``schema.adapter(faults, check_physics=False)``:
at batch 1 on the first case and on each of the first ``--singles`` cases through its own adapter, and at
``--batch``.
One torch thread; timings depend on the machine's load, which is printed with them.
"""
import argparse
import importlib.util
import os
import statistics
import subprocess
import time

import numpy as np
import torch

from lightning_bodyschema.apps.common import add_device_argument, exits_cleanly

ARGS = ("l_geo", "G", "tau", "f_ref", "f_lo", "f_hi", "l_lo", "l_hi")
SINGLE_CALLS_PER_REPEAT = 20  # batch-1 calls timed per repeat (a call is ~1.5 ms: a median of a handful is noise)


def myoarm_cases(n: int, seed: int = 0):
    """``n`` cases on configs/myoarm.yaml's body: the fault_command arguments, the Faults and the postures."""
    import yaml

    from lightning_bodyschema.faults import Faults
    from lightning_bodyschema.faults.bounds import FaultBounds
    from lightning_bodyschema.sim import MusculoskeletalModel, elongation_from_tension, solve_equilibrium_qp
    from lightning_bodyschema.sim.spring import spring_for_model

    data = yaml.safe_load(open("configs/myoarm.yaml"))["data"]
    model = MusculoskeletalModel(data["model"], locked_joints=data["locked_joints"])
    spring, m = spring_for_model(model), model.n_muscles
    rng = np.random.default_rng(seed)
    q, q_jam = model.sample_q(rng, n), model.sample_q(rng, n)
    f_max = np.broadcast_to(np.asarray(spring.f_max_n, float), (n, m))
    l_jam, G_jam, tau_jam = model.kinematics(q_jam)
    f_jam, _ = solve_equilibrium_qp(G_jam, tau_jam, 0.5 * f_max, f_hi_n=f_max)
    cut, fix = np.zeros((n, m), bool), np.zeros((n, m), bool)
    i = rng.integers(0, m, n)
    cut[np.arange(n), i], fix[np.arange(n), (i + rng.integers(1, m, n)) % m] = True, True
    faults = Faults(cut, fix, np.where(fix, l_jam - elongation_from_tension(f_jam, spring), np.nan))
    b = FaultBounds.from_faults(faults, spring.f_max_n, spring)
    l_geo, G, tau = model.kinematics(q)
    return dict(zip(ARGS, (l_geo, G, tau, 0.5 * f_max, b.f_lo_n, b.f_hi_n, b.l_lo_m, b.l_hi_m))), spring, faults, q


def baseline_qp(rev: str):
    """The faults/qp.py of git revision ``rev`` as a module of this package (its relative imports resolve here)."""
    source = subprocess.run(["git", "show", f"{rev}:lightning_bodyschema/faults/qp.py"], check=True,
                            capture_output=True, text=True).stdout
    spec = importlib.util.spec_from_loader("lightning_bodyschema.faults._baseline_qp", loader=None)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "lightning_bodyschema.faults"
    exec(compile(source, f"{rev}:faults/qp.py", "exec"), module.__dict__)
    if "solve_equilibrium_qp" in module.__dict__:  # its positional bounds (f_max, f_min), proxsuite per case
        from lightning_bodyschema.sim import solve_equilibrium_qp

        module.solve_equilibrium_qp = lambda G, tau, f_ref, f_max, f_min=0.0, **kw: solve_equilibrium_qp(  # noqa: E731
            G, tau, f_ref, f_hi_n=f_max, f_lo_n=f_min, **{"solver": "proxqp", **kw})
    return module


def ms_per_case(fn, cases, idx, repeats: int, single: bool) -> float:
    """Median over ``repeats`` of the time per case [ms] of ``fn`` on the cases ``idx`` (one call each if
    ``single``, else one call for all)."""
    pick = lambda j: {k: v[j] for k, v in cases.items()}  # noqa: E731
    groups = [pick(idx[k:k + 1]) for k in range(len(idx))] if single else [pick(idx)]
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for g in groups:
            fn(g)
        times.append((time.perf_counter() - start) / len(idx))
    return 1e3 * statistics.median(times)


def kinds(cases, spring):
    """(crossed, unbalanced) (B,) bool: bounds that cross; a box (uncrossed) whose torque misses tau_bias."""
    from lightning_bodyschema.faults.qp import fault_command, tension_box

    lo, hi = tension_box(cases["l_geo"], cases["f_lo"], cases["f_hi"], cases["l_lo"], cases["l_hi"], spring)
    crossed = (lo > hi).any(1)
    status = fault_command(*(cases[k] for k in ARGS), spring)[2]
    return crossed, (status != "ok") & ~crossed


def compare(cases, spring, args):
    from lightning_bodyschema.faults import qp

    old = baseline_qp(args.baseline)
    run = lambda module, **kw: lambda c: module.fault_command(*(c[k] for k in ARGS), spring, **kw)  # noqa: E731
    n = len(cases["q"])
    for label, idx, single in (("batch 1", np.arange(min(50, n)), True),
                               (f"batch {n}", np.arange(n), False)):
        sub = idx[:args.old_cases]
        t_old = ms_per_case(run(old), cases, sub, max(1, args.repeats // 2), single)
        t_new = ms_per_case(run(qp, num_threads=args.threads), cases, idx, args.repeats, single)
        print(f"fault_command {label}: baseline {args.baseline} {t_old:.3f} ms per case (on {len(sub)} cases), "
              f"batched ({args.threads} thread) {t_new:.3f} ms per case; ratio {t_old / t_new:.1f}x")
    crossed, unbalanced = kinds(cases, spring)
    long = qp.fault_command(*(cases[k] for k in ARGS), spring, max_iter=200)[2] != "ok"
    late = (~long & (crossed | unbalanced)).sum()
    print(f"  cases ok at max_iter 200 but not at QP_MAX_ITER={qp.QP_MAX_ITER}: {late}")
    holdable = ~crossed & ~unbalanced
    for label, mask in (("holdable", holdable), ("crossed bounds", crossed), ("box cannot balance", unbalanced)):
        idx = np.flatnonzero(mask)
        cost = ms_per_case(run(qp, num_threads=args.threads), cases, idx, args.repeats, False) if len(idx) else 0
        print(f"  {label}: {100 * mask.mean():.1f} % of cases, batched {cost:.3f} ms per case")


def adapter_latency(ckpt, faults, q, repeats, device="cpu", singles=50):
    """The prepared adapter's time per case: at batch 1 on one case (the median of ``SINGLE_CALLS_PER_REPEAT`` x
    ``repeats`` calls) and on each of the first ``singles`` cases through its own adapter (the median over ``repeats``
    rounds), and at batch ``len(q)``."""
    from lightning_bodyschema.schemas.loading import load_schema

    schema = load_schema(ckpt, map_location=device).eval()
    for n in (1, len(q)):
        adapter = schema.adapter(faults.take(np.arange(n)), check_physics=False)
        adapter(q[:n])
        times = []
        for _ in range(repeats * (SINGLE_CALLS_PER_REPEAT if n == 1 else 1)):
            start = time.perf_counter()
            adapter(q[:n])
            times.append((time.perf_counter() - start) / n)
        print(f"prepared adapter, batch {n}: {1e3 * statistics.median(times):.3f} ms per case")
    k = min(singles, len(q))
    if k:
        adapters = [schema.adapter(faults.take(np.arange(i, i + 1)), check_physics=False) for i in range(k)]
        call_each = lambda: [adapter(q[i:i + 1]) for i, adapter in enumerate(adapters)]  # noqa: E731
        call_each()
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            call_each()
            times.append((time.perf_counter() - start) / k)
        print(f"prepared adapter, batch 1 on each of {k} cases (holdable and not): "
              f"{1e3 * statistics.median(times):.3f} ms per call")


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4000)
    parser.add_argument("--old-cases", type=int, default=200, help="cases the baseline is timed on")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1, help="proxsuite's threads for the batched solve")
    parser.add_argument("--baseline", default="cd50b84", help="git revision of the per-case loop")
    parser.add_argument("--ckpt", help="a trained StructuredSchema checkpoint on myoArm")
    parser.add_argument("--singles", type=int, default=50, help="cases timed one by one through their own adapters")
    add_device_argument(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    cases, spring, faults, q = myoarm_cases(args.batch)
    cases["q"] = q
    compare(cases, spring, args)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if args.ckpt:
        adapter_latency(args.ckpt, faults, q, args.repeats, args.device, args.singles)
        print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
