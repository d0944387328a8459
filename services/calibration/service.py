"""`trackfusion calibration`: the live calibration service (thin adapter over the core).

Subscribes ``{ns}/trc/**``, ``{ns}/index/**`` and ``{ns}/maintenance/**``; every sample goes
into the runtime's inbox (never blocking Zenoh), drained by ONE worker, so the
:class:`Calibrator` stays single-threaded. The worker decodes (a bad payload becomes a
dead letter), feeds the core a batch, persists what changed (one SQLite transaction), then
publishes the new models on ``{ns}/model/calibration`` and ``{ns}/model/degradation/{group}``:
those the core's publication rule lets out (a material change, at most one version per model
per day of event time; ``calibrator.py``), checked at every batch, so a version held by the
rate limit goes out with the first batch whose events pass the limit.
A queryable on ``{ns}/model/**`` answers late joiners with the latest of each model.
What the core leaves out (a TRC record, a pair, a posterior held by the move bound; ``robust.py``)
is published as a dead letter on ``{ns}/deadletter/calibration`` with the reason, keyed by the
record's own key (``{ns}/trc/{line}/{segment}`` or ``{ns}/index/{line}/{segment}``), the
record as payload when the core kept it. With ``network`` (a network GeoJSON file), events on
segments it does not have are dead-lettered before they reach the core.

At start the store is loaded (the same models, versions and samples are republished), then
the optional initial models (``initial_models``: a JSON5 file, see
``services/defaults/initial-models.json5``) are installed as version 1 where no model exists yet.
"""

from __future__ import annotations

