#!/usr/bin/env python
"""Inference latency with and without fault adaptation: AE-10, VAE-10, Diff-200 and Diff-fast (paper Fig. exp-time).

    python tools/bench_adaptation.py [--ckpt-dir runs/paper] [--json OUT] [--figure OUT.png]
                                     [--sizes 1 40 4000] [--repeats 9] [--reference] [--ablation] [--no-compile]

Times the user-facing calls on BOTH cases (1 cut + 1 jammed muscle, postures from the test split, seed 0):
``schema.adapt(q, faults)`` (adapted; without the optional physics feasibility check, timed separately as
"+ physics check") and ``schema.infer(q)`` (unadapted), one torch thread, flush-denormal on.
Variants: AE-10 / VAE-10 (latent descent, 200 steps), Diff-200 (the paper's sampler: all T = 200 DDPM
steps, guidance at every step) and Diff-fast (``DiffusionSchema(sample_steps=20)``: 20 quad-spaced
posterior-mean steps, guidance twice per step where abar_t >= 0.5). Every variant uses the default
autograd-free fast path; ``--reference`` adds the autograd reference (``fast=False``) for 1 and 40 cases.
Variants are interleaved within each repeat (rotating the order) and the median is reported; for 1 and
40 cases each repeat averages several calls. "sampler only" rows time ``adapt_normalized`` alone with a
prebuilt loss (what the package's samplers cost without ``BodySchema.adapt``'s checks and bookkeeping).
Diff-fast is also timed as a *prepared adapter* (``schema.adapter(faults)(q)``: the fault-dependent set-up
done once, as a controller holding a fault would) and *compiled* (``compile_sampler=True``: the fused loop
through ``torch.compile``); the compile time of each (batch size, guided/unguided) is reported separately.

Paper (GPU): 0.7 s per case adapted (all three models), 0.1 s Diff unadapted, 0.001 s AE/VAE unadapted.
``--ablation`` measures each step of the fast path at batch 1 (Diff-200, Diff-fast, AE-10, VAE-10), chosen by
public options (``fast=False``, ``inference_mode=False``).
Writes a markdown table to stdout, ``--json`` (all numbers) and ``--figure`` (PNG, written atomically).
"""
from __future__ import annotations

import argparse
import functools
import glob
import inspect
import json
import os
import platform
import re
import statistics
import sys
import time

import numpy as np
import torch

torch.set_num_threads(1)  # one thread was fastest on the shared 2-core machine (BENCHMARKS.md)
torch.set_flush_denormal(True)

from lightning_bodyschema.apps.common import add_device_argument  # noqa: E402
from lightning_bodyschema.evaluation import make_fault_cases  # noqa: E402
from lightning_bodyschema.faults import Faults  # noqa: E402
from lightning_bodyschema.schemas import load_datamodule, load_schema  # noqa: E402
from lightning_bodyschema.schemas.base import BodySchema  # noqa: E402

MODELS = {"AE-10": "ae-10", "VAE-10": "vae-10", "Diff": "diff"}
PAPER_S = {"adapted": 0.7, "unadapted": {"AE-10": 1e-3, "VAE-10": 1e-3, "Diff-200": 0.1, "Diff-fast": 0.1}}
FAST_STEPS = 20
# ``BodySchema.adapt`` may also ask the true physics whether any command can hold the posture (a QP per case,
# ``check_physics``): not part of the adaptation the paper times, so the "adapted" rows leave it out and a
# "+ physics check" row shows the default call.
NO_CHECK = {"check_physics": False} if "check_physics" in inspect.signature(BodySchema.adapt).parameters else {}
# (variant, kind, n cases, limit [ms per case]) from the speed issue, for this 2-core CPU, one thread
TARGETS = [("Diff-200", "adapted", 1, 10.0), ("Diff-fast", "adapted", 1, 1.0), ("Diff-fast", "adapted", 4000, 0.05),
           ("AE-10", "adapted", 1, 20.0), ("VAE-10", "adapted", 1, 20.0), ("Diff-fast", "unadapted", 1, 1.0)]
