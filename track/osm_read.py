"""Reading an OpenStreetMap railway extract: its ways and points, with their tags and ids.

Input is what the usual tools export (``osmium export``, ``ogr2ogr``, overpass-turbo's
GeoJSON, or Overpass JSON with ``out geom``): ways as LineStrings with their tags, and
station points. Tags may be flat in ``properties``, nested under ``properties.tags``, or in
ogr2ogr's ``other_tags`` string; the OSM id comes from ``@id``/``id`` (``"way/123"``,
``"w123"`` or a number, with ``@type``). The relations a way is a member of (route
relations carry the names operators use) come from overpass-turbo's ``@relations``
property, or from the relation elements of Overpass JSON. :mod:`track.osm` makes the
network of them.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class OsmWay:
    """One way: its id (``"way/123"``), vertices (lon, lat), end node ids if known, tags."""

    id: str
    lonlat: np.ndarray  # (k, 2) degrees
    tags: Mapping[str, str]
    end_nodes: tuple[str, str] | None = None
    relations: tuple[Mapping[str, str], ...] = ()  # the tags of the relations it is in


@dataclass(frozen=True)
class OsmPoint:
    """One node: its id, position (lon, lat) and tags."""

    id: str
    lonlat: tuple[float, float]
    tags: Mapping[str, str]


_OTHER_TAGS = re.compile(r'"((?:[^"\\]|\\.)*)"=>"((?:[^"\\]|\\.)*)"')


def _tags(props: Mapping) -> dict[str, str]:
    """Tags of a feature's properties: flat, nested under ``tags``, or ogr2ogr's
    ``other_tags`` hstore string."""
    tags = {
        str(k): str(v)
        for k, v in props.items()
        if v is not None and not isinstance(v, Mapping | list) and not str(k).startswith("@")
    }
    nested = props.get("tags")
    if isinstance(nested, Mapping):
        tags |= {str(k): str(v) for k, v in nested.items() if v is not None}
    other = props.get("other_tags")
    if isinstance(other, str):
        tags.pop("other_tags", None)
        tags |= {k: v for k, v in _OTHER_TAGS.findall(other)}
    return tags


def _osm_id(feature: Mapping, props: Mapping, kind: str, n: int) -> str:
    """``way/123`` from ``@id``/``id``/``osm_id`` as ``way/123``, ``w123`` or ``123``."""
    if props.get("@type") in ("node", "way", "relation"):  # osmium export -a type,id
        kind = props["@type"]
    for raw in (props.get("@id"), props.get("id"), props.get("osm_id"), feature.get("id")):
        if raw is None or raw == "":
            continue
        text = str(raw)
        if "/" in text:
            return text
        if text[:1] in "wnr" and text[1:].lstrip("-").isdigit():
            return {"w": "way", "n": "node", "r": "relation"}[text[0]] + "/" + text[1:]
        return f"{kind}/{text}"
    return f"feature{n}"


def _relations(props: Mapping) -> tuple[dict[str, str], ...]:
    """The tags of the relations overpass-turbo lists a feature in (``@relations``)."""
    listed = props.get("@relations")
    if not isinstance(listed, list):
        return ()
    return tuple(
        {str(k): str(v) for k, v in r["reltags"].items() if v is not None}
        for r in listed
        if isinstance(r, Mapping) and isinstance(r.get("reltags"), Mapping)
    )


def _way_members(members) -> list[str]:
    """The ways (``way/123``) among an Overpass relation's members."""
    if not isinstance(members, list):
        return []
    return [
        f"way/{m['ref']}"
        for m in members
        if isinstance(m, Mapping) and m.get("type") == "way" and "ref" in m
    ]


def _coords(where: str, raw) -> np.ndarray:
    try:
        ll = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: coordinates must be a list of [lon, lat] numbers") from None
    if ll.ndim != 2 or ll.shape[1] < 2 or not np.isfinite(ll).all():
        raise ValueError(f"{where}: coordinates must be a list of finite [lon, lat] pairs")
    ll = ll[:, :2]
    if (np.abs(ll[:, 0]) > 180).any() or (np.abs(ll[:, 1]) > 90).any():
        raise ValueError(f"{where}: coordinates must be [lon, lat] in degrees")
    return ll


