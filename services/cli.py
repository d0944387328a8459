"""`trackfusion …`: the command-line entry point.

Each command declares its own arguments and how it runs, in its own module: a service in
its ``service.py`` (``add_arguments(parser)`` and ``run(args) -> int``, which calls the
module's ``main(conf, …)`` with explicit arguments), a tool in ``services/tools/``. This
module only lists them. A command's module is imported when that command is parsed, so
``trackfusion --help`` stays fast.

A ``ValueError`` out of a command (a configuration it cannot use: an unknown key, a file
that does not parse, a value out of range) ends the process with exit code 2 and one line
on stderr saying what to fix (with ``--log-level debug``, after its traceback).
"""

from __future__ import annotations

import argparse
import importlib
import sqlite3
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass

EXIT_USAGE = 2  # what argparse exits with on a bad command line; a bad config is one too
EXIT_IO = 74  # EX_IOERR: a file the command needs cannot be opened or written


@dataclass(frozen=True)
class Command:
    """A subcommand: its name and one-line help, and where it declares its arguments and
    ``run`` (``module:prefix``: ``{prefix}add_arguments`` and ``{prefix}run``; or
    ``subcommands``)."""

    name: str
    help: str
    declared_in: str = ""
    subcommands: tuple[Command, ...] = ()


COMMANDS = (
    Command("up", "run the whole system: embedded router, services, simulator, viewer",
            "services.tools.stack"),
    Command("router", "run a Zenoh router (loopback :7447 by default)", "services.tools.router"),
    Command("ingestion", "validate, correct and map-match raw bogie chunks: raw + GPS in, "
            "accel out", "services.ingestion.service"),
    Command("extraction", "turn positioned bogie accelerations into on-board Top6/Align10 "
            "indices", "services.extraction.service"),
    Command("calibration", "fit H, b, R and degradation posteriors from TRC records and "
            "on-board indices", "services.calibration.service"),
    Command("filtering", "run the per-segment filter bank: events in, SegmentState out",
            "services.filtering.service"),
    Command("alerting", "raise and clear alerts from segment states; answer q/alerts and "
            "q/plan", "services.alerting.service"),
    Command("planning", "plan tamping per segment and week from states and degradation models; "
            "answer q/plan/maintenance", "services.planning.service"),
    Command("viewer", "log states, indices, TRC records, alerts and trains to a Rerun viewer",
            "services.viewer.service"),
    Command("simulate", "publish a simulated fleet, TRC runs and maintenance on Zenoh",
            "simulators.run:simulate_"),
    Command("network", "network files", subcommands=(
        Command("generate", "generate a large random network as GeoJSON",
                "simulators.run:network_generate_"),
        Command("import-osm", "a network file from an OpenStreetMap railway extract (GeoJSON)",
                "services.tools.network_import"),
    )),
    Command("status", "which services are alive (liveliness tokens)",
            "services.tools.operator:status_"),
    Command("state", "state and forecast of a segment (LINE/SEGMENT)",
            "services.tools.operator:state_"),
    Command("alerts", "the alerts raised now", "services.tools.operator:alerts_"),
    Command("plan", "where to send the recording car (the planner's TRC runs by value of "
            "information; without a planner, alerting's segments most likely to exceed), or "
            "`plan maintenance`: the tamping plan",
            "services.tools.operator:plan_"),
    Command("import-trc", "publish a TRC export (CSV: line,segment,t,top6_mm,align10_mm,run_id) "
            "and wait until filtering holds it", "services.tools.trc_import"),
    Command("export", "export states or raised alerts as CSV or GeoJSON",
            "services.tools.operator:export_"),
    Command("report", "a self-contained HTML report for maintenance planners",
            "services.tools.report"),
    Command("deadletters", "print every dead letter: service key reason",
            "services.tools.deadletter_printer"),
    Command("study", "offline studies on the estimation core", subcommands=(
        Command("frequency", "credible-interval width against on-board measurement interval "
                "(paper 4.2)", "services.filtering.study"),
    )),
    Command("gateway", "tools for fleet gateway integrators", subcommands=(
        Command("check", "check a train's gateway traffic against the contract "
                "(schemas/README.md)", "services.tools.gateway_check"),
    )),
    Command("secure-config", "print the TLS + access-control router config for a fleet "
            "(JSON5)", "services.tools.security"),
)  # fmt: skip


class _DeclaredOnUse(argparse._SubParsersAction):
    """Subcommands whose arguments are declared when one of them is chosen."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.pending: dict[str, Callable[[], None]] = {}

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        declare = self.pending.pop(values[0], None)
        if declare is not None:
            declare()
        super().__call__(parser, namespace, values, option_string)


def _add_commands(parser: argparse.ArgumentParser, commands: tuple[Command, ...], dest: str):
    sub = parser.add_subparsers(dest=dest, required=True, metavar="COMMAND", action=_DeclaredOnUse)
    for command in commands:
        p = sub.add_parser(command.name, help=command.help, description=command.help)
        if command.subcommands:
            _add_commands(p, command.subcommands, f"{command.name}_command")
        else:
            sub.pending[command.name] = lambda p=p, c=command: _declare(p, c)
    return sub


def _declare(parser: argparse.ArgumentParser, command: Command) -> None:
    module_name, _, prefix = command.declared_in.partition(":")
    module = importlib.import_module(module_name)
    getattr(module, f"{prefix}add_arguments")(parser)
    parser.set_defaults(run=getattr(module, f"{prefix}run"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trackfusion", description=__doc__.splitlines()[0])
    _add_commands(parser, COMMANDS, "command")
    return parser


def _command_name(args: argparse.Namespace) -> str:
    """``gateway check`` for a subcommand, ``filtering`` for a command."""
    words = [args.command]
    while (word := getattr(args, f"{words[-1]}_command", None)) is not None:
        words.append(word)
    return " ".join(words)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except BrokenPipeError:  # `trackfusion alerts | head`: the reader has gone, not an error
        sys.stderr.close()
        return 0
    except ValueError as exc:  # what to fix, not where in the code it was found
        if getattr(args, "log_level", None) == "debug":
            traceback.print_exc()
        print(f"trackfusion {_command_name(args)}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (OSError, sqlite3.Error) as exc:  # a state file's path or disk: say which
        if getattr(args, "log_level", None) == "debug":
            traceback.print_exc()
        where = getattr(args, "db", None)  # SQLite's own messages name no file
        where = f"{where}: " if isinstance(exc, sqlite3.Error) and where else ""
        print(f"trackfusion {_command_name(args)}: {where}{exc}", file=sys.stderr)
        return EXIT_IO


if __name__ == "__main__":
    sys.exit(main())
