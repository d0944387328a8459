"""The files the commands read when not told otherwise, shipped inside the package.

``demo-network.geojson``, ``service.json5``, ``router.json5``, ``limits.json5``,
``alerting.json5``, ``initial-models.json5``, ``simulator.json5``, ``study.json5`` and
``stack.json5`` are package data, found through :mod:`importlib.resources`, so that an
installed ``trackfusion`` (``pip install .``, run from any directory) reads the same files as
the repository. ``deploy/`` holds what operators adapt and ship: the Dockerfile, compose
file, systemd units and the TLS profiles.

The track register (:mod:`track`) ships no files: the demo network is found here and
handed to it.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from track.network import Network


def default_file(name: str) -> Path:
    """The packaged default file ``name``; ValueError when there is no such file."""
    resource = files(__name__).joinpath(name)
    if not isinstance(resource, Path):  # a zip import: no file to hand to the readers
        raise ValueError(f"{name}: the package is not installed as files ({resource!r})")
    if not resource.is_file():
        raise ValueError(f"{name}: not a default file of {__name__}")
    return resource


DEMO_NETWORK = default_file("demo-network.geojson")


def demo_network(segment_length_m: float | None = None) -> Network:
    """The demo network (3 lines, ~60 km, around Brisbane)."""
    return Network.from_geojson(DEMO_NETWORK, segment_length_m)


def add_network_argument(parser, what: str, *, default: str = "the demo network") -> None:
    """``--network FILE.geojson``: the network file ``what`` is about (a parser or an
    argument group); read it with :func:`load_network`."""
    parser.add_argument(
        "--network", metavar="FILE.geojson", type=Path, help=f"{what} (default: {default})"
    )


def load_network(path: str | Path | None, segment_length_m: float | None = None) -> Network:
    """The network of a command's ``--network``: the GeoJSON file ``path``, the demo network
    without one; ValueError saying what to fix when the file is bad."""
    if path is None:
        return demo_network(segment_length_m)
    try:
        return Network.from_geojson(Path(path), segment_length_m=segment_length_m)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--network {path}: {exc}") from None


def network_name(path: str | Path | None) -> str:
    """How dead letters name the network of ``--network``: the file's name, else "demo"."""
    return Path(path).name if path is not None else "demo"
