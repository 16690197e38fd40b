"""The error types for bad input.

``InputError`` means "the user gave something unusable": a missing or corrupt file, a path
outside its allowed folder, a value out of range.  The library raises it with a message that
names the problem; the command line (``clblur.cli.main``) prints it as one line,
``clblur COMMAND: error: <message>``, and exits with code 2.  Anything else is a bug and keeps
its traceback.

It subclasses ``ValueError`` so callers that catch ``ValueError`` keep working.
``InputTypeError`` is the ``InputError`` for input of the wrong type (a list for an image, an
int8 image, ``samples=2.5``); it is also a ``TypeError``.  Catch ``InputError`` for both.
"""

from __future__ import annotations

__all__ = ["InputError", "InputTypeError"]


class InputError(ValueError):
    """Bad input: a one-line message that names the file, option or value at fault."""


class InputTypeError(InputError, TypeError):
    """Bad input of the wrong type; still a ``TypeError`` for callers that catch that."""
