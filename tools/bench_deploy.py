#!/usr/bin/env python
"""Tail latency of the adapter at batch 1, one schema and path at a time: N consecutive calls each.

    python tools/bench_deploy.py --ckpt CKPT --package runs/adapter.pt2 [--ckpt CKPT2 --package PKG2 ...]
        [--cpp-build build/cpp] [--calls 10000] [--paths eager,compiled,aoti,aoti_wrapper,cpp] [--cut MUSCLE]
        [--rounds 1]

One table for every (checkpoint, package) pair given, diffusion and structured alike. Paths: ``eager`` the
prepared Python adapter (``schema.adapter(faults, check_physics=False)``, 20 steps for the diffusion schema),
``compiled`` the same with ``compiled=True`` (diffusion only: torch.compile, cpp_wrapper), ``aoti`` the package's
raw call from Python on tensors allocated once, ``aoti_wrapper`` ``load_exported(...)(q, faults)`` (numpy in and
out), ``cpp`` examples/cpp's ``control_loop`` (build it first; see README "Deploy in a C++ controller"). Prints one
markdown row per schema and path: first call after loading [ms], p50, p99, p99.9, max [us], resident-memory growth
[kB] over the calls after the first, and how many calls answered ok. ``--cut``: the one cut muscle of every call
(default: the robot's first muscle; '' none). ``--rounds``: the whole table that many times, the pairs interleaved
(side-by-side figures on a shared machine: each round's rows ran minutes apart at most).
"""
import json
import os
import subprocess
import time

import numpy as np

from lightning_bodyschema.apps.common import argument_parser, exits_cleanly, load_checked_schema, torch_one_thread
from lightning_bodyschema.errors import BodySchemaInputError

PATHS = ("eager", "compiled", "aoti", "aoti_wrapper", "cpp")


def rss_kb() -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))


def postures(q_range, calls: int) -> np.ndarray:
    """A slow sweep inside the joint ranges, one posture per call."""
    lo, hi = np.asarray(q_range, float).T
    phase = np.sin(1e-3 * np.arange(calls + 1))[:, None] + np.arange(len(lo))[None, :]
    return lo + (hi - lo) * (0.5 + 0.4 * np.sin(phase))


def timed(load, qs) -> dict:
    """Load, then one call per posture: the first alone, the rest as latencies; RSS growth after the first. A call
    returns its status code (0: ok); ``ok`` counts the calls after the first."""
    start = time.perf_counter()
    fn = load()
    fn(qs[:1])
    ok = 0
    first_ms = 1e3 * (time.perf_counter() - start)
    rss, lat = rss_kb(), np.empty(len(qs) - 1)
    for i in range(1, len(qs)):
        t0 = time.perf_counter()
        code = fn(qs[i:i + 1])
        lat[i - 1] = time.perf_counter() - t0
        ok += int(code == 0)
    return summary(first_ms, 1e6 * lat, rss_kb() - rss, ok)


def summary(first_ms, lat_us, rss_growth_kb, ok) -> dict:
    p50, p99, p999 = np.percentile(lat_us, [50, 99, 99.9])
    return {"first_ms": first_ms, "p50_us": p50, "p99_us": p99, "p999_us": p999, "max_us": float(np.max(lat_us)),
            "rss_growth_kb": rss_growth_kb, "ok": ok}


def python_path(schema, faults, compiled: bool):
    from lightning_bodyschema.schemas import DiffusionSchema

    options = {"n_steps": 20} if isinstance(schema, DiffusionSchema) else {}
    options.update({"compiled": True} if compiled else {})

    def load():
        adapter = schema.adapter(faults, check_physics=False, **options)
        return lambda q: adapter(q).status[0].code
    return load


def aoti_path(package: str, faults, raw: bool):
    from torch._inductor.package import load_package  # noqa: F401  (imported before the clock starts)

    from lightning_bodyschema.deploy import load_exported

    def load():
        adapter = load_exported(package)
        if not raw:
            return lambda q: adapter(q, faults).status[0].code
        tensors = adapter.inputs(np.zeros((1, len(adapter.joint_names))), faults)

        def call(q):
            tensors[0].copy_(torch_from(q))
            return int(adapter.run(*tensors)[2][0])
        return call
    return load


def torch_from(q):
    import torch

    return torch.from_numpy(np.ascontiguousarray(q, dtype=np.float64))


