#!/usr/bin/env python
"""Two structured myoArm checkpoints side by side: ``body_si`` and the prepared adapter, in one process, alternating.

    python tools/bench_body_pair.py --ckpt polynomial=runs/myoarm-polynomial/.../last.ckpt \
                                    --ckpt geometric=runs/myoarm/.../last.ckpt [--rounds 5]

On ``tools/bench_structured_adapter.py``'s 4000 myoArm cases (one cut and one jammed muscle each, seed 0): per
checkpoint and round, ``body_si`` at one posture (mean of 20 calls) and at 4000, the prepared adapter
``schema.adapter(faults, check_physics=False)`` at batch 1 (median over the first 20 cases, each its own adapter)
and at 4000 (per case); thread CPU time, the order alternating between rounds. Prints each metric's medians over
``--rounds``, the second checkpoint over the first, and the load average. One torch thread.
"""
import argparse
import os
import statistics
import sys
import time

import torch

from lightning_bodyschema.apps.common import exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError

METRICS = ("body_si_1", "body_si_4000", "adapter_1", "adapter_4000_per_case")


def thread_ms(call, n: int = 1) -> float:
    start = time.thread_time()
    for _ in range(n):
        call()
    return (time.thread_time() - start) / n * 1e3


def one_round(schema, adapters, big, q) -> dict:
    """Every metric once for one checkpoint [ms]."""
    return {"body_si_1": thread_ms(lambda: schema.body_si(torch.as_tensor(q[:1])), 20),
            "body_si_4000": thread_ms(lambda: schema.body_si(torch.as_tensor(q))),
            "adapter_1": statistics.median(thread_ms(lambda i=i: adapters[i](q[i:i + 1])) for i in range(20)),
            "adapter_4000_per_case": thread_ms(lambda: big(q)) / len(q)}


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ckpt", action="append", required=True, help="LABEL=PATH, twice")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    pairs = [c.partition("=") for c in args.ckpt]
    if len(pairs) != 2 or any(not sep or not label or not path for label, sep, path in pairs) or args.rounds < 1:
        raise BodySchemaInputError(f"--ckpt {args.ckpt} --rounds {args.rounds}: give two LABEL=PATH and rounds >= 1")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_structured_adapter import myoarm_cases

    from lightning_bodyschema.schemas.loading import load_schema

    _, _, faults, q = myoarm_cases(4000)
    runs = {}
    for label, _, path in pairs:
        schema = load_schema(path).eval()
        adapters = [schema.adapter(faults.take([i]), check_physics=False) for i in range(20)]
        runs[label] = (schema, adapters, schema.adapter(faults, check_physics=False), {m: [] for m in METRICS})
    labels = [label for label, _, _ in pairs]
    for r in range(args.rounds):
        for label in labels if r % 2 == 0 else labels[::-1]:
            schema, adapters, big, out = runs[label]
            for metric, value in one_round(schema, adapters, big, q).items():
                out[metric].append(value)
    first, second = (runs[label][3] for label in labels)
    for metric in METRICS:
        a, b = statistics.median(first[metric]), statistics.median(second[metric])
        print(f"{metric}: {labels[0]} {a:.4g} ms, {labels[1]} {b:.4g} ms, {labels[1]} / {labels[0]} {b / a:.2f}")
    print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
