"""`trackfusion extraction`: the thin adapter around :mod:`services.extraction.pipeline`.

Reads ``{ns}/accel/**`` (PositionedChunk) from ingestion's outbox (producers
``ingestion/{instance}``) in ingestion's order, once each message, live or fetched after a gap
or a restart (:class:`~services.runtime.ordered.OrderedSubscription`), and runs every chunk
through the :class:`~services.extraction.pipeline.Extractor` in ONE worker thread (pipelines
per (train, unit) created on demand; no lock needed). Each OnboardIndex goes out on
``{ns}/index/{line}/{segment}`` through this process's outbox (at least once to calibration
and filtering; congestion control BLOCK: an index is never dropped, a slow consumer slows
extraction down). The extractor's state and the position in ingestion's stream are saved
together every few seconds (:mod:`services.runtime.checkpoint`, the file
``checkpoint-extraction-{instance}.sqlite`` beside the outboxes, or ``--db``), so a
restarted extraction resumes mid-pass. A malformed chunk becomes a dead letter. The counters
(passes indexed, skipped by reason) are logged every ``LOG_EVERY_S`` and at exit.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from schemas import PositionedChunk, decode, encode, keys
from services.defaults import load_network
from services.extraction.pipeline import ExtractionConfig, Extractor
from services.runtime.checkpoint import CheckpointStore, dumps, fingerprint, resume
from services.runtime.config import RuntimeConfig
from services.runtime.service import ServiceRuntime, network_stage_command, open_checkpoint
from track.segments import SegmentTable

log = logging.getLogger(__name__)

SERVICE = "extraction"
INGESTION_PRODUCER = "ingestion/"  # the outbox producers read in order
LOG_EVERY_S = 60.0  # wall clock: only for the log line, never for the data


class ExtractionAdapter:
    """Decode -> core -> encode -> put."""

    def __init__(self, rt: ServiceRuntime, extractor: Extractor) -> None:
        self.rt = rt
        self.extractor = extractor
        self.published = 0
        self._next_log = time.monotonic() + LOG_EVERY_S

    def start(self, checkpoint: CheckpointStore, fingerprint: str) -> None:
        """Resume from ``checkpoint`` (the extractor too, when it was saved on the same
        network and configuration ``fingerprint``), then read ingestion's stream."""
        extractor, positions = resume(checkpoint, fingerprint, shared(self.extractor), "extractor")
        self.extractor = extractor or self.extractor
        # at least once to calibration and filtering
        self.indices = self.rt.reliable_publisher(
            checkpoint.path, durable=checkpoint.path is not None
        )
        self.rt.subscribe_checkpointed(
            {"accel": keys.accel_all(self.rt.ns)},
            lambda _kind, key, payload: self.handle(key, payload),
            producers=lambda producer: producer.startswith(INGESTION_PRODUCER),
            checkpoint=checkpoint,
            positions=positions,
            snapshot=lambda: dumps(self.extractor, shared(self.extractor)),
            fingerprint=fingerprint,
            outputs=self.indices,
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


def shared(extractor: Extractor) -> dict[str, object]:
    """What the checkpoint names rather than holds: the segment table and its lines."""
    table = extractor.segments
    return {"segments": table, **{f"line/{k}": line for k, line in table.lines.items()}}


def log_counters(extractor: Extractor) -> None:
    c = extractor.counters()
    log.info(
        "%s: %d units, %d passes indexed, skipped: position %d, slow %d, coverage %d, "
        "implausible %d; %d chunks, %d resets, %d reversals, %d on unknown lines, "
        "%d duplicates",
        SERVICE, len(extractor.pipelines), c.passes_indexed, c.skipped_position,
        c.skipped_slow, c.skipped_coverage, c.skipped_implausible, c.chunks, c.resets,
        c.reversals, c.unknown_line, c.duplicates,
    )  # fmt: skip


def main(
    conf: RuntimeConfig,
    network_path: str | Path | None = None,
    *,
    config: ExtractionConfig | None = None,
    db: str | Path | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the extraction service until ``stop`` is set or SIGINT/SIGTERM; 0."""
    segments = SegmentTable.from_network(load_network(network_path))
    extractor = Extractor(segments, config)
    log.info("%s: %d lines, %d segments", SERVICE, len(segments.lines), segments.n_segments)
    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
        adapter = ExtractionAdapter(rt, extractor)
        adapter.start(open_checkpoint(rt, db), fingerprint(network_path, extractor.config))
        try:
            return rt.run()
        finally:
            log_counters(adapter.extractor)


add_arguments, run = network_stage_command(
    main,
    "Subscribe to {ns}/accel/** (PositionedChunk), publish one OnboardIndex per segment "
    "pass on {ns}/index/{line}/{segment}.",
    network="the segment bounds",
    db="the checkpoint (the extractor's state and ingestion's position)",
)
