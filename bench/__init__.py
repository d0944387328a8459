"""The benches (``python -m bench``: ``make bench``). Each holds a Zenoh router and its client
sessions in one process: enough rx threads for that, before any session opens."""

from services.runtime.config import reserve_rx_threads

reserve_rx_threads()
