"""Stack entries the end-to-end tests of `trackfusion up` share."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import zenoh

from schemas import SegmentState, decode


def estimation_on(network: str, state_dir: Path) -> list[dict[str, Any]]:
    """Stack entries of calibration and filtering on ``network`` (``{network}``: the stack's
    ``--network``), each with its store in ``state_dir``."""
    return [
        {"name": "calibration",
         "args": ["--db", str(state_dir / "cal.sqlite"), "--instance", "calibration",
                  "--initial-models", "{defaults}/initial-models.json5", "--network", network]},
        {"name": "filtering",
         "args": ["--db", str(state_dir / "f.sqlite"), "--instance", "filtering",
                  "--network", network]},
    ]  # fmt: skip


class FoldProgress:
    """A state subscriber's view of a flood: the largest ``n_updates`` seen per segment;
    ``done`` once each of ``segments`` segments has ``passes``, ``indexed`` once any state
    holds an on-board update."""

    def __init__(self, segments: int, passes: int) -> None:
        self.segments, self.passes = segments, passes
        self.folded: dict[str, int] = {}
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.indexed = threading.Event()

    def __call__(self, sample: zenoh.Sample) -> None:
        state = decode(sample.payload.to_bytes(), SegmentState)
        with self.lock:
            self.folded[state.segment] = max(self.folded.get(state.segment, 0), state.n_updates)
            if len(self.folded) == self.segments and min(self.folded.values()) == self.passes:
                self.done.set()
        if state.n_updates:
            self.indexed.set()

    def short(self) -> dict[str, int]:
        """The segments with a state of fewer than ``passes`` updates."""
        with self.lock:
            return {s: n for s, n in self.folded.items() if n < self.passes}
