"""Entry points behind ``tools/*.py``: thin argparse wrappers over the package.

User errors (``BodySchemaInputError``) print one line to stderr and exit 2, without a traceback.
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import time

import numpy as np

from .errors import BodySchemaInputError


def exits_cleanly(main):
    """Turn a user error into ``error: ...`` on stderr and exit code 2."""

    @functools.wraps(main)
    def wrapper(argv=None):
        try:
            return main(argv)
        except BodySchemaInputError as err:
            print(f"error: {' '.join(str(err).split())}", file=sys.stderr)  # one line, whatever the message
            raise SystemExit(2) from None

    return wrapper


@exits_cleanly
def make_dataset_main(argv=None):
    from .data.dataset import build_dataset
    from .sim import MusculoskeletalModel, SpringParams

    parser = _parser("Generate a healthy static-equilibrium dataset (.npz, SI units).")
    parser.add_argument("--model", default="paper_arm", help="'paper_arm' or a path to an MJCF with spatial tendons")
    parser.add_argument("--n", type=int, default=800, help="number of samples (default 800, the paper's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output .npz file")
    parser.add_argument("--qp-solver", default="proxqp", help="proxqp (fast path) or any qpsolvers solver name")
    args = parser.parse_args(argv)
    if args.seed < 0:
        raise BodySchemaInputError(f"--seed {args.seed} must be >= 0")
    if os.path.isdir(args.out):
        raise BodySchemaInputError(f"--out {args.out!r} is a directory; give a file path such as data.npz")
    model = MusculoskeletalModel(args.model)
    start = time.perf_counter()
    arrays = build_dataset(model, args.n, args.seed, SpringParams(), args.qp_solver)
    _write_npz(args.out, arrays)
    f = arrays["f"]
    print(f"wrote {args.out}: {args.n} samples of {model} in {time.perf_counter() - start:.2f} s "
          f"({int(arrays['n_redrawn'])} infeasible draws re-drawn); f in [{f.min():.1f}, {f.max():.1f}] N, "
          f"median {np.median(f):.1f} N")


# ---------------------------------------------------------------------------- fault-case tools
CASE_ARRAYS = ("q_ref", "cut", "fix", "l_fixed", "cond")

# --sampler of tools/adapt_cases.py: name -> options for ``schema.adapt``. Adding a sampler is one line.
ADAPT_SAMPLERS = {
    "ddpm": {},  # the schema's own sampler: all T deterministic DDPM steps (eta = 0), the paper's, unless the
                 # checkpoint was trained with ``sample_steps``
    "ddim20": {"n_steps": 20},  # the strided sampler (DiffusionSchema.STRIDED) over 20 steps: quad spacing,
                                # noise-free posterior-mean steps, 2 guidance steps where abar_t >= 0.5;
                                # diffusion schemas only (~10x faster, same feasible-case accuracy)
}


def _parser(description: str) -> argparse.ArgumentParser:
    """An ArgumentParser whose usage errors are one-line ``BodySchemaInputError`` (exit 2, no usage dump)."""
    parser = argparse.ArgumentParser(description=description)

    def error(message):
        raise BodySchemaInputError(f"{message} (see {parser.prog} --help)")

    parser.error = error
    return parser


def _torch_one_thread():
    import torch

    torch.set_num_threads(1)  # one thread is fastest for these tiny MLPs on the shared cores (DESIGN §7)
    torch.set_flush_denormal(True)


def _check_out(path: str, ckpt: str):
    """Refuse an --out that cannot be a file, or that would overwrite the checkpoint, before doing any work."""
    if os.path.isdir(path):
        raise BodySchemaInputError(f"--out {path!r} is a directory; give a file path such as cases.npz")
    if os.path.abspath(path) == os.path.abspath(ckpt):
        raise BodySchemaInputError(f"--out {path!r} is the checkpoint itself; give another file")


def _write_npz(path: str, arrays: dict):
    """Atomic, deterministic write; an OS failure (permissions, disk full) is a one-line error."""
    from .npz import save_npz

    try:
        save_npz(path, **arrays)
    except OSError as err:
        raise BodySchemaInputError(f"cannot write --out {path!r}: {err.strerror or err}") from None


def _count(values: np.ndarray) -> str:
    """``"CUT 40, FIX 40, BOTH 40"``: each distinct value and its count, in order of first appearance."""
    names, first, counts = np.unique(values, return_index=True, return_counts=True)
    order = np.argsort(first)
    return ", ".join(f"{names[i]} {counts[i]}" for i in order)


@exits_cleanly
def make_cases_main(argv=None):
    parser = _parser("Draw the paper's fault cases (CUT 2 cut, FIX 2 jammed, BOTH 1 + 1) from a checkpoint's "
                     "test split; writes q_ref, cut, fix, l_fixed, cond (.npz, SI units).")
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt); its test split is used")
    parser.add_argument("--seed", type=int, required=True, help="seed of the draw (same seed -> same bytes)")
    parser.add_argument("--out", required=True, help="output case file (.npz)")
    parser.add_argument("--n-per-condition", type=int, default=40, help="cases per condition (default 40, the paper's)")
    args = parser.parse_args(argv)
    if args.seed < 0:
        raise BodySchemaInputError(f"--seed {args.seed} must be >= 0")
    if args.n_per_condition <= 0:
        raise BodySchemaInputError(f"--n-per-condition {args.n_per_condition} must be a positive integer")
    _check_out(args.out, args.ckpt)
    _torch_one_thread()
    from .evaluation.cases import make_fault_cases
    from .schemas.loading import load_datamodule

    datamodule = load_datamodule(args.ckpt)
    q, x = datamodule.splits["val"]  # the held-out split is the test split (DESIGN §6)
    n_muscles = datamodule.robot_model.n_muscles
    cases = make_fault_cases(q.numpy(), x[:, :n_muscles].numpy(), args.n_per_condition, args.seed)
    _write_npz(args.out, {name: getattr(cases, name) for name in CASE_ARRAYS})
    print(f"wrote {args.out}: {len(cases)} fault cases ({_count(cases.cond)}), seed {args.seed}, postures from "
          f"the {len(q)}-sample test split of {args.ckpt}")


def _sampler_options(name: str) -> dict:
    if name not in ADAPT_SAMPLERS:
        raise BodySchemaInputError(f"unknown --sampler {name!r}; allowed: {list(ADAPT_SAMPLERS)}")
    return dict(ADAPT_SAMPLERS[name])


def _check_schema_options(schema, variant: str, sampler: str, options: dict):
    from .schemas.diffusion import DiffusionSchema

    if variant not in schema.VARIANTS:
        raise BodySchemaInputError(f"unknown --variant {variant!r}; allowed: {list(schema.VARIANTS)}")
    if options and not isinstance(schema, DiffusionSchema):
        raise BodySchemaInputError(f"--sampler {sampler!r} needs a diffusion schema; the checkpoint holds a "
                                   f"{type(schema).__name__} (use --sampler ddpm)")


def _load_cases(path: str):
    """A case file checked on its own (file, arrays, dtypes, NaN/inf, cut/jam consistency): no model needed."""
    from .evaluation.cases import FaultCases

    cases = FaultCases.load(path)
    if len(cases) == 0:
        raise BodySchemaInputError(f"case file {path}: it holds no cases")
    return cases


def _check_cases_fit(cases, path: str, model):
    """The cases against the checkpoint's robot: joint and muscle counts, q_ref inside the joint ranges."""
    from .evaluation.cases import validate_cases

    try:
        validate_cases(cases, model.n_joints, model.n_muscles)
    except BodySchemaInputError as err:
        raise BodySchemaInputError(f"case file {path}: {err}; the checkpoint's robot has {model.n_joints} "
                                   f"joints {model.joint_names} and {model.n_muscles} muscles") from None
    try:
        model.check_q(cases.q_ref, within_range=True)
    except BodySchemaInputError as err:
        raise BodySchemaInputError(f"case file {path}: q_ref: {err}") from None


