"""A network from an OpenStreetMap railway extract: ways joined into running lines.

Input is what the usual tools export, read by :mod:`track.osm_read`: ways with their tags,
and station points.

The rules, in order:

1. **Which ways.** ``railway=rail`` ways are kept (``railway_values``: also e.g.
   ``narrow_gauge``, as metre-gauge main lines are tagged in some countries); any
   ``service=*`` (yard, siding, spur, crossover) is left out unless ``keep_service``; every
   other way is dropped with its reason (``railway=tram``, ``railway=abandoned``, ``no
   railway tag``, ...).
2. **Joining.** Ways join at shared end nodes (node ids when the input has them, else
   coordinates rounded to 1e-7 degree) when they are of the same route (``ref``, else
   ``name``) and their ``railway:track_ref`` agrees (equal, or either untagged; a joined
   line keeps the first track ref it meets). A way drawn the other way round is reversed.
   Where more than two ways meet, the walk goes on with the one of the line's own track
   ref, else the straightest, never turning 90 degrees or more (:func:`join_ways`). So a
   double-track route gives one line per track: by ``railway:track_ref``, or, without it,
   because the two tracks are not joined end to end (crossovers are ``service=*``).
3. **Direction.** A joined line runs west to east (south to north when its ends have the
   same longitude), so both tracks of a route share their chainage direction.
4. **Too short.** A joined line shorter than ``min_length_m`` (100 m) is dropped.
5. **Ids.** ``slug(ref or name)``, then ``-t{track_ref}`` if tagged, then ``-2``, ``-3``
   ... for further lines with the same id; ``way{n}`` when the way has neither ref nor
   name. Ids are safe key chunks and, for the same input, the same.
   **Names** (the line's ``name``, what the viewer, the report and the CLI show) are the
   operators' (:func:`line_name`): the name (else ref) of the ``route=railway`` relation
   of most of the line's length, else its ways' ``name``, else a ``route=train``
   relation's (a service, which may run over several lines), else the ways' ``ref``, else
   the first and last station along it ("Sanremo – Albenga"); then ", track
   {railway:track_ref}" when tagged.
6. **Tunnels and bridges.** The chainage ranges of ways with ``tunnel`` (``bridge``) other
   than ``no``, merged where they touch: tunnels are GNSS outages; bridges are a property.
7. **Stations.** Points with ``railway=station|halt|stop``, or ``public_transport=
   stop_position`` unless tagged for another mode only (bus, tram, ...), become stations of
   every line within ``station_snap_m`` (150 m) — both tracks of a route stop there. On one
   line, a station of the same name within ``2 * station_snap_m`` of one already there is
   the same station (a station node and its stop positions). A point far from every line
   is dropped.
8. **Speed.** ``maxspeed`` is read as km/h (``"100"``, ``"100 km/h"``), mph (``"60 mph"``)
   or knots; ``none``, ``signals``, country codes and the like are unknown; of a list
   (``"80;100"``) the lowest counts. A line's ``line_speed_mps`` is the length-weighted
   median of its ways' known speeds, ``default_speed_mps`` when none is known.
9. **Routes and running.** The lines of one route (the same ``ref``, else ``name``) when it
   has several get the same ``route`` (the slug of it). Two tracks of a route drawn side
   by side get ``running`` from the side trains keep to (``running="left"`` or
   ``"right"``, :func:`running_of_pair`): with left-hand running the track on the left of
   a train moving towards increasing chainage carries that direction (``"increasing"``),
   the other ``"decreasing"``. There is no default side: it is a fact about the country
   (left in the UK, France, Switzerland, Italy, Sweden, Japan, Australia...; right in
   Germany, Austria, the Netherlands, Spain, North America, China...), and a wrong guess
   would put every raw-GPS train on the other track without a sign, where no guess leaves
   them visibly unpositioned. Without it, and on routes of one or more than two tracks,
   ``running`` stays ``"both"``.
10. **Warnings.** An extract reaching farther than 200 km from its centre (the local metric
   plane's range), a line without any known speed, and tracks of one route closer than
   10 m to each other (:func:`close_tracks_warnings`: GPS map matching tells them apart
   only by their running direction, so they need ``running``).

Pure: parsed JSON in, a :class:`~track.network.Network`, the extra line properties and an
:class:`ImportReport` out. ``trackfusion network import-osm`` (``services/tools/
network_import.py``) reads and writes the files.
"""

