"""An event-time watermark that no single sender can move: "now" is the newest time that
several segments have reached, so one message dated far ahead (an outlier, a wrong clock)
does not make every other segment look late."""

from __future__ import annotations

import math
from collections.abc import Hashable


class NewestTimes:
    """The newest event time of each segment, and the ``keep`` segments furthest ahead."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self.latest: dict[Hashable, float] = {}  # newest event time per segment
        self._top: list[tuple[float, Hashable]] = []  # the ``keep`` newest, descending

    def __len__(self) -> int:
        return len(self.latest)

    def note(self, where: Hashable, t: float) -> None:
        """Note a segment's event time (an older one than it has changes nothing)."""
        if t <= self.latest.get(where, -math.inf):
            return
        self.latest[where] = t
        top = [entry for entry in self._top if entry[1] != where]
        top.append((t, where))
        top.sort(reverse=True)
        self._top = top[: self.keep]

    def kth(self, k: int) -> float | None:
        """The newest time ``k`` segments have reached (1 <= k <= ``keep``, at most the
        segments known); None before any time."""
        return self._top[k - 1][0] if self._top else None
