"""``tools/make_cases.py`` and ``tools/adapt_cases.py``: fault-case files in, commands out."""
from __future__ import annotations

import time

from .._numpy import to_numpy
from ..errors import BodySchemaInputError
from ..status import status_codes, status_names
from .common import (ADAPT_SAMPLERS, NAME_ARRAYS, argument_parser, check_out, check_robot_names, check_schema_options,
                     count_values, exits_cleanly, import_user_modules, load_checked_schema, resolve_sampler,
                     robot_names, torch_one_thread, write_npz)

# ---------------------------------------------------------------------------- fault-case tools
CASE_ARRAYS = ("q_ref", "cut", "fix", "l_fixed", "cond")


@exits_cleanly
def make_cases_main(argv=None):
    parser = argument_parser("Draw fault cases from a checkpoint's test split: the paper's protocol (CUT 2 cut, FIX 2 "
                             "jammed, BOTH 1 + 1; the default) or the binding one (CUT, FIX, BOTH, WEAK, BAND, every "
                             "case feasible and every fault broken by the healthy command); writes q_ref, cut, fix, "
                             "l_fixed, cond (+ f_max, l_band for binding) (.npz, SI units).", checkpoint=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt); its test split is used")
    parser.add_argument("--seed", type=int, required=True, help="seed of the draw (same seed -> same bytes)")
    parser.add_argument("--out", required=True, help="output case file (.npz)")
    parser.add_argument("--protocol", default="paper", help="paper (default) or binding")
    parser.add_argument("--n", type=int, default=None,
                        help="cases per condition (default: 100 for binding, 40 for paper)")
    parser.add_argument("--n-per-condition", type=int, default=None,
                        help="cases per condition, paper protocol (default 40, the paper's); same as --n")
    args = parser.parse_args(argv)
    n_per_condition = _cases_per_condition(args)
    if args.seed < 0:
        raise BodySchemaInputError(f"--seed {args.seed} must be >= 0")
    check_out(args.out, args.ckpt)
    torch_one_thread()
    from ..schemas.loading import load_datamodule

    import_user_modules(args.imports)
    datamodule = load_datamodule(args.ckpt)
    q, x = datamodule.splits["val"]  # the held-out split is the test split (docs/design.md, evaluation)
    cases, rejected = draw_cases(args.protocol, datamodule.robot_model, datamodule.spring, to_numpy(q), to_numpy(x),
                                 n_per_condition, args.seed)
    arrays = cases.arrays() if args.protocol == "binding" else {name: getattr(cases, name) for name in CASE_ARRAYS}
    write_npz(args.out, {**arrays, **robot_names(datamodule.robot_model)})
    print(f"wrote {args.out}: {len(cases)} fault cases ({count_values(cases.cond)}), protocol {args.protocol}, seed "
          f"{args.seed}, postures from the {len(q)}-sample test split of {args.ckpt}")
    for cond, reasons in (rejected or {}).items():
        print(f"  {cond}: rejected {sum(reasons.values())} draws"
              + (" (" + ", ".join(f"{reason}: {count}" for reason, count in reasons.items()) + ")" if reasons else ""))


def _cases_per_condition(args) -> int:
    from ..evaluation.cases import PROTOCOLS

    if args.protocol not in PROTOCOLS:
        raise BodySchemaInputError(f"--protocol {args.protocol!r}; allowed: {list(PROTOCOLS)}")
    if args.n_per_condition is not None and args.protocol != "paper":
        raise BodySchemaInputError(f"--n-per-condition is the paper protocol's option; use --n with --protocol "
                                   f"{args.protocol}")
    if None not in (args.n, args.n_per_condition) and args.n != args.n_per_condition:
        raise BodySchemaInputError(f"--n {args.n} and --n-per-condition {args.n_per_condition} disagree; give one")
    option, given = ("--n", args.n) if args.n is not None else ("--n-per-condition", args.n_per_condition)
    if given is not None and given <= 0:
        raise BodySchemaInputError(f"{option} {given} must be a positive integer (cases per condition)")
    return given if given is not None else (100 if args.protocol == "binding" else 40)


def draw_cases(protocol: str, model, spring, q_pool, x_pool, n_per_condition: int, seed: int):
    """(cases, rejections or None) of ``protocol`` from a test split: q (P, N) [rad], x = [l_motor, f] (P, 2M);
    ``model``, ``spring``: the robot the split belongs to."""
    from ..evaluation.cases import HealthyPool, make_binding_cases, make_fault_cases

    n_muscles = model.n_muscles
    if protocol == "binding":
        pool = HealthyPool(q_pool, x_pool[:, :n_muscles], x_pool[:, n_muscles:2 * n_muscles])
        return make_binding_cases(model, pool, n_per_condition, seed, spring)
    return make_fault_cases(q_pool, x_pool[:, :n_muscles], n_per_condition, seed), None


def load_cases(path: str):
    """A case file checked on its own (file, arrays, dtypes, NaN/inf, cut/jam consistency): no model needed.
    Returns (cases, the robot's names the file was drawn for: {} in files without them)."""
    from ..evaluation.cases import FaultCases
    from ..npz import load_npz

    cases = FaultCases.load(path)
    if len(cases) == 0:
        raise BodySchemaInputError(f"case file {path}: it holds no cases")
    names = {k: [str(n) for n in v] for k, v in load_npz(path).items() if k in NAME_ARRAYS}
    return cases, names


def check_cases_fit(cases, path: str, model, names: dict | None = None):
    """The cases against the checkpoint's robot: joint and muscle names (when the file has them) and counts, q_ref
    inside the joint ranges."""
    from ..evaluation.cases import validate_cases

    check_robot_names(names or {}, model, f"case file {path}")
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
                             "the case arrays plus l_motor [m], f [N] and status (.npz).", checkpoint=True, device=True)
    parser.add_argument("--ckpt", required=True, help="trained schema checkpoint (.ckpt)")
    parser.add_argument("--cases", required=True, help="fault-case file (.npz from tools/make_cases.py or alike)")
    parser.add_argument("--out", required=True, help="output file (.npz), written only if everything succeeds")
    parser.add_argument("--variant", default="default", help="adaptation variant: default, literal (the paper's), or one "
                        "of the schema's study variants (diffusion: guided, strong, recurrent, inpaint_box, inpaint_spring, "
                        "projected)")
    parser.add_argument("--sampler", default="ddpm", help=f"denoising sampler, one of {list(ADAPT_SAMPLERS)}")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    args.sampler, options = resolve_sampler(args.sampler)
    check_out(args.out, args.ckpt)
    torch_one_thread()
    cases, names = load_cases(args.cases)  # before the checkpoint: a bad case file is reported without heavy imports
    schema = load_checked_schema(args)
    check_schema_options(schema, args.variant, args.sampler, options)
    check_cases_fit(cases, args.cases, schema.robot_model, names)
    adapt_start = time.perf_counter()
    result = adapt_cases(schema, cases, args.variant, options, args.ckpt)
    adapt_seconds = time.perf_counter() - adapt_start
    arrays = cases.arrays()  # the five case arrays, and f_max / l_band when the file has them
    arrays.update(l_motor=result.l_motor_m, f=result.f_n, status=status_names(result.status),
                  status_code=status_codes(result.status), **robot_names(schema.robot_model))
    write_npz(args.out, arrays)
    print(f"wrote {args.out}: {len(cases)} cases, {int(result.ok.sum())} ok (status: {count_values(result.status)}); "
          f"{type(schema).__name__}, variant {args.variant}, sampler {args.sampler}; adapted in {adapt_seconds:.2f} s "
          f"({time.perf_counter() - start:.2f} s in all)")
