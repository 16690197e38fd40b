"""The ``clblur`` command line: the front of the library, never imported by it.

One module per command (``blur``, ``layers`` (``blur-layers``), ``info``, ``demo``,
``calibrate``, ``study``, ``psf``, ``batch``, ``video``), each with ``register(subparsers)`` (its
options) and ``run(args) -> int``, a thin wrapper around a library function; shared
options are in ``clblur.cli.options``.

Conventions
-----------
* Bad input is reported here, once: ``clblur.errors.InputError`` (and the ``ValueError`` /
  ``TypeError`` / file-system errors that library validation raises) becomes one line on
  stderr, ``clblur COMMAND: error: <message>``, and exit code 2.  Command-line syntax errors
  too (one line, no usage block).  Anything else is a bug and keeps its traceback.
* A library warning (e.g. no usable OpenCL device, the numpy reference used instead) is one
  line too: ``clblur COMMAND: warning: <message>``.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import sys
import warnings

from clblur.errors import InputError

__all__ = ["build_parser", "main"]

# imported lazily so `clblur info` stays fast
COMMAND_MODULES = ("blur", "layers", "info", "demo", "calibrate", "study", "psf", "batch",
                   "video")

# errors that mean "this input cannot be used", never "clblur is broken"
INPUT_ERRORS = (InputError, ValueError, TypeError, FileNotFoundError, FileExistsError,
                IsADirectoryError, NotADirectoryError, PermissionError)
# path faults that carry no OSError subclass of their own: a name longer than the file system
# takes, a symlink loop, a read-only file system named as the output
PATH_ERRNOS = (errno.ENAMETOOLONG, errno.ELOOP, errno.EROFS)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (the usage block would make it several)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="clblur",
                     description="Photo-consistent motion blur (Lin & Chang 2006).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"clblur.cli.{name}").register(sub)
    return parser


def one_line(error: BaseException) -> str:
    """An exception as one line (multi-line library messages are joined)."""
    text = " ".join(str(error).split())
    if isinstance(error, OSError) and error.filename and str(error.filename) not in text:
        text = f"{text}: {error.filename}"
    return text or type(error).__name__


def _one_line_warning(command: str):
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split()).removeprefix("clblur: ")
        print(f"clblur {command}: warning: {text}", file=sys.stderr if file is None else file)
    return show


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code (0 ok, 1 partial failure, 2 bad input)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help, or a syntax error already printed in one line
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    try:
        with warnings.catch_warnings():  # a library warning is one line too, named as ours
            warnings.showwarning = _one_line_warning(args.command)
            return int(args.func(args) or 0)
    except INPUT_ERRORS as e:
        print(f"clblur {args.command}: error: {one_line(e)}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno not in PATH_ERRNOS:
            raise
        print(f"clblur {args.command}: error: {one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"clblur {args.command}: interrupted", file=sys.stderr)
        return 130