from __future__ import annotations

import math
import re
import unicodedata
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from track.network import Line, Network, lonlat_to_xy
from track.osm_read import OsmPoint, OsmWay, read_osm

MIN_LENGTH_M = 100.0  # a joined line shorter than this is dropped
STATION_SNAP_M = 150.0  # a station this far from every line is dropped
DEFAULT_SPEED_MPS = 25.0  # a line without any known maxspeed (90 km/h)
PARALLEL_M = 10.0  # ingestion's ambiguity_m: GPS map matching cannot tell lines this close
CLOSE_STEP_M = 200.0  # along-track step of that check
SIDE_BY_SIDE_M = 50.0  # two tracks of a route this close are a double track (running)
RUNNING_SIDES = ("left", "right")
PLANE_RADIUS_M = 200e3  # track.network's projection is good within about this of the origin
STATION_RAILWAY = ("station", "halt", "stop")
NON_TRAIN_MODES = ("bus", "tram", "trolleybus", "share_taxi", "ferry", "light_rail", "subway")
COORD_DIGITS = 7  # end nodes with coordinates equal at this many decimals are one node
KMH = 1 / 3.6
MPH = 1609.344 / 3600
KNOT = 1852 / 3600


@dataclass
class ImportedLine:
    """What became of one joined line (for the report)."""

    id: str
    name: str
    ways: list[str]
    length_m: float
    segments: int
    tunnels: int
    stations: int
    speed_mps: float
    speed_known: bool


@dataclass
class ImportReport:
    """What was made, what was dropped and why (reason -> OSM ids), and warnings."""

    lines: list[ImportedLine] = field(default_factory=list)
    dropped: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))
    warnings: list[str] = field(default_factory=list)
    ways_read: int = 0
    points_read: int = 0

    def drop(self, reason: str, osm_id: str) -> None:
        self.dropped[reason].append(osm_id)

    def text(self, max_ids: int = 8, max_lines: int = 50) -> str:
        """The report as lines of text for an operator (the first ``max_lines`` lines, the
        first ``max_ids`` ids of each reason)."""
        km = sum(line.length_m for line in self.lines) / 1e3
        out = [
            f"read {self.ways_read} ways and {self.points_read} points",
            f"made {len(self.lines)} lines, {km:.1f} km, "
            f"{sum(line.segments for line in self.lines)} segments, "
            f"{sum(line.tunnels for line in self.lines)} tunnels, "
            f"{sum(line.stations for line in self.lines)} stations",
        ]
        for line in self.lines[:max_lines]:
            speed = f"{line.speed_mps * 3.6:.0f} km/h" + ("" if line.speed_known else " (default)")
            out.append(
                f"  {line.id:<20} {line.name[:30]:<30} {line.length_m / 1e3:7.2f} km "
                f"{line.segments:5d} segments {line.tunnels:3d} tunnels "
                f"{line.stations:3d} stations {speed:>17}  {len(line.ways)} ways"
            )
        if len(self.lines) > max_lines:
            out.append(f"  ... and {len(self.lines) - max_lines} more lines")
        if self.dropped:
            n = sum(len(ids) for ids in self.dropped.values())
            out.append(f"dropped {n}:")
            for reason, ids in sorted(self.dropped.items(), key=lambda kv: (-len(kv[1]), kv[0])):
                more = f" (+{len(ids) - max_ids} more)" if len(ids) > max_ids else ""
                out.append(f"  {len(ids):5d}  {reason}: {' '.join(ids[:max_ids])}{more}")
        out += [f"warning: {w}" for w in self.warnings]
        return "\n".join(out)


