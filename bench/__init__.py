"""The benches (``python -m bench``: ``make bench``). Most hold a Zenoh router and its client
sessions in one process: enough rx threads for that, before any session opens. The soaks
start `trackfusion up` and the router with ``users_env()``: Zenoh's own runtime, as users."""

from services.runtime.config import reserve_rx_threads

reserve_rx_threads()
