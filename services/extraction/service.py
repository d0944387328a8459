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

import argparse
import logging
import threading
import time
from pathlib import Path

from schemas import PositionedChunk, decode, encode, keys
from services.defaults import DEMO_NETWORK, add_network_argument
from services.extraction.pipeline import ExtractionConfig, Extractor
from services.runtime.config import RuntimeConfig, add_zenoh_arguments, config_from_args
from services.runtime.service import ServiceRuntime, configure_logging
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
            self.log_counters()

    def log_counters(self) -> None:
        c = self.extractor.counters()
        log.info(
            "%s: %d units, %d passes indexed, skipped: position %d, slow %d, coverage %d, "
            "implausible %d; %d chunks, %d resets, %d reversals, %d on unknown lines",
            SERVICE, len(self.extractor.pipelines), c.passes_indexed, c.skipped_position,
            c.skipped_slow, c.skipped_coverage, c.skipped_implausible, c.chunks, c.resets,
            c.reversals, c.unknown_line,
        )  # fmt: skip


def load_segments(network_path: str | Path | None) -> SegmentTable:
    """The segment table of a network GeoJSON file; ValueError says what is wrong."""
    path = Path(network_path or DEMO_NETWORK)
    try:
        return SegmentTable.from_geojson(path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"network {path}: {exc}") from None


def main(
    conf: RuntimeConfig,
    network_path: str | Path | None = None,
    *,
    config: ExtractionConfig | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the extraction service until ``stop`` is set or SIGINT/SIGTERM; 0."""
    segments = load_segments(network_path)
    extractor = Extractor(segments, config)
    log.info("%s: %d lines, %d segments", SERVICE, len(segments.lines), segments.n_segments)
    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
        adapter = ExtractionAdapter(rt, extractor)
        adapter.start()
        try:
            return rt.run()
        finally:
            adapter.log_counters()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion extraction``."""
    parser.description = (
        "Subscribe to {ns}/accel/** (PositionedChunk), publish one OnboardIndex per "
        "segment pass on {ns}/index/{line}/{segment}."
    )
    add_network_argument(parser, "the segment bounds")
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    configure_logging(args.log_level)
    return main(config_from_args(args), network_path=args.network)
