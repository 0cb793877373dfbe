"""Notes: what the library tells a user about a choice it made for them (a joint it locked, muscles it left out).

``note(message)`` prints one line to stderr, unless an application holds the notes (``held_notes``): a tool whose
run ends in a refused input shows the user that one error line alone and keeps its notes in its log
(``apps.common.notes_held``). No Lightning, no torch.
"""
from __future__ import annotations

import contextlib
import contextvars
import sys

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
