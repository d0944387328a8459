"""Dead letters: a rejected payload is published with a reason and counted; nothing crashes."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from schemas import DeadLetter, encode, keys

log = logging.getLogger(__name__)

PAYLOAD_HEAD_BYTES = 256
MAX_REASON_CHARS = 1000  # a letter's reason is cut here
MAX_REASONS = 1000  # distinct reasons counted; the rest are counted together under OTHER
OTHER = "(other reasons)"


class DeadLetterPublisher:
    """Publishes :class:`schemas.DeadLetter` on ``{ns}/deadletter/{service}``.

    ``counts`` maps each reason to the number of rejections so far (thread-safe to call
    :meth:`reject` from several workers). Publishing failures are logged, never raised.
    """

    def __init__(
        self,
        session: zenoh.Session,
        ns: str,
        service: str,
        *,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.service = service
        self.key = keys.deadletter(ns, service)
        self.counts: dict[str, int] = {}
        self._clock = clock  # wall clock on purpose: a rejected payload has no trusted time
        self._lock = threading.Lock()
        # BLOCK, like every data path: a rejection's letter is its only record for the
        # sender, so a busy router slows the service down rather than dropping it
        self._publisher: zenoh.Publisher | None = session.declare_publisher(
            self.key, congestion_control=zenoh.CongestionControl.BLOCK
        )

    def reject(
        self,
        key: str | zenoh.KeyExpr,
        reason: str,
        payload: bytes | bytearray | memoryview | zenoh.ZBytes | None = None,
    ) -> DeadLetter:
        """Count and publish one rejection of ``payload`` received on ``key``."""
        reason = (reason or "unspecified")[:MAX_REASON_CHARS]
        with self._lock:
            # reasons quote the bad values: a sender must not grow the counter without bound
            counted = reason if reason in self.counts or len(self.counts) < MAX_REASONS else OTHER
            self.counts[counted] = self.counts.get(counted, 0) + 1
            count = self.counts[counted]
        letter = DeadLetter(
            service=self.service,
            key=str(key),
            reason=reason,
            payload_head=_head(payload),
            received_at=self._clock(),
        )
        log.warning("dead letter #%d from %s: %s", count, letter.key, reason)
        publisher = self._publisher
        if publisher is None:
            log.error("dead letter publisher closed; dropped dead letter for %s", letter.key)
            return letter
        try:
            publisher.put(encode(letter))
        except zenoh.ZError as e:  # session closing: the counter still has it
            log.error("could not publish dead letter for %s: %s", letter.key, e)
        return letter

    def reject_sample(self, sample: zenoh.Sample, reason: str) -> DeadLetter:
        return self.reject(sample.key_expr, reason, sample.payload)

    @property
    def publisher(self) -> zenoh.Publisher | None:
        """The underlying publisher (None once undeclared), e.g. for its matching status."""
        return self._publisher

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def undeclare(self) -> None:
        publisher, self._publisher = self._publisher, None
        if publisher is not None:
            publisher.undeclare()


def _head(payload: bytes | bytearray | memoryview | zenoh.ZBytes | None) -> bytes:
    if payload is None:
        return b""
    if isinstance(payload, zenoh.ZBytes):
        payload = payload.to_bytes()
    return bytes(payload[:PAYLOAD_HEAD_BYTES])
