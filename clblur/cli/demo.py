"""``clblur demo``: render the paper's Figure 3 and a Figure-4-like scene."""

from __future__ import annotations

import argparse
from pathlib import Path

from clblur.cli.options import add_backend_options, check_device

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser("demo", help="render the paper's Figure 3 and a Figure-4-like scene",
                       description="Render built-in scenes (no downloads) blurred "
                                   "conventionally and photo-consistently.")
    p.add_argument("--out", default="clblur-demo", metavar="DIR",
                   help="output folder (default: ./clblur-demo)")
    add_backend_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from clblur.demo import render

    check_device(args)
    for path in render(Path(args.out), backend=args.backend, device=args.device):
        print(f"wrote {path}")
    return 0