# --- tags ---------------------------------------------------------------------------------


def parse_maxspeed(value: str | None) -> float | None:
    """``maxspeed`` in m/s, None when unknown (``none``, ``signals``, ``DE:rural``, ...).

    A bare number is km/h; ``mph`` and ``knots`` units are understood; of a list
    (``"80;100"``) the lowest counts.
    """
    if value is None:
        return None
    speeds = []
    for part in str(value).split(";"):
        m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(km/h|kmh|kph|mph|knots)?\s*", part.lower())
        if m:
            factor = {"mph": MPH, "knots": KNOT}.get(m.group(2) or "", KMH)
            speeds.append(float(m.group(1)) * factor)
    speeds = [s for s in speeds if s > 0]
    return min(speeds) if speeds else None


def _yes(value: str | None) -> bool:
    return value is not None and value.lower() not in ("no", "false", "0")


def slug(text: str) -> str:
    """A safe key chunk of a name: ASCII letters, digits, ``_ . -``."""
    ascii_text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", ascii_text).strip("-.")


def route_of(tags: Mapping[str, str]) -> str:
    """Ways of the same route (``ref``, else ``name``) may join."""
    return tags.get("ref") or tags.get("name") or ""


def track_of(tags: Mapping[str, str]) -> str:
    """The way's ``railway:track_ref`` (``""``: untagged, joins any track of its route)."""
    return tags.get("railway:track_ref") or ""


def _why_dropped(tags: Mapping[str, str], keep_service: bool, railway_values) -> str | None:
    railway = tags.get("railway")
    if railway is None:
        return "no railway tag"
    if railway not in railway_values:
        return f"railway={railway}"
    if "service" in tags and not keep_service:
        return f"service={tags['service']} (yards and sidings: --keep-service to keep them)"
    return None


def _station_reason(tags: Mapping[str, str]) -> str | None:
    """None if the point is a station for trains, else why it is not."""
    if tags.get("railway") in STATION_RAILWAY:
        return None
    if tags.get("public_transport") == "stop_position":
        if _yes(tags.get("train")) or not any(_yes(tags.get(m)) for m in NON_TRAIN_MODES):
            return None
        return "stop_position of another mode than train"
    return "not a station (railway=station|halt|stop or public_transport=stop_position)"


# --- joining ------------------------------------------------------------------------------


@dataclass
class _Chain:
    key: tuple[str, str]
    pieces: list[tuple[OsmWay, bool]]  # (way, reversed)

    def lonlat(self) -> np.ndarray:
        parts = [w.lonlat[::-1] if rev else w.lonlat for w, rev in self.pieces]
        return np.concatenate([parts[0], *[p[1:] for p in parts[1:]]])


def _ends(way: OsmWay, by_node: bool) -> tuple:
    if by_node and way.end_nodes is not None:
        return way.end_nodes
    a, b = np.round(way.lonlat[[0, -1]], COORD_DIGITS)
    return (tuple(a), tuple(b))


def _direction(lonlat: np.ndarray) -> np.ndarray:
    """Unit vector (east, north) from the first vertex to the next distinct one, locally
    scaled."""
    moved = np.flatnonzero((lonlat[1:] != lonlat[0]).any(axis=1))
    if not len(moved):
        return np.zeros(2)
    d = (lonlat[moved[0] + 1] - lonlat[0]) * (math.cos(math.radians(lonlat[0, 1])), 1.0)
    return d / float(np.hypot(*d))


