"""`trackfusion ingestion`: the thin adapter around :mod:`services.ingestion.core`.

Subscribes ``{ns}/raw/**`` (RawChunk) and ``{ns}/gps/*`` (GpsFix); both subscriptions feed
the runtime's inbox, drained by ONE worker (order kept per key), so the core is
single-threaded and no Zenoh callback waits for it.
Payloads are decoded with ``schemas.decode`` (a malformed one is a dead letter with the
decoder's reason); PositionedChunks go out with ``session.put`` on
``{ns}/accel/{train}/{unit}`` (congestion control BLOCK: extraction must not lose samples);
the core's rejections go to ``{ns}/deadletter/ingestion``. When the subscriptions end
(shutdown), the held chunks are flushed (``position_ok`` False where their knots are
missing) before the worker exits.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path

import zenoh

from schemas import GpsFix, PositionedChunk, RawChunk, decode, encode, keys
from services.defaults import load_network
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore, Output, Rejection
from services.runtime.config import RuntimeConfig
from services.runtime.service import ServiceRuntime, network_stage_command

log = logging.getLogger(__name__)

SERVICE = "ingestion"


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

    def start(self) -> None:
        ns = self.rt.ns
        self.rt.subscribe_in_order(
            {"raw": keys.raw_all(ns), "gps": keys.gps_all(ns)},
            lambda kind, key, payload: self.publish(self.handle(kind, key, payload)),
            on_end=self._finish,
        )

    def _finish(self) -> None:
        """Every subscription has ended: release the held chunks and say what was done."""
        self.publish(self.core.flush())
        log.info(
            "%s: %d positioned chunks published, %d dead letters",
            SERVICE,
            self.published,
            self.rt.deadletters.total,
        )

    def handle(self, kind: str, key: str, payload: bytes) -> list[Output]:
        """One payload through the core, with this machine's clock as the bound on future
        times (event time stays the data's); raises SchemaError for a malformed one."""
        return self.core.step(decode_gateway(kind, key, payload), time.time())

    def publish(self, outputs: list[Output]) -> None:
        ns, session = self.rt.ns, self.rt.session
        for out in outputs:
            match out:
                case PositionedChunk():
                    session.put(
                        keys.accel(ns, out.train, out.unit),
                        encode(out),
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
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
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the ingestion service until ``stop`` is set or SIGINT/SIGTERM; 0.

    Thresholds come from the config file's ``services.ingestion`` section
    (:class:`services.ingestion.config.IngestionConfig` field names).
    """
    config = ingestion_config(conf)
    network = load_network(network_path)
    core = IngestionCore(network, config)
    log.info("%s: %r", SERVICE, network)
    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
        IngestionAdapter(rt, core).start()
        return rt.run()


add_arguments, run = network_stage_command(
    main,
    "Subscribe to {ns}/raw/** and {ns}/gps/*, publish PositionedChunks on "
    "{ns}/accel/{train}/{unit}; thresholds in the config file's services.ingestion.",
    network="the lines to map-match on",
)
