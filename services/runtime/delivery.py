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

What it guarantees: on the first ``max_publishers`` keys a process publishes (2,000 by
default; past them, plain puts, see :class:`ReliablePublisher`), a subscriber that was away
(restart, router restart, link cut) for less than a publisher's cache window,
``cache_samples`` messages per key, gets every message it missed, while that publisher
process is alive. Messages arrive at least once: history and
recovery repeat what a subscriber may already have; every consumer is idempotent
(the filtering fold, calibration's pairing, alerting's hysteresis). What it does not: a
publisher's cache dies with its process, so a message published by a process that has
since died reaches only those who were connected then.

Settings (``services.delivery`` in the config file): ``cache_samples`` (default 64 per
key), ``heartbeat_s`` (default 0.5: the longest a gap stays unnoticed when no newer message
follows it), ``max_publishers`` (default 2,000 keys per process with a cache).
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
    max_publishers: int = 2000

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
        if not (isinstance(settings.max_publishers, int) and settings.max_publishers >= 1):
            raise ValueError(
                f"services.delivery.max_publishers must be an integer ≥ 1, "
                f"got {settings.max_publishers!r}"
            )
        return settings


class ReliablePublisher:
    """``put(key, payload)`` on any concrete key: the first ``max_publishers`` distinct keys
    each through their own cached ``AdvancedPublisher``, every further key through a plain
    ``session.put`` (at most once).

    A key's advanced publisher is declared on its first put and kept for the life of the
    process. Why a bound, and why not a recently-used set: every advanced publisher holds a
    cache, a heartbeat timer, a queryable and a liveliness token that the routers and every
    advanced subscriber track (each subscriber queries a new publisher's cache), and the
    cost grows faster than their number (``bench/delivery_scale.py``, one router, one
    subscriber: 1,000 publishers took 0.4 s to declare and 1 % of a core idle; 10,000 took
    40 s and a whole core idle). Evicting the least recently used publisher to declare one
    for a new key costs a declaration and an undeclaration per put, and every subscriber a
    query: 133 puts/s and growing router memory at 10,000 keys through 2,000 publishers.
    So past the bound a key is published plainly: a consumer connected at that moment gets
    it, a returning one recovers the newest *state* from the ``q/state`` queryables, and a
    process that publishes more keys than its bound says so once in its log. Size the
    bound (``services.delivery.max_publishers``) and the key ranges per process together.
    Thread-safe. :meth:`undeclare` undeclares them all.

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
        self.plain_puts = 0  # puts on keys past the bound

    def put(self, key: str, payload: bytes) -> None:
        with self._lock:
            publisher = self._publishers.get(key)
            if publisher is None:
                if len(self._publishers) < self._settings.max_publishers:
                    publisher = self._declare(key)
                    self._publishers[key] = publisher
                else:
                    if not self.plain_puts:
                        log.warning(
                            "more than %d keys (services.delivery.max_publishers): %s and "
                            "every further key are published without a cache (at most once)",
                            self._settings.max_publishers,
                            key,
                        )
                    self.plain_puts += 1
        if publisher is None:
            self._session.put(key, payload, congestion_control=self._congestion_control)
        else:
            publisher.put(payload)

    def cached(self, key: str) -> bool:
        """Whether ``key`` has an advanced publisher (a cache for returning subscribers)."""
        with self._lock:
            return key in self._publishers

    def __len__(self) -> int:
        return len(self._publishers)

    def undeclare(self) -> None:
        with self._lock:
            publishers, self._publishers = list(self._publishers.values()), {}
        for publisher in publishers:
            self._undeclare(publisher)

    @staticmethod
    def _undeclare(publisher: zenoh.ext.AdvancedPublisher) -> None:
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
