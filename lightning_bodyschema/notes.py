"""Notes: what the library tells a user about a choice it made for them (a joint it locked, muscles it left out).

``note(message)`` prints one line to stderr, unless an application holds the notes (``held_notes``): a tool whose
run ends in a refused input shows the user that one error line alone and keeps its notes in its log
(``notes_held``). No Lightning, no torch.
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import os
import sys
import time

from .errors import BodySchemaInputError

_HELD: contextvars.ContextVar[list | None] = contextvars.ContextVar("lightning_bodyschema_notes", default=None)


def note(message: str) -> None:
    """One line for the user: on stderr, or into the notes held by ``held_notes``."""
    held = _HELD.get()
    if held is None:
        print(message, file=sys.stderr)
    else:
        held.append(message)


@contextlib.contextmanager
def held_notes():
    """Collect the notes made inside the block into the yielded list instead of printing them."""
    held: list[str] = []
    token = _HELD.set(held)
    try:
        yield held
    finally:
        _HELD.reset(token)


def notes_held(log_path):
    """Decorator for a tool's main (inside ``apps.common.exits_cleanly``): the notes made while it runs are held,
    then printed to stderr when it returns, or appended to the file ``log_path()`` names when a refused input
    (``BodySchemaInputError``) ends it, so that the error is the one line on stderr; any other exception prints
    them beside its traceback."""

    def decorate(main):
        @functools.wraps(main)
        def wrapper(argv=None):
            with held_notes() as notes:
                try:
                    result = main(argv)
                except BodySchemaInputError as err:
                    _log(log_path(), notes, err)
                    raise
                except BaseException:
                    _print(notes)
                    raise
            _print(notes)
            return result

        return wrapper

    return decorate


def _print(notes: list) -> None:
    for line in notes:
        print(line, file=sys.stderr)


def _log(path: str, notes: list, err: BaseException) -> None:
    """Append the run's command, notes and error to ``path`` (best effort: a log that cannot be written is skipped,
    the error line stays the user's answer)."""
    if not notes:
        return
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "a") as fh:
            fh.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(sys.argv)}\n"
                     + "".join(f"  note: {line}\n" for line in notes) + f"  error: {' '.join(str(err).split())}\n")
    except OSError:
        pass
