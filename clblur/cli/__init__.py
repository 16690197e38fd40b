"""The ``clblur`` command line: a thin dispatcher.

Each sub-command lives beside the code it drives and exposes ``register(subparsers)``, which
adds its parser and sets ``func(args) -> int``.  Bad input (``ValueError``/``TypeError`` from
the library) becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# (module, sub-commands it registers); imported lazily so `clblur info` stays fast.
COMMAND_MODULES = (
    "clblur.commands",   # blur, info
    "clblur.demo",       # demo
    "clblur.calibration.cli",  # calibrate
    "clblur.study.cli",  # study
    "clblur.batch",      # batch
    "clblur.video",      # video
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="clblur", description="Photo-consistent motion blur (Lin & Chang 2006).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, FileNotFoundError) as e:
        print(f"clblur {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"clblur {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
