#!/usr/bin/env python
"""The learned body's evaluation time: ``StructuredSchema.body_si`` and its two parts, per batch size.

    python tools/bench_body_eval.py --ckpt CKPT [--batches 1 4000] [--repeats 5] [--paths]

At ``--batches`` seeded uniform postures of the checkpoint's robot: ``body_si`` (lengths, moment arms and torque as
float64 arrays), the length model's ``with_jacobian`` (with its coefficients as the schema keeps them) and the
torque, in ms per call (medians of ``--repeats`` rounds; at batch 1 each round times 100 calls). Only public calls:
run it from another worktree (its ``PYTHONPATH``) on the same checkpoint for a side-by-side figure. With ``--paths``
(a per-muscle checkpoint) also the length model by the few-postures path and by blocks of rows
(``networks.snapshot.FEW_ELEMENTS`` forced), and a gravity torque's forward kinematics by pointer jumping and node
by node (``networks.snapshot.JUMP_ROWS`` forced), and ``body_si`` in numpy and in torch
(``schemas.structured_body.HOST_ROWS`` forced): the figures behind the three thresholds. One torch thread; the load average
is printed with the figures.
"""
import argparse
import os
import statistics
import time

import numpy as np
import torch

from lightning_bodyschema.apps.common import exits_cleanly
from lightning_bodyschema.errors import BodySchemaInputError

CALLS_AT_BATCH_1 = 100  # a call is ~1 ms at batch 1: one timing of a handful is noise


def ms_per_call(fn, batch: int, repeats: int) -> float:
    """Median over ``repeats`` rounds of the time per call [ms] of ``fn()`` (many calls per round at batch 1)."""
    calls = CALLS_AT_BATCH_1 if batch == 1 else 1
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - start) / calls)
    return 1e3 * statistics.median(times)


def rows(schema, batch: int, repeats: int, paths: bool):
    """``(label, ms)`` pairs at ``batch`` postures."""
    q = torch.as_tensor(schema.robot_model.sample_q(np.random.default_rng(0), batch))
    q_n = schema.normalizer.encode_q(q.to(torch.float64)).to(schema.dtype)
    kept = getattr(schema.length_net, "snapshot", lambda: None)()  # as the schema keeps it (per-muscle)
    lengths = (lambda: schema.length_net.with_jacobian(q_n)) if kept is None else \
        (lambda: schema.length_net.with_jacobian(q_n, kept))
    out = [("body_si", ms_per_call(lambda: schema.body_si(q), batch, repeats)),
           ("lengths and moment arms", ms_per_call(lengths, batch, repeats)),
           ("torque", ms_per_call(lambda: schema.torque(q_n), batch, repeats))]
    if paths:
        from lightning_bodyschema.networks import snapshot as few_postures

        budget = few_postures.FEW_ELEMENTS
        for label, elements in (("few-postures path", 10 ** 18), ("blockwise path", 0)):
            few_postures.FEW_ELEMENTS = elements
            out.append((f"lengths, {label}", ms_per_call(lengths, batch, repeats)))
        few_postures.FEW_ELEMENTS = budget
        if schema.hparams.get("torque_model") == "gravity":
            from lightning_bodyschema.networks import snapshot as gravity  # the eager torque's kinematics

            kept = gravity.JUMP_ROWS
            for label, rows_jump in (("pointer jumping", 10 ** 9), ("node by node", 0)):
                gravity.JUMP_ROWS = rows_jump
                out.append((f"torque, {label}", ms_per_call(lambda: schema.torque(q_n), batch, repeats)))
            gravity.JUMP_ROWS = kept
        out += host_rows(schema, q, batch, repeats)
    return out


def host_rows(schema, q, batch: int, repeats: int):
    """``body_si`` by the numpy evaluation and by torch (``schemas.structured_body.HOST_ROWS`` forced), where the
    checkpoint's body has a numpy evaluation: the figures behind that threshold."""
    from lightning_bodyschema.schemas import structured_body

    out, kept = [], structured_body.HOST_ROWS
    for label, limit in (("numpy", 10 ** 9), ("torch", 0)):
        structured_body.HOST_ROWS = limit
        if label == "numpy" and schema._host_body(q) is None:
            break
        out.append((f"body_si, {label}", ms_per_call(lambda: schema.body_si(q), batch, repeats)))
    structured_body.HOST_ROWS = kept
    return out


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True, help="a trained StructuredSchema checkpoint with its model")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 4000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--paths", action="store_true",
                        help="also the few-postures and blockwise paths (per-muscle only)")
    args = parser.parse_args(argv)
    if min(args.batches) < 1 or args.repeats < 1:
        raise BodySchemaInputError(f"--batches {args.batches} and --repeats {args.repeats}: expected integers >= 1")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    from lightning_bodyschema.schemas.loading import load_schema

    schema = load_schema(args.ckpt).eval()
    if not hasattr(schema, "body_si") or getattr(schema, "robot_model", None) is None:
        raise BodySchemaInputError(f"{args.ckpt}: not a StructuredSchema with a model (body_si needs both)")
    if args.paths and schema.hparams.get("length_model") != "per_muscle":
        raise BodySchemaInputError("--paths: the checkpoint's length model is not per_muscle")
    with torch.no_grad():
        for batch in args.batches:
            for label, ms in rows(schema, batch, args.repeats, args.paths):
                print(f"batch {batch:>6}  {label:<32} {ms:9.3f} ms per call  {ms / batch:8.4f} ms per posture")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
