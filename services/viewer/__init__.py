"""The operators' Rerun viewer: pure core (core.py) and Zenoh adapter (service.py)."""
