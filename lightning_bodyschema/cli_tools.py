"""Entry points behind ``tools/*.py``: thin argparse wrappers over the package.

User errors (``BodySchemaInputError``) print one line to stderr and exit 2, without a traceback.
"""
from __future__ import annotations

import argparse
import functools
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
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(2) from None

    return wrapper


@exits_cleanly
def make_dataset_main(argv=None):
    from .data.dataset import build_dataset
    from .npz import save_npz
    from .sim import MusculoskeletalModel, SpringParams

    parser = argparse.ArgumentParser(description="Generate a healthy static-equilibrium dataset (.npz, SI units).")
    parser.add_argument("--model", default="paper_arm", help="'paper_arm' or a path to an MJCF with spatial tendons")
    parser.add_argument("--n", type=int, default=800, help="number of samples (default 800, the paper's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output .npz file")
    parser.add_argument("--qp-solver", default="proxqp", help="proxqp (fast path) or any qpsolvers solver name")
    args = parser.parse_args(argv)
    model = MusculoskeletalModel(args.model)
    start = time.perf_counter()
    arrays = build_dataset(model, args.n, args.seed, SpringParams(), args.qp_solver)
    save_npz(args.out, **arrays)
    f = arrays["f"]
    print(f"wrote {args.out}: {args.n} samples of {model} in {time.perf_counter() - start:.2f} s "
          f"({int(arrays['n_redrawn'])} infeasible draws re-drawn); f in [{f.min():.1f}, {f.max():.1f}] N, "
          f"median {np.median(f):.1f} N")
