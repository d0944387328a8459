"""`trackfusion network import-osm`: a network file from an OpenStreetMap railway extract.

Reads the GeoJSON (or Overpass JSON) export, joins the ways into running lines by
:func:`track.osm.import_osm` (its docstring has the rules), writes the network file every
service reads (``--network``) and prints what was made and what was dropped, and why.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

from track.osm import MIN_LENGTH_M, RUNNING_SIDES, STATION_SNAP_M, import_osm, to_geojson


def main(
    in_path: str | Path,
    out_path: str | Path,
    *,
    keep_service: bool = False,
    railway_values: tuple[str, ...] = ("rail",),
    station_snap_m: float = STATION_SNAP_M,
    segment_length_m: float = 200.0,
    min_length_m: float = MIN_LENGTH_M,
    running: str | None = None,
    out: TextIO | None = None,
) -> int:
    """Import ``in_path`` into the network file ``out_path``; print the report; 0.

    ValueError naming the file (and the feature) when the input cannot be imported.
    """
    try:
        text = Path(in_path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(
            f"{in_path}: cannot read it as text ({exc}); for a .osm.pbf, convert it first "
            "with `osmium export` (README.md: A network from OpenStreetMap)"
        ) from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(
            f"{in_path}: not JSON ({exc}); expected GeoJSON from osmium export, ogr2ogr or "
            "overpass-turbo, or Overpass JSON"
        ) from None
    try:
        network, extra, report = import_osm(
            doc,
            keep_service=keep_service,
            railway_values=railway_values,
            station_snap_m=station_snap_m,
            segment_length_m=segment_length_m,
            min_length_m=min_length_m,
            running=running,
        )
    except ValueError as exc:
        raise ValueError(f"{in_path}: {exc}") from None
    try:
        Path(out_path).write_text(json.dumps(to_geojson(network, extra)) + "\n")
    except OSError as exc:
        raise ValueError(f"--out {out_path}: cannot write it ({exc})") from None
    out = out if out is not None else sys.stdout  # the stdout of now, not of the import
    print(report.text(), file=out)
    print(f"wrote {out_path}: trackfusion up --network {out_path}", file=out)
    return 0


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion network import-osm``."""
    parser.description = (
        "Join the railway=rail ways of an OpenStreetMap extract (GeoJSON of osmium export, "
        "ogr2ogr or overpass-turbo; or Overpass JSON) into lines, one per track, with "
        "tunnels, stations and speeds, and write the network file; print what was made "
        "and what was left out, and why."
    )
    parser.add_argument("input", metavar="IN", help="the OSM export (.geojson or .json)")
    parser.add_argument("--out", required=True, metavar="OUT.geojson", help="network file")
    parser.add_argument(
        "--keep-service",
        action="store_true",
        help="keep service=* ways (yards, sidings, spurs, crossovers); left out by default",
    )
    parser.add_argument(
        "--railway",
        default="rail",
        metavar="VALUES",
        help="railway=* values to keep, comma-separated (default %(default)s; e.g. "
        "rail,narrow_gauge where metre-gauge main lines are tagged so)",
    )
    parser.add_argument(
        "--station-snap-m",
        type=_positive,
        default=STATION_SNAP_M,
        metavar="M",
        help="a station farther than this from every line is dropped (default %(default)g)",
    )
    parser.add_argument(
        "--segment-length",
        type=_positive,
        default=200.0,
        metavar="M",
        help="segment length in m (default %(default)g)",
    )
    parser.add_argument(
        "--min-length",
        type=float,
        default=MIN_LENGTH_M,
        metavar="M",
        help="a joined line shorter than this is dropped (default %(default)g)",
    )
    parser.add_argument(
        "--running",
        choices=RUNNING_SIDES,
        default=None,
        help="the side trains keep to on double track (left: UK, France, Switzerland, Italy, "
        "Sweden, Japan, Australia...; right: Germany, Austria, the Netherlands, Spain, North "
        "America...): sets each track's running direction, by which GPS map matching tells "
        "the two tracks of a route apart. No default (a wrong guess would misplace every "
        "train silently): without it, trains with raw GPS on double track are not positioned",
    )


def run(args: argparse.Namespace) -> int:
    return main(
        args.input,
        args.out,
        keep_service=args.keep_service,
        railway_values=tuple(v.strip() for v in args.railway.split(",") if v.strip()),
        station_snap_m=args.station_snap_m,
        segment_length_m=args.segment_length,
        min_length_m=args.min_length,
        running=args.running,
    )
