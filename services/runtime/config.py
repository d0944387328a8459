"""Service configuration: a JSON5 file overlaid with command-line flags (flags win).

A configuration file is a Zenoh configuration (``mode``, ``connect``, ``listen``, ``scouting``,
``transport``, ``access_control`` …, see the Zenoh docs) plus a few TrackFusion keys at the top
level, which are taken out before the rest is handed to Zenoh:

``ns``
    namespace, the first chunk of every key expression (default ``"tf"``);
``instance``
    instance id of the service, a single key chunk (default ``{hostname}-{pid}``);
``services``
    per-service settings, ``{"filtering": {...}, ...}``: one section per entry of ``SECTIONS``,
    each read by its service with :meth:`RuntimeConfig.options`, which names the keys it knows.

A file without these keys (``services/defaults/router.json5``) is therefore also a valid ``zenohd``
configuration. Whatever the file says, multicast scouting is turned off: every process
connects or listens on explicit endpoints.

Whatever cannot be used (a file that does not parse, a value out of range, a section or key
nobody reads) raises ``ValueError`` saying what to fix; the command line turns it into exit
code 2 (:mod:`services.cli`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import json5

from services.defaults import default_file

if TYPE_CHECKING:
    import zenoh  # imported when a config is built, so that `trackfusion --help` stays fast

DEFAULT_NS = "tf"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
MODES = ("client", "peer", "router")
TRACKFUSION_KEYS = ("ns", "instance", "services")
# The services.{name} sections some process reads (the runtime reads `delivery`). The other
# services take no settings from the file: a section of theirs is refused like a typo.
SECTIONS = ("calibration", "delivery", "filtering", "ingestion")

ROUTER_CONFIG = default_file("router.json5")
SERVICE_CONFIG = default_file("service.json5")

_FORBIDDEN = set("*$?# ")


@dataclass(frozen=True)
class RuntimeConfig:
    """What a service needs to join the bus; build it with :func:`load_config`."""

    ns: str = DEFAULT_NS
    instance: str | None = None  # None: default_instance() when the service starts
    zenoh: Mapping[str, Any] = field(default_factory=dict)  # plain-JSON Zenoh settings
    services: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    source: Path | None = None  # the file it came from, for error messages

    @property
    def mode(self) -> str:
        return str(self.zenoh.get("mode") or "client")

    def options(self, service: str, known: Iterable[str]) -> dict[str, Any]:
        """The ``services.{service}`` section of the file (empty if absent), whose keys must
        be among ``known``; ValueError naming the file, section and key otherwise."""
        section = dict(self.services.get(service, {}))
        known = sorted(known)
        for key in section:
            if key not in known:
                raise ValueError(
                    f"{_where(self.source)}: services.{service}: unknown key {key!r}; "
                    f"known keys: {', '.join(known) or 'none'}"
                )
        return section

    def zenoh_config(self) -> zenoh.Config:
        return zenoh_config(self)


def _where(source: Path | None) -> str:
    return f"config file {source}" if source else "configuration"


def default_db(service: str, instance: str | None) -> Path:
    """``./var/{service}-{instance}.sqlite``: one state file per service instance, named after
    the configured instance id, ``default`` without one (never the hostname-pid id, which
    would give every restart a new, empty file)."""
    return Path("var") / f"{service}-{instance or 'default'}.sqlite"


def default_instance() -> str:
    """``{hostname}-{pid}``, reduced to characters safe in a key chunk."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, mode: bool = True) -> None:
    """Add the flags every service shares; :func:`config_from_args` reads them back."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--config", metavar="FILE", type=Path, help="JSON5 configuration file")
    if mode:
        group.add_argument("--mode", choices=MODES, help="Zenoh mode (default: client)")
    group.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help=f"endpoint to connect to, repeatable (default: {DEFAULT_ENDPOINT})",
    )
    group.add_argument(
        "--listen", metavar="ENDPOINT", action="append", default=[], help="repeatable"
    )
    group.add_argument("--ns", metavar="NAMESPACE", help=f"key namespace (default: {DEFAULT_NS})")
    group.add_argument("--instance", metavar="ID", help="instance id (default: hostname-pid)")
    group.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))


def add_db_argument(parser: argparse.ArgumentParser, service: str, what: str) -> None:
    """``--db FILE``: the SQLite file of ``what``, :func:`default_db` when not given."""
    parser.add_argument(
        "--db",
        metavar="FILE",
        type=Path,
        help=f"SQLite file of {what} (default: ./{default_db(service, '{instance}')}, "
        "instance 'default' without --instance)",
    )


def config_from_args(
    args: argparse.Namespace, *, default_file: Path | None = None, mode: str | None = None
) -> RuntimeConfig:
    """Load ``args.config`` (else ``default_file``) and overlay the flags of
    :func:`add_zenoh_arguments`; ``mode`` forces a mode (the router)."""
    return load_config(
        args.config or default_file,
        mode=mode or getattr(args, "mode", None),
        connect=args.connect,
        listen=args.listen,
        ns=args.ns,
        instance=args.instance,
    )


def flag_values(args: argparse.Namespace, names: Iterable[str]) -> dict[str, Any]:
    """``{name: args.<name>}``: the flags that set the keywords (or override the config
    file's keys) of the same names; None where a flag was not given."""
    return {name: getattr(args, name) for name in names}


def load_config(
    path: str | Path | None = None,
    *,
    mode: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    ns: str | None = None,
    instance: str | None = None,
) -> RuntimeConfig:
    """Read the JSON5 file at ``path`` (if any) and overlay the given values.

    Non-empty ``connect`` / ``listen`` replace the file's endpoints. Raises ``ValueError``
    with a message saying what to fix when the file or a value is unusable.
    """
    source = Path(path) if path is not None else None
    try:
        data = read_json5(source) if source is not None else {}
    except ValueError as e:
        raise ValueError(f"config file {e}") from None
    where = _where(source)

    ns = ns if ns is not None else data.pop("ns", DEFAULT_NS)
    instance = instance if instance is not None else data.pop("instance", None)
    services = data.pop("services", {})
    data.pop("ns", None)
    data.pop("instance", None)

    _check_chunk("ns", ns, where)
    if instance is not None:
        _check_chunk("instance", instance, where)
    if not isinstance(services, dict) or not all(isinstance(v, dict) for v in services.values()):
        raise ValueError(f"{where}: 'services' must be an object of objects, got {services!r}")
    for name in services:
        if name not in SECTIONS:
            raise ValueError(
                f"{where}: services: unknown section {name!r} (that service takes no settings "
                f"from the file, or the name is misspelt); known sections: {', '.join(SECTIONS)}"
            )

    if mode is not None:
        data["mode"] = mode
    if data.get("mode") is not None and data["mode"] not in MODES:
        raise ValueError(f"{where}: mode must be one of {', '.join(MODES)}, got {data['mode']!r}")
    if connect:
        _section(data, "connect", where)["endpoints"] = list(connect)
    if listen:
        _section(data, "listen", where)["endpoints"] = list(listen)

    conf = RuntimeConfig(ns=ns, instance=instance, zenoh=data, services=services, source=source)
    zenoh_config(conf)  # fail now, with the file's name, rather than when a session opens
    return conf


def read_json5(path: str | Path) -> dict[str, Any]:
    """The JSON5 object in the file ``path``: every configuration file is read with this.
    ``ValueError`` naming the file (and the line, for a syntax error) and what is wrong."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ValueError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text: {e}") from None
    try:
        data = json5.loads(text)
    except ValueError as e:  # json5 says "<string>:LINE what"
        found = re.match(r"<string>:(\d+) (.*)", str(e), re.DOTALL)
        where, what = (f"{path}:{found[1]}", found[2]) if found else (str(path), str(e))
        raise ValueError(f"{where}: not valid JSON5: {what}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: must hold a JSON5 object {{...}}, got {type(data).__name__}")
    return data


# Zenoh's runtime threads that read the links (rx) are shared by every session of a process,
# 2 on 2 cores. A process that holds a router *and* client sessions of it (a test, a bench)
# can deadlock: when every rx thread is blocked forwarding BLOCK messages (replies, states)
# to an in-process client, none is left to read for that client; after 5 s the router closes
# the transports (two in-process queryables of 5,000 replies each did it with 2 threads).
# More rx threads than producers avoid it. A process holding only a router (`trackfusion
# router`, `trackfusion up`'s supervisor) needs none, nor one holding only clients: the
# deployed topology, which tests/e2e/test_sharded_query.py runs.
ROUTER_AND_CLIENTS_RUNTIME = "(rx: (worker_threads: 8))"


def reserve_rx_threads() -> None:
    """For a process that will hold a router and its clients: enough rx threads (above);
    call before its first session (the runtime is made then); a value already set wins."""
    os.environ.setdefault("ZENOH_RUNTIME", ROUTER_AND_CLIENTS_RUNTIME)


def users_env() -> dict[str, str]:
    """This process's environment without what :func:`reserve_rx_threads` set: for a child
    that must run as users run it (`trackfusion up`, a router) with Zenoh's own runtime."""
    env = dict(os.environ)
    if env.get("ZENOH_RUNTIME") == ROUTER_AND_CLIENTS_RUNTIME:
        del env["ZENOH_RUNTIME"]
    return env


def zenoh_config(conf: RuntimeConfig | Mapping[str, Any] | None = None) -> zenoh.Config:
    """A ``zenoh.Config`` from ``conf``: client mode connecting to the local router unless told
    otherwise, a router listening on it, multicast scouting always off."""
    import zenoh

    if isinstance(conf, RuntimeConfig):
        settings, source = conf.zenoh, conf.source
    else:
        settings, source = conf or {}, None
    where = f"config file {source}" if source else "Zenoh configuration"
    data: dict[str, Any] = json.loads(json.dumps(settings))  # deep copy, JSON-only values
    mode = data.setdefault("mode", "client")
    if mode in ("client", "peer") and not _endpoints(data, "connect"):
        _section(data, "connect", where)["endpoints"] = [DEFAULT_ENDPOINT]
    if mode == "router" and not _endpoints(data, "listen"):
        _section(data, "listen", where)["endpoints"] = [DEFAULT_ENDPOINT]
    _section(_section(data, "scouting", where), "multicast", where)["enabled"] = False
    try:
        return zenoh.Config.from_json5(json.dumps(data))
    except zenoh.ZError as e:
        raise ValueError(f"{where}: invalid Zenoh settings: {e}") from None


def endpoints(conf: RuntimeConfig, section: str) -> list[str]:
    """The ``connect`` or ``listen`` endpoints Zenoh will use for ``conf``'s mode."""
    value = json.loads(zenoh_config(conf).get_json(f"{section}/endpoints"))
    if isinstance(value, dict):
        value = value.get(conf.mode, [])
    return list(value or [])


def _endpoints(data: Mapping[str, Any], section: str) -> bool:
    """Whether the settings name endpoints (a list, or a per-mode object) for ``section``."""
    value = data.get(section)
    return bool(value.get("endpoints")) if isinstance(value, dict) else False


def _section(data: dict[str, Any], name: str, where: str) -> dict[str, Any]:
    value = data.setdefault(name, {})
    if not isinstance(value, dict):
        raise ValueError(f"{where}: '{name}' must be an object like {{endpoints: [...]}}")
    return value


def _check_chunk(name: str, value: object, where: str) -> None:
    """Same rule as schemas.keys: one non-empty key chunk."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"{where}: {name} must be a non-empty string, got {value!r}")
    bad = (_FORBIDDEN | {"/"}).intersection(value)
    if bad:
        raise ValueError(f"{where}: {name} {value!r} contains forbidden characters {sorted(bad)}")
