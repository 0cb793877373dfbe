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
from ..variants import check_variant


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
    "strided20": {"n_steps": 20},  # each variant's strided preset (DiffusionSchema.ADAPT) over 20 steps:
                                   # quad spacing, noise-free DDPM posterior-mean steps (eta = 1), 2 guidance steps
                                   # where abar_t >= 0.5; diffusion schemas only
}
SAMPLER_ALIASES = {"ddim20": "strided20"}  # earlier name of strided20 (it never was DDIM); scripts depend on it


def argument_parser(description: str, checkpoint: bool = False, device: bool = False) -> argparse.ArgumentParser:
    """An ArgumentParser whose usage errors are one-line ``BodySchemaInputError`` (exit 2, no usage dump).

    checkpoint: the tool reads a --ckpt; add ``--import MODULE`` for checkpoints of a user's schema class.
    device: the tool runs the schema; add ``--device`` (``load_checked_schema`` moves the schema there).
    """
    parser = argparse.ArgumentParser(description=description)

    def error(message):
        raise BodySchemaInputError(f"{message} (see {parser.prog} --help)")

    parser.error = error
    if checkpoint:
        parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                            help="import this module (a dotted name on the Python path, or a .py file) before loading "
                                 "the checkpoint, so that a schema class it defines is known; repeatable. A checkpoint "
                                 "itself never makes anything get imported")
    if device:
        add_device_argument(parser)
    return parser


def add_device_argument(parser) -> None:
    """``--device``: where a tool runs the schema (``schemas.loading.check_device`` checks it)."""
    parser.add_argument("--device", default="cpu", help="torch device the schema runs on: cpu (default), cuda, "
                        "cuda:N; inputs and outputs stay numpy, the MuJoCo checks run on the CPU")


def import_user_modules(names) -> None:
    """Run the modules the USER named with --import (their BodySchema subclasses register themselves)."""
    import importlib.util

    for name in names:
        if name.endswith(".py"):
            if not os.path.isfile(name):
                raise BodySchemaInputError(f"--import {name!r} does not exist")
            module_name = os.path.splitext(os.path.basename(name))[0]
            spec = importlib.util.spec_from_file_location(module_name, name)
        else:
            try:
                spec = importlib.util.find_spec(name)
            except (ImportError, ValueError):
                spec = None
            if spec is None:
                raise BodySchemaInputError(f"--import {name!r}: no such module on the Python path (give a dotted "
                                           "module name, e.g. with PYTHONPATH set, or a .py file)")
            module_name = name
        if module_name in sys.modules:
            continue
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)


def load_checked_schema(args):
    """The tools' one way to a schema: the user's --import modules, then ``load_schema`` (every check)."""
    from ..schemas.loading import load_schema

    import_user_modules(args.imports)
    return load_schema(args.ckpt, map_location=getattr(args, "device", None))


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

    check_variant(schema, variant, "--variant")
    if options and not isinstance(schema, DiffusionSchema):
        raise BodySchemaInputError(f"--sampler {sampler!r} needs a diffusion schema; the checkpoint holds a "
                                   f"{type(schema).__name__} (use --sampler ddpm)")


def require_positive(**options: int) -> None:
    """Refuse, in one line naming them, the integer options (``--name``) below 1."""
    bad = [f"--{name.replace('_', '-')} {value}" for name, value in options.items() if value < 1]
    if bad:
        raise BodySchemaInputError(f"{', '.join(bad)}: must be >= 1")


def config_data(path: str) -> dict:
    """The ``data:`` section of the config file at ``path`` (``{class_path, init_args}`` or plain keys), as a dict."""
    import yaml

    if not os.path.isfile(path):
        raise BodySchemaInputError(f"--config {path!r} does not exist; give a config with a data: section")
    with open(path) as fh:
        data = (yaml.safe_load(fh) or {}).get("data") or {}
    return dict(data.get("init_args", data))


def robot_options(data: dict) -> dict:
    """Keyword arguments of ``MusculoskeletalModel`` from a config's data section, as the data module passes them
    (data.model, data.muscles, data.gravity, data.locked_joints, data.fixed_base)."""
    return {"source": data.get("model", "paper_arm"), "muscles": data.get("muscles"), "gravity": data.get("gravity"),
            "locked_joints": data.get("locked_joints"), "fixed_base": bool(data.get("fixed_base"))}


def robot_from_config(path: str):
    """(model, spring, data section) of a config's robot, resolved as the data module resolves them (data.model,
    data.muscles, data.gravity, data.locked_joints, data.fixed_base, spring constants), without building a dataset.
    For the benchmark tools."""
    from ..sim import MusculoskeletalModel
    from ..sim.spring import spring_for_model

    data = config_data(path)
    model = MusculoskeletalModel(**robot_options(data))
    spring = spring_for_model(model, data.get("k_n"), data.get("alpha_per_m", 20.0), data.get("f_max_n"))
    return model, spring, data


# the robot a case file was drawn for: a mask column means a muscle by its position, so a file must not meet a robot
# whose joints or muscles are ordered (or named) otherwise. Files without these arrays are checked by counts only.
NAME_ARRAYS = ("joints", "muscles")


def check_robot_names(names: dict, model, what: str) -> None:
    """Refuse a file whose ``joints`` / ``muscles`` arrays (when it has them) are not the model's, in order."""
    for key, expected in robot_names(model).items():
        if key in names and [str(n) for n in names[key]] != expected.tolist():
            raise BodySchemaInputError(f"{what} was written for {key} {[str(n) for n in names[key]]}, but the "
                                       f"checkpoint's robot has {expected.tolist()} (a fault mask names a muscle by its "
                                       f"position); draw the cases for this checkpoint")


def robot_names(model) -> dict:
    """{joints, muscles}: the names of ``model``, written beside the cases (as tools/predict.py writes them)."""
    return {"joints": np.array(model.joint_names, dtype=str),
            "muscles": np.array(model.muscle_names, dtype=str)}
