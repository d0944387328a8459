"""The TLS + access-control router profile: who may publish, subscribe and query what.

:func:`router_acl_config` builds a complete router configuration (a Zenoh config dict, see
``deploy/router-tls.json5``): it listens on TLS only, requires a client certificate signed by
the fleet's CA (mutual TLS), and denies every message that no rule below allows. A remote
is identified by the common name (CN) of its certificate:

``gateway-{train}``
    the on-board gateway of one train: may only put ``{ns}/raw/{train}/**`` and
    ``{ns}/gps/{train}``;
a role of :data:`ROLES` (``ingestion``, ``filtering``, ``operator`` …)
    exactly the keys that service needs (see the table in ``deploy/SECURITY.md``).

Since the gateway rules name the trains, the file is generated for a fleet:
``trackfusion secure-config --trains T001,T002 --ns tf --certs /etc/trackfusion/certs``.

How a grant becomes Zenoh rules (``ingress``: from the remote into the router, ``egress``:
from the router to the remote; a rule's key expression must *include* the message's):

* publish K: ``put`` ingress on K, and ``declare_subscriber`` egress on the key kind's
  subtree so that the publisher learns of matching subscribers;
* subscribe K: ``declare_subscriber`` ingress and ``put`` egress on K;
* query K: ``query`` ingress and ``reply`` egress on K, ``declare_queryable`` egress;
* answer K (a queryable): ``declare_queryable`` ingress, ``query`` egress, ``reply`` ingress;
* liveliness token K: ``liveliness_token`` ingress, and ``liveliness_query`` ingress plus
  ``liveliness_token`` egress on K (a service asks for its own token before closing);
* watch liveliness K: ``declare_liveliness_subscriber`` and ``liveliness_query`` ingress,
  ``liveliness_token`` egress;
* the at-least-once replay (:mod:`services.runtime.delivery`): a service that publishes
  answers queries on its outbox ``{ns}/q/outbox/{service}/*`` and holds a liveliness token
  there; one that subscribes queries ``{ns}/q/outbox/**`` and watches those tokens. A
  replayed message is a reply on its own key, so ``reply`` ingress on K for a publisher
  and egress on K for a subscriber: a replay reaches a role only on the keys it may read.

``delete`` is never allowed: no TrackFusion key is ever deleted.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from schemas import keys
from schemas.keys import DEFAULT_NS
from schemas.wire import check_id

GATEWAY_PREFIX = "gateway-"
DEFAULT_LISTEN = "tls/0.0.0.0:7447"
# File names under --certs (what `deploy/SECURITY.md` tells you to create).
CA_FILE = "ca.pem"
ROUTER_CERT_FILE = "router.pem"
ROUTER_KEY_FILE = "router-key.pem"


@dataclass(frozen=True)
class Grant:
    """What one role may do; every key is a template with ``{ns}`` (and ``{service}``)."""

    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    query: tuple[str, ...] = ()
    answer: tuple[str, ...] = ()  # queryables
    tokens: tuple[str, ...] = ()  # liveliness tokens it declares (and queries back)
    watch: tuple[str, ...] = ()  # liveliness it subscribes to / queries
    outbox: bool = True  # publishes through an outbox / replays from them (a service)


def _service(
    name: str,
    *,
    publish: Sequence[str] = (),
    subscribe: Sequence[str] = (),
    query: Sequence[str] = (),
    answer: Sequence[str] = (),
) -> Grant:
    """A service run by ``ServiceRuntime``: it also puts its dead letters and declares its
    liveliness token ``{ns}/alive/{service}/{instance}``."""
    return Grant(
        publish=(*publish, f"{{ns}}/deadletter/{name}"),
        subscribe=tuple(subscribe),
        query=tuple(query),
        answer=tuple(answer),
        tokens=(f"{{ns}}/alive/{name}/*",),
    )


#: Certificate common name -> what that remote may do. Keys as in
#: docs/architecture.md#key-expressions.
ROLES: Mapping[str, Grant] = {
    "ingestion": _service(
        "ingestion",
        subscribe=("{ns}/raw/**", "{ns}/gps/*"),
        publish=("{ns}/accel/**",),
    ),
    "extraction": _service(
        "extraction",
        subscribe=("{ns}/accel/**",),
        publish=("{ns}/index/**",),
    ),
    "calibration": _service(
        "calibration",
        subscribe=("{ns}/trc/**", "{ns}/index/**", "{ns}/maintenance/**"),
        publish=("{ns}/model/**",),
        answer=("{ns}/model/**",),
    ),
    "filtering": _service(
        "filtering",
        subscribe=("{ns}/index/**", "{ns}/trc/**", "{ns}/maintenance/**", "{ns}/model/**"),
        query=("{ns}/model/**",),
        publish=("{ns}/state/**",),
        answer=("{ns}/q/state/**",),
    ),
    "alerting": _service(
        "alerting",
        subscribe=("{ns}/state/**", "{ns}/trc/**"),
        publish=("{ns}/alert/**",),
        answer=("{ns}/q/alerts", "{ns}/q/plan"),
    ),
    "viewer": _service(
        "viewer",
        subscribe=(
            "{ns}/state/**",
            "{ns}/index/**",
            "{ns}/trc/**",
            "{ns}/alert/**",
            "{ns}/gps/*",
        ),
    ),
    # `trackfusion status|state|alerts|plan|export|deadletters`: read-only. `deadletters`
    # runs a ServiceRuntime of its own, hence its dead-letter key and token.
    "operator": Grant(
        query=("{ns}/q/**",),
        watch=("{ns}/alive/**",),
        subscribe=("{ns}/deadletter/**",),
        publish=("{ns}/deadletter/deadletters",),
        tokens=("{ns}/alive/deadletters/*",),
    ),
    # `trackfusion import-trc`: publishes TRC records and asks filtering's states whether
    # it holds them.
    "trc-import": Grant(publish=("{ns}/trc/**",), query=("{ns}/q/state/**",)),
    # Whatever feeds tamping and other maintenance events.
    "maintenance-feed": Grant(publish=("{ns}/maintenance/**",)),
}


def gateway_grant(train: str) -> Grant:
    """The on-board gateway of ``train``: its own raw and GPS keys, nothing else."""
    check_id("train", train)
    return Grant(publish=(f"{{ns}}/raw/{train}/**", f"{{ns}}/gps/{train}"), outbox=False)


def gateway_name(train: str) -> str:
    """The certificate common name of ``train``'s gateway."""
    return f"{GATEWAY_PREFIX}{train}"


