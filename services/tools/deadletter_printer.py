"""`trackfusion deadletters`: print every dead letter of a namespace, one line each.

Output on stdout, flushed per line: ``{service} {key} {reason}`` (service and key contain no
spaces, so ``line.split(" ", 2)`` gives the three fields back). Logs go to stderr.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from typing import TextIO

from schemas import DeadLetter, SchemaError, decode, keys
from services.runtime.config import RuntimeConfig, add_zenoh_arguments
from services.runtime.service import ServiceRuntime, run_command

log = logging.getLogger(__name__)

SERVICE = "deadletters"


def format_line(letter: DeadLetter) -> str:
    reason = " ".join(letter.reason.split())  # one line, whatever the reason holds
    return f"{letter.service} {letter.key} {reason}"


def main(
    conf: RuntimeConfig,
    out: TextIO | None = None,
    *,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Print dead letters to ``out`` (stdout) until ``stop`` is set or SIGINT/SIGTERM; 0."""
    out = out or sys.stdout

    def on_letter(_kind: str, key: str, payload: bytes) -> None:
        try:
            letter = decode(payload, DeadLetter)
        except SchemaError as e:
            # never dead-letter a dead letter: that would loop through our own subscription
            log.warning("undecodable dead letter on %s: %s", key, e)
            return
        out.write(format_line(letter) + "\n")
        out.flush()

    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
        rt.subscribe_in_order({"deadletter": keys.deadletter_all(rt.ns)}, on_letter)
        return rt.run()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion deadletters``."""
    parser.description = "Subscribe to {ns}/deadletter/** and print one line per dead letter."
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return run_command(args, main)
