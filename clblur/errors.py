"""The one error type for bad input.

``InputError`` means "the user gave something unusable": a missing or corrupt file, a path
outside its allowed folder, a value out of range.  The library raises it with a message that
names the problem; the command line (``clblur.cli.main``) prints it as one line,
``clblur: <message>``, and exits with code 2.  Anything else is a bug and keeps its traceback.

It subclasses ``ValueError`` so callers that catch ``ValueError`` keep working.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad input: a one-line message that names the file, option or value at fault."""
