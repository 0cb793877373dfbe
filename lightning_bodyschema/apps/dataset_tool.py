"""``tools/make_dataset.py``: a healthy static-equilibrium dataset file."""
from __future__ import annotations

import os
import time

import numpy as np

from ..errors import BodySchemaInputError
from .common import argument_parser, exits_cleanly, write_npz


@exits_cleanly
def make_dataset_main(argv=None):
    from ..data.dataset import build_dataset
    from ..sim import MusculoskeletalModel, SpringParams

    parser = argument_parser("Generate a healthy static-equilibrium dataset (.npz, SI units).")
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
    write_npz(args.out, arrays)
    f = arrays["f"]
    print(f"wrote {args.out}: {args.n} samples of {model} in {time.perf_counter() - start:.2f} s "
          f"({int(arrays['n_redrawn'])} infeasible draws re-drawn); f in [{f.min():.1f}, {f.max():.1f}] N, "
          f"median {np.median(f):.1f} N")
