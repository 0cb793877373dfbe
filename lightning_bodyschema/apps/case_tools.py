"""``tools/make_cases.py`` and ``tools/adapt_cases.py``: fault-case files in, commands out."""
from __future__ import annotations

import time

from ..errors import BodySchemaInputError
from .common import (ADAPT_SAMPLERS, argument_parser, check_out, check_schema_options, count_values, exits_cleanly,
                     resolve_sampler, torch_one_thread, write_npz)

# ---------------------------------------------------------------------------- fault-case tools
CASE_ARRAYS = ("q_ref", "cut", "fix", "l_fixed", "cond")


@exits_cleanly
def make_cases_main(argv=None):
    parser = argument_parser("Draw the paper's fault cases (CUT 2 cut, FIX 2 jammed, BOTH 1 + 1) from a checkpoint's "
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
    check_out(args.out, args.ckpt)
    torch_one_thread()
    from ..evaluation.cases import make_fault_cases
    from ..schemas.loading import load_datamodule

    datamodule = load_datamodule(args.ckpt)
    q, x = datamodule.splits["val"]  # the held-out split is the test split (docs/design.md, evaluation)
    n_muscles = datamodule.robot_model.n_muscles
    cases = make_fault_cases(q.numpy(), x[:, :n_muscles].numpy(), args.n_per_condition, args.seed)
    write_npz(args.out, {name: getattr(cases, name) for name in CASE_ARRAYS})
    print(f"wrote {args.out}: {len(cases)} fault cases ({count_values(cases.cond)}), seed {args.seed}, postures from "
          f"the {len(q)}-sample test split of {args.ckpt}")



def load_cases(path: str):
    """A case file checked on its own (file, arrays, dtypes, NaN/inf, cut/jam consistency): no model needed."""
    from ..evaluation.cases import FaultCases

    cases = FaultCases.load(path)
    if len(cases) == 0:
        raise BodySchemaInputError(f"case file {path}: it holds no cases")
    return cases



def check_cases_fit(cases, path: str, model):
    """The cases against the checkpoint's robot: joint and muscle counts, q_ref inside the joint ranges."""
    from ..evaluation.cases import validate_cases

    try:
        validate_cases(cases, model.n_joints, model.n_muscles)
    except BodySchemaInputError as err:
        raise BodySchemaInputError(f"case file {path}: {err}; the checkpoint's robot has {model.n_joints} "
                                   f"joints {model.joint_names} and {model.n_muscles} muscles") from None
    try:
        model.check_q(cases.q_ref, within_range=True)
    except BodySchemaInputError as err:
        raise BodySchemaInputError(f"case file {path}: q_ref: {err}") from None



def adapt_cases(schema, cases, variant: str, options: dict, ckpt: str):
    try:
        return schema.adapt(cases.q_ref, cases.faults, variant=variant, **options)
    except NotImplementedError as err:  # a custom schema without adaptation
        raise BodySchemaInputError(f"checkpoint {ckpt!r}: {err}") from None



@exits_cleanly
def adapt_cases_main(argv=None):
    parser = argument_parser("Adapt a trained schema's commands to every case of a fault-case file in one batch; writes "
                             "the case arrays plus l_motor [m], f [N] and status (.npz).")
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt)")
    parser.add_argument("--cases", required=True, help="fault-case file (.npz from tools/make_cases.py or alike)")
    parser.add_argument("--out", required=True, help="output file (.npz), written only if everything succeeds")
    parser.add_argument("--variant", default="default", help="adaptation variant: default, literal (the paper's), or one "
                        "of the schema's study variants (diffusion: guided, strong, recurrent, inpaint_box, inpaint_spring, "
                        "projected; RESULTS.md)")
    parser.add_argument("--sampler", default="ddpm", help=f"denoising sampler, one of {list(ADAPT_SAMPLERS)}")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    args.sampler, options = resolve_sampler(args.sampler)
    check_out(args.out, args.ckpt)
    torch_one_thread()
    cases = load_cases(args.cases)  # before the checkpoint: a bad case file is reported without the heavy imports
    from ..schemas.loading import load_schema

    schema = load_schema(args.ckpt)
    check_schema_options(schema, args.variant, args.sampler, options)
    check_cases_fit(cases, args.cases, schema.robot_model)
    adapt_start = time.perf_counter()
    result = adapt_cases(schema, cases, args.variant, options, args.ckpt)
    adapt_seconds = time.perf_counter() - adapt_start
    arrays = {name: getattr(cases, name) for name in CASE_ARRAYS}
    arrays.update(l_motor=result.l_motor_m, f=result.f_n, status=result.status)
    write_npz(args.out, arrays)
    print(f"wrote {args.out}: {len(cases)} cases, {int(result.ok.sum())} ok (status: {count_values(result.status)}); "
          f"{type(schema).__name__}, variant {args.variant}, sampler {args.sampler}; adapted in {adapt_seconds:.2f} s "
          f"({time.perf_counter() - start:.2f} s in all)")