def _subtree(ns: str, key: str) -> str:
    """``{ns}/{kind}/**`` of a key: where the subscribers a publisher must see declare."""
    return f"{ns}/{keys.kind(key)}/**"


def _rules(rule_id: str, grant: Grant, ns: str, service: str) -> list[dict[str, Any]]:
    """The allow rules of one grant (rule ids ``{rule_id}:{what}``)."""

    def keys(templates: Iterable[str]) -> list[str]:
        return sorted({t.format(ns=ns, service=service) for t in templates})

    def rule(what: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
        return {
            "id": f"{rule_id}:{what}",
            "permission": "allow",
            "flows": [flow],
            "messages": messages,
            "key_exprs": key_exprs,
        }

    out: list[dict[str, Any]] = []
    if grant.outbox and grant.publish:
        outbox = keys(("{ns}/q/outbox/{service}/*",))
        messages = ["declare_queryable", "reply", "liveliness_token", "liveliness_query"]
        out.append(rule("outbox", "ingress", messages, outbox))
        out.append(rule("outbox-queries", "egress", ["query", "liveliness_token"], outbox))
    if grant.outbox and grant.subscribe:
        outboxes = keys(("{ns}/q/outbox/**",))
        messages = ["query", "declare_liveliness_subscriber", "liveliness_query"]
        out.append(rule("replay", "ingress", messages, outboxes))
        messages = ["reply", "declare_queryable", "liveliness_token"]
        out.append(rule("replay-replies", "egress", messages, outboxes))
    if grant.publish:
        published = keys(grant.publish)
        out.append(rule("put", "ingress", ["put"], published))
        out.append(rule("replayed", "ingress", ["reply"], published))
        subtrees = sorted({_subtree(ns, k) for k in published})
        out.append(rule("put-matching", "egress", ["declare_subscriber"], subtrees))
    if grant.subscribe:
        subscribed = keys(grant.subscribe)
        out.append(rule("sub", "ingress", ["declare_subscriber"], subscribed))
        out.append(rule("sub-data", "egress", ["put", "reply"], subscribed))
    if grant.query:
        queried = keys(grant.query)
        out.append(rule("query", "ingress", ["query"], queried))
        out.append(rule("query-replies", "egress", ["reply", "declare_queryable"], queried))
    if grant.answer:
        answered = keys(grant.answer)
        out.append(rule("queryable", "ingress", ["declare_queryable", "reply"], answered))
        out.append(rule("queryable-queries", "egress", ["query"], answered))
    if grant.tokens:
        tokens = keys(grant.tokens)
        out.append(rule("token", "ingress", ["liveliness_token", "liveliness_query"], tokens))
        out.append(rule("token-echo", "egress", ["liveliness_token"], tokens))
    if grant.watch:
        watched = keys(grant.watch)
        messages = ["declare_liveliness_subscriber", "liveliness_query"]
        out.append(rule("watch", "ingress", messages, watched))
        out.append(rule("watch-tokens", "egress", ["liveliness_token"], watched))
    return out


def access_control(ns: str, trains: Iterable[str]) -> dict[str, Any]:
    """The ``access_control`` section: default deny, one subject and policy per role and per
    train's gateway, matched by certificate common name."""
    check_id("ns", ns)
    grants: dict[str, Grant] = dict(ROLES)
    for train in dict.fromkeys(trains):  # keep order, drop duplicates
        grants[gateway_name(train)] = gateway_grant(train)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for name, grant in grants.items():
        these = _rules(name, grant, ns, name)
        rules.extend(these)
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": name, "rules": [r["id"] for r in these], "subjects": [name]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def router_acl_config(
    ns: str,
    trains: Iterable[str],
    listen: str | Sequence[str],
    ca: str | Path,
    cert: str | Path,
    key: str | Path,
) -> dict[str, Any]:
    """A full router configuration: TLS-only listener(s) ``listen`` with the router's
    ``cert``/``key``, client certificates required and checked against ``ca``, and the
    access control of :func:`access_control` for the fleet ``trains``."""
    endpoints = [listen] if isinstance(listen, str) else list(listen)
    for endpoint in endpoints:
        if not endpoint.startswith("tls/"):
            raise ValueError(f"listen: {endpoint!r} is not a tls/… endpoint")
    return {
        "mode": "router",
        "listen": {"endpoints": endpoints},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],  # nothing but TLS is accepted (or opened)
                "tls": {
                    "root_ca_certificate": str(ca),
                    "listen_certificate": str(cert),
                    "listen_private_key": str(key),
                    "enable_mtls": True,  # a client without a CA-signed certificate is refused
                    "close_link_on_expiration": True,  # an expired certificate ends the link
                },
            },
        },
        "access_control": access_control(ns, trains),
    }