def join_ways(ways: list[OsmWay]) -> list[_Chain]:
    """Chains of ways of one route joined end to end (rules 2 and 3).

    A chain is walked from an end node no other way of its route shares (a terminus), then
    from junctions, then what is left (rings). At each end node it goes on with an unused
    way of its route that turns less than 90 degrees and whose track ref agrees (equal, or
    either untagged), preferring the chain's own track ref, then the straightest. A chain
    takes the first track ref it meets: untagged open line joins the numbered tracks of a
    station, and the two tracks of a route never cross over to each other on it.
    """
    by_node = bool(ways) and all(w.end_nodes is not None for w in ways)
    groups: dict[str, list[OsmWay]] = defaultdict(list)
    for w in ways:
        groups[route_of(w.tags)].append(w)
    chains = []
    for route, members in groups.items():
        ends = [_ends(w, by_node) for w in members]
        tracks = [track_of(w.tags) for w in members]
        touching: dict[tuple, list[int]] = defaultdict(list)
        for i, (a, b) in enumerate(ends):
            touching[a].append(i)
            touching[b].append(i)
        used = [False] * len(members)
        degree = [[len(touching[node]) for node in pair] for pair in ends]
        starts = [(i, rev) for i in range(len(members)) for rev in (False, True)]
        starts.sort(key=lambda s: {1: 0, 2: 2}.get(degree[s[0]][s[1]], 1))  # stable
        for first, first_rev in starts:
            if used[first]:
                continue
            used[first] = True
            track = tracks[first]
            pieces = [(first, first_rev)]
            while True:
                i, rev = pieces[-1]
                node = ends[i][0] if rev else ends[i][1]
                arriving = -_direction(members[i].lonlat[::-1] if not rev else members[i].lonlat)
                best, best_rank = None, (2, math.pi / 2)
                for j in touching[node]:
                    if used[j] or (track and tracks[j] and tracks[j] != track):
                        continue
                    rev_j = ends[j][0] != node
                    leaving = _direction(members[j].lonlat[::-1] if rev_j else members[j].lonlat)
                    turn = math.acos(float(np.clip(arriving @ leaving, -1.0, 1.0)))
                    rank = (0 if track and tracks[j] == track else 1, turn)
                    if turn < math.pi / 2 and rank < best_rank:
                        best, best_rank = (j, rev_j), rank
                if best is None:
                    break
                used[best[0]] = True
                pieces.append(best)
                track = track or tracks[best[0]]
            chain = _Chain((route, track), [(members[i], rev) for i, rev in pieces])
            ll = chain.lonlat()
            if tuple(ll[-1]) < tuple(ll[0]):  # west to east, else south to north
                chain = _Chain(chain.key, [(w, not r) for w, r in reversed(chain.pieces)])
            chains.append(chain)
    return chains