import argparse
import logging
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from schemas import (
    MaintenanceEvent,
    OnboardIndex,
    SchemaError,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.calibration.calibrator import Calibrator
from services.calibration.config import CalibratorConfig
from services.calibration.initial import initial_models
from services.calibration.state import Event, Model, Quarantine
from services.calibration.store import SqliteStore
from services.defaults import add_network_argument
from services.runtime.config import (
    RuntimeConfig,
    add_db_argument,
    add_zenoh_arguments,
    default_db,
    flag_values,
    read_json5,
)
from services.runtime.delivery import MARK
from services.runtime.latest import LatestValues
from services.runtime.service import ServiceRuntime, run_command
from track.network import Network
from track.segments import KnownSegments

log = logging.getLogger(__name__)

SERVICE = "calibration"
BATCH = 512  # samples handed to the core before one flush + one transaction
_KINDS: dict[str, type[Event]] = {
    "trc": TrcRecord,
    "index": OnboardIndex,
    "maintenance": MaintenanceEvent,
}


@dataclass(frozen=True)
class Settings:
    """What the service needs besides the bus (``db`` None: ``./var/calibration-{instance}``)."""

    core: CalibratorConfig = field(default_factory=CalibratorConfig)
    db: Path | None = None
    initial_models: Path | None = None
    network: Path | None = None  # refuse events on segments it does not have (None: any)


# The keys of services.calibration: the files, and the core's settings (not its priors).
OPTIONS = (
    "db",
    "initial_models",
    "network",
    *sorted(set(CalibratorConfig.__dataclass_fields__) - {"drift_prior", "level_prior"}),
)
# The options a flag of the same name overrides (add_arguments).
FLAGS = (
    "db",
    "initial_models",
    "network",
    "min_pairs",
    "refit_every",
    "tolerance_days",
    "samples",
    "seed",
)


def settings_from(options: Mapping[str, Any], **overrides: Any) -> Settings:
    """Settings from the config file's ``services.calibration`` section, then ``overrides``
    (command-line values; None means "not given").

    Keys: ``db``, ``initial_models``, ``network`` and every field of :class:`CalibratorConfig`
    (``min_pairs``, ``refit_every``, ``tolerance_days``, ``samples``, ``seed``, …).
    """
    merged = dict(options)
    merged.update({k: v for k, v in overrides.items() if v is not None})
    db = merged.pop("db", None)
    initial = merged.pop("initial_models", None)
    network = merged.pop("network", None)
    try:
        core = CalibratorConfig(**merged)
    except (TypeError, ValueError) as e:
        raise ValueError(f"services.calibration: {e}") from None
    return Settings(
        core=core,
        db=Path(db) if db is not None else None,
        initial_models=Path(initial) if initial is not None else None,
        network=Path(network) if network is not None else None,
    )


def load_initial_models(path: Path, core: CalibratorConfig):
    """The initial models of the JSON5 file at ``path``; ValueError saying what is wrong."""
    spec = read_json5(path)
    try:
        return initial_models(spec, samples=core.samples, seed=core.seed)
    except ValueError as e:
        raise ValueError(f"initial models {path}: {e}") from None


def known_segments(network: Path | None) -> KnownSegments | None:
    """The segments of a network file, or None (accept any); as the filtering service's
    ``--network``."""
    if network is None:
        return None
    try:
        return KnownSegments.of(Network.from_geojson(network), network.name)
    except (OSError, ValueError) as exc:
        raise ValueError(f"network {network}: {exc}") from None


def quarantine_key(ns: str, q: Quarantine) -> str:
    """The key a left-out record came on: its dead letter's key."""
    make = keys.trc if q.kind == "trc" else keys.index
    return make(ns, q.line, q.segment)


def model_key(ns: str, model: Model) -> str:
    return keys.key_of(ns, model)


def main(
    conf: RuntimeConfig,
    settings: Settings | None = None,
    *,
    stop_event: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the calibration service until SIGINT/SIGTERM or ``stop_event``; returns 0."""
    settings = settings or settings_from(conf.options(SERVICE, OPTIONS))
    with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop_event) as rt:
        db = settings.db or default_db(SERVICE, conf.instance)
        store = SqliteStore(db)
        try:
            state = store.load()
            core = Calibrator(settings.core, state=state)
            log.info(
                "store %s: %d pairs, %d pending indices, models %s",
                db,
                len(core.pairs),
                core.n_pending(),
                [type(m).__name__ + f" v{m.version}" for m in core.models()],
            )
            if settings.initial_models is not None:
                cal, posts = load_initial_models(settings.initial_models, settings.core)
                installed = core.install_initial(cal, posts)
                if installed:
                    log.info("initial models installed: %d", len(installed))
            store.apply(core.drain_changes())
            known = known_segments(settings.network)
            return _serve(rt, core, store, known, state.positions)
        finally:
            store.close()


def _serve(
    rt: ServiceRuntime,
    core: Calibrator,
    store: SqliteStore,
    known: KnownSegments | None = None,
    positions: Mapping[str, tuple[str, int]] | None = None,
) -> int:
    ns = rt.ns
    latest = LatestValues()
    models_out = rt.reliable_publisher(beside=store.path)  # replayed to returning consumers

    def publish(models: list[Model]) -> None:
        for model in models:
            key, payload = model_key(ns, model), encode(model)
            latest.put(key, payload)
            models_out.put(key, payload)
            log.info("published %s version %d", key, model.version)

    def decode_sample(key: str, payload: bytes) -> Event:
        message = decode(payload, _KINDS[keys.kind(key)])
        keys.check_key(key, message)
        if known is not None:
            known.check(message)
        return message

    def ingest(_kind: str, key: str, payload: bytes) -> None:
        core.ingest(decode_sample(key, payload))

    def handle_batch(batch: list[tuple[str, str, bytes]]) -> None:
        replayed: dict[str, tuple[str, int]] = {}
        for kind, key, payload in batch:  # a bad one: a dead letter (ValueError: its reason)
            if kind == MARK:  # a producer's replay is in: stored with what it brought
                epoch, head = msgpack.unpackb(payload)
                replayed[key] = (epoch, head)
                continue
            rt.guarded(ingest, kind, key, payload, refusals=(SchemaError, ValueError))
        log.debug("batch of %d", len(batch))
        try:
            models = core.flush()
        finally:
            changes = core.drain_changes()
            changes.positions.update(replayed)
            store.apply(changes)  # persisted before anyone sees the models
        for q in core.drain_quarantined():
            payload = encode(q.message) if q.message is not None else None
            rt.deadletters.reject(quarantine_key(ns, q), q.reason, payload)
        publish(models)

    publish(core.models())  # restored and initial models, for those already listening
    rt.declare_queryable(keys.model_all(ns), latest.on_query)
    subscriptions = {kind: keys.segment_keys(ns, kind) for kind in _KINDS}
    rt.subscribe_batches(
        subscriptions, handle_batch, max_batch=BATCH, reliable=True, positions=positions or {}
    )
    return rt.run()  # leaving: the worker handles what is queued, persists, then ends


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion calibration``: the flags override the config file's
    ``services.calibration``; the defaults are :class:`CalibratorConfig`'s."""
    parser.description = (
        "Pair TRC records with on-board indices, fit the observation model, build degradation "
        "posteriors per group, publish them on {ns}/model/**. Flags override the config "
        "file's services.calibration section."
    )
    core = CalibratorConfig()
    add_db_argument(parser, SERVICE, "the pairs, records and models")
    parser.add_argument(
        "--initial-models",
        type=Path,
        metavar="FILE.json5",
        help="prior models published as version 1 until data gives better ones "
        "(e.g. services/defaults/initial-models.json5; default: none)",
    )
    add_network_argument(
        parser, "refuse events on segments this network does not have", default="accept any"
    )
    parser.add_argument(
        "--min-pairs", type=int, help=f"pairs before the first fit (default: {core.min_pairs})"
    )
    parser.add_argument(
        "--refit-every", type=int, help=f"new pairs between refits (default: {core.refit_every})"
    )
    parser.add_argument(
        "--tolerance-days",
        type=float,
        help="pair an index without run_id with a TRC record this close in time "
        f"(default: {core.tolerance_days:g})",
    )
    parser.add_argument(
        "--samples", type=int, help=f"posterior samples Ns (default: {core.samples})"
    )
    parser.add_argument(
        "--seed", type=int, help=f"seed of the posterior draws (default: {core.seed})"
    )
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    def with_flags(conf: RuntimeConfig) -> int:
        return main(conf, settings_from(conf.options(SERVICE, OPTIONS), **flag_values(args, FLAGS)))

    return run_command(args, with_flags)
