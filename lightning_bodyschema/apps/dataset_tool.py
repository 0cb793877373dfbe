"""``tools/make_dataset.py``: a healthy static-equilibrium dataset file, optionally as a real robot would record it.

The file is the recorded-data format (``data/recorded.py``): columns ``q_<joint>``, ``l_<muscle>``, ``f_<muscle>`` in
SI units with the joint and tension limits, CSV for ``*.csv`` and NPZ otherwise, so ``RecordedDataModule`` reads it
back. ``--noise-*`` adds Gaussian sensor noise; ``--mismatch`` makes the data with a perturbed copy of the robot
(``sim/mismatch.py``): the data a researcher would record on a robot the model only approximates.
"""
from __future__ import annotations

import os
import time

import numpy as np

from ..errors import BodySchemaInputError
from .common import argument_parser, exits_cleanly, robot_from_config


def add_sensor_noise(arrays: dict, noise_q_rad, noise_l_m, noise_f_n, seed: int) -> dict:
    """Gaussian sensor noise on q, l_motor and f (standard deviations in SI units: scalars, or one per channel),
    from its own seeded stream."""
    rng = np.random.default_rng([int(seed), 16])  # apart from the posture stream: noise 0 leaves the data as it was
    noisy = dict(arrays)
    for name, sigma in (("q", noise_q_rad), ("l_motor", noise_l_m), ("f", noise_f_n)):
        noise = rng.standard_normal(arrays[name].shape)
        noisy[name] = arrays[name] + np.asarray(sigma) * noise if np.any(np.asarray(sigma) > 0) else arrays[name]
    return noisy


def _check_args(args):
    if args.seed < 0:
        raise BodySchemaInputError(f"--seed {args.seed} must be >= 0")
    if os.path.isdir(args.out):
        raise BodySchemaInputError(f"--out {args.out!r} is a directory; give a file path such as data.npz")
    for flag, value in (("--noise-q", args.noise_q), ("--noise-l", args.noise_l), ("--noise-f", args.noise_f)):
        if not np.isfinite(value) or value < 0:
            raise BodySchemaInputError(f"{flag} {value!r} must be a standard deviation >= 0 (SI units: rad, m, N)")
    if args.workers is not None and args.workers < 0:
        raise BodySchemaInputError(f"--workers {args.workers} must be >= 0 (0 or 1: in this process; "
                                   "default: every core)")
    if not 0.0 <= args.mismatch < 1.0:
        raise BodySchemaInputError(f"--mismatch {args.mismatch!r} must lie in [0, 1) (0.1 = up to +-10 %)")


@exits_cleanly
def make_dataset_main(argv=None):
    from ..data.dataset import build_dataset
    from ..data.recorded import write_recorded
    from ..sim import MusculoskeletalModel
    from ..sim.mismatch import mismatched_robot
    from ..sim.spring import spring_for_model

    parser = argument_parser("Generate a healthy static-equilibrium dataset in the recorded-data format "
                             "(q_<joint>, l_<muscle>, f_<muscle> columns, SI units; .csv or .npz).")
    parser.add_argument("--model", default="paper_arm", help="'paper_arm', myo:<name> (needs myo-sim) or a path to an "
                        "MJCF with spatial tendons")
    parser.add_argument("--config", help="take the robot from a config's data section instead of --model (model, "
                        "muscles, locked_joints, fixed_base, spring constants), e.g. configs/myoarm-diff.yaml")
    parser.add_argument("--fixed-base", action="store_true", help="weld --model's floating base (free joint) at its "
                        "reference pose, e.g. for myo:myolegs")
    parser.add_argument("--n", type=int, default=800, help="number of samples (default 800, the paper's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output file: .csv, else .npz")
    parser.add_argument("--qp-solver", default="newton",
                        help="newton (batched dual Newton, the same bytes every run; default), proxqp or any qpsolvers solver name")
    parser.add_argument("--noise-q", type=float, default=0.0, metavar="RAD", help="joint-angle sensor noise (std)")
    parser.add_argument("--noise-l", type=float, default=0.0, metavar="M", help="motor-length sensor noise (std)")
    parser.add_argument("--noise-f", type=float, default=0.0, metavar="N", help="tension sensor noise (std)")
    parser.add_argument("--mismatch", type=float, default=0.0, metavar="FRACTION",
                        help="make the data with a copy of the model whose wrap radii, path sites, link masses and "
                             "spring constants are each scaled by up to +-FRACTION")
    parser.add_argument("--mismatch-seed", type=int, default=0, metavar="S", help="seed of the mismatch draw")
    parser.add_argument("--workers", type=int, default=None, metavar="N", help="processes that draw the samples "
                        "(default: every core; 0 or 1: this process); the file is the same bytes for any N")
    parser.add_argument("--quiet", action="store_true", help="no progress bar (it shows only on a terminal anyway)")
    args = parser.parse_args(argv)
    _check_args(args)
    if args.config:
        model, spring, _ = robot_from_config(args.config)
    else:  # the data module's defaults: the actuators' peak forces for MyoSuite bodies, the paper's 150 N otherwise
        model = MusculoskeletalModel(args.model, fixed_base=args.fixed_base)
        spring = spring_for_model(model, None, 20.0, None)
    source = model
    if args.mismatch > 0:
        source, spring = mismatched_robot(model, spring, args.mismatch, args.mismatch_seed)
    start = time.perf_counter()
    arrays = build_dataset(source, args.n, args.seed, spring, args.qp_solver, args.workers,
                           progress=False if args.quiet else None)
    arrays = add_sensor_noise(arrays, args.noise_q, args.noise_l, args.noise_f, args.seed)
    ranges = {f"q_{j}": lim for j, lim in zip(model.joint_names, model.q_range.tolist())}
    f_max = np.broadcast_to(np.asarray(spring.f_max_n, float), (model.n_muscles,))
    ranges.update({f"f_{m}": (0.0, float(hi)) for m, hi in zip(model.muscle_names, f_max)})  # read back as f_range
    meta = {"model_xml": model.xml, "n_redrawn": int(arrays["n_redrawn"]), "seed": args.seed,
            "noise_q_rad": args.noise_q, "noise_l_m": args.noise_l, "noise_f_n": args.noise_f,
            "mismatch": args.mismatch, "mismatch_seed": args.mismatch_seed}
    try:
        write_recorded(args.out, arrays["q"], arrays["l_motor"], arrays["f"], model.joint_names, model.muscle_names,
                       ranges, meta)
    except OSError as err:
        raise BodySchemaInputError(f"cannot write --out {args.out!r}: {err.strerror or err}") from None
    f = arrays["f"]
    print(f"wrote {args.out}: {args.n} samples of {model} in {time.perf_counter() - start:.2f} s "
          f"({int(arrays['n_redrawn'])} infeasible draws re-drawn); f in [{f.min():.1f}, {f.max():.1f}] N, "
          f"median {np.median(f):.1f} N; noise q {args.noise_q} rad, l {args.noise_l} m, f {args.noise_f} N; "
          f"mismatch {args.mismatch} (seed {args.mismatch_seed})")
