"""Generated networks for the simulators, scale tests and benchmarks.

The network itself (lines, chainage, segments, GeoJSON I/O) is the track register,
:mod:`track.network`; this module only makes random ones and the simulators' seeded
generators.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from track.network import Line, Network, xy_to_lonlat

DEFAULT_ORIGIN = (153.02, -27.47)  # Brisbane, lon/lat degrees


def stable_rng(seed: int, *parts: int | str) -> np.random.Generator:
    """A generator seeded from ``seed`` and stable ids (strings hashed with CRC-32).

    Keying every random draw by what it is about (line, segment, run, ...) rather than by
    the order of the loops makes results independent of iteration order.
    """
    key = [int(seed)] + [zlib.crc32(p.encode()) if isinstance(p, str) else int(p) for p in parts]
    return np.random.default_rng(key)


def _smooth_curve(rng: np.random.Generator, length_m: float, step_m: float, kappa_max: float):
    """Heading-integrated curve whose curvature is a sum of a few long-wavelength sines."""
    s = np.arange(0.0, length_m + step_m, step_m)
    s[-1] = length_m
    lam = rng.uniform(2e3, 15e3, 4)  # wavelengths of curvature change, m
    amp = rng.uniform(0.2, 1.0, 4) * kappa_max / 4  # |kappa| <= kappa_max
    phase = rng.uniform(0, 2 * np.pi, 4)
    kappa = (amp * np.sin(2 * np.pi * s[:, None] / lam + phase)).sum(axis=1)
    ds = np.diff(s)
    heading = rng.uniform(0, 2 * np.pi) + np.r_[0.0, np.cumsum(kappa[:-1] * ds)]
    steps = ds[:, None] * np.stack([np.cos(heading[:-1]), np.sin(heading[:-1])], -1)
    return np.r_[np.zeros((1, 2)), np.cumsum(steps, axis=0)]


def generate_network(
    n_lines: int,
    line_length_km: float,
    seed: int,
    segment_length_m: float = 200.0,
    origin=DEFAULT_ORIGIN,
    vertex_spacing_m: float = 50.0,
) -> Network:
    """A random network of smooth curved lines (for scale tests and benchmarks).

    Each line starts at a random point of a square around the origin (side
    ``max(20 km, 10 km * sqrt(n_lines))``) with a random heading; its curvature is a sum
    of sines with 2-15 km wavelengths, radius never below 600 m. Per line: 0-2 tunnels of
    0.3-1.5 km, stations every 2-6 km, a cruise speed of 20-35 m/s. Lines may cross.
    """
    if n_lines < 1 or not line_length_km > 0:
        raise ValueError("n_lines must be >= 1 and line_length_km > 0")
    length = line_length_km * 1e3
    half = 0.5 * max(20e3, 10e3 * math.sqrt(n_lines))
    width = len(str(n_lines))
    lines = {}
    for k in range(n_lines):
        line_id = f"L{k + 1:0{width}d}"
        rng = stable_rng(seed, "network", line_id)
        xy = rng.uniform(-half, half, 2) + _smooth_curve(rng, length, vertex_spacing_m, 1 / 600)
        tunnels = []
        for _ in range(rng.integers(0, 3)):
            a = rng.uniform(0.05, 0.9) * length
            tunnels.append((round(a, 1), round(min(a + rng.uniform(300, 1500), length - 1), 1)))
        stations = np.cumsum(rng.uniform(2e3, 6e3, int(length / 2e3) + 1))
        stations = np.r_[0.0, stations[stations < length - 1e3], length - 1].round(1)
        lines[line_id] = Line(
            line_id,
            xy_to_lonlat(xy, origin),
            origin,
            segment_length_m=segment_length_m,
            tunnels=sorted(tunnels),
            stations=stations,
            line_speed_mps=round(float(rng.uniform(20, 35)), 1),
        )
    return Network(lines, segment_length_m, origin)
