"""OpenStreetMap import at a national network's size: CPU time and peak memory.

A seeded synthetic extract shaped like ``osmium export``'s: ``routes`` double-track routes
of 30 km (smooth random curves within ±120 km of the centre, tracks 4.5 m apart, each
track split into 20 ways, half of them drawn reversed, maxspeed 80/100/120) and a station
15 m off every 3 km. ``python -m bench.osm_import [--routes 300]`` prints the sizes, the
CPU seconds of :func:`track.osm.import_osm` and of writing the network file, and the
process's peak RSS. Not part of ``make bench``.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import time

import numpy as np

from track.osm import import_osm, to_geojson

LAT0, LON0 = 47.0, 8.3
WAYS_PER_TRACK, POINTS_PER_WAY, STEP_M = 20, 30, 50.0
TRACK_SPACING_M = 4.5


def synthetic_extract(routes: int, seed: int = 1) -> dict:
    """A GeoJSON FeatureCollection of ``2 * 20 * routes`` ways and their stations."""
    rng = np.random.default_rng(seed)
    kx, ky = 1 / (111_195 * math.cos(math.radians(LAT0))), 1 / 111_195
    features: list[dict] = []
    n_points = WAYS_PER_TRACK * POINTS_PER_WAY
    for r in range(routes):
        start = rng.uniform(-120e3, 120e3, 2)
        heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, 0.01, n_points))
        xy = start + np.cumsum(STEP_M * np.c_[np.cos(heading), np.sin(heading)], axis=0)
        normal = np.c_[-np.sin(heading), np.cos(heading)]
        for track, offset in (("1", 0.0), ("2", TRACK_SPACING_M)):
            t = xy + offset * normal
            ll = np.c_[LON0 + t[:, 0] * kx, LAT0 + t[:, 1] * ky].round(7)
            for w in range(WAYS_PER_TRACK):
                coords = ll[w * POINTS_PER_WAY : (w + 1) * POINTS_PER_WAY + 1].tolist()
                if rng.random() < 0.5:
                    coords = coords[::-1]
                tags = {"railway": "rail", "ref": f"R{r}", "railway:track_ref": track}
                tags["maxspeed"] = str(rng.choice([80, 100, 120]))
                features.append(_feature(f"way/{len(features)}", tags, "LineString", coords))
        for k in range(0, n_points, 60):
            p = xy[k] + 15.0 * normal[k]
            coords = [LON0 + p[0] * kx, LAT0 + p[1] * ky]
            tags = {"railway": "station", "name": f"S{r}-{k}"}
            features.append(_feature(f"node/{len(features)}", tags, "Point", coords))
    return {"type": "FeatureCollection", "features": features}


def _feature(osm_id: str, tags: dict, kind: str, coords) -> dict:
    return {
        "type": "Feature",
        "properties": {"@id": osm_id, **tags},
        "geometry": {"type": kind, "coordinates": coords},
    }


def main(routes: int) -> dict:
    doc = synthetic_extract(routes)
    t0 = time.process_time()
    network, extra, report = import_osm(doc)
    t1 = time.process_time()
    text = json.dumps(to_geojson(network, extra))
    t2 = time.process_time()
    return {
        "ways": report.ways_read,
        "points": report.points_read,
        "lines": len(network.lines),
        "km": round(sum(line.length_m for line in network.lines.values()) / 1e3),
        "segments": network.n_segments,
        "import_cpu_s": round(t1 - t0, 2),
        "write_cpu_s": round(t2 - t1, 2),
        "file_mb": round(len(text) / 1e6, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--routes", type=int, default=300)
    print(json.dumps(main(parser.parse_args().routes)))