# Diff-fast is also timed as a prepared adapter (``schema.adapter(faults)``: the fault-dependent set-up done
# once, as a controller would) and with the sampling loop compiled (``compile_sampler``); each target is
# checked for every such way of calling it
FAST_NOTES = ("", "prepared adapter", "compiled", "prepared adapter, compiled")


def find_checkpoint(ckpt_dir: str, prefix: str) -> str:
    """The final checkpoint of run ``{prefix}`` or ``{prefix}-<epochs>`` under ckpt_dir (highest epoch wins)."""
    found = []
    for run in glob.glob(os.path.join(ckpt_dir, prefix)) + glob.glob(os.path.join(ckpt_dir, f"{prefix}-*")):
        if not re.fullmatch(re.escape(prefix) + r"(-\d+)?", os.path.basename(run)):
            continue  # "ae-10" must not pick up "ae-100"
        for path in glob.glob(os.path.join(run, "lightning_logs", "version_*", "checkpoints", "epoch=*.ckpt")):
            epoch = int(re.search(r"epoch=(\d+)", path).group(1))
            found.append((epoch, os.path.getmtime(path), path))
    if not found:
        raise SystemExit(f"error: no checkpoint for {prefix!r} under {ckpt_dir} "
                         f"(expected {prefix}[-EPOCHS]/lightning_logs/version_*/checkpoints/epoch=*.ckpt)")
    return max(found)[2]


def both_cases(datamodule, n_muscles: int, n: int):
    """n BOTH cases (1 cut + 1 jammed muscle) from the test split, seed 0 (the paper's timing condition)."""
    q, x = datamodule.splits["val"]
    cases = make_fault_cases(q.numpy(), x[:, :n_muscles].numpy(), n, seed=0, n_cut={"BOTH": 1}, n_fix={"BOTH": 1})
    return cases.q_ref, Faults(cases.cut, cases.fix, cases.l_fixed)


def _take(q, faults, n):
    return q[:n], Faults(faults.cut[:n], faults.fix[:n], faults.l_fixed_m[:n])


def sampler_only(schema, q, faults, **options):
    """``adapt_normalized`` with the penalty built once outside the timed call."""
    with torch.no_grad():
        penalty = schema.penalty_builder("default")(faults.constraints(schema.spring.f_max_n))
        q_n = schema.encode_q(torch.as_tensor(q))

    def run():
        with torch.no_grad():
            return schema.adapt_normalized(q_n, penalty, "default", **options)
    return run


def time_interleaved(fns: dict, repeats: int, min_seconds: float = 0.02) -> dict:
    """Median seconds per call of each fn; fns run in rotating order within each repeat, each timing
    averaging enough calls to last ~min_seconds."""
    inner = {}
    for name, fn in fns.items():  # warm-up (caches, lazy builds) and calibration
        fn()
        start = time.perf_counter()
        fn()
        one = time.perf_counter() - start
        inner[name] = max(1, min(200, int(min_seconds / max(one, 1e-6))))
    times = {name: [] for name in fns}
    names = list(fns)
    for r in range(repeats):
        for name in names[r % len(names):] + names[:r % len(names)]:
            fn, n = fns[name], inner[name]
            start = time.perf_counter()
            for _ in range(n):
                fn()
            times[name].append((time.perf_counter() - start) / n)
    return {name: statistics.median(t) for name, t in times.items()}


def compile_all(compiled, q_all, faults_all, sizes) -> dict:
    """Trigger ``torch.compile`` for every (batch size, guided/unguided) the timing will use; seconds each."""
    seconds = {}
    for n in sizes:
        q, faults = _take(q_all, faults_all, n)
        for kind, fn in (("adapted", lambda: compiled.adapt(q, faults, **NO_CHECK)), ("unadapted", lambda: compiled.infer(q))):
            start = time.perf_counter()
            fn()
            seconds[f"{kind}, {n} case(s)"] = time.perf_counter() - start
            print(f"compiled Diff-fast {kind} for {n} case(s) in {seconds[f'{kind}, {n} case(s)']:.1f} s",
                  file=sys.stderr, flush=True)
    return seconds


