"""A batch of events folded together equals its messages stepped one by one.

``Tracker.step_events`` folds the in-order indices of many segments in one vectorised pass
and takes the exact path for everything else; these tests step one mixed stream both ways
and compare every segment's arrays, encoded SegmentState and detected tamping, bit for bit.
"""

from __future__ import annotations

import json

import msgspec
import numpy as np
import pytest

from schemas import (
    DAY_S,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    SchemaError,
    encode,
    keys,
)
from services.filtering import store as store_module
from services.filtering.banks import CUSUM_THRESHOLD
from services.filtering.coordinator import PersistentTracker, _Batch
from services.filtering.events import event_of
from services.filtering.payloads import decode_keyed
from services.filtering.store import Store, index_identity
from services.filtering.testing import T0
from tests.unit.test_filtering_tracker import (
    MU,
    Z_PLUS,
    Z_WORN,
    assert_same_states,
    calibration,
    index,
    new_tracker,
    onboard_days,
    posterior,
    tamping,
    trc,
    unit_calibration,
)

SEGMENTS = [("L1", f"s{k}") for k in range(8)] + [("L2", f"s{k}") for k in range(4)]


def on(msg, line: str, segment: str):
    return msgspec.structs.replace(msg, line=line, segment=segment)


def mixed_stream(seed: int) -> list:
    """Models, then a year-ish of events on twelve segments, in a nearly time-ordered
    stream with everything the exact path handles: late indices, duplicates, TRC records
    (one dropping older events, one late and refused), tampings known and interval-only, a
    correction with a higher revision, a tamping starting a segment without a TRC record,
    unreported tampings the CUSUM finds, and calibrations (fleet and per unit) arriving
    in between."""
    rng = np.random.default_rng(seed)
    timed: list[tuple[float, int, object]] = []  # (arrival day, tie, message)
    for k, (line, seg) in enumerate(SEGMENTS):
        tamped = k % 3 == 0  # an unreported tamping at day 30.3: the CUSUM finds it
        if k != 5:  # s5 starts from a tamping, no TRC record
            timed.append((-1.0, 0, trc(0.0, *np.exp(Z_WORN).tolist(), line=line, segment=seg)))
        else:
            timed.append((2.0, 0, tamping(1.0, line=line, segment=seg)))
        days = np.arange(1, 80) + 0.01 * k
        passes = onboard_days(rng, days, Z_WORN, MU, t_tamp=30.3 if tamped else None, z_plus=Z_PLUS)
        for day, msg in zip(days, passes, strict=True):
            msg = on(msg, line, seg)
            if k % 4 == 1 and day > 50:
                msg = msgspec.structs.replace(msg, train="T2")  # read with T2's own model
            arrival = day + (3.5 if rng.random() < 0.08 else 0.0)  # some arrive late
            timed.append((arrival, 1, msg))
            if rng.random() < 0.05:
                timed.append((arrival + rng.uniform(0, 2), 1, msg))  # a duplicate
        if k % 4 == 2:  # a reported tamping, then its correction (higher revision)
            report = tamping(40.0, 44.0, line=line, segment=seg)
            timed.append((45.0, 2, report))
            fix = msgspec.structs.replace(report, revision=1, t_start=T(41.0), t_end=T(41.0))
            timed.append((47.5, 2, fix))
        if k == 7:  # a TRC record that drops the events before it, then a late index
            timed.append((60.5, 2, trc(60.2, 3.1, 2.6, line=line, segment=seg)))
            timed.append((61.0, 2, on(index(59.0, 3.0, 2.5), line, seg)))  # refused
            timed.append((61.0, 2, trc(20.0, 3.0, 2.5, line=line, segment=seg)))  # refused
    timed.append((-2.0, -1, calibration(1)))
    timed.append((-2.0, -1, posterior()))
    timed.append((-2.0, -1, posterior("line.L2", seed=4)))
    timed.append((35.0, -1, calibration(2, 1.03)))  # a new fleet calibration: re-run
    timed.append((50.0, -1, unit_calibration("T2", "u1")))  # T2's own model from day 50
    timed.sort(key=lambda item: (item[0], item[1]))
    return [msg for _, _, msg in timed]


def keyed(msg) -> tuple[str, bytes]:
    return keys.key_of("tf", msg), encode(msg)


def T(days: float) -> float:
    return 1_767_225_600.0 + days * DAY_S


