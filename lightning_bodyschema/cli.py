"""``bodyschema``: the LightningCLI front end (fit, validate, test).

    bodyschema fit --config configs/diff.yaml
    bodyschema fit --config configs/ae-10.yaml --config configs/quick.yaml
    bodyschema fit --model DiffusionSchema --data.n_samples 800 --trainer.max_epochs 100
    bodyschema fit --config configs/diff.yaml --optimizer AdamW --optimizer.lr 3e-4 \
        --lr_scheduler CosineAnnealingLR --lr_scheduler.T_max 10000

The data module's robot (XML, muscles, spring) is linked into the schema at instantiation, so every
checkpoint is self-contained. User errors exit with code 2 and one line, without a traceback, before
anything is written (``cli_parser.OneLineErrorParser``: a misspelt option gets a "did you mean"); an option of a
fixed group (``--trainer.*``, ``--checkpoint.*``, ...) is checked against ``cli_options`` before torch and Lightning
are imported, so a typo costs no heavy import. ``validate`` and ``test`` log into the checkpoint's run folder
(``.../version_N/<subcommand>``), never into a new version folder; a fit ends by printing where its outputs are. There
is no ``predict`` subcommand: LightningCLI's predict runs over the data module's split, while a controller's
requests carry their own faults; ``tools/predict.py`` serves those. Beyond what jsonargparse checks:

* options must be spelt in full (no argparse prefix abbreviations: ``--trainer.max_epoch`` is an error);
* ``--trainer.max_epochs`` must be positive, or -1 (endless) with ``--model.lr_final=null``;
* ``--lr_scheduler`` needs ``--optimizer`` (without it the schema's Adam + cosine schedule train);
* ``--ckpt_path`` must be a readable lightning_bodyschema checkpoint of the data's robot (model XML,
  muscles and spring), checked before Lightning loads it; ``last`` is the newest ``last.ckpt`` under
  ``--trainer.default_root_dir``; ``best`` (only known inside one Python process) is refused;
* ``--trainer.max_steps`` must be positive or -1;
* ``--checkpoint.monitor`` on a renamed metric (``val/eq_residual_nm``) is refused, naming the new one;
"""
from __future__ import annotations

import difflib
import sys
from typing import TYPE_CHECKING, Optional

if TYPE_CHECKING:
    from .cli_app import BodySchemaCLI

_CLOSE_ENOUGH = 0.75  # as cli_parser's: max_epoch -> max_epochs is 0.95; unrelated options score below 0.6


def main(args: Optional[list[str]] = None) -> Optional["BodySchemaCLI"]:
    """Run the ``bodyschema`` command.

    ``main()`` (the console script, ``python -m lightning_bodyschema.cli``) reads ``sys.argv`` and returns
    None, so the ``sys.exit(main())`` of the console script exits 0 after a successful run (a returned object
    would be printed and exit 1). ``main([...])`` runs those arguments and returns the CLI object
    (``cli.trainer``, ``cli.model``, ...) for scripts and tests; ``sys.argv`` is then never read.
    """
    from_command_line = args is None
    # resolved here, once, and handed to LightningCLI explicitly (see cli_app.BodySchemaCLI.parse_arguments)
    args = sys.argv[1:] if from_command_line else [str(arg) for arg in args]
    refuse_unknown_options(args)
    from .cli_app import run  # torch, Lightning and the schemas: only for arguments that may be right

    cli = run(args)
    if from_command_line:
        _close_process_group()
    return None if from_command_line else cli


def _close_process_group() -> None:
    """Destroy the distributed process group a DDP run started (Lightning leaves that to the script): a gloo group
    still alive when the interpreter exits aborted a run that had finished and written everything ("terminate called
    without an active exception", exit 134) in about half of the 2-rank CPU fits."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def refuse_unknown_options(args: list[str]) -> None:
    """Exit 2 with one line (as the full parser would) on an option of a fixed group that the subcommand's parser
    does not know; options of class groups (``--model.*``, ``--data.*``, ...) and anything the copy in
    ``cli_options`` cannot judge (another Lightning version, no subcommand) are left to the parser."""
    from . import cli_options

    subcommand = next((arg for arg in args if not arg.startswith("-")), None)
    known = cli_options.options(str(subcommand))
    if not known or not _same_lightning(cli_options.LIGHTNING_VERSION):
        return
    for arg in args[args.index(subcommand) + 1:]:
        name = arg.split("=", 1)[0]
        if name.startswith("--") and not _accepted(name, known):
            close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=_CLOSE_ENOUGH)
            hint = f"; did you mean {close[0]}?" if close else ""
            sys.stderr.write(f"error: unrecognized arguments: {arg}{hint}\n"
                             f"(bodyschema {subcommand} --help lists every option)\n")
            raise SystemExit(2)


def _accepted(name: str, known: set[str]) -> bool:
    """``name`` is an option, lies under a class option (``--trainer.logger.init_args.x``), or under a group whose
    class is chosen on the command line (``--model.*``: the parser knows those options once it has the class)."""
    parts = name.split(".")
    if name in known or f"{parts[0]}.help" in known:
        return True
    return any(".".join(parts[:end]) in known for end in range(2, len(parts)))


def _same_lightning(version_copied: str) -> bool:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lightning") == version_copied
    except PackageNotFoundError:
        return False


def __getattr__(name):
    """``BodySchemaCLI`` and the rest of ``cli_app``, imported on first use (``main`` refuses bad options first).
    Not for dunder names: ``from lightning_bodyschema.cli import main`` asks for ``__path__`` first."""
    if name.startswith("__"):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from . import cli_app

    return getattr(cli_app, name)


if __name__ == "__main__":
    main()
