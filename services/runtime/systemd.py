"""The systemd notify protocol (``Type=notify``, ``WatchdogSec=``), without a dependency.

systemd passes ``NOTIFY_SOCKET`` (a datagram socket path, ``@`` for the abstract namespace)
and, with ``WatchdogSec=``, ``WATCHDOG_USEC``. A service says ``READY=1`` once it holds its
liveliness token and ``WATCHDOG=1`` from its worker loops at least every half interval;
systemd restarts it when the pings stop (a hung worker). Outside systemd every call is a
no-op, so the same code runs under ``trackfusion up``, in tests and by hand.
"""

from __future__ import annotations

import os
import socket
import threading
import time

_lock = threading.Lock()
_last_ping = 0.0


def _socket_path() -> str | None:
    path = os.environ.get("NOTIFY_SOCKET")
    if not path:
        return None
    return "\0" + path[1:] if path.startswith("@") else path


def notify(message: str) -> bool:
    """Send ``message`` (e.g. ``"READY=1"``) to systemd; False when not run by systemd."""
    path = _socket_path()
    if path is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.connect(path)
            sock.sendall(message.encode())
    except OSError:
        return False
    return True


def watchdog_interval_s() -> float | None:
    """The watchdog interval systemd asked for (``WATCHDOG_USEC``), or None."""
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or (pid and pid != str(os.getpid())):
        return None
    return int(usec) / 1e6


def ping_watchdog() -> None:
    """``WATCHDOG=1``, at most every quarter interval (cheap to call from every loop turn)."""
    global _last_ping
    interval = watchdog_interval_s()
    if interval is None:
        return
    now = time.monotonic()
    with _lock:
        if now - _last_ping < interval / 4:
            return
        _last_ping = now
    notify("WATCHDOG=1")
