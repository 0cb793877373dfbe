"""The ``bodyschema`` argument parser: a bad option is one line, not a page of usage.

jsonargparse's default error prints the whole usage (about 90 lines for ``bodyschema fit``, every trainer,
callback and data option) before the one line that says what was wrong. ``OneLineErrorParser`` prints

    error: unrecognized arguments: --trainer.max_epoch 3; did you mean --trainer.max_epochs?
    (bodyschema fit --help lists every option)

and exits with code 2. "did you mean" names the closest known option(s) of the subcommand (difflib), when
one is close enough. ``bodyschema predict`` is refused the same way, naming ``tools/predict.py``.
"""
from __future__ import annotations

import difflib
import inspect
import re
import sys
from typing import NoReturn, Optional

from jsonargparse import ActionSubCommands
from lightning.pytorch.cli import LightningArgumentParser

# what to say when a removed or unsupported subcommand is typed (see cli.BodySchemaCLI.subcommands)
SUBCOMMAND_HINTS = {
    "predict": "bodyschema has no predict: requests with their own faults are not a dataloader; "
               "use python tools/predict.py --ckpt CKPT --requests requests.yaml --out commands.json",
}
_CLOSE_ENOUGH = 0.75  # difflib ratio: max_epoch -> max_epochs is 0.95; unrelated options score below 0.6
# the option names a jsonargparse error message points at: --flag, or 'dotted.key' of a config file
_BAD_FLAG = re.compile(r"(--[\w.\-]+)")
_BAD_KEY = re.compile(r"(?:option|key|Key)\s+'([\w.\-]+)'")
_INVALID_CHOICE = re.compile(r"invalid choice: '([^']*)'")
# jsonargparse's multi-line Union errors, reduced to their one fact: an unknown --model class, or an init argument
# the class does not have
_UNKNOWN_CLASS = re.compile(r"Parser key \"model\": - Expected a path but (\S+) either not accessible")
_CLASS_OPTION = re.compile(r"Parser key \"([\w.]+)\".*class_path '([\w.]+)': Option '([\w.]+)' is not accepted")


class OneLineErrorParser(LightningArgumentParser):
    """``LightningArgumentParser`` whose errors are one line (plus a did-you-mean and a pointer to --help)."""

    def parse_args(self, args=None, *rest, **kwargs):
        self._argv = list(sys.argv[1:] if args is None else args)  # to find the subcommand an error is about
        return super().parse_args(args, *rest, **kwargs)

    def error(self, message: str, ex: Optional[Exception] = None) -> NoReturn:
        if not self.exit_on_error:  # jsonargparse parses nested parts with exit_on_error off and catches the raise
            super().error(message, ex)
        parser = getattr(ex, "subcommand_parser", None) or _chosen_subcommand_parser(self) or self
        line = " ".join(str(message).split())  # jsonargparse's messages may span lines
        class_option = _CLASS_OPTION.search(line)
        if class_option:  # the one fact in a page-long Union error
            key, class_path, option = class_option.groups()
            line = f"--{key}.{option}: {class_path} does not accept option {option!r}"
            hint = _did_you_mean(f"--{key}.{option}", _init_options(key, class_path))
        elif _UNKNOWN_CLASS.search(line):  # --model=NoSuchSchema: name the schemas there are
            name, known = _UNKNOWN_CLASS.search(line).group(1), [c for c in _schema_classes() if c != "BodySchema"]
            line = (f"--model {name} is not a schema class; give one of {sorted(known)} or a class path "
                    "(package.module.Class)")
            close = difflib.get_close_matches(name, known, n=1, cutoff=_CLOSE_ENOUGH)
            hint = f"did you mean {close[0]}?" if close else None
        else:
            hint = _subcommand_hint(line) or _did_you_mean(line, _known_options(parser))
        sys.stderr.write(f"error: {line}{'; ' + hint if hint else ''}\n")
        sys.stderr.write(f"({parser.prog.replace(' [options]', '')} --help lists every option)\n")
        self.exit(2)


def _chosen_subcommand_parser(parser) -> Optional[LightningArgumentParser]:
    """The subcommand parser named on the command line (``fit``, ...), if the main parser holds subcommands."""
    actions = [a for a in parser._actions if isinstance(a, ActionSubCommands)]
    if not actions:
        return None
    chosen = [arg for arg in getattr(parser, "_argv", []) if arg in actions[0]._name_parser_map]
    return actions[0]._name_parser_map[chosen[0]] if chosen else None


def _known_options(parser) -> list[str]:
    """Every ``--option`` the parser accepts (nested groups included, as their dotted names)."""
    return sorted({option for action in parser._actions for option in action.option_strings
                   if option.startswith("--")})


def _schema_classes() -> dict[str, type]:
    """``BodySchema`` and every subclass loaded so far (ours, and a user's given by class path), by class name."""
    from .schemas import BodySchema

    classes, found = [BodySchema], {}
    while classes:
        cls = classes.pop()
        classes.extend(cls.__subclasses__())
        found[cls.__qualname__] = cls
    return found


def _init_options(key: str, class_path: str) -> list[str]:
    """``--key.<argument>`` for every ``__init__`` argument of the schema or data-module class ``class_path``."""
    from .data import EquilibriumDataModule, RecordedDataModule  # --data is a subclass option too

    classes = {**_schema_classes(), "EquilibriumDataModule": EquilibriumDataModule,
               "RecordedDataModule": RecordedDataModule}
    cls = classes.get(class_path.rsplit(".", 1)[-1])  # jsonargparse may name it by its package
    return [] if cls is None else [f"--{key}.{name}" for name in inspect.signature(cls.__init__).parameters
                                   if name != "self"]


def _subcommand_hint(line: str) -> Optional[str]:
    choice = _INVALID_CHOICE.search(line)
    return SUBCOMMAND_HINTS.get(choice.group(1)) if choice else None


def _did_you_mean(line: str, known: list[str]) -> Optional[str]:
    """``did you mean --x?`` for the first misspelt option in ``line`` that has a close known option."""
    bad = [flag.split("=")[0] for flag in _BAD_FLAG.findall(line)] + [f"--{key}" for key in _BAD_KEY.findall(line)]
    for flag in bad:
        if flag in known:
            continue
        close = difflib.get_close_matches(flag, known, n=1, cutoff=_CLOSE_ENOUGH)
        if close:
            return f"did you mean {close[0]}?"
    return None
