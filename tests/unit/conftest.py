"""Fixtures the unit tests share."""

from __future__ import annotations

import pytest

from services.defaults import demo_network
from simulators.truth import load_config


@pytest.fixture(scope="module")
def net():
    """The demo network."""
    return demo_network()


@pytest.fixture(scope="module")
def cfg():
    """The simulator's default configuration."""
    return load_config()
