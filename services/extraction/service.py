"""`trackfusion extraction`: the thin adapter around :mod:`services.extraction.pipeline`.

Subscribes ``{ns}/accel/**`` (PositionedChunk from ingestion), runs every chunk through the
:class:`~services.extraction.pipeline.Extractor` in ONE worker thread (pipelines per
(train, unit) created on demand; no lock needed), and publishes each OnboardIndex on
``{ns}/index/{line}/{segment}`` through the runtime's at-least-once publisher (cached per
key for consumers that come back; congestion control BLOCK: an index is never dropped, a
slow consumer slows extraction down). A malformed chunk becomes a dead
letter. The counters (passes indexed, skipped by reason) are logged every
``LOG_EVERY_S`` and at exit.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from schemas import PositionedChunk, decode, encode, keys
from services.defaults import load_network
from services.extraction.pipeline import ExtractionConfig, Extractor
from services.runtime.config import RuntimeConfig
from services.runtime.service import ServiceRuntime, network_stage_command
from track.segments import SegmentTable

log = logging.getLogger(__name__)

SERVICE = "extraction"
LOG_EVERY_S = 60.0  # wall clock: only for the log line, never for the data


class ExtractionAdapter:
    """Decode -> core -> encode -> put."""

    def __init__(self, rt: ServiceRuntime, extractor: Extractor) -> None:
        self.rt = rt
        self.extractor = extractor
        self.published = 0
        self._next_log = time.monotonic() + LOG_EVERY_S

    def start(self) -> None:
        self.indices = self.rt.reliable_publisher()  # at-least-once to calibration, filtering
        self.rt.subscribe_in_order(
            {"accel": keys.accel_all(self.rt.ns)},
            lambda _kind, key, payload: self.handle(key, payload),
        )

    def handle(self, key: str, payload: bytes) -> None:
        chunk = decode(payload, PositionedChunk)
        keys.check_key(key, chunk)
        for index in self.extractor.process(chunk):
            self.indices.put(keys.index(self.rt.ns, index.line, index.segment), encode(index))
            self.published += 1
        if time.monotonic() >= self._next_log:
            self._next_log = time.monotonic() + LOG_EVERY_S
            log_counters(self.extractor)


def log_counters(extractor: Extractor) -> None:
    c = extractor.counters()
    log.info(
        "%s: %d units, %d passes indexed, skipped: position %d, slow %d, coverage %d, "
        "implausible %d; %d chunks, %d resets, %d reversals, %d on unknown lines",
        SERVICE, len(extractor.pipelines), c.passes_indexed, c.skipped_position,
        c.skipped_slow, c.skipped_coverage, c.skipped_implausible, c.chunks, c.resets,
        c.reversals, c.unknown_line,
    )  # fmt: skip


def main(
    conf: RuntimeConfig,
    network_path: str | Path | None = None,
    *,
    config: ExtractionConfig | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the extraction service until ``stop`` is set or SIGINT/SIGTERM; 0."""
    segments = SegmentTable.from_network(load_network(network_path))
    extractor = Extractor(segments, config)
    log.info("%s: %d lines, %d segments", SERVICE, len(segments.lines), segments.n_segments)
    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
        ExtractionAdapter(rt, extractor).start()
        try:
            return rt.run()
        finally:
            log_counters(extractor)


add_arguments, run = network_stage_command(
    main,
    "Subscribe to {ns}/accel/** (PositionedChunk), publish one OnboardIndex per segment "
    "pass on {ns}/index/{line}/{segment}.",
    network="the segment bounds",
)
