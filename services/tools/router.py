"""`trackfusion router`: a Zenoh router in a Python process (no zenohd needed on one machine).

It routes pub/sub, queries and liveliness between client services and enforces TLS and
access control from its configuration; it cannot load zenohd plugins (storages, REST), for
which the real ``zenohd -c services/defaults/router.json5`` takes the same file.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from types import FrameType

import zenoh

from services.runtime.config import (
    ROUTER_CONFIG,
    RuntimeConfig,
    add_zenoh_arguments,
    config_from_args,
    endpoints,
    zenoh_config,
)
from services.runtime.service import configure_logging

log = logging.getLogger(__name__)


def main(conf: RuntimeConfig, stop: threading.Event | None = None) -> int:
    """Run a router session from ``conf`` until ``stop`` is set or SIGINT/SIGTERM; exit 0.

    ``conf`` is normally ``services/defaults/router.json5`` overlaid with ``--listen`` and
    ``--connect``; its mode is forced to router.
    """
    conf = RuntimeConfig(
        ns=conf.ns,
        instance=conf.instance,
        zenoh={**conf.zenoh, "mode": "router"},
        services=conf.services,
        source=conf.source,
    )
    stop = stop or threading.Event()
    previous = _install_signal_handlers(stop)
    try:
        with zenoh.open(zenoh_config(conf)) as session:
            log.info(
                "router %s listening on %s%s",
                session.zid(),
                ", ".join(endpoints(conf, "listen")),
                f", connecting to {', '.join(c)}" if (c := endpoints(conf, "connect")) else "",
            )
            stop.wait()
            log.info("router stopping")
    except zenoh.ZError as e:
        raise SystemExit(
            f"router: cannot listen on {', '.join(endpoints(conf, 'listen'))}: {e}; "
            "is another router already running there? (choose another one with --listen)"
        ) from None
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    log.info("router closed")
    return 0


def _install_signal_handlers(stop: threading.Event) -> dict[int, object]:
    if threading.current_thread() is not threading.main_thread():
        return {}

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("router: received %s", signal.Signals(signum).name)
        # Event.set takes a lock the interrupted main thread may hold: set it from a thread.
        threading.Thread(target=stop.set, name="stop", daemon=True).start()

    return {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion router``: the flags every process takes, without ``--mode``."""
    parser.description = f"Run a Zenoh router; --config defaults to {ROUTER_CONFIG}."
    add_zenoh_arguments(parser, mode=False)


def run(args: argparse.Namespace) -> int:
    configure_logging(args.log_level)
    return main(config_from_args(args, default_file=ROUTER_CONFIG, mode="router"))
