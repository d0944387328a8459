"""Segment bounds by line: how the services look a chainage or a segment id up.

The network's segments (:mod:`track.network`) as sorted arrays per line, without the
geometry: what extraction needs to cut a unit's stream into segments, and what filtering
and calibration need to tell a known segment from an unknown one.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas import SchemaError
from track.network import Network


@dataclass(frozen=True)
class LineSegments:
    """Segment bounds of one line: ``[starts[k], ends[k])`` with ids, increasing chainage."""

    line: str
    ids: tuple[str, ...]
    starts: np.ndarray
    ends: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.ids)
        if n == 0 or self.starts.shape != (n,) or self.ends.shape != (n,):
            raise ValueError(f"line {self.line}: ids, starts and ends must have one entry each")
        if not (np.all(self.ends > self.starts) and np.all(self.starts[1:] >= self.ends[:-1])):
            raise ValueError(f"line {self.line}: segments must be increasing and not overlap")

    def locate(self, x: np.ndarray, inset_m: float = 0.0) -> np.ndarray:
        """Segment index of each chainage in ``[start + inset, end - inset)``, else -1."""
        k = np.searchsorted(self.starts, x, side="right") - 1
        kc = np.clip(k, 0, len(self.ids) - 1)
        inside = (x >= self.starts[kc] + inset_m) & (x < self.ends[kc] - inset_m)
        return np.where((k >= 0) & inside, kc, -1)


class SegmentTable:
    """The network's segments by line id (what the extraction needs of the network)."""

    def __init__(self, lines: dict[str, LineSegments]) -> None:
        self.lines = dict(lines)

    @classmethod
    def from_network(cls, network) -> SegmentTable:
        """From a :class:`track.network.Network` (lines with ``segments``)."""
        out = {}
        for line_id, line in network.lines.items():
            segs = line.segments
            out[line_id] = LineSegments(
                line_id,
                tuple(s.id for s in segs),
                np.array([s.start_m for s in segs], dtype=np.float64),
                np.array([s.end_m for s in segs], dtype=np.float64),
            )
        return cls(out)

    @classmethod
    def from_geojson(cls, path: str | Path, segment_length_m: float | None = None) -> SegmentTable:
        """Read a network GeoJSON file (:meth:`track.network.Network.from_geojson`)."""
        return cls.from_network(Network.from_geojson(Path(path), segment_length_m))

    @property
    def n_segments(self) -> int:
        return sum(len(s.ids) for s in self.lines.values())


class KnownSegments:
    """The (line, segment) ids of one network, under its name.

    A service given a network refuses a message on any other segment (a dead letter that
    names the network), so a sender cannot make it keep state for ids that do not exist.
    """

    def __init__(self, ids: Iterable[tuple[str, str]], network: str) -> None:
        self.ids = frozenset(ids)
        self.network = network

    @classmethod
    def of(cls, network: Network, name: str) -> KnownSegments:
        """The segments of a :class:`track.network.Network`; ``name`` is its file's."""
        return cls(((line.id, seg.id) for line, seg in network.segments()), name)

    def __len__(self) -> int:
        return len(self.ids)

    def check(self, message) -> None:
        """Refuse a message (with ``line`` and ``segment``) on a segment the network lacks:
        SchemaError ``SegmentState: segment L1/s99 is not in the network demo.geojson``."""
        if (message.line, message.segment) not in self.ids:
            raise SchemaError(
                f"{type(message).__name__}: segment {message.line}/{message.segment} is not "
                f"in the network {self.network}"
            )
