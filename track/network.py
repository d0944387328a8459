"""The track register: lines as polylines with chainage, cut into fixed-length segments.

Geometry lives in two frames. On the wire and in GeoJSON, WGS84 longitude/latitude in
degrees. For distances, a local metric plane around the network's origin by the
equirectangular projection

.. math::

    x = R \\cos\\varphi_0 \\,(\\lambda - \\lambda_0), \\qquad y = R\\,(\\varphi - \\varphi_0),

with :math:`R` the mean Earth radius and angles in radians; x points east, y north. Its
scale error grows with the square of the distance from the origin: below 0.1 % within
100 km of it, so networks should stay within about 200 km.

Chainage is the distance along a line's polyline in metres from its first vertex. A line
is cut into segments of ``segment_length_m`` (default 200 m); the remainder becomes a last
segment if it is at least half a segment long, else it is merged into the previous one,
so every segment is in ``[L/2, 3L/2)`` and segment ids (``s00000``, ``s00001``, ...) are
stable as long as the geometry and the segment length are.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

EARTH_RADIUS_M = 6_371_008.8  # mean radius (IUGG)
_ID_FORBIDDEN = set("/*$?# ")
RUNNING = ("increasing", "decreasing", "both")  # Line.running: normal direction of chainage


def check_id(name: str, value) -> str:
    """Return ``value`` if it is a safe key chunk, else raise ValueError."""
    if not isinstance(value, str) or not value or _ID_FORBIDDEN.intersection(value):
        raise ValueError(f"{name}: {value!r} must be a non-empty string without / * $ ? # space")
    return value


def lonlat_to_xy(lonlat, origin_lonlat) -> np.ndarray:
    """Equirectangular projection of ``(..., 2)`` lon/lat degrees to metres around the origin."""
    ll = np.asarray(lonlat, dtype=np.float64)
    lon0, lat0 = origin_lonlat
    k = math.radians(1.0) * EARTH_RADIUS_M
    return np.stack(
        [(ll[..., 0] - lon0) * k * math.cos(math.radians(lat0)), (ll[..., 1] - lat0) * k], -1
    )


def xy_to_lonlat(xy, origin_lonlat) -> np.ndarray:
    """Inverse of :func:`lonlat_to_xy`."""
    xy = np.asarray(xy, dtype=np.float64)
    lon0, lat0 = origin_lonlat
    k = math.radians(1.0) * EARTH_RADIUS_M
    return np.stack(
        [lon0 + xy[..., 0] / (k * math.cos(math.radians(lat0))), lat0 + xy[..., 1] / k], -1
    )


@dataclass(frozen=True)
class Segment:
    """One fixed-length piece of a line, ``[start_m, end_m)`` in chainage."""

    line: str
    id: str  # "s00042": unique within the line, safe as a key chunk
    index: int  # position along the line, 0-based
    start_m: float
    end_m: float

    @property
    def length_m(self) -> float:
        return self.end_m - self.start_m

    @property
    def mid_m(self) -> float:
        return 0.5 * (self.start_m + self.end_m)


def cut_segments(line_id: str, length_m: float, segment_length_m: float) -> list[Segment]:
    """Cut ``[0, length_m]`` into segments; a remainder under half a segment joins the last."""
    if not segment_length_m > 0:
        raise ValueError(f"segment_length_m: must be > 0, got {segment_length_m}")
    n = max(1, int(length_m // segment_length_m))
    if length_m - n * segment_length_m >= 0.5 * segment_length_m:
        n += 1
    bounds = np.minimum(np.arange(n + 1) * segment_length_m, length_m)
    bounds[-1] = length_m
    width = max(5, len(str(n - 1)))
    return [
        Segment(line_id, f"s{i:0{width}d}", i, float(bounds[i]), float(bounds[i + 1]))
        for i in range(n)
    ]


class Line:
    """A line: polyline, chainage, segments, tunnels (GPS dropouts), stations and speed.

    Parameters
    ----------
    id : str
        Safe key chunk, e.g. ``"L1"``.
    lonlat : array_like, shape (k, 2)
        Polyline vertices in WGS84 degrees; consecutive duplicates are dropped.
    origin_lonlat : (float, float)
        Origin of the network's local metric plane.
    segment_length_m : float
    tunnels : sequence of (start_m, end_m)
        Chainage ranges without GPS.
    stations : sequence of float
        Chainages where trains stop.
    line_speed_mps : float
        Cruise speed.
    name : str
        What operators call it (``""``: none; labels then use the id).
    station_names : sequence of str
        One per station in the order given (``()``: none).
    route : str
        Id of the route this line is a track of (``""``: the line is its own route). The
        tracks of a double-track route lie a few metres apart, closer than GPS can tell.
    running : str
        ``"increasing"``, ``"decreasing"`` or ``"both"``: the direction of chainage trains
        normally run in on this track. Map matching tells the tracks of one route apart by
        it, since on double track each track normally carries one direction.
    """

    def __init__(
        self,
        id: str,
        lonlat,
        origin_lonlat,
        *,
        segment_length_m: float = 200.0,
        tunnels=(),
        stations=(),
        line_speed_mps: float = 25.0,
        name: str = "",
        station_names=(),
        route: str = "",
        running: str = "both",
    ):
        self.id = check_id("id", id)
        self.name = str(name)
        self.route = check_id("route", route) if route else ""
        if running not in RUNNING:
            raise ValueError(
                f"line {id}: running must be one of {', '.join(RUNNING)}, got {running!r}"
            )
        self.running = running
        ll = np.asarray(lonlat, dtype=np.float64)
        if ll.ndim != 2 or ll.shape[1] != 2 or not np.isfinite(ll).all():
            raise ValueError(f"line {id}: lonlat must be finite (k, 2), got shape {ll.shape}")
        if (np.abs(ll[:, 0]) > 180).any() or (np.abs(ll[:, 1]) > 90).any():
            raise ValueError(f"line {id}: coordinates must be [lon, lat] in degrees")
        keep = np.r_[True, (np.diff(ll, axis=0) != 0).any(axis=1)]
        self.lonlat = ll[keep]
        if len(self.lonlat) < 2:
            raise ValueError(f"line {id}: needs at least 2 distinct vertices")
        self.origin_lonlat = (float(origin_lonlat[0]), float(origin_lonlat[1]))
        self.xy = lonlat_to_xy(self.lonlat, self.origin_lonlat)
        piece = np.hypot(*np.diff(self.xy, axis=0).T)
        self.chainage_m = np.r_[0.0, np.cumsum(piece)]
        self.length_m = float(self.chainage_m[-1])
        self.segments = cut_segments(self.id, self.length_m, segment_length_m)
        self.segment_starts_m = np.array([s.start_m for s in self.segments])
        self.segment_ends_m = np.array([s.end_m for s in self.segments])
        self.tunnels = [(float(a), float(b)) for a, b in tunnels]
        for a, b in self.tunnels:
            if not 0 <= a < b <= self.length_m:
                raise ValueError(f"line {id}: tunnel ({a}, {b}) not within [0, {self.length_m}]")
        names = [str(n) for n in station_names]
        if names and len(names) != len(stations):
            raise ValueError(f"line {id}: one station name per station, or none")
        pairs = sorted(
            zip([float(c) for c in stations], names or [""] * len(stations), strict=True)
        )
        self.stations = [c for c, _ in pairs]
        self.station_names = [n for _, n in pairs] if names else []
        if any(not 0 <= c <= self.length_m for c in self.stations):
            raise ValueError(f"line {id}: stations must lie within [0, {self.length_m:.1f}] m")
        self.line_speed_mps = float(line_speed_mps)
        if not (math.isfinite(self.line_speed_mps) and self.line_speed_mps > 0):
            raise ValueError(f"line {id}: line_speed_mps must be > 0, got {line_speed_mps}")

    def __repr__(self) -> str:
        return f"Line({self.id!r}, {self.length_m:.0f} m, {len(self.segments)} segments)"

    def _piece(self, chainage) -> tuple[np.ndarray, np.ndarray]:
        c = np.clip(np.asarray(chainage, dtype=np.float64), 0.0, self.length_m)
        i = np.clip(np.searchsorted(self.chainage_m, c, side="right") - 1, 0, len(self.xy) - 2)
        return c, i

    def xy_at(self, chainage) -> np.ndarray:
        """Local x, y (m) at chainages, shape ``chainage.shape + (2,)``; clipped to the line."""
        c, i = self._piece(chainage)
        f = ((c - self.chainage_m[i]) / (self.chainage_m[i + 1] - self.chainage_m[i]))[..., None]
        return self.xy[i] * (1 - f) + self.xy[i + 1] * f

    def lonlat_at(self, chainage) -> np.ndarray:
        """WGS84 lon, lat (degrees) at chainages, shape ``chainage.shape + (2,)``."""
        return xy_to_lonlat(self.xy_at(chainage), self.origin_lonlat)

    @property
    def route_id(self) -> str:
        """The route this line is a track of: ``route``, or the line's own id."""
        return self.route or self.id

    def heading_at(self, chainage) -> np.ndarray:
        """Direction of increasing chainage in radians, counter-clockwise from east (x)."""
        _, i = self._piece(chainage)
        d = self.xy[i + 1] - self.xy[i]
        return np.arctan2(d[..., 1], d[..., 0])

    def segment_index_at(self, chainage) -> np.ndarray:
        """Index of the segment containing each chainage, -1 outside ``[0, length_m]``."""
        c = np.asarray(chainage, dtype=np.float64)
        i = np.searchsorted(self.segment_starts_m, c, side="right") - 1
        i = np.minimum(i, len(self.segments) - 1)
        return np.where((c >= 0) & (c <= self.length_m), i, -1)

    def project(self, xy, chunk: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
        """Nearest point on the polyline of local points ``(..., 2)``.

        Returns
        -------
        chainage_m, lateral_m : ndarray, shape ``xy.shape[:-1]``
            Chainage of the nearest point and the signed distance to it, positive to the
            left of the direction of increasing chainage.
        """
        p = np.asarray(xy, dtype=np.float64)
        shape = p.shape[:-1]
        p = p.reshape(-1, 2)
        a, d = self.xy[:-1], np.diff(self.xy, axis=0)
        dd = (d * d).sum(axis=1)
        chain, lateral = np.empty(len(p)), np.empty(len(p))
        step = max(1, chunk // len(d))  # bounds the (points x pieces) temporaries
        for lo in range(0, len(p), step):
            q = p[lo : lo + step, None, :] - a  # (m, pieces, 2)
            f = np.clip((q * d).sum(axis=2) / dd, 0.0, 1.0)
            dist2 = ((q - f[..., None] * d) ** 2).sum(axis=2)
            j = dist2.argmin(axis=1)
            rows = np.arange(len(j))
            fj, qj = f[rows, j], q[rows, j]
            chain[lo : lo + step] = self.chainage_m[j] + fj * np.sqrt(dd[j])
            cross = d[j, 0] * qj[:, 1] - d[j, 1] * qj[:, 0]
            lateral[lo : lo + step] = np.copysign(np.sqrt(dist2[rows, j]), cross)
        return chain.reshape(shape), lateral.reshape(shape)

    def segment_lonlat(self, segment: Segment) -> np.ndarray:
        """The polyline of one segment (its end points and the vertices between them)."""
        inner = (self.chainage_m > segment.start_m) & (self.chainage_m < segment.end_m)
        c = np.r_[segment.start_m, self.chainage_m[inner], segment.end_m]
        return self.lonlat_at(c)


class Network:
    """Lines by id sharing one local metric plane and one segment length.

    ``segments()`` and every per-segment array of the simulators follow the order of
    ``lines`` (insertion order: file order for GeoJSON) and then the chainage.
    """

    def __init__(self, lines: Mapping[str, Line], segment_length_m: float, origin_lonlat):
        self.lines = dict(lines)
        self.segment_length_m = float(segment_length_m)
        self.origin_lonlat = (float(origin_lonlat[0]), float(origin_lonlat[1]))

    def __repr__(self) -> str:
        km = sum(line.length_m for line in self.lines.values()) / 1e3
        return f"Network({len(self.lines)} lines, {km:.1f} km, {self.n_segments} segments)"

    def segments(self) -> Iterator[tuple[Line, Segment]]:
        """Every (line, segment) in the network's stable order."""
        for line in self.lines.values():
            for seg in line.segments:
                yield line, seg

    @property
    def n_segments(self) -> int:
        return sum(len(line.segments) for line in self.lines.values())

    def to_xy(self, lonlat) -> np.ndarray:
        return lonlat_to_xy(lonlat, self.origin_lonlat)

    def to_lonlat(self, xy) -> np.ndarray:
        return xy_to_lonlat(xy, self.origin_lonlat)

    @classmethod
    def from_geojson(cls, obj_or_path, segment_length_m: float | None = None) -> Network:
        """Read a FeatureCollection of LineString lines (path, JSON text or parsed dict).

        Line features carry ``properties.id`` and optionally ``tunnels`` ([[start_m,
        end_m], ...]), ``stations`` ([chainage_m, ...]), ``line_speed_mps``, and ``name``
        and ``station_names`` (one per station), which labels show, and ``route`` and
        ``running`` (see :class:`Line`: tracks of one route told apart by the direction
        trains run on them). Features with
        ``properties.kind == "segment"`` (written by :meth:`to_geojson`) are skipped.
        The local origin is the collection's ``origin_lonlat`` member if present, else the
        centre of the bounding box; the segment length, ``segment_length_m`` if given, else
        the collection's ``segment_length_m`` member (what wrote it cut), else 200 m.
        """
        obj = obj_or_path
        if isinstance(obj, Path) or (isinstance(obj, str) and not obj.lstrip().startswith("{")):
            obj = Path(obj).read_text()
        if isinstance(obj, str):
            try:
                obj = json.loads(obj)
            except json.JSONDecodeError as exc:
                raise ValueError(f"GeoJSON: not valid JSON ({exc})") from None
        if not isinstance(obj, Mapping) or obj.get("type") != "FeatureCollection":
            raise ValueError('GeoJSON: expected an object with "type": "FeatureCollection"')
        features = obj.get("features")
        if not isinstance(features, list):
            raise ValueError('GeoJSON: "features" must be a list of Feature objects')
        raw = []
        for n, f in enumerate(features):
            props = (f.get("properties") or {}) if isinstance(f, Mapping) else {}
            if not isinstance(props, Mapping):
                raise ValueError(f"feature {n}: properties must be an object")
            if props.get("kind") == "segment":
                continue
            where = f"feature {n}" + (f" (id {props['id']!r})" if "id" in props else "")
            geom = f.get("geometry") if isinstance(f, Mapping) else None
            if not isinstance(geom, Mapping) or geom.get("type") != "LineString":
                got = geom.get("type") if isinstance(geom, Mapping) else geom
                raise ValueError(f"{where}: geometry must be a LineString, got {got!r}")
            coords = geom.get("coordinates")
            try:
                ll = np.asarray(coords, dtype=np.float64)[..., :2]  # drop altitude if any
            except (TypeError, ValueError):
                raise ValueError(f"{where}: coordinates must be a list of [lon, lat]") from None
            if ll.ndim != 2 or len(ll) < 2:
                raise ValueError(f"{where}: coordinates must be at least 2 [lon, lat] pairs")
            if "id" not in props:
                raise ValueError(f'{where}: properties must have an "id" (e.g. "L1")')
            raw.append((where, props, ll))
        if not raw:
            raise ValueError("GeoJSON: no LineString line features")
        ids = [p["id"] for _, p, _ in raw]
        if len(set(map(str, ids))) != len(ids):
            raise ValueError(f"GeoJSON: line ids must be unique, got {ids}")
        if segment_length_m is None:
            segment_length_m = obj.get("segment_length_m", 200.0)
            if not isinstance(segment_length_m, int | float) or not segment_length_m > 0:
                raise ValueError(f"GeoJSON: segment_length_m must be > 0, got {segment_length_m}")
        origin = obj.get("origin_lonlat")
        if origin is None:
            all_ll = np.concatenate([ll for _, _, ll in raw])
            origin = 0.5 * (all_ll.min(axis=0) + all_ll.max(axis=0))
        lines = {}
        for where, props, ll in raw:
            try:
                line = Line(
                    props["id"],
                    ll,
                    origin,
                    segment_length_m=segment_length_m,
                    tunnels=props.get("tunnels") or (),
                    stations=props.get("stations") or (),
                    line_speed_mps=props.get("line_speed_mps", 25.0),
                    name=props.get("name") or "",
                    station_names=props.get("station_names") or (),
                    route=props.get("route") or "",
                    running=props.get("running") or "both",
                )
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where}: {exc}") from None
            lines[line.id] = line
        return cls(lines, segment_length_m, origin)

    def to_geojson(self, include_segments: bool = True) -> dict:
        """A FeatureCollection: one feature per line, then one per segment if asked."""
        features = []
        for line in self.lines.values():
            props = {
                "kind": "line",
                "id": line.id,
                "length_m": round(line.length_m, 3),
                "line_speed_mps": line.line_speed_mps,
                "tunnels": [list(t) for t in line.tunnels],
                "stations": line.stations,
            }
            if line.name:
                props["name"] = line.name
            if line.station_names:
                props["station_names"] = line.station_names
            if line.route:
                props["route"] = line.route
            if line.running != "both":
                props["running"] = line.running
            features.append(_feature(line.lonlat, props))
        if include_segments:
            for line, seg in self.segments():
                props = {"kind": "segment", "line": line.id, "segment": seg.id}
                props |= {"index": seg.index, "start_m": seg.start_m, "end_m": seg.end_m}
                features.append(_feature(line.segment_lonlat(seg), props))
        return {
            "type": "FeatureCollection",
            "origin_lonlat": list(self.origin_lonlat),
            "segment_length_m": self.segment_length_m,
            "features": features,
        }


def _feature(lonlat: np.ndarray, props: dict) -> dict:
    return {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": lonlat.tolist()},
        "properties": props,
    }
