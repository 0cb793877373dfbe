#!/usr/bin/env python
"""Cost of the diagnosis on a checkpoint (the issue's target body: configs/myoarm.yaml's), one torch thread.

    python tools/bench_diagnose.py --ckpt CKPT [--rows 5] [--batch 4000] [--repeats 7] [--ticks 300]

Times, side by side in one run (medians over ``--repeats``; the machine's load printed with them):
- ``schema.diagnose`` of one ``--rows``-row log (batch 1), and of ``--batch`` such logs at once (ms per log);
- the same split into the learned body at the logs' postures (``learned_body_si``) and the rest (the two stages);
- ``monitor.update`` per tick while the robot holds a posture (``--ticks`` ticks, median and p99), the body evaluated
  at the first tick and then reused within ``Monitor.reuse_rad``, and per tick when every tick moves beyond it.
The logs are healthy readings (commands plus the documented sensor noise at postures of the held-out split): the
cost does not depend on what the log shows.
"""
import argparse
import os
import statistics
import time

import numpy as np
import torch


def healthy_log(schema, q, rows: int, rng):
    from lightning_bodyschema.diagnosis import SensorLog, SensorNoise

    noise, n = SensorNoise(), len(q)
    l_cmd, f_cmd = schema.infer(q)
    f_max = np.broadcast_to(np.asarray(schema.spring.f_max_n, float), f_cmd.shape[1:])
    read = (q + noise.q_rad * rng.standard_normal(q.shape), l_cmd + noise.l_m * rng.standard_normal(l_cmd.shape),
            f_cmd + noise.f_frac * f_max * rng.standard_normal(f_cmd.shape))
    case = np.repeat(np.arange(n // rows), rows)[:n]
    return SensorLog.from_rows(schema.robot_model.joint_names, schema.robot_model.muscle_names, read[0], read[1], l_cmd,
                               f_cmd, read[2], case)


def timed(fn, repeats: int, calls: int = 1) -> float:
    """Median seconds per call over ``repeats`` blocks of ``calls`` calls."""
    fn()
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        out.append((time.perf_counter() - start) / calls)
    return statistics.median(out)


def monitor_ticks(schema, q0, ticks: int, rng, moving: bool):
    from lightning_bodyschema.diagnosis import SensorNoise

    noise, monitor = SensorNoise(), schema.monitor()
    l_cmd, f_cmd = schema.infer(q0[None])
    f_max = np.broadcast_to(np.asarray(schema.spring.f_max_n, float), l_cmd.shape[1:])
    costs = []
    for k in range(ticks):
        q = q0 + (0.02 * k if moving else 0.0) + noise.q_rad * rng.standard_normal(q0.shape)
        reading = (q, l_cmd[0] + noise.l_m * rng.standard_normal(l_cmd.shape[1]),
                   f_cmd[0] + noise.f_frac * f_max * rng.standard_normal(f_cmd.shape[1]))
        start = time.perf_counter()
        monitor.update((l_cmd[0], f_cmd[0]), reading)
        costs.append(time.perf_counter() - start)
    costs = np.array(costs[5:]) * 1e3
    return float(np.median(costs)), float(np.quantile(costs, 0.99))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--rows", type=int, default=5)
    parser.add_argument("--batch", type=int, default=4000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--ticks", type=int, default=300)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    from lightning_bodyschema.schemas.loading import load_datamodule, load_schema

    schema = load_schema(args.ckpt)
    q_pool = np.asarray(load_datamodule(args.ckpt).splits["val"][0], float)
    schema.body_error()
    rng = np.random.default_rng(0)
    one = healthy_log(schema, q_pool[:args.rows], args.rows, rng)
    many = healthy_log(schema, q_pool[:args.rows * args.batch], args.rows, rng)
    q_one, q_many = one.q_rad[one.rows], many.q_rad[many.rows]
    print(f"{type(schema).__name__}, {schema.n_joints} joints / {schema.n_muscles} muscles; "
          f"load {os.getloadavg()[0]:.2f}")
    for name, log, q, calls in (("batch 1", one, q_one, 20), (f"batch {args.batch}", many, q_many, 1)):
        total = timed(lambda: schema.diagnose(log), args.repeats, calls)
        body = timed(lambda: schema.learned_body_si(q), args.repeats, calls)
        per_log = 1e3 * total / len(log)
        print(f"diagnose {name} ({args.rows} rows a log): {per_log:.4f} ms per log (body {1e3 * body / len(log):.4f}, "
              f"stages {per_log - 1e3 * body / len(log):.4f})")
    for moving in (False, True):
        p50, p99 = monitor_ticks(schema, q_pool[0], args.ticks, rng, moving)
        print(f"monitor.update per tick, {'moving 20 mrad a tick' if moving else 'holding a posture'}: median "
              f"{p50:.3f} ms, p99 {p99:.3f} ms")
    print(f"load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
