"""One exception type for bad user input, so the CLI and tools can exit 2 with one clear line."""


class BodySchemaInputError(ValueError):
    """Raised for input a user can fix: a bad model file, an unknown muscle, a NaN posture, ...

    The message names the bad value and what is allowed. Subclasses ``ValueError`` so library
    users can catch it the usual way.
    """


def did_you_mean(name, known) -> str:
    """`` (did you mean 'X'?)`` for the known name(s) closest to a misspelt one (a prefix of it first: ``BIClong``
    for ``BIClong_tendon``), else ``""``: for messages that then list every allowed name."""
    import difflib

    known = [str(k) for k in known]
    text = str(name)
    close = [k for k in known if k.lower().startswith(text.lower())][:2] if text else []
    close = close or difflib.get_close_matches(text, known, n=2, cutoff=0.6)
    return f" (did you mean {' or '.join(repr(k) for k in close)}?)" if close else ""