def _ranges(chainage: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Sorted ranges with touching ones merged."""
    merged: list[list[float]] = []
    for a, b in sorted(chainage):
        if merged and a <= merged[-1][1] + 1e-6:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return [(float(a), float(b)) for a, b in merged]


def _weighted_median(values: list[float], weights: list[float]) -> float:
    order = np.argsort(values)
    v, w = np.asarray(values)[order], np.asarray(weights)[order]
    c = np.cumsum(w)
    return float(v[np.searchsorted(c, 0.5 * c[-1])])


# --- the import ---------------------------------------------------------------------------


def import_osm(
    obj,
    *,
    keep_service: bool = False,
    railway_values: tuple[str, ...] = ("rail",),
    station_snap_m: float = STATION_SNAP_M,
    segment_length_m: float = 200.0,
    min_length_m: float = MIN_LENGTH_M,
    default_speed_mps: float = DEFAULT_SPEED_MPS,
    running: str | None = None,
) -> tuple[Network, dict[str, dict], ImportReport]:
    """A network of a parsed OSM export (module docstring: the rules).

    Returns
    -------
    network : Network
        Lines with ``name`` and ``station_names``, in a stable order (by id).
    extra : dict
        Further properties of each line's feature by line id: ``ref``, ``track_ref``,
        ``bridges`` ([[start_m, end_m], ...]) and ``osm_ways``.
    report : ImportReport
    """
    if running is not None and running not in RUNNING_SIDES:
        raise ValueError(f"running: the side trains keep to, left or right, got {running!r}")
    if not station_snap_m > 0 or not segment_length_m > 0 or not min_length_m >= 0:
        raise ValueError("station snap and segment length must be > 0, min length >= 0")
    report = ImportReport()
    ways, points, other = read_osm(obj)
    report.ways_read, report.points_read = len(ways), len(points)
    for reason, osm_id in other:
        report.drop(reason, osm_id)
    chains = join_ways(_railway_ways(ways, keep_service, railway_values, report))
    if not chains:
        kept_text = "|".join(railway_values)
        raise ValueError(
            f"no railway={kept_text} way to make a line of (is it an OSM railway export?)"
        )
    origin = _origin(chains, report)
    made = _named_chains(chains, origin, min_length_m, report)
    probes = {m[0]: Line(m[0], m[2], origin, segment_length_m=segment_length_m) for m in made}
    on_line = _snap_stations(points, probes, origin, station_snap_m, report)
    route_of_line, running_of_line = _routes(made, probes, running)
    lines, extra = {}, {}
    for line_id, chain, ll, bounds in sorted(made, key=lambda m: m[0]):
        line, extra[line_id], known = _line(
            line_id,
            chain,
            ll,
            bounds,
            probes[line_id].length_m,
            _stations(on_line[line_id], station_snap_m, probes[line_id].length_m),
            default_speed_mps,
            origin_lonlat=origin,
            segment_length_m=segment_length_m,
            route=route_of_line.get(line_id, ""),
            running=running_of_line.get(line_id, "both"),
        )
        lines[line_id] = line
        ways_of_line = [w.id for w, _ in chain.pieces]
        report.lines.append(
            ImportedLine(
                line_id,
                line.name,
                ways_of_line,
                line.length_m,
                len(line.segments),
                len(line.tunnels),
                len(line.stations),
                line.line_speed_mps,
                known,
            )
        )
        if not known:
            report.warnings.append(
                f"line {line_id}: no maxspeed on any of its ways; "
                f"{default_speed_mps * 3.6:.0f} km/h assumed"
            )
    if not lines:
        raise ValueError(
            f"no line of at least {min_length_m:g} m could be joined from the railway=rail ways"
        )
    report.warnings += close_tracks_warnings(lines)
    return Network(lines, segment_length_m, origin), extra, report


def _railway_ways(
    ways: list[OsmWay], keep_service: bool, railway_values, report: ImportReport
) -> list[OsmWay]:
    """The ways lines are made of; the others dropped into ``report`` with the reason."""
    kept = []
    for w in ways:
        reason = _why_dropped(w.tags, keep_service, railway_values)
        if reason is None and len(w.lonlat) < 2:
            reason = "a way of fewer than 2 points"
        if reason:
            report.drop(reason, w.id)
        else:
            kept.append(w)
    return kept


def _origin(chains: list[_Chain], report: ImportReport) -> tuple[float, float]:
    """The centre of the extract, the network's origin; a warning when the extract reaches
    farther from it than the local metric plane is good for."""
    all_ll = np.concatenate([c.lonlat() for c in chains])
    origin = tuple(0.5 * (all_ll.min(axis=0) + all_ll.max(axis=0)))
    reach_m = float(np.hypot(*lonlat_to_xy(all_ll, origin).T).max())
    if reach_m > PLANE_RADIUS_M:
        report.warnings.append(
            f"the extract reaches {reach_m / 1e3:.0f} km from its centre: the network's local "
            f"metric plane is good within about {PLANE_RADIUS_M / 1e3:.0f} km of it (track/"
            f"network.py): distances farther out are off; import a smaller region"
        )
    return origin


def _named_chains(
    chains: list[_Chain], origin, min_length_m: float, report: ImportReport
) -> list[tuple[str, _Chain, np.ndarray, np.ndarray]]:
    """``(line id, chain, lon/lat, chainage of its ways' ends)`` of every chain long enough
    to be a line; ids from the chain's name or ref (and track ref), unique."""
    made = []
    taken: set[str] = set()
    for chain in sorted(chains, key=lambda c: (c.key, c.pieces[0][0].id)):
        ll = chain.lonlat()
        xy = lonlat_to_xy(ll, origin)
        length = float(np.hypot(*np.diff(xy, axis=0).T).sum())
        if length < min_length_m or length == 0:
            short = f"shorter than {min_length_m:g} m after joining" if length else "zero length"
            for w, _ in chain.pieces:
                report.drop(short, w.id)
            continue
        name_or_ref, track_ref = chain.key
        base = slug(name_or_ref) or "way" + re.sub(r"\D", "", chain.pieces[0][0].id)
        if track_ref and slug(track_ref):
            base += f"-t{slug(track_ref)}"
        line_id, k = base, 1
        while line_id in taken:
            k += 1
            line_id = f"{base}-{k}"
        taken.add(line_id)
        way_lengths = [
            float(np.hypot(*np.diff(lonlat_to_xy(w.lonlat, origin), axis=0).T).sum())
            for w, _ in chain.pieces
        ]
        made.append((line_id, chain, ll, np.r_[0.0, np.cumsum(way_lengths)]))
    return made


def _snap_stations(
    points: list[OsmPoint], probes: Mapping[str, Line], origin, snap_m: float, report
) -> dict[str, list[tuple[float, OsmPoint]]]:
    """The stations within ``snap_m`` of each line, ``(chainage, point)`` by line id; the
    other points dropped into ``report``."""
    station_points = []
    for p in points:
        reason = _station_reason(p.tags)
        if reason is None:
            station_points.append(p)
        else:
            report.drop(reason, p.id)
    on_line: dict[str, list[tuple[float, OsmPoint]]] = defaultdict(list)
    snapped: set[str] = set()
    station_xy = lonlat_to_xy(np.array([p.lonlat for p in station_points]).reshape(-1, 2), origin)
    for line_id, probe in probes.items():
        lo, hi = probe.xy.min(axis=0) - snap_m, probe.xy.max(axis=0) + snap_m
        near = np.flatnonzero(((station_xy >= lo) & (station_xy <= hi)).all(axis=1))
        if not len(near):
            continue
        chainage, lateral = probe.project(station_xy[near])
        for k, c, off in zip(near, chainage, lateral, strict=True):
            if abs(float(off)) <= snap_m:
                on_line[line_id].append((float(c), station_points[k]))
                snapped.add(station_points[k].id)
    for p in station_points:
        if p.id not in snapped:
            report.drop(f"station farther than {snap_m:g} m from every line", p.id)
    return on_line


def _routes(
    made, probes: Mapping[str, Line], running: str | None
) -> tuple[dict[str, str], dict[str, str]]:
    """The route of each line that shares its name with another, and the ``running`` of the
    two tracks of a route drawn side by side (with ``running``, the side trains keep to)."""
    by_route: dict[tuple[str, str], list[str]] = defaultdict(list)
    for line_id, chain, _, _ in made:
        by_route[chain.key[0], slug(chain.key[0]) or line_id].append(line_id)
    route_of_line: dict[str, str] = {}
    running_of_line: dict[str, str] = {}
    for (_, route), ids in by_route.items():
        if len(ids) < 2:
            continue
        route_of_line |= dict.fromkeys(ids, route)
        if running is not None and len(ids) == 2:
            pair = running_of_pair(probes[ids[0]], probes[ids[1]], running)
            if pair is not None:
                running_of_line |= dict(zip(ids, pair, strict=True))
    return route_of_line, running_of_line


def _line(
    line_id: str,
    chain: _Chain,
    ll: np.ndarray,
    bounds: np.ndarray,
    length_m: float,
    stations: tuple[list, list],
    default_speed_mps: float,
    **line_args,
) -> tuple[Line, dict, bool]:
    """The line of a chain, its feature's further properties, and whether any of its ways
    had a maxspeed."""
    pieces = list(zip(chain.pieces, bounds[:-1], bounds[1:], strict=True))
    # scale the ways' chainages to the line's (the same projection: equal up to rounding)
    scale = length_m / bounds[-1] if bounds[-1] > 0 else 1.0
    tunnels = _ranges([(a * scale, b * scale) for (w, _), a, b in pieces if _tunnel(w)])
    bridges = _ranges(
        [(a * scale, b * scale) for (w, _), a, b in pieces if _yes(w.tags.get("bridge"))]
    )
    tunnels = [(round(a, 1), min(round(b, 1), length_m)) for a, b in tunnels]
    tunnels = [(a, b) for a, b in tunnels if b > a]  # none of under 0.1 m
    speeds = [(parse_maxspeed(w.tags.get("maxspeed")), b - a) for (w, _), a, b in pieces]
    known = [(s, length) for s, length in speeds if s is not None]
    speed = _weighted_median(*zip(*known, strict=True)) if known else default_speed_mps
    lengths = [((w, rev), b - a) for (w, rev), a, b in pieces]
    line = Line(
        line_id,
        ll,
        tunnels=tunnels,
        stations=stations[0],
        station_names=stations[1],
        line_speed_mps=round(speed, 3),
        name=line_name(lengths, chain.key[1], stations[1], line_id),
        **line_args,
    )
    extra = {
        "ref": chain.pieces[0][0].tags.get("ref", ""),
        "track_ref": chain.key[1],
        "bridges": [[round(float(a), 1), round(float(b), 1)] for a, b in bridges],
        "osm_ways": [w.id for w, _ in chain.pieces],
    }
    return line, extra, bool(known)


def line_name(
    pieces: list[tuple[tuple[OsmWay, bool], float]],
    track_ref: str,
    station_names: list[str],
    line_id: str,
) -> str:
    """The name operators give a line of ``pieces`` (``((way, reversed), length)``, in
    order along it), its stations' names in chainage order (rule 5): each candidate of the
    most of the line's length, so a bridge's or a station's own name on one way does not
    win."""

    def most(name_of) -> str:
        named: dict[str, float] = defaultdict(float)
        for (w, _), length in pieces:
            for name in name_of(w):
                if name:
                    named[name] += length
        return max(named, key=lambda n: (named[n], n)) if named else ""

    def route(kind: str):
        return lambda w: [
            r.get("name") or r.get("ref") or "" for r in w.relations if r.get("route") == kind
        ]

    name = (
        most(route("railway"))
        or most(lambda w: [w.tags.get("name", "")])
        or most(route("train"))
        or most(lambda w: [w.tags.get("ref", "")])
    )
    if not name:
        named = [n for n in station_names if not re.fullmatch(r"node/-?\d+", n)]
        name = f"{named[0]} – {named[-1]}" if len(set(named)) > 1 else line_id
    if track_ref and name != line_id:
        name += f", track {track_ref}"
    return name


def running_of_pair(a: Line, b: Line, side: str) -> tuple[str, str] | None:
    """``running`` of two tracks of one route drawn side by side, trains keeping to ``side``.

    Points of ``a`` every 200 m within ``SIDE_BY_SIDE_M`` of ``b`` are projected on ``b``;
    the sign of the median lateral offset (positive left of ``b``'s increasing chainage)
    says on which side ``a`` lies. A train running towards increasing chainage keeps to
    ``side``, so the track on that side is ``"increasing"``, the other ``"decreasing"``.
    None when the tracks are not side by side, or do not share their chainage direction
    there (then neither can be told from the other by direction).
    """
    if side not in RUNNING_SIDES:
        raise ValueError(f"side: left or right, got {side!r}")
    at = np.linspace(0.0, a.length_m, int(a.length_m // CLOSE_STEP_M) + 2)
    chainage, lateral = b.project(a.xy_at(at))
    near = np.abs(lateral) <= SIDE_BY_SIDE_M
    if not near.any():
        return None
    turn = a.heading_at(at[near]) - b.heading_at(chainage[near])
    if np.median(np.cos(turn)) <= 0:
        return None
    a_left = float(np.median(lateral[near])) > 0
    a_increasing = a_left == (side == "left")
    return ("increasing", "decreasing") if a_increasing else ("decreasing", "increasing")


def close_tracks_warnings(
    lines: Mapping[str, Line], within_m: float = PARALLEL_M, max_listed: int = 5
) -> list[str]:
    """Warnings for tracks of one route that run within ``within_m`` of each other.

    GPS cannot tell such tracks apart: map matching (``services/ingestion/matching.py``)
    tells them apart by the direction a train runs in, when they have ``running`` set to
    opposite directions (the warning says so); otherwise trains with raw GPS there are not
    positioned (the warning says to pass ``--running``). The on-board indices of ``simulate
    --fidelity index`` and TRC records name their line and are not affected. Checked every
    200 m along each track, against the other tracks of its route only (the ones drawn side
    by side). More than ``max_listed`` pairs make one warning listing the first of them.
    """
    by_route: dict[str, list[Line]] = defaultdict(list)
    for line in lines.values():
        by_route[line.route or line.name or line.id].append(line)
    pairs = []
    for tracks in by_route.values():
        for k, a in enumerate(tracks):
            points = a.xy_at(np.linspace(0.0, a.length_m, int(a.length_m // CLOSE_STEP_M) + 2))
            for b in tracks[k + 1 :]:
                _, lateral = b.project(points)
                close_km = float((np.abs(lateral) < within_m).mean()) * a.length_m / 1e3
                if close_km > 0:
                    apart = {a.running, b.running} == {"increasing", "decreasing"}
                    pairs.append((a.id, b.id, close_km, apart))
    if all(apart for *_, apart in pairs):
        why = "GPS cannot tell them apart; map matching (ingestion) tells them apart by "
        why += "their running direction"
    else:
        why = "GPS map matching (ingestion) cannot tell them apart, so raw-GPS trains there "
        why += "are not positioned: pass --running left|right (the side trains keep to) to "
        why += "tell double tracks apart by their running direction"
    if len(pairs) <= max_listed:
        return [
            f"lines {a} and {b} run within {within_m:g} m of each other over {km:.1f} km: {why}"
            for a, b, km, _ in pairs
        ]
    listed = ", ".join(f"{a}/{b} ({km:.1f} km)" for a, b, km, _ in pairs[:max_listed])
    return [
        f"{len(pairs)} pairs of lines run within {within_m:g} m of each other, "
        f"{sum(km for _, _, km, _ in pairs):.0f} km in all: {listed}, ... : {why}"
    ]


def _tunnel(way: OsmWay) -> bool:
    return _yes(way.tags.get("tunnel"))


def _stations(
    hits: list[tuple[float, OsmPoint]], snap_m: float, length_m: float
) -> tuple[list[float], list[str]]:
    """One line's stations (chainage, name), a name's duplicates within 2 snap_m merged."""
    found = sorted((min(max(c, 0.0), length_m), p.tags.get("name") or p.id) for c, p in hits)
    chainages: list[float] = []
    names: list[str] = []
    for c, name in found:
        kept = zip(chainages, names, strict=True)
        if any(n == name and abs(c - c0) <= 2 * snap_m for c0, n in kept):
            continue
        chainages.append(math.floor(c * 10) / 10)  # 0.1 m, never past the end
        names.append(name)
    return chainages, names


def to_geojson(network: Network, extra: Mapping[str, Mapping]) -> dict:
    """The network file: :meth:`Network.to_geojson` with each line's extra properties."""
    doc = network.to_geojson(include_segments=True)
    for feature in doc["features"]:
        props = feature["properties"]
        if props.get("kind") == "line":
            props |= dict(extra.get(props["id"], {}))
    doc["source"] = "OpenStreetMap contributors (ODbL): trackfusion network import-osm"
    return doc