def render(config: Mapping[str, Any], command: str) -> str:
    """``config`` as a JSON5 file with a header saying how to regenerate it."""
    header = (
        "// TrackFusion router: TLS only, client certificates required (mutual TLS), access\n"
        "// control with default deny. GENERATED: do not edit by hand, regenerate with\n"
        f"//   {command}\n"
        "// (a new train needs a new file: its gateway rules name the train). See\n"
        "// deploy/SECURITY.md for the certificates and who may publish what.\n"
        "// Run with `trackfusion router --config FILE` or `zenohd -c FILE`.\n"
    )
    return header + _dump(config, 0) + "\n"


def _dump(value: Any, indent: int, used: int = 0, width: int = 100) -> str:
    """JSON (valid JSON5) with an object or list on one line when it fits in ``width``
    (``used`` characters of the line already taken), else one item per line."""
    flat = json.dumps(value, separators=(", ", ": "))
    if not isinstance(value, (dict, list)) or not value or used + len(flat) <= width:
        return flat
    pad = " " * (indent + 2)
    if isinstance(value, dict):
        items = []
        for k, v in value.items():
            head = f"{pad}{json.dumps(k)}: "
            items.append(head + _dump(v, indent + 2, len(head), width))
    else:
        items = [pad + _dump(v, indent + 2, len(pad), width) for v in value]
    opening, closing = ("{", "}") if isinstance(value, dict) else ("[", "]")
    return opening + "\n" + ",\n".join(items) + "\n" + " " * indent + closing


def main(ns: str, trains: Sequence[str], certs: Path, listen: str, command: str) -> str:
    """The text of ``trackfusion secure-config``."""
    config = router_acl_config(
        ns,
        trains,
        listen,
        ca=certs / CA_FILE,
        cert=certs / ROUTER_CERT_FILE,
        key=certs / ROUTER_KEY_FILE,
    )
    return render(config, command)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion secure-config``."""
    parser.description = (
        "Print a router configuration that accepts only mutual-TLS clients and lets each one "
        "(by certificate common name) use only its keys: gateway-{train} its own raw and gps "
        "keys, each service what it needs. See deploy/SECURITY.md."
    )
    parser.add_argument(
        "--trains", required=True, metavar="T1,T2,…", help="the fleet's train ids, comma-separated"
    )
    parser.add_argument("--ns", default=DEFAULT_NS, help="key namespace (default: %(default)s)")
    parser.add_argument(
        "--certs",
        required=True,
        type=Path,
        metavar="DIR",
        help="directory of ca.pem, router.pem and router-key.pem as the router will see it",
    )
    parser.add_argument(
        "--listen", default=DEFAULT_LISTEN, help="TLS endpoint (default: %(default)s)"
    )


def run(args: argparse.Namespace) -> int:
    trains = [t.strip() for t in args.trains.split(",") if t.strip()]
    if not trains:
        raise SystemExit("--trains: give at least one train id, e.g. --trains T001,T002")
    command = (
        f"trackfusion secure-config --trains {','.join(trains)} --ns {args.ns} "
        f"--certs {args.certs} --listen {args.listen}"
    )
    try:
        text = main(args.ns, trains, args.certs, args.listen, command)
    except ValueError as exc:
        raise SystemExit(f"secure-config: {exc}") from None
    sys.stdout.write(text)
    return 0
