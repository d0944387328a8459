"""The latest value per key, answered to queries: how a late joiner gets models and states.

A service keeps the newest encoded payload of each key it publishes (``put`` from its worker)
and declares :meth:`LatestValues.on_query` as the callback of a queryable; a query gets one
reply per kept key that its key expression matches, on that key. The callback only copies
references under the lock and replies (replying from a callback is allowed), so it never
holds up the worker or the session.
"""

from __future__ import annotations

import threading

import zenoh


class LatestValues:
    """``{key: latest payload}``, shared by a worker (``put``) and a queryable callback."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._payloads: dict[str, tuple[zenoh.KeyExpr, bytes]] = {}

    def put(self, key: str, payload: bytes) -> None:
        """Keep ``payload`` as the latest of ``key`` (a concrete key: ValueError for a wildcard)."""
        if "*" in key:
            raise ValueError(f"key: {key!r} is a key expression with wildcards, not a key")
        key_expr = zenoh.KeyExpr(key)
        with self._lock:
            self._payloads[key] = (key_expr, payload)

    def matching(self, key_expr: zenoh.KeyExpr) -> list[tuple[zenoh.KeyExpr, bytes]]:
        """The kept ``(key, payload)`` pairs whose key ``key_expr`` matches."""
        text = str(key_expr)
        if "*" not in text:  # a concrete key (no `*`, `**` or `$*`): one lookup, not a scan
            with self._lock:
                held = self._payloads.get(text)
            return [held] if held is not None else []
        with self._lock:
            held_all = list(self._payloads.values())
        return [(key, payload) for key, payload in held_all if key_expr.intersects(key)]

    def on_query(self, query: zenoh.Query) -> None:
        """Queryable callback: reply with every kept value the query's key expression matches."""
        for key, payload in self.matching(query.key_expr):
            query.reply(key, payload)
