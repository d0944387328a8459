"""What the report (:mod:`services.tools.report`) draws of the network: segment polylines,
chainages, stations, line names and speeds, read from a network file."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from schemas.keys import SegmentId
from services.limits import network_line_speeds


@dataclass(frozen=True)
class Station:
    line: str
    lon: float
    lat: float
    label: str


@dataclass(frozen=True)
class NetworkMap:
    """What the report draws of the network: each segment's polyline ([lon, lat] pairs) and
    chainage range (m), and the stations."""

    polylines: dict[SegmentId, list[tuple[float, float]]] = field(default_factory=dict)
    chainage_m: dict[SegmentId, tuple[float, float]] = field(default_factory=dict)
    stations: list[Station] = field(default_factory=list)
    line_names: dict[str, str] = field(default_factory=dict)  # id -> the name operators use
    line_speeds_kmh: dict[str, float] = field(default_factory=dict)  # id -> line speed

    def label(self, line: str) -> str:
        """A line as a planner knows it: ``id (name)``, or the id when it has no name."""
        name = self.line_names.get(line)
        return f"{line} ({name})" if name and name != line else line


def network_map(network_path: str | None = None) -> NetworkMap:
    """Segment polylines and chainages, and stations, of a network file (default: the demo).

    A line feature may name its stations with ``station_names`` (one per ``stations``
    chainage); without names a station is labelled with its chainage in km.
    """
    from services.defaults import DEMO_NETWORK
    from track.network import Network

    path = Path(network_path or DEMO_NETWORK)
    try:
        raw = json.loads(path.read_text())
        network = Network.from_geojson(raw)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--network {path}: {exc}") from None  # the CLI exits 2
    props = {
        f["properties"]["id"]: f["properties"]
        for f in raw["features"]
        if isinstance(f.get("properties"), dict) and "id" in f["properties"]
    }
    polylines, chainage, stations = {}, {}, []
    for line in network.lines.values():
        for seg in line.segments:
            polylines[(line.id, seg.id)] = [tuple(p) for p in line.segment_lonlat(seg).tolist()]
            chainage[(line.id, seg.id)] = (seg.start_m, seg.end_m)
        names = props.get(line.id, {}).get("station_names") or []
        for k, c in enumerate(line.stations):
            lon, lat = map(float, line.lonlat_at(c))
            label = str(names[k]) if k < len(names) else f"{line.id} km {c / 1e3:.1f}"
            stations.append(Station(line.id, lon, lat, label))
    names = {line.id: line.name for line in network.lines.values() if line.name}
    return NetworkMap(polylines, chainage, stations, names, network_line_speeds(network))
