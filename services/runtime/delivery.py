"""At-least-once delivery for the event and model streams, on Zenoh's advanced pub/sub.

A plain ``put`` reaches the subscribers that are connected at that moment and no one else:
a subscriber being restarted, a router being restarted or a cut link loses it. The index,
TRC, maintenance, model and state streams therefore go through
:class:`ReliablePublisher` and are read with :func:`declare_reliable_subscriber`:

* the publisher keeps, per key, the last ``cache_samples`` samples (a
  ``zenoh.ext.AdvancedPublisher`` with a cache, sequence numbers, sporadic heartbeats and a
  liveliness token ``{key}/@adv/pub/…``);
* the subscriber (``zenoh.ext.AdvancedSubscriber``) asks every matching publisher's cache for
  its history when it starts and whenever a publisher appears (a restarted subscriber, a
  publisher seen again after a router restart), and asks again for what it missed when a
  heartbeat or a later sample shows a gap in a publisher's sequence numbers (a cut link,
  a dropped message).

What it guarantees: a subscriber that was away (restart, router restart, link cut) for less
than a publisher's cache window, ``cache_samples`` messages per key, gets every message it
missed, while that publisher process is alive. Messages arrive at least once: history and
recovery repeat what a subscriber may already have; every consumer is idempotent
(the filtering fold, calibration's pairing, alerting's hysteresis). What it does not: a
publisher's cache dies with its process, so a message published by a process that has
since died reaches only those who were connected then.

Settings (``services.delivery`` in the config file): ``cache_samples`` (default 64 per
key), ``heartbeat_s`` (default 0.5: the longest a gap stays unnoticed when no newer message
follows it).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext

log = logging.getLogger(__name__)

ADVANCED_CHUNK = "@adv"  # the verbatim chunk under which zenoh-ext declares its machinery


@dataclass(frozen=True)
class DeliverySettings:
    """How much each publisher keeps for late and returning subscribers."""

    cache_samples: int = 64
    heartbeat_s: float = 0.5

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> DeliverySettings:
        """From the ``services.delivery`` section (its keys checked by the config loader);
        ValueError says which value to fix."""
        settings = cls(**options)
        if not (isinstance(settings.cache_samples, int) and settings.cache_samples >= 1):
            raise ValueError(
                f"services.delivery.cache_samples must be an integer ≥ 1, "
                f"got {settings.cache_samples!r}"
            )
        if not (isinstance(settings.heartbeat_s, int | float) and settings.heartbeat_s > 0):
            raise ValueError(
                f"services.delivery.heartbeat_s must be a number > 0, got {settings.heartbeat_s!r}"
            )
        return settings


class ReliablePublisher:
    """``put(key, payload)`` on any concrete key, each key through its own cached
    ``AdvancedPublisher`` (declared on first use and kept: declaring per message is what
    zenoh#1518 warns against). Thread-safe. :meth:`undeclare` undeclares them all.

    ``congestion_control`` BLOCK (the default) makes a slow router slow the caller down
    instead of dropping; the cache covers what a disconnected subscriber misses.
    """

    def __init__(
        self,
        session: zenoh.Session,
        settings: DeliverySettings = DeliverySettings(),
        *,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
    ) -> None:
        self._session = session
        self._settings = settings
        self._congestion_control = congestion_control
        self._publishers: dict[str, zenoh.ext.AdvancedPublisher] = {}
        self._lock = threading.Lock()

    def put(self, key: str, payload: bytes) -> None:
        with self._lock:
            publisher = self._publishers.get(key)
            if publisher is None:
                publisher = self._declare(key)
                self._publishers[key] = publisher
        publisher.put(payload)

    def __len__(self) -> int:
        return len(self._publishers)

    def undeclare(self) -> None:
        with self._lock:
            publishers, self._publishers = list(self._publishers.values()), {}
        for publisher in publishers:
            try:
                publisher.undeclare()
            except zenoh.ZError as e:
                log.warning("undeclare advanced publisher: %s", e)

    def _declare(self, key: str) -> zenoh.ext.AdvancedPublisher:
        return zenoh.ext.declare_advanced_publisher(
            self._session,
            key,
            congestion_control=self._congestion_control,
            cache=zenoh.ext.CacheConfig(
                self._settings.cache_samples,
                replies_config=zenoh.ext.RepliesConfig(
                    congestion_control=zenoh.CongestionControl.BLOCK
                ),
            ),
            # sporadic: a heartbeat only after the sequence number moved, so an idle key
            # (most segments, most of the time) costs nothing
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                sporadic_heartbeat=self._settings.heartbeat_s
            ),
            publisher_detection=True,
        )


def declare_reliable_subscriber(
    session: zenoh.Session, key: str, handler: Any
) -> zenoh.ext.AdvancedSubscriber:
    """An ``AdvancedSubscriber`` on ``key`` that fetches the history of every matching
    cached publisher (at start and when one appears) and recovers missed samples."""
    return zenoh.ext.declare_advanced_subscriber(
        session,
        key,
        handler,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
        recovery=zenoh.ext.RecoveryConfig(heartbeat=True),
        subscriber_detection=True,
    )