def latency_rows(schemas: dict, q_all, faults_all, sizes, repeats: int, reference: bool, compiled=None,
                 other_variants=()) -> list[dict]:
    rows = []
    for n in sizes:
        q, faults = _take(q_all, faults_all, n)
        fns = {}
        for name, schema in schemas.items():
            fns[(name, "adapted", "")] = lambda s=schema: s.adapt(q, faults, **NO_CHECK)
            fns[(name, "unadapted", "")] = lambda s=schema: s.infer(q)
            if name.startswith("Diff"):
                fns[(name, "adapted", "prepared adapter")] = functools.partial(
                    schema.adapter(faults, check_physics=False), q)
                for v in other_variants:  # side by side with the default, same run
                    fns[(name, "adapted", f"variant {v}, prepared adapter")] = functools.partial(
                        schema.adapter(faults, variant=v, check_physics=False), q)
                    if compiled is not None and name == "Diff-fast":
                        fns[(name, "adapted", f"variant {v}, prepared adapter, compiled")] = functools.partial(
                            compiled.adapter(faults, variant=v, check_physics=False), q)
            if name == "Diff-fast":
                if compiled is not None:
                    fns[(name, "adapted", "compiled")] = lambda s=compiled: s.adapt(q, faults, **NO_CHECK)
                    fns[(name, "adapted", "prepared adapter, compiled")] = functools.partial(
                        compiled.adapter(faults, check_physics=False), q)
                    fns[(name, "unadapted", "compiled")] = lambda s=compiled: s.infer(q)
            if n == 1:
                fns[(name, "adapted", "sampler only")] = sampler_only(schema, q, faults)
                if NO_CHECK:
                    fns[(name, "adapted", "+ physics check")] = lambda s=schema: s.adapt(q, faults)
            if reference and n <= 40:
                fns[(name, "adapted", "autograd reference")] = lambda s=schema: s.adapt(q, faults, fast=False,
                                                                                          **NO_CHECK)
        print(f"timing {len(fns)} variants at {n} case(s), {repeats} repeats ...", file=sys.stderr, flush=True)
        medians = time_interleaved(fns, repeats, min_seconds=0.02 if n <= 40 else 0.0)
        for (name, kind, note), seconds in medians.items():
            paper = PAPER_S["adapted"] if kind == "adapted" else PAPER_S["unadapted"][name]
            rows.append({"variant": name, "kind": kind, "note": note, "cases": n, "ms_per_call": 1e3 * seconds,
                         "ms_per_case": 1e3 * seconds / n, "paper_s_per_case": paper,
                         "ratio_to_paper": seconds / n / paper})
    return rows


def ablation_rows(schemas: dict, q_all, faults_all, repeats: int) -> list[dict]:
    """Each step of the fast path, end to end (``schema.adapt``) at batch 1, selected by public options."""
    q, faults = _take(q_all, faults_all, 1)
    steps = [("0 autograd reference (fast=False)", dict(fast=False)),
             ("1 frozen network (hand-written backward), analytic loss gradient, coefficients folded into per-step "
              "matrices, buffers allocated once (fast=True, inference_mode=False)", dict(inference_mode=False)),
             ("2 + torch.inference_mode (the default fast path)", dict())]
    rows = []
    for name in ("Diff-200", "Diff-fast", "AE-10", "VAE-10"):
        schema = schemas[name]
        fns = {label: functools.partial(schema.adapt, q, faults, **options, **NO_CHECK) for label, options in steps}
        print(f"ablation {name} ...", file=sys.stderr, flush=True)
        for label, seconds in time_interleaved(fns, repeats).items():
            rows.append({"variant": name, "step": label, "ms": 1e3 * seconds})
    return rows


