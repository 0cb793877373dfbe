#!/usr/bin/env python
"""A structured checkpoint's ``body_si`` and prepared adapter, two source trees in lockstep on one machine.

    python tools/bench_lockstep.py --ckpt runs/myoarm/.../last.ckpt --base 6b06edf [--rounds 21]
                                   [--metrics body_si_1,adapter_1_case0,...]

Checks ``--base`` out into a temporary git worktree and starts two worker processes, one importing the package from
that worktree and one from this tree, on the same checkpoint and the same cases: configs/myoarm.yaml's body, 4000
seeded postures with one cut and one jammed muscle each (``tools/bench_structured_adapter.py``'s ``myoarm_cases``,
seed 0). Each round asks both workers for every metric, alternating which goes first; a worker answers the thread
CPU time of its calls, so the other processes on a shared machine cost it little. Prints per metric the medians over
``--rounds``, the ratio this tree / base, and the minima's ratio, then the load average. One torch thread per
worker. Metrics: ``body_si_1``, ``body_si_16``, ``body_si_400`` (one call at that batch), ``adapter_1_case0`` (the
prepared adapter ``schema.adapter(faults, check_physics=False)`` of case 0 on its posture), ``adapter_1_50cases``
(each of the first 50 cases through its own adapter, per call), ``adapter_4000_per_case`` (one call on all 4000,
per case); all in ms.
"""
import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
METRICS = ("body_si_1", "body_si_16", "body_si_400", "adapter_1_case0", "adapter_1_50cases", "adapter_4000_per_case")


def _cases(path: str) -> None:
    """Write the 4000 cases (postures and faults as plain arrays) to ``path`` (.npz) from this tree's tool."""
    spec = importlib.util.spec_from_file_location("bench_structured_adapter",
                                                  os.path.join(ROOT, "tools", "bench_structured_adapter.py"))
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    os.chdir(ROOT)  # the tool reads configs/myoarm.yaml
    _, _, faults, q = tool.myoarm_cases(4000, seed=0)
    np.savez(path, q=q, cut=faults.cut, fix=faults.fix, l_fixed_m=faults.l_fixed_m)


def worker(tree: str, ckpt: str, cases: str) -> None:
    """Answer one line per metric name read from stdin: its thread CPU time [ms] (per call, or per case)."""
    sys.path.insert(0, tree)
    import torch

    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    import lightning_bodyschema as package
    from lightning_bodyschema.faults import Faults
    from lightning_bodyschema.schemas.loading import load_schema

    assert os.path.realpath(package.__file__).startswith(os.path.realpath(tree)), package.__file__
    schema = load_schema(ckpt).eval()
    data = np.load(cases)
    q, faults = data["q"], Faults(data["cut"], data["fix"], data["l_fixed_m"])
    q_t = torch.as_tensor(q)
    one = schema.adapter(faults.take(np.arange(1)), check_physics=False)
    singles = [schema.adapter(faults.take(np.arange(i, i + 1)), check_physics=False) for i in range(50)]
    every = schema.adapter(faults, check_physics=False)
    table = {"body_si_1": (lambda: schema.body_si(q_t[:1]), 100, 1),
             "body_si_16": (lambda: schema.body_si(q_t[:16]), 20, 1),
             "body_si_400": (lambda: schema.body_si(q_t[:400]), 1, 1),
             "adapter_1_case0": (lambda: one(q[:1]), 30, 1),
             "adapter_1_50cases": (lambda: [a(q[i:i + 1]) for i, a in enumerate(singles)], 1, 50),
             "adapter_4000_per_case": (lambda: every(q), 1, len(q))}
    for fn, _, _ in table.values():
        fn()  # warm-up
    print("ready", flush=True)
    for line in sys.stdin:
        fn, calls, per = table[line.strip()]
        start = time.thread_time()
        for _ in range(calls):
            fn()
        print(1e3 * (time.thread_time() - start) / calls / per, flush=True)


def lockstep(trees: dict, ckpt: str, cases: str, metrics, rounds: int) -> dict:
    """``{side: {metric: [ms per round]}}`` from one worker per tree, alternating which answers first."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    workers = {side: subprocess.Popen([sys.executable, os.path.abspath(__file__), "--worker", tree, ckpt, cases],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
               for side, tree in trees.items()}
    for process in workers.values():
        if process.stdout.readline().strip() != "ready":
            raise SystemExit("a worker did not start (see its error above)")
    times = {side: {m: [] for m in metrics} for side in workers}
    order = list(workers)
    for r in range(rounds):
        for m in metrics:
            for side in (order if r % 2 == 0 else order[::-1]):
                workers[side].stdin.write(m + "\n")
                workers[side].stdin.flush()
                times[side][m].append(float(workers[side].stdout.readline()))
    for process in workers.values():
        process.stdin.close()
        process.wait()
    return times


def main(argv=None):
    if argv is None and sys.argv[1:2] == ["--worker"]:
        return worker(*sys.argv[2:5])  # imports the package from its tree: nothing of it may be imported before
    from lightning_bodyschema.apps.common import exits_cleanly

    return exits_cleanly(_compare)(argv)


def _compare(argv):
    from lightning_bodyschema.errors import BodySchemaInputError

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ckpt", required=True, help="a trained StructuredSchema checkpoint of configs/myoarm.yaml")
    parser.add_argument("--base", required=True, help="the git revision to compare against, e.g. 6b06edf")
    parser.add_argument("--rounds", type=int, default=21)
    parser.add_argument("--metrics", default=",".join(METRICS), help=f"comma-separated, of {', '.join(METRICS)}")
    args = parser.parse_args(argv)
    metrics = args.metrics.split(",")
    bad = [m for m in metrics if m not in METRICS]
    if bad or args.rounds < 1:
        raise BodySchemaInputError(f"--metrics {bad} / --rounds {args.rounds}: metrics from {list(METRICS)}, "
                                   "rounds >= 1")
    with tempfile.TemporaryDirectory() as tmp:
        base = os.path.join(tmp, "base")
        subprocess.run(["git", "-C", ROOT, "worktree", "add", "--detach", "-q", base, args.base], check=True)
        try:
            _cases(os.path.join(tmp, "cases.npz"))
            times = lockstep({"base": base, "new": ROOT}, os.path.abspath(args.ckpt), os.path.join(tmp, "cases.npz"),
                             metrics, args.rounds)
        finally:
            subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", base], check=False)
    for m in metrics:
        b, n = statistics.median(times["base"][m]), statistics.median(times["new"][m])
        lo_b, lo_n = min(times["base"][m]), min(times["new"][m])
        print(f"{m:24s} {args.base} {b:9.4f} ms  this tree {n:9.4f} ms  ratio {n / b:.3f} (medians of {args.rounds}); "
              f"minima ratio {lo_n / lo_b:.3f}")
    print(f"load average {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
