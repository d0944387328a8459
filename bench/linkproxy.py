"""A TCP proxy on loopback whose link can be cut and restored: a network fault on demand.

``cut()`` closes every connection through it and refuses new ones (the peers see their
link drop, as when a cable is pulled or a firewall resets it); ``restore()`` accepts again,
so a Zenoh client that retries its connection finds the router again by itself.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading


class LinkProxy:
    """Forward ``127.0.0.1:{port}`` to ``127.0.0.1:{target_port}`` until :meth:`close`."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.setblocking(False)
        self.port: int = self._listener.getsockname()[1]
        self.connections = 0  # accepted so far (a reconnection shows up here)
        self._up = threading.Event()
        self._up.set()
        self._closing = threading.Event()
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._accepted = threading.Condition(self._lock)
        self._thread = threading.Thread(target=self._serve, name="linkproxy", daemon=True)
        self._thread.start()

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def cut(self) -> None:
        """Drop every connection and refuse new ones until :meth:`restore`."""
        self._up.clear()
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for a, b in pairs:
            for s in (a, b):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def restore(self) -> None:
        self._up.set()

    def wait_connections(self, n: int, timeout: float) -> bool:
        """Wait until ``n`` connections have been accepted in all (a reconnection)."""
        with self._accepted:
            return self._accepted.wait_for(lambda: self.connections >= n, timeout)

    def close(self) -> None:
        self._closing.set()
        self.cut()
        self._thread.join(5)
        self._listener.close()

    # --- the forwarding loop (one thread, non-blocking sockets) ------------------------------

    def _serve(self) -> None:
        selector = selectors.DefaultSelector()
        selector.register(self._listener, selectors.EVENT_READ, None)
        peers: dict[socket.socket, socket.socket] = {}
        while not self._closing.is_set():
            for key, _ in selector.select(timeout=0.05):
                sock = key.fileobj
                if sock is self._listener:
                    self._accept(selector, peers)
                    continue
                other = peers.get(sock)
                data = b""
                with contextlib.suppress(OSError):
                    data = sock.recv(1 << 16)
                if data and other is not None:
                    try:
                        other.setblocking(True)
                        other.sendall(data)
                        other.setblocking(False)
                        continue
                    except OSError:
                        pass
                self._drop(selector, peers, sock)
            with self._lock:
                live = {s for pair in self._pairs for s in pair}
            for sock in [s for s in peers if s not in live]:  # cut meanwhile
                self._drop(selector, peers, sock)
        for sock in list(peers):
            self._drop(selector, peers, sock)
        selector.close()

    def _accept(self, selector: selectors.BaseSelector, peers: dict) -> None:
        try:
            client, _ = self._listener.accept()
        except BlockingIOError:
            return
        if not self._up.is_set():
            client.close()  # refused: the link is down
            return
        try:
            upstream = socket.create_connection(("127.0.0.1", self.target_port), timeout=5)
        except OSError:
            client.close()
            return
        for s in (client, upstream):
            s.setblocking(False)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            selector.register(s, selectors.EVENT_READ, None)
        peers[client], peers[upstream] = upstream, client
        with self._accepted:
            self._pairs.append((client, upstream))
            self.connections += 1
            self._accepted.notify_all()

    @staticmethod
    def _drop(selector: selectors.BaseSelector, peers: dict, sock: socket.socket) -> None:
        other = peers.pop(sock, None)
        for s in (sock, other):
            if s is None:
                continue
            peers.pop(s, None)
            with contextlib.suppress(KeyError, ValueError):
                selector.unregister(s)
            s.close()
