"""`trackfusion ingestion`: the thin adapter around :mod:`services.ingestion.core`.

Reads ``{ns}/raw/**`` (RawChunk) and ``{ns}/gps/*`` (GpsFix) into ONE worker, so the core is
single-threaded and no Zenoh callback waits for it. A gateway that keeps an outbox (producer
``gateway/{id}``, see :mod:`services.runtime.delivery`) is read in its own order, once each
message, live or fetched from the outbox after a gap or a restart
(:class:`~services.runtime.ordered.OrderedSubscription`); a gateway that keeps none is read
as it comes, at most once. The core's state and the position in each gateway's stream are
saved together every few seconds (:mod:`services.runtime.checkpoint`, the file
``checkpoint-ingestion-{instance}.sqlite`` beside the outboxes, or ``--db``): a restarted
ingestion resumes where the checkpoint stopped, and a gateway's message the checkpoint
counts is never lost.

Payloads are decoded with ``schemas.decode`` (a malformed one is a dead letter with the
decoder's reason); PositionedChunks go out on ``{ns}/accel/{train}/{unit}`` through this
process's outbox (producer ``ingestion/{instance}``, the raw chain's retention), which
extraction reads in order; the core's rejections go to ``{ns}/deadletter/ingestion``.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path

from schemas import GpsFix, PositionedChunk, RawChunk, decode, encode, keys
from services.defaults import load_network
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore, Output, Rejection
from services.runtime.checkpoint import CheckpointStore, dumps, fingerprint, resume
from services.runtime.config import RuntimeConfig
from services.runtime.service import ServiceRuntime, network_stage_command, open_checkpoint

log = logging.getLogger(__name__)

SERVICE = "ingestion"
GATEWAY_PRODUCER = "gateway/"  # the outbox producers read in order: gateway/{id}


def decode_gateway(kind: str, key: str, payload: bytes) -> RawChunk | GpsFix:
    """A gateway's payload (``kind`` "raw" or "gps") decoded and checked against its key;
    SchemaError says what is wrong. ``trackfusion gateway check`` uses it too."""
    message = decode(payload, RawChunk if kind == "raw" else GpsFix)
    keys.check_key(key, message)
    return message


class IngestionAdapter:
    """Decode → core → encode → put; one instance per running service."""

    def __init__(self, rt: ServiceRuntime, core: IngestionCore) -> None:
        self.rt = rt
        self.core = core
        self.published = 0

    def start(self, checkpoint: CheckpointStore, fingerprint: str) -> None:
        """Resume from ``checkpoint`` (the core too, when it was saved on the same network
        and configuration ``fingerprint``), then read the gateways."""
        core, positions = resume(checkpoint, fingerprint, self.shared(), "core")
        self.core = core or self.core
        self.outputs = self.rt.reliable_publisher(
            checkpoint.path, durable=checkpoint.path is not None, raw=True
        )
        ns = self.rt.ns
        self.rt.subscribe_checkpointed(
            {"raw": keys.raw_all(ns), "gps": keys.gps_all(ns)},
            lambda kind, key, payload: self.publish(self.handle(kind, key, payload)),
            producers=lambda producer: producer.startswith(GATEWAY_PRODUCER),
            checkpoint=checkpoint,
            positions=positions,
            snapshot=lambda: dumps(self.core, self.shared()),
            fingerprint=fingerprint,
            outputs=self.outputs,
        )

    def shared(self) -> dict[str, object]:
        """What the checkpoint names rather than holds: the map matcher, built from the
        network (tens of MB for a national one)."""
        return {"positioner": self.core.positioner}

    def handle(self, kind: str, key: str, payload: bytes) -> list[Output]:
        """One payload through the core, with this machine's clock as the bound on future
        times (event time stays the data's); raises SchemaError for a malformed one."""
        return self.core.step(decode_gateway(kind, key, payload), time.time())

    def publish(self, outputs: list[Output]) -> None:
        ns = self.rt.ns
        for out in outputs:
            match out:
                case PositionedChunk():
                    self.outputs.put(keys.accel(ns, out.train, out.unit), encode(out))
                    self.published += 1
                case Rejection(reason=reason, message=message):
                    if isinstance(message, RawChunk):
                        key = keys.raw(ns, message.train, message.unit)
                    else:
                        key = keys.gps(ns, message.train)
                    self.rt.deadletters.reject(key, reason, encode(message)[:256])


def ingestion_config(conf: RuntimeConfig) -> IngestionConfig:
    """The thresholds of the config file's ``services.ingestion`` section; ValueError says
    what to fix."""
    options = conf.options(SERVICE, (f.name for f in dataclasses.fields(IngestionConfig)))
    try:
        return IngestionConfig.from_dict(options)
    except TypeError as exc:
        raise ValueError(f"services.{SERVICE}: {exc}") from None


def main(
    conf: RuntimeConfig,
    network_path: str | Path | None = None,
    *,
    db: str | Path | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the ingestion service until ``stop`` is set or SIGINT/SIGTERM; 0.

    Thresholds come from the config file's ``services.ingestion`` section
    (:class:`services.ingestion.config.IngestionConfig` field names); ``db``: the checkpoint
    file (default: ``checkpoint-ingestion-{instance}.sqlite`` beside the outboxes).
    """
    config = ingestion_config(conf)
    network = load_network(network_path)
    core = IngestionCore(network, config)
    log.info("%s: %r", SERVICE, network)
    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
        checkpoint = open_checkpoint(rt, db)
        IngestionAdapter(rt, core).start(checkpoint, fingerprint(network_path, config))
        return rt.run()


add_arguments, run = network_stage_command(
    main,
    "Subscribe to {ns}/raw/** and {ns}/gps/*, publish PositionedChunks on "
    "{ns}/accel/{train}/{unit}; thresholds in the config file's services.ingestion.",
    network="the lines to map-match on",
    db="the checkpoint (the core's state and the gateways' positions)",
)