def chunks(messages: list, rng: np.random.Generator, most: int):
    """The stream cut into batches of random sizes, a model always alone (``handle_batch``
    applies a batch's models first, which one by one is not)."""
    batch: list = []
    for msg in messages:
        if isinstance(msg, Calibration | DegradationPosterior):
            if batch:
                yield batch
            yield [msg]
            batch = []
            continue
        batch.append(msg)
        if len(batch) >= rng.integers(1, most + 1):
            yield batch
            batch = []
    if batch:
        yield batch


@pytest.mark.parametrize("most", [1, 7, 64, 400])
def test_a_batch_folds_to_the_bits_of_its_messages_one_by_one(most):
    messages = mixed_stream(11)
    one, one_found, one_reasons = new_tracker(), [], []
    for msg in messages:
        step = one.step(msg)
        one_found.extend(step.detected)
        one_reasons.append(step.reason)
    assert len(one_found) >= 3  # the CUSUM found the unreported tampings
    assert sum(r == "duplicate" for r in one_reasons) >= 3
    assert "older than the latest TRC record" in one_reasons

    batched, found, reasons, published = new_tracker(), [], [], {}
    for batch in chunks(messages, np.random.default_rng(most), most):
        if isinstance(batch[0], Calibration | DegradationPosterior):
            update = batched.update_models(batch)
            reasons.append("" if update.accepted else update.ignored[0][1])
            states = update.states
        else:
            got, states, detected, _ = batched.step_events(batch)
            reasons.extend(got)
            found.extend(detected)
        for state in states:
            published[(state.line, state.segment)] = encode(state)

    assert reasons == one_reasons
    assert [encode(m) for m in found] == [encode(m) for m in one_found]
    assert_same_states(one, batched)  # arrays with np.array_equal, encoded states
    for sid, hist in one.histories.items():
        assert (hist.state.cusum, hist.state.cusum_t0) == (
            batched.histories[sid].state.cusum,
            batched.histories[sid].state.cusum_t0,
        ) or np.isnan(hist.state.cusum_t0)
    assert published == {
        sid: encode(one.segment_state(hist)) for sid, hist in one.histories.items()
    }


def test_a_detection_inside_a_batch_stops_the_fold_there():
    """Every pass of a tamped segment in one batch: the CUSUM reaches the threshold inside
    it, the detected tamping and the state after it are those of one pass at a time."""
    rng = np.random.default_rng(7)
    record = trc(0.0, *np.exp(Z_WORN).tolist())
    passes = onboard_days(rng, np.arange(1, 90), Z_WORN, MU, t_tamp=50.3, z_plus=Z_PLUS)
    one, batched = new_tracker(), new_tracker()
    found = []
    for msg in [calibration(), posterior(), record, *passes]:
        found.extend(one.step(msg).detected)
    for msg in [calibration(), posterior(), record]:
        batched.step(msg)
    reasons, _, detected, _ = batched.step_events(passes)
    assert not any(reasons) and len(found) == 1
    assert [encode(m) for m in detected] == [encode(m) for m in found]
    assert_same_states(one, batched)
    assert batched.histories[("L1", "s1")].state.cusum < CUSUM_THRESHOLD


def test_fold_events_defers_the_summaries_to_states_of():
    messages = mixed_stream(3)
    eager, lazy = new_tracker(), new_tracker()
    events = [m for m in messages if not isinstance(m, Calibration | DegradationPosterior)]
    for tracker in (eager, lazy):
        tracker.update_models([calibration(1), posterior(), posterior("line.L2", seed=4)])
    _, states, _, _ = eager.step_events(events)
    _, changed, _, _ = lazy.fold_events(events)
    assert sorted(changed) == sorted(SEGMENTS)
    assert [encode(s) for s in lazy.states_of(changed)] == [
        encode(s) for s in sorted(states, key=lambda s: changed.index((s.line, s.segment)))
    ]


def test_a_batch_commits_what_one_by_one_commits(tmp_path):
    """``handle_batch`` (grouped inserts) leaves the store as ``handle`` of each message."""
    messages = mixed_stream(5)
    one = PersistentTracker(new_tracker(), Store(tmp_path / "one.sqlite"))
    for msg in messages:
        one.handle(*keyed(msg))
    batched = PersistentTracker(new_tracker(), Store(tmp_path / "batch.sqlite"))
    for batch in chunks(messages, np.random.default_rng(0), 200):
        batched.handle_batch([keyed(m) for m in batch])
    # the same rows; not in the same order: a batch commits its detected tampings first
    rows = "SELECT line, segment, kind, key, identity, t, payload FROM events ORDER BY 1, 2, 5"
    stored = list(batched.store._db.execute(rows))
    assert list(one.store._db.execute(rows)) == stored
    for _line, _segment, _kind, key, identity, t, payload in stored:
        event = event_of(decode_keyed(key, payload))
        assert (identity, t) == (json.dumps(list(event.identity)), event.t_s)
    rebuilt = PersistentTracker(new_tracker(), Store(tmp_path / "batch.sqlite"))
    rebuilt.rebuild()
    assert_same_states(one.tracker, rebuilt.tracker)
    for node in (one, batched, rebuilt):
        node.store.close()


