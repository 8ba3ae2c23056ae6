"""The ``facecast`` command line: one argparse tree, one module per command.

Each module in ``facecast.cli.commands`` registers its own sub-parser and imports
its heavy dependencies only when run, so ``facecast --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from facecast import __version__
from facecast.cli.errors import CommandError

__all__ = ["COMMAND_MODULES", "CommandError", "build_parser", "limit_blas_threads", "main"]

# Order is the order shown by --help.
COMMAND_MODULES = (
    "demo",
    "expressions",
    "fit",
    "clone",
    "eval",
    "bench",
    "serve",
    "rigs",
    "stream",
    "publish",
    "perform",
    "track",
    "watch",
    "record",
    "loadtest",
    "bridge",
    "import_",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="facecast",
        description="Real-time example-based facial expression cloning.",
    )
    parser.add_argument("--version", action="version", version=f"facecast {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"facecast.cli.commands.{name}")
        module.register(sub)
    return parser


def limit_blas_threads() -> None:
    """One BLAS thread unless the user says otherwise, set before numpy loads.

    facecast's products are small (tens of rows) or memory-bound; a second BLAS thread only
    adds contention, and the server parallelises across connections instead.
    """
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")


def main(argv: Sequence[str] | None = None) -> int:
    limit_blas_threads()
    parser = build_parser()
    args = parser.parse_args(argv)
    from facecast.protocol.errors import ProtocolError
    from facecast.rig.errors import RigError

    handled = (CommandError, RigError, OSError, ProtocolError)
    try:
        result = args.func(args)
    except KeyboardInterrupt:
        print("facecast: interrupted", file=sys.stderr)
        return 130
    except handled as exc:
        print(f"facecast {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
