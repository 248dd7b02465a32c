"""User-facing errors.

Anything a user can cause (a missing file, a corrupt PLY, a bad flag) raises
:class:`SsgwarpError` (or a subclass) with a one-line message that says what
was wrong and how to fix it. The CLI prints that line and exits with code 2;
``--debug`` shows the traceback. A Ctrl-C stays a ``KeyboardInterrupt``: the stages write their
checkpoint and re-raise it, and the CLI exits with code 130.
"""


class SsgwarpError(Exception):
    """An error caused by the user's input, reported as one line (exit code 2)."""


class InputError(SsgwarpError, ValueError):
    """Bad input data: missing or corrupt files, wrong shapes, NaN values."""


class WeightsNotFound(SsgwarpError):
    """Pretrained weights were asked for but are not on this machine."""
