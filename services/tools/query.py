"""The Zenoh side of a command: open a short-lived session, and ask a queryable."""

from __future__ import annotations

import zenoh

from services.runtime.config import RuntimeConfig

QUERY_TIMEOUT_S = 10.0  # `--timeout`: a service catching up on a backlog answers late


def ask(session: zenoh.Session, selector: str, timeout: float = QUERY_TIMEOUT_S):
    """(key, payload bytes) of every reply to a query; errors from the queryable raise."""
    # replies take the query's QoS: BLOCK, so that none is dropped under congestion
    block = zenoh.CongestionControl.BLOCK
    for reply in session.get(selector, timeout=timeout, congestion_control=block):
        if reply.ok is None:
            reason = reply.err.payload.to_string()
            if reason == "Timeout":  # Zenoh's own error when the answer is incomplete
                raise SystemExit(
                    f"{selector}: no complete answer within {timeout:g} s. A service that is "
                    "catching up on a backlog answers only after the events queued ahead of "
                    "the question: try again, or give a larger --timeout."
                )
            raise SystemExit(f"{selector}: {reason}")
        yield str(reply.ok.key_expr), reply.ok.payload.to_bytes()


def open_session(conf: RuntimeConfig) -> zenoh.Session:
    """A session of a command; SystemExit saying what to check when the router is not there."""
    try:
        return zenoh.open(conf.zenoh_config())
    except zenoh.ZError as exc:
        raise SystemExit(f"cannot reach the router ({exc}); is `trackfusion up` running?") from None