def markdown(rows, ablation) -> str:
    out = ["| variant | kind | cases | ms per call | ms per case | paper [s/case] | ratio to paper |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        kind = r["kind"] + (f" ({r['note']})" if r["note"] else "")
        out.append(f"| {r['variant']} | {kind} | {r['cases']} | {r['ms_per_call']:.3g} | {r['ms_per_case']:.3g} | "
                   f"{r['paper_s_per_case']:g} | {r['ratio_to_paper']:.2g} |")
    out += ["", "| target (one thread) | measured | verdict |", "|---|---|---|"]
    for t in target_checks(rows):
        how = f" ({t['note']})" if t["note"] else ""
        out.append(f"| {t['variant']} {t['kind']}{how}, {t['cases']} case(s): <= {t['limit_ms']:g} ms/case | "
                   f"{t['ms_per_case']:.3g} ms/case | {'met' if t['met'] else 'MISSED'} |")
    if ablation:
        out += ["", "| variant | step (batch 1, `schema.adapt`) | ms | speed-up vs previous | vs reference |",
                "|---|---|---|---|---|"]
        for name in dict.fromkeys(r["variant"] for r in ablation):
            sub = [r for r in ablation if r["variant"] == name]
            for i, r in enumerate(sub):
                prev = f"{sub[i - 1]['ms'] / r['ms']:.2f}x" if i else ""
                out.append(f"| {name} | {r['step']} | {r['ms']:.3g} | {prev} | {sub[0]['ms'] / r['ms']:.1f}x |")
    return "\n".join(out)


def target_checks(rows) -> list[dict]:
    out = []
    for variant, kind, n, limit in TARGETS:
        for note in FAST_NOTES if variant == "Diff-fast" else ("", "prepared adapter") if variant == "Diff-200" else ("",):
            hit = [r for r in rows if (r["variant"], r["kind"], r["cases"], r["note"]) == (variant, kind, n, note)]
            if hit:
                out.append({"variant": variant, "kind": kind, "note": note, "cases": n, "limit_ms": limit,
                            "ms_per_case": hit[0]["ms_per_case"], "met": hit[0]["ms_per_case"] <= limit})
    return out


def figure(rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    names = list(dict.fromkeys(r["variant"] for r in rows))
    one = {(r["variant"], r["kind"]): r["ms_per_case"] for r in rows if r["cases"] == 1 and not r["note"]}
    width = 0.38
    for k, (kind, color) in enumerate((("unadapted", "tab:gray"), ("adapted", "tab:blue"))):
        values = [one.get((n, kind), np.nan) for n in names]
        bars = ax1.bar(np.arange(len(names)) + (k - 0.5) * width, values, width, label=f"{kind} (ours)", color=color)
        ax1.bar_label(bars, fmt="%.2g", fontsize=7)
    ax1.axhline(700, color="tab:red", ls="--", lw=1, label="paper, adapted (0.7 s)")
    ax1.axhline(100, color="tab:orange", ls=":", lw=1, label="paper, Diff unadapted (0.1 s)")
    ax1.axhline(1, color="tab:green", ls=":", lw=1, label="paper, AE/VAE unadapted (1 ms)")
    ax1.set_xticks(np.arange(len(names)), names)
    ax1.set_yscale("log")
    ax1.set_ylabel("ms per case (1 BOTH case)")
    ax1.legend(fontsize=6, loc="upper left")
    for n, color in zip(names, plt.rcParams["axes.prop_cycle"].by_key()["color"]):
        for kind, style in (("adapted", "-o"), ("unadapted", "--s")):
            pts = sorted((r["cases"], r["ms_per_case"]) for r in rows
                         if r["variant"] == n and r["kind"] == kind and not r["note"])
            if pts:
                ax2.plot(*zip(*pts), style, color=color, ms=3, lw=1, label=f"{n} {kind}")
    ax2.set_xscale("log")
    ax2.set_yscale("log")
    ax2.set_xlabel("cases per call (batched)")
    ax2.set_ylabel("ms per case")
    ax2.legend(fontsize=6)
    fig.suptitle("Inference time with and without adaptation (2-core CPU, one thread)", fontsize=9)
    fig.tight_layout()
    return fig


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt-dir", default="runs/paper", help="where ae-10*, vae-10* and diff* runs live")
    parser.add_argument("--json", help="write every number here")
    parser.add_argument("--figure", default="docs/bench_adaptation.png", help="timing figure (PNG); '' to skip")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 40, 4000])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--reference", action="store_true", help="also time the autograd reference (1 and 40 cases)")
    parser.add_argument("--ablation", action="store_true", help="time each optimisation step at batch 1")
    parser.add_argument("--variants", nargs="*", default=[],
                        help="also time these adaptation variants of the diffusion schemas (e.g. guided), side by side")
    parser.add_argument("--no-compile", dest="compile", action="store_false",
                        help="skip the torch.compile rows (compiling takes ~20 s per batch size and kind)")
    add_device_argument(parser)
    args = parser.parse_args(argv)
    if any(n < 1 for n in args.sizes) or args.repeats < 1:
        raise SystemExit("error: --sizes and --repeats must be positive")
    paths = {name: find_checkpoint(args.ckpt_dir, prefix) for name, prefix in MODELS.items()}
    load = functools.partial(load_schema, map_location=args.device)
    schemas = {"AE-10": load(paths["AE-10"]), "VAE-10": load(paths["VAE-10"]), "Diff-200": load(paths["Diff"]),
               "Diff-fast": load(paths["Diff"])}
    schemas["Diff-fast"].hparams.sample_steps = FAST_STEPS  # = DiffusionSchema(sample_steps=20): infer and adapt
    q_all, faults_all = both_cases(load_datamodule(paths["Diff"]), schemas["Diff-200"].n_muscles, max(args.sizes))
    started = time.strftime("%Y-%m-%d %H:%M")
    compiled, compile_s = None, {}
    if args.compile:
        compiled = load(paths["Diff"])
        compiled.hparams.sample_steps, compiled.hparams.compile_sampler = FAST_STEPS, True
        compile_s = compile_all(compiled, q_all, faults_all, sorted(args.sizes))
    rows = latency_rows(schemas, q_all, faults_all, sorted(args.sizes), args.repeats, args.reference, compiled,
                        args.variants)
    ablation = ablation_rows(schemas, q_all, faults_all, args.repeats) if args.ablation else []
    print(markdown(rows, ablation))
    if compile_s:
        print("\n| torch.compile of Diff-fast (first call, inductor on-disk cache as found) | seconds |\n|---|---|")
        print("\n".join(f"| {name} | {sec:.1f} |" for name, sec in compile_s.items()))
    command = "python tools/bench_adaptation.py " + " ".join(argv if argv is not None else sys.argv[1:])
    report = {"date": started, "command": command.strip(), "checkpoints": paths,
              "machine": {"cpus": os.cpu_count(), "torch": torch.__version__, "threads": torch.get_num_threads(),
                          "python": platform.python_version(), "load_average": os.getloadavg()},
              "rows": rows, "targets": target_checks(rows), "ablation": ablation, "compile_seconds": compile_s}
    if args.json:
        from lightning_bodyschema.npz import atomic_write_bytes

        atomic_write_bytes(args.json, (json.dumps(report, indent=1) + "\n").encode())
    if args.figure:
        from lightning_bodyschema.plots.arm import save_figure_atomic

        os.makedirs(os.path.dirname(os.path.abspath(args.figure)), exist_ok=True)
        save_figure_atomic(figure(rows), args.figure)
        print(f"\nwrote {args.figure}", file=sys.stderr)


if __name__ == "__main__":
    main()