def read_osm(obj) -> tuple[list[OsmWay], list[OsmPoint], list[tuple[str, str]]]:
    """Ways and points of a parsed GeoJSON FeatureCollection or Overpass JSON document.

    Returns the ways, the points and the features that are neither (``(reason, id)``:
    areas, relations, points without tags). ValueError naming the feature when one is
    malformed.
    """
    if isinstance(obj, Mapping) and isinstance(obj.get("elements"), list):
        return _read_overpass(obj["elements"])
    if not isinstance(obj, Mapping) or obj.get("type") != "FeatureCollection":
        raise ValueError(
            "expected a GeoJSON FeatureCollection (osmium export, ogr2ogr, overpass-turbo) "
            'or Overpass JSON ({"elements": [...]})'
        )
    features = obj.get("features")
    if not isinstance(features, list):
        raise ValueError('"features" must be a list of Feature objects')
    ways, points, other = [], [], []
    for n, f in enumerate(features):
        if not isinstance(f, Mapping) or f.get("type") != "Feature":
            raise ValueError(f'feature {n}: must be an object with "type": "Feature"')
        props = f.get("properties") or {}
        if not isinstance(props, Mapping):
            raise ValueError(f"feature {n}: properties must be an object")
        geom = f.get("geometry")
        gtype = geom.get("type") if isinstance(geom, Mapping) else None
        osm_id = _osm_id(f, props, "node" if gtype == "Point" else "way", n)
        where = f"feature {n} ({osm_id})"
        tags = _tags(props)
        if gtype == "LineString":
            coords = _coords(where, geom.get("coordinates"))
            ways.append(OsmWay(osm_id, coords, tags, relations=_relations(props)))
        elif gtype == "MultiLineString":
            parts = geom.get("coordinates")
            if not isinstance(parts, list):
                raise ValueError(f"{where}: MultiLineString coordinates must be a list")
            for k, part in enumerate(parts):
                coords = _coords(where, part)
                ways.append(OsmWay(f"{osm_id}#{k}", coords, tags, relations=_relations(props)))
        elif gtype == "Point":
            ll = _coords(where, [geom.get("coordinates")])[0]
            points.append(OsmPoint(osm_id, (float(ll[0]), float(ll[1])), tags))
        elif gtype is None:
            raise ValueError(f"{where}: has no geometry object with a type")
        else:
            other.append((f"geometry {gtype}", osm_id))
    return ways, points, other


def _read_overpass(elements: list) -> tuple[list[OsmWay], list[OsmPoint], list[tuple[str, str]]]:
    ways, points, other = [], [], []
    member_of: dict[str, list[dict[str, str]]] = {}  # way id -> tags of its relations
    for n, e in enumerate(elements):
        if not isinstance(e, Mapping) or "type" not in e:
            raise ValueError(f'element {n}: must be an object with a "type"')
        osm_id = f"{e['type']}/{e.get('id', n)}"
        where = f"element {n} ({osm_id})"
        tags = {str(k): str(v) for k, v in (e.get("tags") or {}).items()}
        if e["type"] == "way":
            geometry = e.get("geometry")
            if not isinstance(geometry, list):
                raise ValueError(f'{where}: needs "geometry" (query with "out geom;")')
            try:
                ll = [[float(p["lon"]), float(p["lat"])] for p in geometry]
            except (TypeError, KeyError, ValueError):
                raise ValueError(f"{where}: geometry must be a list of {{lat, lon}}") from None
            nodes = e.get("nodes")
            ends = (str(nodes[0]), str(nodes[-1])) if isinstance(nodes, list) and nodes else None
            ways.append(OsmWay(osm_id, _coords(where, ll), tags, ends))
        elif e["type"] == "node":
            if tags:  # untagged nodes are a way's vertices (out body; >; out skel;)
                try:
                    ll = _coords(where, [[float(e["lon"]), float(e["lat"])]])[0]
                except (KeyError, TypeError, ValueError):
                    raise ValueError(f"{where}: a node needs numbers lat and lon") from None
                points.append(OsmPoint(osm_id, (float(ll[0]), float(ll[1])), tags))
        elif e["type"] == "relation" and (members := _way_members(e.get("members"))):
            for way_id in members:
                member_of.setdefault(way_id, []).append(tags)
        else:
            other.append((f"element {e['type']}", osm_id))
    ways = [replace(w, relations=tuple(member_of.get(w.id, ()))) for w in ways]
    return ways, points, other
