#!/usr/bin/env python
"""Tail latency of the adapter at batch 1, one path at a time: N consecutive calls each.

    python tools/bench_deploy.py --ckpt CKPT --package runs/adapter.pt2 [--cpp-build build/cpp] [--calls 10000]
        [--paths eager,compiled,aoti,aoti_wrapper,cpp] [--cut shoulder_flexor]

Paths: ``eager`` the prepared Python adapter (``schema.adapter(faults, n_steps=20, check_physics=False)``),
``compiled`` the same with ``compiled=True`` (torch.compile, cpp_wrapper), ``aoti`` the package's raw call from
Python on tensors allocated once, ``aoti_wrapper`` ``load_exported(...)(q, faults)`` (numpy in and out), ``cpp``
examples/cpp's ``control_loop`` (build it first; see README "Deploy in a C++ controller"). Prints one markdown row per path: first call
after loading [ms], p50, p99, p99.9, max [us] and resident-memory growth [kB] over the calls after the first.
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
    """Load, then one call per posture: the first alone, the rest as latencies; RSS growth after the first."""
    start = time.perf_counter()
    fn = load()
    fn(qs[:1])
    first_ms = 1e3 * (time.perf_counter() - start)
    rss, lat = rss_kb(), np.empty(len(qs) - 1)
    for i in range(1, len(qs)):
        t0 = time.perf_counter()
        fn(qs[i:i + 1])
        lat[i - 1] = time.perf_counter() - t0
    return summary(first_ms, 1e6 * lat, rss_kb() - rss)


def summary(first_ms, lat_us, rss_growth_kb) -> dict:
    p50, p99, p999 = np.percentile(lat_us, [50, 99, 99.9])
    return {"first_ms": first_ms, "p50_us": p50, "p99_us": p99, "p999_us": p999, "max_us": float(np.max(lat_us)),
            "rss_growth_kb": rss_growth_kb}


def python_path(schema, faults, compiled: bool):
    def load():
        adapter = schema.adapter(faults, n_steps=20, check_physics=False, **({"compiled": True} if compiled else {}))
        return lambda q: adapter(q)
    return load


def aoti_path(package: str, faults, raw: bool):
    from torch._inductor.package import load_package  # noqa: F401  (imported before the clock starts)

    from lightning_bodyschema.deploy import load_exported

    def load():
        adapter = load_exported(package)
        if not raw:
            return lambda q: adapter(q, faults)
        tensors = adapter.inputs(np.zeros((1, len(adapter.joint_names))), faults)

        def call(q):
            tensors[0].copy_(torch_from(q))
            return adapter.run(*tensors)
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
            "p999_us": out["p999_us"], "max_us": out["max_us"], "rss_growth_kb": out["rss_growth_kb"], "wall_s": wall}


@exits_cleanly
def main(argv=None):
    parser = argument_parser("Tail latency of the adapter at batch 1 on each deployment path.", checkpoint=True)
    parser.add_argument("--ckpt", required=True, help="the diffusion checkpoint the package was exported from")
    parser.add_argument("--package", required=True, help="the exported package (tools/export_adapter.py)")
    parser.add_argument("--cpp-build", default=None, help="build folder of examples/cpp (for the cpp path)")
    parser.add_argument("--calls", type=int, default=10000, help="consecutive calls per path (default 10000)")
    parser.add_argument("--paths", default=",".join(PATHS), help=f"comma-separated, of {list(PATHS)}")
    parser.add_argument("--cut", default="shoulder_flexor", help="the one fault of every call (a cut muscle; '' none)")
    args = parser.parse_args(argv)
    paths = args.paths.split(",")
    unknown = sorted(set(paths) - set(PATHS))
    if unknown or args.calls < 10:
        raise BodySchemaInputError(f"--paths {unknown} unknown (allowed {list(PATHS)}) or --calls {args.calls} < 10")
    torch_one_thread()
    schema = load_checked_schema(args)
    from lightning_bodyschema.faults import Faults

    cut = [[args.cut]] if args.cut else [[]]
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=cut, n_cases=1)
    qs = postures(schema.robot_model.q_range, args.calls)
    print(f"batch 1, {args.calls} calls per path, cut {args.cut or 'none'}")
    print("| path | first call after load [ms] | p50 [us] | p99 [us] | p99.9 [us] | max [us] | RSS growth [kB] |")
    print("|---|---|---|---|---|---|---|")
    for path in paths:
        if path == "cpp":
            if args.cpp_build is None:
                raise BodySchemaInputError("the cpp path needs --cpp-build (the examples/cpp build folder)")
            row = cpp_path(args.cpp_build, args.package, args.calls, args.cut)
        elif path in ("eager", "compiled"):
            row = timed(python_path(schema, faults, path == "compiled"), qs)
        else:
            row = timed(aoti_path(args.package, faults, path == "aoti"), qs)
        print(f"| {path} | {row['first_ms']:.1f} | {row['p50_us']:.0f} | {row['p99_us']:.0f} | {row['p999_us']:.0f} "
              f"| {row['max_us']:.0f} | {row['rss_growth_kb']} |", flush=True)


if __name__ == "__main__":
    main()
