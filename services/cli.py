"""`trackfusion …`: the command-line entry point.

Argument parsing lives here; every subcommand calls a ``main(conf, …)`` with explicit
arguments in its own module, imported lazily so that ``trackfusion --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trackfusion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    # --- router (services/runtime) -------------------------------------------------------
    # --- study (services/filtering/study.py) ---------------------------------------------

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
