"""One exception type for bad user input, so the CLI and tools can exit 2 with one clear line."""


class BodySchemaInputError(ValueError):
    """Raised for input a user can fix: a bad model file, an unknown muscle, a NaN posture, ...

    The message names the bad value and what is allowed. Subclasses ``ValueError`` so library
    users can catch it the usual way.
    """
