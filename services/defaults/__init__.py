"""The files the commands read when not told otherwise, shipped inside the package.

``demo-network.geojson``, ``service.json5``, ``router.json5``, ``limits.json5``,
``alerting.json5``, ``initial-models.json5``, ``simulator.json5``, ``study.json5`` and
``stack.json5`` are package data, found through :mod:`importlib.resources`, so that an
installed ``trackfusion`` (``pip install .``, run from any directory) reads the same files as
the repository. ``deploy/`` holds what operators adapt and ship: the Dockerfile, compose
file, systemd units and the TLS profiles.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def default_file(name: str) -> Path:
    """The packaged default file ``name``; ValueError when there is no such file."""
    resource = files(__name__).joinpath(name)
    if not isinstance(resource, Path):  # a zip import: no file to hand to the readers
        raise ValueError(f"{name}: the package is not installed as files ({resource!r})")
    if not resource.is_file():
        raise ValueError(f"{name}: not a default file of {__name__}")
    return resource