def test_an_index_identity_is_its_json(monkeypatch):
    """The events table's identity of an index, made from a prefix kept per unit, is
    ``json.dumps`` of it, whatever the ids hold (quotes, backslashes, other scripts) and
    after the kept prefixes are forgotten."""
    monkeypatch.setattr(store_module, "_INDEX_PREFIXES_MAX", 3)
    ids = ["T1", 'T"2', "u\\3", "Zug-ü", "列車", "@x"]
    times = [1_767_225_600.0, 0.1, 1e22, 123.456789012345, 5e-324]
    for train in ids:
        for unit in reversed(ids):
            for t in times:
                assert index_identity(train, unit, t) == json.dumps(["index", train, unit, t])
    assert len(store_module._INDEX_PREFIXES) <= 3


def test_evolve_is_dataclasses_replace():
    from dataclasses import replace

    import services.filtering.histories as core

    messages = mixed_stream(2)
    tracker = new_tracker()
    for msg in messages:
        tracker.step(msg)
    hist = tracker.histories[SEGMENTS[0]]
    changes = {"log": hist.log[:3], "state": None, "group": "line.L9"}
    assert core.evolve(hist, **changes) == replace(hist, **changes)
    with pytest.raises(TypeError):
        core.evolve(hist, stat=None)


def test_a_batch_refuses_its_bad_indices_with_the_reasons_of_one_at_a_time(tmp_path):
    """The indices of a batch decode in one call; a batch with a bad one among them (on
    another segment's key, truncated, out of range) refuses exactly those, each with the
    reason decode_keyed gives, and folds the others as one at a time does."""
    messages = mixed_stream(5)
    good = [keyed(m) for m in messages]
    first_index = next(i for i, m in enumerate(messages) if m.__class__.__name__ == "OnboardIndex")
    key, payload = good[first_index]
    wrong_key = (key.rsplit("/", 1)[0] + "/s99", payload)
    truncated = (key, payload[:-4])
    raw = msgspec.msgpack.decode(payload)
    out_of_range = (key, msgspec.msgpack.encode({**raw, "align10_mm": float("nan")}))
    bad = [wrong_key, truncated, out_of_range]
    items = good[: first_index + 40] + bad + good[first_index + 40 :]
    one = PersistentTracker(new_tracker(), Store(tmp_path / "one.sqlite"))
    reasons = {}
    for k, p in items:
        try:
            decode_keyed(k, p)
        except SchemaError as e:
            reasons[(k, p)] = str(e)
            continue
        one.handle(k, p)
    assert len(reasons) == 3
    batched = PersistentTracker(new_tracker(), Store(tmp_path / "batch.sqlite"))
    rejected = []
    for batch in chunks(items, np.random.default_rng(1), 400):
        rejected += batched.handle_batch(batch).rejected
    assert [(k, p) for k, _r, p in rejected] == bad
    assert {(k, p): r for k, r, p in rejected} == reasons
    assert_same_states(one.tracker, batched.tracker)
    for node in (one, batched):
        node.store.close()


def test_a_batch_publishes_its_net_detection_changes_whichever_path_made_them():
    def detection(t_start):
        return MaintenanceEvent(
            line="L1", segment="s1", event_id="detected-9", t_start=t_start, t_end=T0 + 9 * DAY_S,
            detected=True,
        )  # fmt: skip

    a, b = detection(T0 + 8 * DAY_S), detection(T0 + 7 * DAY_S)

    def net(*steps):
        batch = _Batch([])
        for found, withdrawn in steps:
            batch.note(found, withdrawn)
        result = batch.result()
        return result.detected, result.withdrawn

    assert net(([a], [])) == ((a,), ())
    assert net(([a], []), ([], [a])) == ((), ())  # found then withdrawn: nothing to say
    assert net(([], [a]), ([a], [])) == ((), ())  # withdrawn then found as it was
    assert net(([], [a])) == ((), (a,))
    assert net(([], [a]), ([b], [])) == ((b,), ())  # found otherwise: b outranks a anew
