"""Order independence of filtering with maintenance detection on: seeded random event
sequences of one segment (TRC runs, on-board indices over unreported tampings, known and
interval tamping reports and their corrections, ties at equal times, degenerate values),
each delivered in several orders (shuffled, duplicated, late), through one message at a time
(:meth:`Tracker.step`), through batches (:meth:`PersistentTracker.handle_batch` on a real
SQLite file) and after a restart from that file. Every delivery must end in the bytes of
delivering the events in canonical order: the log's identities, the detected tampings
held, and the packed state (:func:`pack_state`). The detections and withdrawals the batches
publish (as the service numbers them, :class:`Revisions`), folded in a shuffled order by the
consumers' rule (per ``event_id`` the highest ``MaintenanceEvent.rank``; a withdrawal is no
tamping), must leave the same detected tampings since the latest TRC record (one before it
was pruned by the record, not withdrawn: a consumer keeps it).

``tests/unit/test_filtering_order.py`` runs a few sequences; this runs many:
``python -m bench.order_check [sequences] [orders] [--seed S]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import Counter
from pathlib import Path

import msgspec
import numpy as np

from schemas import DAY_S, MaintenanceEvent, OnboardIndex, TrcRecord, encode, keys
from services.filtering.coordinator import PersistentTracker
from services.filtering.events import event_of, tamping_time
from services.filtering.segment import is_detected
from services.filtering.service import Revisions
from services.filtering.state import pack_state
from services.filtering.store import Store
from services.filtering.testing import T0, example_models
from services.filtering.tracker import Tracker
from services.limits import load_limits

SAMPLES = 16  # posterior samples: detection and ties do not need many
H = np.array([[0.9, 0.05], [0.05, 0.75]])  # example_models' observation model
B = np.array([-0.25, -0.35])
R = np.array([[0.01, 0.002], [0.002, 0.03]])
Z_WORN = np.log([4.5, 3.5])
Z_PLUS = np.log([2.0, 1.8])
MU = np.array([7e-4, 4e-4])  # per day
LIMITS = load_limits()
LINE, SEGMENT = "L1", "s1"


def _index(t_days: float, z: np.ndarray, rng, train: str = "T1") -> OnboardIndex:
    y = H @ z + B + np.linalg.cholesky(R) @ rng.standard_normal(2)
    top6, align10 = np.exp(y).tolist()
    return OnboardIndex(
        line=LINE, segment=SEGMENT, train=train, unit="u1", t=T0 + t_days * DAY_S,
        top6_mm=top6, align10_mm=align10, speed_mps=30.0, coverage=1.0,
    )  # fmt: skip


def _trc(t_days: float, z: np.ndarray, run: str) -> TrcRecord:
    top6, align10 = np.exp(z).tolist()
    return TrcRecord(
        line=LINE, segment=SEGMENT, t=T0 + t_days * DAY_S, top6_mm=top6, align10_mm=align10,
        run_id=run,
    )  # fmt: skip


def _tamping(event_id: str, start: float, end: float, revision: int = 0) -> MaintenanceEvent:
    return MaintenanceEvent(
        line=LINE, segment=SEGMENT, event_id=event_id, t_start=T0 + start * DAY_S,
        t_end=T0 + end * DAY_S, revision=revision,
    )  # fmt: skip


def sequence(rng: np.random.Generator) -> list:
    """One segment's events: indices every 1-3 days over 60-200 days of a track that
    degrades and is tamped at unreported times, TRC runs (none, one or several; one may
    fall on a tamping's or an index's time), tamping reports (known time, an interval, a
    zero-width one, a correction with a higher revision, one near an unreported tamping),
    and ties (two trains at one time)."""
    days = float(rng.integers(60, 200))
    hidden = sorted(rng.uniform(10.0, days - 5.0, rng.integers(1, 4)).round(2).tolist())
    t, z, out = 0.0, Z_WORN.copy(), []
    tamped = list(hidden)
    while t < days:
        step = float(rng.choice([1.0, 1.0, 2.0, 3.0]))
        while tamped and tamped[0] <= t + step:
            age = t + step - tamped.pop(0)
            z = Z_PLUS + MU * age
        z = z + MU * step
        t += step
        out.append(_index(t, z, rng))
        if rng.random() < 0.05:  # a second train at the same time
            out.append(_index(t, z, rng, train="T2"))
    times = [m.t for m in out]
    n_trc = int(rng.choice([0, 1, 1, 2, 3]))
    for k in range(n_trc):
        if k == 0 and rng.random() < 0.8:
            when = 0.0
        elif rng.random() < 0.3:  # on an index's time
            when = (float(rng.choice(times)) - T0) / DAY_S
        else:
            when = float(rng.uniform(0.0, days)).__round__(2)
        out.append(_trc(when, Z_WORN - MU * 30 * rng.random(), f"run{k}"))
    for k in range(int(rng.integers(0, 4))):
        kind = rng.integers(0, 4)
        near = hidden[k % len(hidden)] + float(rng.uniform(-20.0, 20.0))
        start = max(0.5, round(near if rng.random() < 0.5 else rng.uniform(0.0, days), 2))
        if kind == 0:  # known time
            msg = _tamping(f"m{k}", start, start)
        elif kind == 1:  # an interval
            msg = _tamping(f"m{k}", start, start + float(rng.uniform(0.5, 10.0)))
        elif kind == 2:  # at an index's time, zero width
            when = (float(rng.choice(times)) - T0) / DAY_S
            msg = _tamping(f"m{k}", when, when)
        else:  # an interval, and its correction to a known time
            out.append(_tamping(f"m{k}", start, start + 4.0))
            msg = _tamping(f"m{k}", start + 1.0, start + 1.0, revision=1)
        out.append(msg)
    if n_trc and rng.random() < 0.3:  # a tamping at a TRC record's time
        trc_t = [m.t for m in out if isinstance(m, TrcRecord)][-1]
        when = (trc_t - T0) / DAY_S
        out.append(_tamping("at-trc", when, when))
    return out


def canonical(events: list) -> list:
    """The events in canonical order (the log's order: time, kind, identity)."""
    return sorted(events, key=lambda m: event_of(m).order)


def deliveries(rng: np.random.Generator, events: list, count: int) -> list[list]:
    """``count`` deliveries of ``events``: shuffled, shuffled with duplicates, or in
    canonical order with some events held back and delivered late."""
    ordered = canonical(events)
    out = []
    for k in range(count):
        if k % 3 == 0:
            got = list(events)
            rng.shuffle(got)
        elif k % 3 == 1:
            got = list(events) + [events[i] for i in rng.integers(0, len(events), len(events) // 4)]
            rng.shuffle(got)
        else:
            late = set(rng.choice(len(ordered), max(1, len(ordered) // 10), replace=False).tolist())
            got = [m for i, m in enumerate(ordered) if i not in late]
            for i in sorted(late):
                got.insert(int(rng.integers(i, len(got) + 1)), ordered[i])
        out.append(got)
    return out


def fingerprint(tracker: Tracker) -> dict:
    """Each segment's log identities, detected tampings held and packed state."""
    out = {}
    for sid in sorted(tracker.histories):
        hist = tracker.histories[sid]
        out[sid] = (
            [str(e.identity) for e in hist.log],
            sorted(bytes(encode(e.message)) for e in hist.log if is_detected(e)),
            None if hist.state is None else pack_state(hist.state),
            hist.trc_t,
            hist.group,
        )
    return out


def new_tracker() -> Tracker:
    return Tracker(LIMITS.for_line, LIMITS.levels)


def stepped(models: list, msgs: list) -> dict:
    """One message at a time through :meth:`Tracker.step`."""
    tracker = new_tracker()
    for msg in [*models, *msgs]:
        tracker.step(msg)
    return fingerprint(tracker)


def keyed(msg) -> tuple[str, bytes]:
    if isinstance(msg, OnboardIndex | TrcRecord | MaintenanceEvent):
        kind = {OnboardIndex: "index", TrcRecord: "trc", MaintenanceEvent: "maintenance"}
        key = keys.segment_keys("tf", kind[type(msg)], f"{msg.line}/{msg.segment}")
    elif getattr(msg, "group", None):
        key = keys.degradation("tf", msg.group)
    else:
        key = keys.calibration("tf")
    return key, encode(msg)


def consumed(published: list[MaintenanceEvent], rng, trc_t: dict) -> dict:
    """Per segment, the detected tampings a consumer holds after ``published`` in a
    shuffled order (the highest rank per ``event_id``, withdrawals no tamping), as stored
    by filtering (revision 0), from the segment's latest TRC record on (``trc_t``)."""
    held: dict[tuple[str, str, str], MaintenanceEvent] = {}
    for k in rng.permutation(len(published)):
        msg = published[k]
        key = (msg.line, msg.segment, msg.event_id)
        if key not in held or msg.rank > held[key].rank:
            held[key] = msg
    out: dict = {}
    for (line, segment, _), msg in sorted(held.items()):
        since = trc_t.get((line, segment))
        if not msg.withdrawn and (since is None or tamping_time(msg) >= since):
            plain = msgspec.structs.replace(msg, revision=0)
            out.setdefault((line, segment), []).append(bytes(encode(plain)))
    return {sid: sorted(found) for sid, found in out.items()}


def batched(models: list, msgs: list, rng, db: Path, seen: Counter) -> tuple[dict, dict, dict]:
    """In batches of random sizes through :meth:`PersistentTracker.handle_batch` on the
    SQLite file ``db``, each detection coming back as the bus would bring it (its echo),
    then the instance restarted from the file: both fingerprints, and the detections a
    consumer holds from what the batches published (:func:`consumed`). ``seen`` counts
    the detections found and withdrawn on the way."""
    node = PersistentTracker(new_tracker(), Store(db), checkpoint_s=0.0)
    node.handle_batch([keyed(m) for m in models])
    revisions = Revisions()
    published: list[MaintenanceEvent] = []
    at = 0
    while at < len(msgs):
        size = int(rng.integers(1, 12))
        done = node.handle_batch([keyed(m) for m in msgs[at : at + size]])
        at += size
        seen["detected"] += len(done.detected)
        seen["withdrawn"] += len(done.withdrawn)
        out = [revisions.stamp(m, withdrawn=True) for m in done.withdrawn]
        out += [revisions.stamp(m, withdrawn=False) for m in done.detected]
        published += out
        if out:  # what the service publishes comes back as its echo: no input
            node.handle_batch([keyed(m) for m in out])
    live = fingerprint(node.tracker)
    trc_t = {sid: node.tracker.histories[sid].trc_t for sid in node.tracker.histories}
    consumers = consumed(published, rng, trc_t)
    node.close()
    node.store.close()
    again = PersistentTracker(new_tracker(), Store(db))
    again.restore()
    restarted = fingerprint(again.tracker)
    again.store.close()
    return live, restarted, consumers


def check(seed: int, orders: int, tmp: Path, seen: Counter | None = None) -> list[str]:
    """The deliveries of sequence ``seed`` that do not end as the canonical one, by path;
    ``seen`` counts the detections the batches found and withdrew."""
    seen = Counter() if seen is None else seen
    rng = np.random.default_rng(seed)
    models = example_models(SAMPLES, seed, z_plus_sd=0.05)
    events = sequence(rng)
    truth = stepped(models, canonical(events))
    bad = []
    for k, msgs in enumerate(deliveries(rng, events, orders)):
        if stepped(models, msgs) != truth:
            bad.append(f"seed {seed} order {k}: step")
        db = tmp / f"{seed}-{k}.sqlite"
        live, restarted, consumers = batched(models, msgs, rng, db, seen)
        if live != truth:
            bad.append(f"seed {seed} order {k}: batch")
        if restarted != truth:
            bad.append(f"seed {seed} order {k}: restart")
        if consumers != {sid: found for sid, (_, found, *_) in truth.items() if found}:
            bad.append(f"seed {seed} order {k}: consumers")
    return bad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", type=int, nargs="?", default=200)
    parser.add_argument("orders", type=int, nargs="?", default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    started = time.perf_counter()
    bad: list[str] = []
    seen: Counter = Counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seed, args.seed + args.sequences):
            bad.extend(check(seed, args.orders, Path(tmp), seen))
    took = time.perf_counter() - started
    print(
        f"order check: {args.sequences} sequences × {args.orders} deliveries × 4 paths, "
        f"{len(bad)} differ from the canonical order; on the way the batches detected "
        f"{seen['detected']} tampings and withdrew {seen['withdrawn']} ({took:.0f} s)"
    )
    for line in bad:
        print(" ", line)
    raise SystemExit(1 if bad else 0)


if __name__ == "__main__":
    main()
