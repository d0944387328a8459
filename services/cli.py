"""`trackfusion …`: the command-line entry point.

Argument parsing lives here; every subcommand calls a ``main(conf, …)`` with explicit
arguments in its own module, imported lazily so that ``trackfusion --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.defaults import default_file


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trackfusion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    # --- router (services/runtime) -------------------------------------------------------
    from services.runtime.config import ROUTER_CONFIG, add_zenoh_arguments

    def _router(args: argparse.Namespace) -> int:
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging
        from services.tools import router

        configure_logging(args.log_level)
        default = ROUTER_CONFIG if ROUTER_CONFIG.is_file() else None  # else built-in defaults
        return router.main(config_from_args(args, default_file=default, mode="router"))

    def _deadletters(args: argparse.Namespace) -> int:
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging
        from services.tools import deadletters

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

    # --- filtering (services/filtering/service.py) ----------------------------------------
    def _filtering(args: argparse.Namespace) -> int:
        from services.filtering import service as filtering
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        return filtering.main(
            config_from_args(args),
            selector=args.selector,
            db=args.db,
            limits=args.limits,
            network=args.network,
        )

    p = sub.add_parser(
        "filtering",
        help="run the per-segment filter bank: events in, SegmentState out",
        description="Filter every segment under --selector; state persisted in SQLite.",
    )
    p.add_argument(
        "--selector",
        metavar="KEYEXPR_SUFFIX",
        help="the part of the network this instance owns, e.g. 'L1/**' (default: **)",
    )
    p.add_argument(
        "--network",
        metavar="FILE.geojson",
        help="refuse events on segments this network does not have (default: accept any)",
    )
    p.add_argument(
        "--db",
        metavar="FILE",
        help="SQLite file of the accepted events and models "
        "(default: ./var/filtering-{instance}.sqlite, instance 'default' without --instance)",
    )
    p.add_argument(
        "--limits", metavar="FILE", help="limits file (default: services/defaults/limits.json5)"
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=_filtering)

    # --- calibration (services/calibration/service.py) -----------------------------------
    def _calibration(args: argparse.Namespace) -> int:
        from services.calibration import service as calibration
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        conf = config_from_args(args)
        settings = calibration.settings_from(
            conf.options(calibration.SERVICE),
            db=args.db,
            initial_models=args.initial_models,
            network=args.network,
            min_pairs=args.min_pairs,
            refit_every=args.refit_every,
            tolerance_days=args.tolerance_days,
            samples=args.samples,
            seed=args.seed,
        )
        return calibration.main(conf, settings)

    p = sub.add_parser(
        "calibration",
        help="fit H, b, R and degradation posteriors from TRC records and on-board indices",
        description="Pair TRC records with on-board indices, fit the observation model, build "
        "degradation posteriors per group, publish them on {ns}/model/**. Flags override the "
        "config file's services.calibration section.",
    )
    p.add_argument(
        "--db", type=Path, help="SQLite file (default: ./var/calibration-{instance}.sqlite)"
    )
    p.add_argument(
        "--initial-models",
        type=Path,
        metavar="FILE.json5",
        help="prior models published as version 1 until data gives better ones "
        "(e.g. services/defaults/initial-models.json5; default: none)",
    )
    p.add_argument(
        "--network",
        type=Path,
        metavar="FILE.geojson",
        help="refuse events on segments this network does not have (default: accept any)",
    )
    p.add_argument("--min-pairs", type=int, help="pairs before the first fit (default: 30)")
    p.add_argument("--refit-every", type=int, help="new pairs between refits (default: 10)")
    p.add_argument(
        "--tolerance-days",
        type=float,
        help="pair an index without run_id with a TRC record this close in time (default: 1)",
    )
    p.add_argument("--samples", type=int, help="posterior samples Ns (default: 200)")
    p.add_argument("--seed", type=int, help="seed of the posterior draws (default: 0)")
    add_zenoh_arguments(p)
    p.set_defaults(func=_calibration)

    # --- simulate, network (simulators/run.py) --------------------------------------------
    def _simulate(args: argparse.Namespace) -> int:
        from datetime import datetime

        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging
        from simulators import run

        configure_logging(args.log_level)
        try:
            start_t = datetime.fromisoformat(args.start).timestamp()
        except ValueError:
            raise SystemExit(f"--start {args.start!r}: not an ISO date, e.g. 2026-01-01") from None
        return run.main_simulate(
            config_from_args(args),
            network_path=args.network,
            trains=args.trains,
            days=args.days,
            speedup=args.speedup,
            fidelity=args.fidelity,
            seed=args.seed,
            start_t=start_t,
            truth_path=args.truth,
            config_path=args.sim_config,
            units=args.units,
            progress=not args.no_progress and sys.stderr.isatty(),
            from_day=args.from_day,
            to_day=args.to_day,
            linger_s=args.linger,
        )

    def _speedup(text: str) -> float:
        from simulators.run import parse_speedup

        try:
            return parse_speedup(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    p = sub.add_parser(
        "simulate",
        help="publish a simulated fleet, TRC runs and maintenance on Zenoh",
        description="Run the fleet simulator on a network and publish its gateways' raw data "
        "(--fidelity raw) or on-board indices (--fidelity index), TRC records and tamping.",
    )
    p.add_argument("--network", metavar="FILE.geojson", help="network (default: the demo)")
    p.add_argument(
        "--trains", type=int, default=6, help="raw: trains; index: passes per line per day"
    )
    p.add_argument("--days", type=float, default=1.0, help="simulated days (default 1)")
    p.add_argument("--speedup", type=_speedup, default=1.0, help="simulated s per wall s, or 'inf'")
    p.add_argument("--fidelity", choices=["raw", "index"], default="index")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--units", type=int, default=1, help="on-board units per train (raw)")
    p.add_argument(
        "--from-day", type=float, default=0.0, help="publish only from this day of the world"
    )
    p.add_argument("--to-day", type=float, help="publish only up to this day of the world")
    p.add_argument("--start", default="2026-01-01T00:00:00+00:00", help="ISO start time (UTC)")
    p.add_argument("--truth", metavar="FILE.sqlite", help="write the ground truth here")
    p.add_argument(
        "--sim-config", metavar="FILE.json5", help="default: services/defaults/simulator.json5"
    )
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "--linger",
        type=float,
        default=0.0,
        metavar="S",
        help="stay up S seconds after the last message, serving the per-key caches to "
        "subscribers that come back (default 0)",
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=_simulate)

    def _network_generate(args: argparse.Namespace) -> int:
        from simulators import run

        return run.main_network_generate(
            lines=args.lines,
            length_km=args.length_km,
            seed=args.seed,
            segment_length_m=args.segment_m,
            out=args.out,
        )

    network_parser = sub.add_parser("network", help="network files")
    networks = network_parser.add_subparsers(dest="network_command", required=True)
    p = networks.add_parser("generate", help="generate a large random network as GeoJSON")
    p.add_argument("--lines", type=int, default=40)
    p.add_argument("--length-km", type=float, default=50.0)
    p.add_argument("--segment-m", type=float, default=200.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", metavar="FILE.geojson", help="default: stdout")
    p.set_defaults(func=_network_generate)

    # --- up (services/tools/stack.py) -------------------------------------------------------------
    def _up(args: argparse.Namespace) -> int:
        from services.runtime.service import configure_logging
        from services.tools import stack

        configure_logging(args.log_level)
        return stack.main(args.stack, ns=args.ns, listen=args.listen)

    p = sub.add_parser(
        "up",
        help="run the whole system: embedded router, services, simulator, viewer",
        description="Start everything of the stack file with a live status table; Ctrl-C "
        "stops it all.",
    )
    p.add_argument(
        "--stack",
        default=str(default_file("stack.json5")),
        help="stack file (default: %(default)s)",
    )
    p.add_argument("--ns", help="namespace (stack file's by default)")
    p.add_argument("--listen", metavar="ENDPOINT", help="router endpoint (stack file's)")
    p.add_argument("--log-level", default="warning", choices=["debug", "info", "warning"])
    p.set_defaults(func=_up)

    # --- operator commands (services/tools/operator.py) ------------------------------------------
    def _operator(command: str):
        def run(args: argparse.Namespace) -> int:
            from services.runtime.config import config_from_args
            from services.tools import operator

            conf = config_from_args(args)
            match command:
                case "status":
                    return operator.main_status(conf, args.timeout)
                case "state":
                    return operator.main_state(conf, args.segment, args.timeout)
                case "alerts":
                    return operator.main_alerts(conf, args.timeout)
                case "plan":
                    return operator.main_plan(conf, args.limit, args.timeout)
                case "import-trc":
                    return operator.main_import_trc(conf, args.file)
                case "export":
                    return operator.main_export(
                        conf, args.what, args.format, args.network, args.timeout
                    )
            raise AssertionError(command)

        return run

    def _seconds(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not value > 0 or value == float("inf"):
            raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
        return value

    def add_timeout_argument(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--timeout",
            type=_seconds,
            default=10.0,  # services.tools.operator.QUERY_TIMEOUT_S (not imported: --help's speed)
            metavar="S",
            help="seconds to wait for the whole answer (default: %(default)g)",
        )

    p = sub.add_parser("status", help="which services are alive (liveliness tokens)")
    add_zenoh_arguments(p, mode=False)
    add_timeout_argument(p)
    p.set_defaults(func=_operator("status"))
    p = sub.add_parser("state", help="state and forecast of a segment (LINE/SEGMENT)")
    p.add_argument("segment", metavar="LINE/SEGMENT", help="e.g. L1/s00042, or L1/** for a line")
    add_zenoh_arguments(p, mode=False)
    add_timeout_argument(p)
    p.set_defaults(func=_operator("state"))
    p = sub.add_parser("alerts", help="the alerts raised now")
    add_zenoh_arguments(p, mode=False)
    add_timeout_argument(p)
    p.set_defaults(func=_operator("alerts"))
    p = sub.add_parser("plan", help="the TRC inspection plan: segments most likely to exceed")
    p.add_argument("--limit", type=int, default=20, help="rows to show (default 20)")
    add_zenoh_arguments(p, mode=False)
    add_timeout_argument(p)
    p.set_defaults(func=_operator("plan"))
    p = sub.add_parser(
        "import-trc",
        help="publish a TRC export (CSV: line,segment,t,top6_mm,align10_mm,run_id)",
        description="Publish every good row of a TRC CSV export as a TrcRecord; bad rows are "
        "reported with their line numbers (exit code 1 when there were any).",
    )
    p.add_argument("file", metavar="FILE.csv")
    add_zenoh_arguments(p, mode=False)
    p.set_defaults(func=_operator("import-trc"))
    p = sub.add_parser("export", help="export states or raised alerts as CSV or GeoJSON")
    p.add_argument("what", choices=["states", "alerts"])
    p.add_argument("--format", choices=["csv", "geojson"], default="csv")
    p.add_argument("--network", metavar="FILE.geojson", help="geometry (default: the demo)")
    add_zenoh_arguments(p, mode=False)
    add_timeout_argument(p)
    p.set_defaults(func=_operator("export"))

    # --- report (services/tools/report.py) -----------------------------------------------------
    def _report(args: argparse.Namespace) -> int:
        from services.runtime.config import config_from_args
        from services.tools import report

        return report.main(
            config_from_args(args),
            out_path=args.out,
            line=args.line,
            network_path=args.network,
            worst_n=args.worst,
            timeout=args.timeout,
        )

    p = sub.add_parser(
        "report",
        help="a self-contained HTML report for maintenance planners",
        description="Map, ranked segments, forecast fans and open alerts in one HTML file "
        "(inline CSS and SVG, no external resource).",
    )
    p.add_argument("--line", help="one line (default: all lines)")
    p.add_argument("--out", default="report.html", metavar="FILE.html", help="(%(default)s)")
    p.add_argument("--network", metavar="FILE.geojson", help="geometry (default: the demo)")
    p.add_argument("--worst", type=int, default=6, metavar="N", help="fans drawn (%(default)s)")
    add_zenoh_arguments(p, mode=False)
    add_timeout_argument(p)
    p.set_defaults(func=_report)

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
        default=str(default_file("study.json5")),
        help="study config (JSON5): scenarios, intervals, sizes (default: %(default)s)",
    )
    p.add_argument("--paths", type=int, help="Monte Carlo paths per scenario (config: 1000)")
    p.add_argument("--seed", type=int, help="random seed (config value by default)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--plot", metavar="FILE.png", help="draw W_k against time (like Fig. 7)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=_study_frequency)

    # --- alerting (services/alerting) ----------------------------------------------------
    def _alerting(args: argparse.Namespace) -> int:
        from services.alerting import service as alerting
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        return alerting.main(
            config_from_args(args),
            alerting_config=args.config_alerting,
            limits=args.limits,
            db=args.db,
        )

    p = sub.add_parser(
        "alerting",
        help="raise and clear alerts from segment states; answer q/alerts and q/plan",
        description="Subscribe to {ns}/state/** and {ns}/trc/**, publish Alerts on "
        "{ns}/alert/{line}/{segment}, answer {ns}/q/alerts and {ns}/q/plan.",
    )
    p.add_argument(
        "--config-alerting",
        metavar="FILE",
        type=Path,
        default=default_file("alerting.json5"),
        help="alerting thresholds, JSON5 (default: %(default)s)",
    )
    p.add_argument(
        "--limits",
        metavar="FILE",
        type=Path,
        default=default_file("limits.json5"),
        help="alert and intervention limits per line, JSON5 (default: %(default)s)",
    )
    p.add_argument(
        "--db",
        metavar="FILE",
        type=Path,
        help="SQLite file of the raised alerts (default: ./var/alerting-{instance}.sqlite, "
        "'default' when --instance is not given)",
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=_alerting)

    # --- ingestion (services/ingestion/service.py) ---------------------------------------
    def _ingestion(args: argparse.Namespace) -> int:
        from services.ingestion import service as ingestion
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        return ingestion.main(config_from_args(args), network_path=args.network)

    p = sub.add_parser(
        "ingestion",
        help="validate, correct and map-match raw bogie chunks: raw + GPS in, accel out",
        description="Subscribe to {ns}/raw/** and {ns}/gps/*, publish PositionedChunks on "
        "{ns}/accel/{train}/{unit}; thresholds in the config file's services.ingestion.",
    )
    p.add_argument(
        "--network",
        metavar="FILE.geojson",
        type=Path,
        default=default_file("demo-network.geojson"),
        help="network to map-match on (default: %(default)s)",
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=_ingestion)

    # --- viewer (services/viewer/service.py) -----------------------------------------------
    def _viewer(args: argparse.Namespace) -> int:
        import os

        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging
        from services.viewer import service as viewer

        configure_logging(args.log_level)
        if args.action == "select":  # a tool: tell the running viewer, then exit
            if args.segment is None:
                raise SystemExit("viewer select: which segment? e.g. viewer select L1/s00042")
            try:
                return viewer.main_select(config_from_args(args), args.segment)
            except ValueError as exc:
                raise SystemExit(f"viewer select: {exc}") from None
        ports = {"web_port": args.web_port, "grpc_port": args.grpc_port}
        if args.rrd is not None:
            sink = viewer.Sink("rrd", path=args.rrd, **ports)
        elif args.web:
            sink = viewer.Sink("web", **ports)
        elif args.spawn:
            sink = viewer.Sink("spawn", **ports)
        else:  # the environment is read here, at the edge, and passed down
            sink = viewer.default_sink(os.environ, **ports)
        return viewer.main(
            config_from_args(args),
            args.network,
            sink,
            worst_n=args.worst,
        )

    p = sub.add_parser(
        "viewer",
        help="log states, indices, TRC records, alerts and trains to a Rerun viewer",
        description="Subscribe to {ns}/state/**, index/**, trc/**, alert/** and gps/* (dropping "
        "the oldest when behind) and log them to Rerun on the event_time timeline. Default "
        "sink: the native viewer when DISPLAY/WAYLAND_DISPLAY is set, else the web viewer "
        "(its URL is printed on stdout).",
    )
    p.add_argument(
        "--network",
        metavar="FILE.geojson",
        type=Path,
        default=default_file("demo-network.geojson"),
        help="the map (default: %(default)s)",
    )
    viewer_sink = p.add_mutually_exclusive_group()
    viewer_sink.add_argument(
        "--rrd", metavar="FILE", type=Path, help="save the recording to FILE (headless)"
    )
    viewer_sink.add_argument(
        "--web", action="store_true", help="serve the web viewer and print its URL on stdout"
    )
    viewer_sink.add_argument("--spawn", action="store_true", help="start the native viewer")
    p.add_argument("--web-port", type=int, default=9090, help="web viewer HTTP port (%(default)s)")
    p.add_argument(
        "--grpc-port", type=int, default=9876, help="Rerun gRPC log stream port (%(default)s)"
    )
    p.add_argument(
        "--worst", type=int, default=3, help="worst segments plotted beside the map (%(default)s)"
    )
    p.add_argument(
        "action",
        nargs="?",
        choices=["select"],
        help="select LINE/SEGMENT: plot that segment in the running viewer's selected row",
    )
    p.add_argument("segment", nargs="?", metavar="LINE/SEGMENT", help="e.g. L1/s00042")
    add_zenoh_arguments(p)
    p.set_defaults(func=_viewer)

    # --- extraction (services/extraction/service.py) -------------------------------------
    def _extraction(args: argparse.Namespace) -> int:
        from services.extraction import service as extraction
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging

        configure_logging(args.log_level)
        return extraction.main(config_from_args(args), network_path=args.network)

    p = sub.add_parser(
        "extraction",
        help="turn positioned bogie accelerations into on-board Top6/Align10 indices",
        description="Subscribe to {ns}/accel/** (PositionedChunk), publish one OnboardIndex per "
        "segment pass on {ns}/index/{line}/{segment}.",
    )
    p.add_argument(
        "--network",
        metavar="FILE",
        type=Path,
        help="network GeoJSON with the segment bounds "
        "(default: services/defaults/demo-network.geojson)",
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=_extraction)

    # --- gateway check (services/tools/gateway_check.py) ----------------------------------------
    def _gateway_check(args: argparse.Namespace) -> int:
        from services.runtime.config import config_from_args
        from services.runtime.service import configure_logging
        from services.tools import gateway_check

        configure_logging(args.log_level)
        return gateway_check.main(config_from_args(args), args.train, args.seconds)

    gateway_parser = sub.add_parser("gateway", help="tools for fleet gateway integrators")
    gateways = gateway_parser.add_subparsers(dest="gateway_command", required=True)
    p = gateways.add_parser(
        "check",
        help="check a train's gateway traffic against the contract (schemas/README.md)",
        description="Subscribe to {ns}/raw/TRAIN/**, {ns}/gps/TRAIN and ingestion's dead "
        "letters for S seconds (or until Ctrl-C), check every message as ingestion does and "
        "print a report. Exit code 0 clean, 1 deviations found, 2 nothing arrived.",
    )
    p.add_argument("--train", required=True, help="the train id the gateway publishes as")
    p.add_argument("--seconds", type=float, metavar="S", help="how long (default: until Ctrl-C)")
    add_zenoh_arguments(p)
    p.set_defaults(func=_gateway_check)

    # --- secure-config (services/tools/security.py) ------------------------------------
    def _secure_config(args: argparse.Namespace) -> int:
        from services.tools import security

        trains = [t.strip() for t in args.trains.split(",") if t.strip()]
        if not trains:
            raise SystemExit("--trains: give at least one train id, e.g. --trains T001,T002")
        command = (
            f"trackfusion secure-config --trains {','.join(trains)} --ns {args.ns} "
            f"--certs {args.certs} --listen {args.listen}"
        )
        try:
            text = security.main(args.ns, trains, args.certs, args.listen, command)
        except ValueError as exc:
            raise SystemExit(f"secure-config: {exc}") from None
        sys.stdout.write(text)
        return 0

    p = sub.add_parser(
        "secure-config",
        help="print the TLS + access-control router config for a fleet (JSON5)",
        description="Print a router configuration that accepts only mutual-TLS clients and "
        "lets each one (by certificate common name) use only its keys: gateway-{train} its "
        "own raw and gps keys, each service what it needs. See deploy/SECURITY.md.",
    )
    p.add_argument(
        "--trains", required=True, metavar="T1,T2,…", help="the fleet's train ids, comma-separated"
    )
    p.add_argument("--ns", default="tf", help="key namespace (default: %(default)s)")
    p.add_argument(
        "--certs",
        required=True,
        type=Path,
        metavar="DIR",
        help="directory of ca.pem, router.pem and router-key.pem as the router will see it",
    )
    p.add_argument(
        "--listen", default="tls/0.0.0.0:7447", help="TLS endpoint (default: %(default)s)"
    )
    p.set_defaults(func=_secure_config)

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # `trackfusion alerts | head`: the reader has gone, not an error
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