def _adapt(schema, cases, variant: str, options: dict, ckpt: str):
    try:
        return schema.adapt(cases.q_ref, cases.faults, variant=variant, **options)
    except NotImplementedError as err:  # a custom schema without adaptation
        raise BodySchemaInputError(f"checkpoint {ckpt!r}: {err}") from None


@exits_cleanly
def adapt_cases_main(argv=None):
    parser = _parser("Adapt a trained schema's commands to every case of a fault-case file in one batch; writes "
                     "the case arrays plus l_motor [m], f [N] and status (.npz).")
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt)")
    parser.add_argument("--cases", required=True, help="fault-case file (.npz from tools/make_cases.py or alike)")
    parser.add_argument("--out", required=True, help="output file (.npz), written only if everything succeeds")
    parser.add_argument("--variant", default="default", help="adaptation variant: default or literal (the paper's)")
    parser.add_argument("--sampler", default="ddpm", help=f"denoising sampler, one of {list(ADAPT_SAMPLERS)}")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    options = _sampler_options(args.sampler)
    _check_out(args.out, args.ckpt)
    _torch_one_thread()
    cases = _load_cases(args.cases)  # before the checkpoint: a bad case file is reported without the heavy imports
    from .schemas.loading import load_schema

    schema = load_schema(args.ckpt)
    _check_schema_options(schema, args.variant, args.sampler, options)
    _check_cases_fit(cases, args.cases, schema.robot_model)
    adapt_start = time.perf_counter()
    result = _adapt(schema, cases, args.variant, options, args.ckpt)
    adapt_seconds = time.perf_counter() - adapt_start
    arrays = {name: getattr(cases, name) for name in CASE_ARRAYS}
    arrays.update(l_motor=result.l_motor_m, f=result.f_n, status=result.status)
    _write_npz(args.out, arrays)
    print(f"wrote {args.out}: {len(cases)} cases, {int(result.ok.sum())} ok (status: {_count(result.status)}); "
          f"{type(schema).__name__}, variant {args.variant}, sampler {args.sampler}; adapted in {adapt_seconds:.2f} s "
          f"({time.perf_counter() - start:.2f} s in all)")
