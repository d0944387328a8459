"""`trackfusion …`: the command-line entry point.

Argument parsing lives here; every subcommand calls a ``main(conf, …)`` with explicit
arguments in its own module, imported lazily so that ``trackfusion --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trackfusion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    # --- router (services/runtime) -------------------------------------------------------
    from services.runtime.config import ROUTER_CONFIG, add_zenoh_arguments

    def _router(args: argparse.Namespace) -> int:
        from services.runtime import router
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        default = ROUTER_CONFIG if ROUTER_CONFIG.is_file() else None  # else built-in defaults
        return router.main(config_from_args(args, default_file=default, mode="router"))

    def _deadletters(args: argparse.Namespace) -> int:
        from services.runtime import deadletters
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        return deadletters.main(config_from_args(args))

    p = sub.add_parser(
        "router",
        help="run a Zenoh router (loopback :7447 by default)",
        description=f"Run a Zenoh router; --config defaults to {ROUTER_CONFIG}.",
    )
    add_zenoh_arguments(p, mode=False)
    p.set_defaults(func=_router)

    p = sub.add_parser(
        "deadletters",
        help="print every dead letter: service key reason",
        description="Subscribe to {ns}/deadletter/** and print one line per dead letter.",
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=_deadletters)

    # --- study (services/filtering/study.py) ---------------------------------------------
    def _study_frequency(args: argparse.Namespace) -> int:
        from services.filtering import study

        return study.main(
            args.config,
            as_json=args.json,
            plot_path=args.plot,
            paths=args.paths,
            seed=args.seed,
            progress=not args.no_progress and sys.stderr.isatty(),
        )

    study_parser = sub.add_parser("study", help="offline studies on the estimation core")
    studies = study_parser.add_subparsers(dest="study", required=True, metavar="STUDY")
    p = studies.add_parser(
        "frequency",
        help="credible-interval width against on-board measurement interval (paper 4.2)",
        description="Monte Carlo of the paper's section 4.2: prints a table like its Table 2.",
    )
    p.add_argument(
        "--config",
        default=str(Path(__file__).resolve().parents[1] / "deploy" / "study.json5"),
        help="study config (JSON5): scenarios, intervals, sizes (default: %(default)s)",
    )
    p.add_argument("--paths", type=int, help="Monte Carlo paths per scenario (config: 1000)")
    p.add_argument("--seed", type=int, help="random seed (config value by default)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--plot", metavar="FILE.png", help="draw W_k against time (like Fig. 7)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=_study_frequency)

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