def cpp_path(build: str, package: str, calls: int, cut: str) -> dict:
    program = os.path.join(build, "control_loop")
    if not os.path.isfile(program):
        raise BodySchemaInputError(f"--cpp-build {build!r} has no control_loop; build examples/cpp first")
    args = [program, package, "--ticks", str(calls), "--json"] + (["--cut", cut] if cut else [])
    start = time.perf_counter()
    out = json.loads(subprocess.run(args, capture_output=True, text=True, check=True).stdout)
    wall = time.perf_counter() - start
    return {"first_ms": out["load_ms"] + out["first_call_us"] / 1e3, "p50_us": out["p50_us"], "p99_us": out["p99_us"],
            "p999_us": out["p999_us"], "max_us": out["max_us"], "rss_growth_kb": out["rss_growth_kb"], "wall_s": wall,
            "ok": out["ok_ticks"]}


@exits_cleanly
def main(argv=None):
    parser = argument_parser("Tail latency of the adapter at batch 1 on each deployment path.", checkpoint=True)
    parser.add_argument("--ckpt", required=True, action="append", help="a checkpoint a package was exported from "
                        "(diffusion or structured; repeat with --package for one table of several)")
    parser.add_argument("--package", required=True, action="append", help="its package (tools/export_adapter.py)")
    parser.add_argument("--cpp-build", default=None, help="build folder of examples/cpp (for the cpp path)")
    parser.add_argument("--calls", type=int, default=10000, help="consecutive calls per path (default 10000)")
    parser.add_argument("--paths", default=",".join(PATHS), help=f"comma-separated, of {list(PATHS)}")
    parser.add_argument("--cut", default=None, help="the one cut muscle of every call (default: the first; '' none)")
    parser.add_argument("--rounds", type=int, default=1, help="repeat every pair and path, interleaved (default 1)")
    args = parser.parse_args(argv)
    paths = args.paths.split(",")
    unknown = sorted(set(paths) - set(PATHS))
    if unknown or args.calls < 10 or args.rounds < 1 or len(args.ckpt) != len(args.package):
        raise BodySchemaInputError(f"--paths {unknown} unknown (allowed {list(PATHS)}), --calls {args.calls} < 10, "
                                   f"--rounds {args.rounds} < 1, or {len(args.ckpt)} --ckpt for "
                                   f"{len(args.package)} --package (give pairs)")
    if "cpp" in paths and args.cpp_build is None:
        raise BodySchemaInputError("the cpp path needs --cpp-build (the examples/cpp build folder)")
    torch_one_thread()
    print_rounds(args, paths)


def print_rounds(args, paths) -> None:
    """One markdown row per round, (checkpoint, package) pair and path, the pairs interleaved within a round."""
    print(f"batch 1, {args.calls} calls per path")
    print("| round | schema | package | path | first call after load [ms] | p50 [us] | p99 [us] | p99.9 [us] | max [us] "
          "| RSS growth [kB] | ok calls |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    schemas, ckpts = {}, list(args.ckpt)
    for round_ in range(1, args.rounds + 1):
        for ckpt, package in zip(ckpts, args.package):
            if ckpt not in schemas:
                args.ckpt = ckpt  # what load_checked_schema reads
                schemas[ckpt] = load_checked_schema(args)
            schema = schemas[ckpt]
            for path in paths:
                row = bench_path(schema, package, path, args)
                if row is not None:
                    print(f"| {round_} | {type(schema).__name__} ({schema.n_muscles} muscles) | "
                          f"{os.path.basename(package)} | {path} | {row['first_ms']:.1f} | {row['p50_us']:.0f} | "
                          f"{row['p99_us']:.0f} | {row['p999_us']:.0f} | {row['max_us']:.0f} | "
                          f"{row['rss_growth_kb']} | {row['ok']}/{args.calls} |", flush=True)
    print(f"load average (1, 5, 15 min) at the end: {os.getloadavg()}")


def bench_path(schema, package: str, path: str, args):
    """One row (``summary``) of ``schema`` on ``path``; None where the path does not apply (compiled: diffusion)."""
    from lightning_bodyschema.faults import Faults
    from lightning_bodyschema.schemas import DiffusionSchema

    names = schema.robot_model.muscle_names
    cut = names[0] if args.cut is None else args.cut
    faults = Faults.from_names(names, cut=[[cut]] if cut else [[]], n_cases=1)
    if path == "cpp":
        return cpp_path(args.cpp_build, package, args.calls, cut)
    if path == "compiled" and not isinstance(schema, DiffusionSchema):
        return None
    qs = postures(schema.robot_model.q_range, args.calls)
    if path in ("eager", "compiled"):
        return timed(python_path(schema, faults, path == "compiled"), qs)
    return timed(aoti_path(package, faults, path == "aoti"), qs)


if __name__ == "__main__":
    main()
