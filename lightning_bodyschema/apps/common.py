"""What every application shares: one-line errors (exit 2), argument parsing, safe output files, sampler names.

User errors (``BodySchemaInputError``) print one line to stderr and exit 2, without a traceback.
"""
from __future__ import annotations

import argparse
import functools
import os
import sys

import numpy as np

from ..errors import BodySchemaInputError


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


# --sampler of tools/adapt_cases.py and tools/predict.py: name -> options for ``schema.adapt``. One line each.
ADAPT_SAMPLERS = {
    "ddpm": {},  # the schema's own sampler: all T deterministic DDPM mean steps (the paper's), unless the checkpoint
                 # was trained with ``sample_steps``
    "strided20": {"n_steps": 20},  # the strided posterior-mean sampler (DiffusionSchema.STRIDED) over 20 steps:
                                   # quad spacing, noise-free DDPM posterior-mean steps (eta = 1), 2 guidance steps
                                   # where abar_t >= 0.5; diffusion schemas only (~10x faster, same accuracy)
}
SAMPLER_ALIASES = {"ddim20": "strided20"}  # earlier name of strided20 (it never was DDIM); scripts depend on it


def argument_parser(description: str) -> argparse.ArgumentParser:
    """An ArgumentParser whose usage errors are one-line ``BodySchemaInputError`` (exit 2, no usage dump)."""
    parser = argparse.ArgumentParser(description=description)

    def error(message):
        raise BodySchemaInputError(f"{message} (see {parser.prog} --help)")

    parser.error = error
    return parser



def torch_one_thread():
    import torch

    torch.set_num_threads(1)  # one thread is fastest for these tiny MLPs on the shared cores (docs/design.md)
    torch.set_flush_denormal(True)



def check_out(path: str, ckpt: str):
    """Refuse an --out that cannot be a file, or that would overwrite the checkpoint, before doing any work."""
    if os.path.isdir(path):
        raise BodySchemaInputError(f"--out {path!r} is a directory; give a file path such as cases.npz")
    if os.path.abspath(path) == os.path.abspath(ckpt):
        raise BodySchemaInputError(f"--out {path!r} is the checkpoint itself; give another file")



def write_npz(path: str, arrays: dict):
    """Atomic, deterministic write; an OS failure (permissions, disk full) is a one-line error."""
    from ..npz import save_npz

    try:
        save_npz(path, **arrays)
    except OSError as err:
        raise BodySchemaInputError(f"cannot write --out {path!r}: {err.strerror or err}") from None



def count_values(values: np.ndarray) -> str:
    """``"CUT 40, FIX 40, BOTH 40"``: each distinct value and its count, in order of first appearance."""
    names, first, counts = np.unique(values, return_index=True, return_counts=True)
    order = np.argsort(first)
    return ", ".join(f"{names[i]} {counts[i]}" for i in order)



def resolve_sampler(name: str) -> tuple[str, dict]:
    """(canonical name, options for ``schema.adapt``) of a --sampler name or alias."""
    canonical = SAMPLER_ALIASES.get(name, name)
    if canonical not in ADAPT_SAMPLERS:
        raise BodySchemaInputError(f"unknown --sampler {name!r}; allowed: {list(ADAPT_SAMPLERS)} "
                                   f"(aliases: {SAMPLER_ALIASES})")
    return canonical, dict(ADAPT_SAMPLERS[canonical])


def check_schema_options(schema, variant: str, sampler: str, options: dict):
    from ..schemas.diffusion import DiffusionSchema

    if variant not in schema.VARIANTS:
        raise BodySchemaInputError(f"unknown --variant {variant!r}; allowed: {list(schema.VARIANTS)}")
    if options and not isinstance(schema, DiffusionSchema):
        raise BodySchemaInputError(f"--sampler {sampler!r} needs a diffusion schema; the checkpoint holds a "
                                   f"{type(schema).__name__} (use --sampler ddpm)")
