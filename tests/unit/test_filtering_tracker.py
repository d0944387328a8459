"""The filtering core (tracker) and its store: lists of messages in, lists of states out."""

from __future__ import annotations

import msgpack
import msgspec
import numpy as np
import pytest

from schemas import (
    DAY_S,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    NDArray,
    OnboardIndex,
    SchemaError,
    SegmentState,
    TrcRecord,
    encode,
    keys,
)
from services.filtering.coordinator import PersistentTracker
from services.filtering.degradation import DegradationParams
from services.filtering.kalman import FilterBank, ObservationModel, update
from services.filtering.mixture import (
    effective_sample_size,
    forecast,
    summarize,
    weights_from_log,
)
from services.filtering.segment import DERIVED, WITHDRAWAL
from services.filtering.store import Store
from services.filtering.summary import state_weights
from services.filtering.testing import example_posterior, onboard_index
from services.filtering.tracker import Tracker
from services.limits import load_limits
from track.segments import KnownSegments

T0 = 1_767_225_600.0  # 2026-01-01 UTC
NS = 40
H = np.array([[0.9, 0.05], [0.05, 0.75]])
B = np.array([-0.25, -0.35])
R = np.array([[0.01, 0.002], [0.002, 0.03]])
LIMITS = load_limits()


def calibration(version: int = 1, scale: float = 1.0) -> Calibration:
    return Calibration(
        version=version,
        t=T0,
        indicators=["top6", "align10"],
        indices=["top6", "align10"],
        H=NDArray.of(H * scale),
        b=NDArray.of(B),
        R=NDArray.of(R),
        n_pairs=50,
        r2=NDArray.of([0.8, 0.7]),
    )


def posterior(
    group: str = "net", version: int = 1, seed: int = 0, ns: int = NS
) -> DegradationPosterior:
    return example_posterior(
        ns, seed, group=group, version=version, z_plus_sd=0.05, n_increments=30, n_levels=10
    )


def params_of(post: DegradationPosterior) -> DegradationParams:
    return DegradationParams(
        post.mu.array(), post.sigma.array(), post.z_plus.array(), post.sigma_z_plus.array()
    )


def trc(t_days: float, top6: float = 3.0, align10: float = 2.5, line="L1", segment="s1"):
    return TrcRecord(
        line=line,
        segment=segment,
        t=T0 + t_days * DAY_S,
        top6_mm=top6,
        align10_mm=align10,
        run_id=f"run{t_days:g}",
    )


def index(t_days: float, top6: float, align10: float, line="L1", segment="s1", train="T1"):
    return onboard_index(line, segment, T0 + t_days * DAY_S, top6, align10, train)


def tamping(t_start_days: float, t_end_days: float | None = None, line="L1", segment="s1"):
    t_end_days = t_start_days if t_end_days is None else t_end_days
    return MaintenanceEvent(
        line=line,
        segment=segment,
        event_id=f"tamp{t_start_days:g}",
        t_start=T0 + t_start_days * DAY_S,
        t_end=T0 + t_end_days * DAY_S,
    )


def history(rng: np.random.Generator, segments=("s1", "s2", "s3")) -> list:
    """Events of a few segments: TRC records, weekly-ish indices, a known and an interval
    tamping, and equal-time ties."""
    events = []
    for k, seg in enumerate(segments):
        events.append(trc(0.0, 3.0 + k, 2.5, segment=seg))
        for week in range(1, 20):
            top6, align10 = np.exp(rng.normal([0.8, 0.5], 0.1)).tolist()
            events.append(index(7.0 * week + 0.5 * k, top6, align10, segment=seg))
        events.append(index(14.0 + 0.5 * k, 2.0, 2.0, segment=seg, train="T2"))  # same t
        events.append(tamping(60.0, segment=seg) if k % 2 else tamping(58.0, 64.0, segment=seg))
        events.append(trc(100.0, 2.2, 2.0, segment=seg))
        events.append(index(100.0, 2.1, 1.9, segment=seg))  # tie with the TRC record
    return events


def new_tracker() -> Tracker:
    return Tracker(LIMITS.for_line, LIMITS.levels)


def run(messages) -> tuple[Tracker, list[SegmentState]]:
    tracker = new_tracker()
    out = []
    for msg in messages:
        out.extend(tracker.step(msg).states)
    return tracker, out


def assert_same_states(a: Tracker, b: Tracker) -> None:
    assert a.histories.keys() == b.histories.keys()
    for sid in a.histories:
        ta, tb = a.histories[sid], b.histories[sid]
        assert [e.identity for e in ta.log] == [e.identity for e in tb.log]
        assert (ta.state is None) == (tb.state is None)
        if ta.state is not None:
            assert np.array_equal(ta.state.z, tb.state.z)
            assert np.array_equal(ta.state.P, tb.state.P)
            assert np.array_equal(ta.state.log_w, tb.state.log_w)
            assert (ta.state.t_s, ta.state.n_updates, ta.state.nis) == (
                tb.state.t_s,
                tb.state.n_updates,
                tb.state.nis,
            )
        sa, sb = a.segment_state(ta), b.segment_state(tb)
        assert (sa is None) == (sb is None)
        if sa is not None:
            assert encode(sa) == encode(sb)  # every field, bit for bit


MODELS = [calibration(), posterior()]


def test_shuffled_and_duplicated_delivery_give_the_in_order_state():
    rng = np.random.default_rng(1)
    events = history(rng)
    in_order = sorted(events, key=lambda m: getattr(m, "t", getattr(m, "t_start", 0.0)))
    reference, _ = run(MODELS + in_order)
    for seed in range(5):
        shuffled = list(events)
        np.random.default_rng(seed).shuffle(shuffled)
        tracker, _ = run(MODELS + shuffled)
        assert_same_states(reference, tracker)
        duplicated = shuffled + shuffled[::3]
        np.random.default_rng(seed + 10).shuffle(duplicated)
        tracker, _ = run(duplicated[:7] + MODELS + duplicated[7:])  # models arrive late too
        assert_same_states(reference, tracker)


def test_duplicates_and_events_before_the_latest_trc_are_refused():
    tracker, _ = run([*MODELS, trc(0.0), index(3.0, 2.0, 2.0), trc(10.0)])
    assert tracker.step(index(3.0, 2.0, 2.0)).reason == "older than the latest TRC record"
    step = tracker.step(index(12.0, 2.0, 2.0))
    assert step.accepted and len(step.states) == 1
    assert tracker.step(index(12.0, 2.0, 2.0)).reason == "duplicate"
    assert [e.t_s for e in tracker.histories[("L1", "s1")].log] == [
        T0 + 10 * DAY_S,
        T0 + 12 * DAY_S,
    ]


def test_trc_restart_sets_every_sample_to_the_record():
    tracker, _ = run([*MODELS, trc(0.0), index(3.0, 2.0, 2.0)])
    (state,) = tracker.step(trc(20.0, 4.0, 3.0)).states
    hist = tracker.histories[("L1", "s1")]
    np.testing.assert_array_equal(hist.state.z, np.broadcast_to(np.log([4.0, 3.0]), (NS, 2)))
    np.testing.assert_array_equal(hist.state.P, 0.0)
    assert state.last_trc_t == T0 + 20 * DAY_S and state.n_updates == 0 and state.nis is None
    np.testing.assert_allclose(state.ci_low_mm.array(), [4.0, 3.0])
    np.testing.assert_allclose(state.ci_high_mm.array(), [4.0, 3.0])
    assert state.width == 0.0


def bank_replay(post, steps) -> FilterBank:
    """The FilterBank core on one segment: steps are (op, t_days, value)."""
    bank = FilterBank(1, params_of(post))
    model = ObservationModel(H, B, R)
    for op, t_days, value in steps:
        if op == "restart":
            bank.restart([0], np.log([value]), t_days)
        elif op == "tamping":
            bank.predict_to([0], t_days, tamping_age=[0.0])
        else:
            bank.observe([0], t_days, np.log([value]), model)
    return bank


@pytest.mark.parametrize("interval", [None, (50.0, 60.0)], ids=["known", "interval"])
def test_results_equal_the_filter_bank_core(interval):
    post = posterior()
    t_tamp = 55.0 if interval is None else 0.5 * sum(interval)
    tamp = tamping(55.0) if interval is None else tamping(*interval)
    messages = [trc(0.0, 3.0, 2.5), tamp]
    steps = [("restart", 0.0, (3.0, 2.5)), ("tamping", t_tamp, None)]
    rng = np.random.default_rng(3)
    for day in (4.0, 11.0, 30.0, 54.0, 56.0, 70.0):
        y = tuple(np.exp(rng.normal([0.8, 0.5], 0.1)).tolist())
        messages.append(index(day, *y))
        steps.append(("index", day, y))
    steps.sort(key=lambda s: s[1])
    tracker, states = run([calibration(), post, *messages])
    bank = bank_replay(post, steps)
    hist = tracker.histories[("L1", "s1")]
    np.testing.assert_allclose(hist.state.z, bank.z[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(hist.state.P, bank.P[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(hist.state.log_w, bank.log_w[0], rtol=1e-12)
    assert hist.state.t_s == T0 + 70 * DAY_S and bank.t[0] == 70.0
    # the published summary is the mixture of that bank, weighted by its likelihoods
    state = states[-1]
    limits = LIMITS.for_line("L1")
    w = weights_from_log(bank.log_w[0])
    assert w.std() > 0  # the weights are not equal: this checks the weighting
    now = summarize(bank.z[0], bank.P[0], limits, weights=w)
    ahead = forecast(bank.z[0], bank.P[0], params_of(post), [30.0, 90.0, 180.0], weights=w)
    np.testing.assert_allclose(state.mean.array(), now.mean, atol=1e-12)
    np.testing.assert_allclose(state.cov.array(), now.cov, atol=1e-12)
    np.testing.assert_allclose(state.ci_high_mm.array(), now.ci_high_mm, rtol=1e-9)
    np.testing.assert_allclose(state.p_exceed.array(), now.p_exceed, atol=1e-9)
    np.testing.assert_allclose(state.forecast_mean.array(), ahead.mean, atol=1e-12)
    np.testing.assert_allclose(state.forecast_ci_low_mm.array(), ahead.ci_low_mm, rtol=1e-9)
    for level in range(2):
        fp = forecast(
            bank.z[0], bank.P[0], params_of(post), [30.0, 90.0, 180.0], limits[level], weights=w
        )
        np.testing.assert_allclose(state.forecast_p_exceed.array()[:, level], fp.p_exceed)
    assert state.n_updates == 6 and state.last_trc_t == T0
    assert state.posterior_group == "net" and state.calibration_version == 1


def test_tamping_resets_to_the_post_tamping_level():
    post = posterior()
    tracker, _ = run([calibration(), post, trc(0.0), index(5.0, 2.0, 2.0), tamping(8.0, 12.0)])
    hist = tracker.histories[("L1", "s1")]
    np.testing.assert_array_equal(hist.state.z, post.z_plus.array())
    np.testing.assert_array_equal(hist.state.P, post.sigma_z_plus.array())
    assert hist.state.t_s == T0 + 10 * DAY_S  # mid-interval
    assert hist.state.n_updates == 1  # a tamping keeps the count since the TRC record


def test_tamping_starts_a_segment_without_trc():
    post = posterior()
    tracker, states = run([calibration(), post, index(1.0, 2.0, 2.0), tamping(3.0)])
    assert len(states) == 1 and states[0].last_trc_t is None and states[0].n_updates == 0
    step = tracker.step(index(5.0, 2.1, 1.9))
    assert step.states[0].n_updates == 1
    bank = bank_replay(post, [("tamping", 3.0, None), ("index", 5.0, (2.1, 1.9))])
    np.testing.assert_allclose(tracker.histories[("L1", "s1")].state.z, bank.z[0], atol=1e-12)


def test_no_state_without_start_posterior_or_calibration():
    tracker, states = run([index(1.0, 2.0, 2.0), trc(0.0)])
    assert states == []  # no posterior
    assert tracker.step(posterior()).states == ()  # an index but no calibration
    step = tracker.step(calibration())
    assert step.accepted and [s.n_updates for s in step.states] == [1]
    tracker, states = run([posterior(), trc(0.0)])
    assert [s.calibration_version for s in states] == [0]  # nothing to update: publishable
    assert run([*MODELS, index(1.0, 2.0, 2.0)])[1] == []  # nothing to start from


def test_model_change_reruns_the_segments_from_their_trc_record():
    rng = np.random.default_rng(2)
    events = history(rng)
    old, _ = run([calibration(1), posterior(seed=0), *events])
    for change, fresh in (
        ([calibration(2, scale=1.1)], [calibration(2, scale=1.1), posterior(seed=0)]),
        ([posterior(version=2, seed=5)], [calibration(1), posterior(version=2, seed=5)]),
        ([posterior("line.L1", seed=6)], [calibration(1), posterior("line.L1", seed=6)]),
    ):
        tracker, _ = run([calibration(1), posterior(seed=0), *events])
        for msg in change:
            step = tracker.step(msg)
            assert step.accepted and len(step.states) == 3
        reference, _ = run([*fresh, *events])
        for sid, hist in tracker.histories.items():
            np.testing.assert_array_equal(hist.state.z, reference.histories[sid].state.z)
            assert not np.array_equal(hist.state.z, old.histories[sid].state.z)
    step = tracker.step(posterior(version=1, seed=9))
    assert not step.accepted and step.states == ()


def test_most_specific_group_wins():
    tracker, _ = run([calibration(), posterior("net"), posterior("line.L1", seed=1)])
    tracker.step(trc(0.0, segment="s1"))
    tracker.step(trc(0.0, line="L2", segment="s1"))
    step = tracker.step(posterior("seg.L1.s1", seed=2))
    assert [s.posterior_group for s in step.states] == ["seg.L1.s1"]
    assert tracker.state_of("L2", "s1").posterior_group == "net"
    assert tracker.state_of("L1", "s1").limits_mm.array().tolist() == LIMITS.for_line("L1").tolist()


def feed(db, messages) -> PersistentTracker:
    node = PersistentTracker(new_tracker(), Store(db))
    for msg in messages:
        node.handle(*keyed(msg))
    return node


def test_store_rebuilds_identical_states_after_an_unclean_stop(tmp_path):
    rng = np.random.default_rng(4)
    events = history(rng)
    rng.shuffle(events)
    db = tmp_path / "filtering-test.sqlite"
    first = feed(db, [calibration(1), posterior(), *events[:40], calibration(2, 1.05)])
    # No close(): the first connection is simply abandoned, as after a SIGKILL.
    second = PersistentTracker(new_tracker(), Store(db))
    states = second.rebuild()
    assert len(states) == 3
    assert_same_states(first.tracker, second.tracker)
    for msg in events[40:]:  # both go on identically
        first.tracker.step(msg)
        second.handle(*keyed(msg))
    assert_same_states(first.tracker, second.tracker)
    # the TRC records at day 100 pruned everything before them but the tamping reports:
    # the store holds the logs
    rebuilt = PersistentTracker(new_tracker(), Store(db))
    rebuilt.rebuild()
    in_logs = sum(len(hist.log) for hist in first.tracker.histories.values())
    assert rebuilt.store.count_events() == in_logs == 3 * (7 + 1)
    assert_same_states(first.tracker, rebuilt.tracker)
    for node in (second, rebuilt):
        node.store.close()


def test_a_batch_equals_its_messages_one_by_one(tmp_path):
    """handle_batch (models first and coalesced, events folded then summarised together, one
    transaction) leaves the tracker and the store as handle() of each message does, and
    publishes each changed segment's newest state, bit for bit; bad payloads come back."""
    rng = np.random.default_rng(5)
    events = history(rng)
    rng.shuffle(events)
    messages = [calibration(1), posterior(), *events[:30], calibration(2, 1.05), *events[30:]]
    one_by_one = feed(tmp_path / "one.sqlite", messages)
    batched = PersistentTracker(new_tracker(), Store(tmp_path / "batch.sqlite"))
    items = [keyed(m) for m in messages]
    bad = (keys.index("tf", "L1", "s1"), b"\xc1")
    results = [batched.handle_batch(chunk) for chunk in (items[:25], [*items[25:50], bad])]
    results.append(batched.handle_batch(items[50:]))

    assert_same_states(one_by_one.tracker, batched.tracker)
    assert [len(r.rejected) for r in results] == [0, 1, 0]
    assert results[1].rejected[0][0] == bad[0]
    newest = {(s.line, s.segment): encode(s) for r in results for s in r.states}
    assert newest == {
        sid: encode(one_by_one.tracker.segment_state(hist))
        for sid, hist in one_by_one.tracker.histories.items()
    }
    assert batched.store.count_events() == one_by_one.store.count_events()
    for node in (one_by_one, batched):
        node.store.close()


def test_the_store_keeps_the_message_and_refuses_what_it_cannot_store(tmp_path):
    """A valid message is stored re-encoded; a message with a large unknown field
    (every type refuses a field it does not have), a model version beyond SQLite's
    INTEGER, or a payload nested 10,000 deep, is a dead letter naming the field, not an
    exception out of the batch."""
    node = PersistentTracker(new_tracker(), Store(tmp_path / "f.sqlite"))
    post = posterior()
    index = OnboardIndex(line="L1", segment="s1", train="T1", unit="u1", t=T0 + DAY_S,
                         top6_mm=2.0, align10_mm=1.5, speed_mps=30.0, coverage=1.0)  # fmt: skip
    trc = TrcRecord(line="L1", segment="s1", t=T0, top6_mm=2.1, align10_mm=1.6, run_id="r1")
    blob = b"\x00" * (DegradationPosterior.MAX_BYTES - len(encode(post)) - 100)
    padded = [
        (key, msgpack.packb({**msgpack.unpackb(payload), "blob": extra}))
        for (key, payload), extra in [
            (keyed(calibration()), b"\x00" * 10_000),
            (keyed(post), blob),
            (keyed(trc), b"\x00" * 3_000),
            (keyed(index), b"\x00" * 3_000),
        ]
    ]
    big = msgpack.packb({**msgpack.unpackb(keyed(calibration(2))[1]), "version": 2**63})
    deep_key, deep_payload = keyed(index)
    deep = b"\xde" + (len(msgpack.unpackb(deep_payload)) + 1).to_bytes(2, "big")
    deep += msgpack.packb("extra") + b"\x91" * 10_000 + b"\x90" + deep_payload[1:]
    valid = [keyed(m) for m in (calibration(), post, trc, index)]
    done = node.handle_batch([*padded, *valid, (keys.calibration("tf"), big), (deep_key, deep)])

    assert done.accepted == 4 and len(done.states) == 1
    reasons = [reason for _key, reason, _payload in done.rejected]
    assert len(reasons) == 6
    for reason, name in zip(reasons, ("Calibration", "DegradationPosterior", "TrcRecord",
                                      "OnboardIndex"), strict=False):  # fmt: skip
        assert reason.startswith(f"{name}: ") and "unknown field `blob`" in reason, reason
    assert reasons[4].startswith("Calibration: version: 9223372036854775808 outside")
    assert reasons[5].startswith("OnboardIndex:")  # beyond its size limit, or too deep
    stored = [payload for _kind, _key, payload in [*node.store.models(), *node.store.events()]]
    assert sorted(stored) == sorted(encode(m) for m in (calibration(), post, trc, index))
    node.store.close()
    rebuilt = PersistentTracker(new_tracker(), Store(tmp_path / "f.sqlite"))
    assert [encode(s) for s in rebuilt.rebuild()] == [encode(s) for s in done.states]
    rebuilt.store.close()


def test_events_on_segments_the_network_lacks_are_refused_and_hold_nothing(tmp_path):
    node = PersistentTracker(
        new_tracker(),
        Store(tmp_path / "known.sqlite"),
        known=KnownSegments([("L1", "s1")], "demo.geojson"),
    )
    known, unknown = trc(0.0, 3.0, 2.5, segment="s1"), trc(0.0, 3.0, 2.5, segment="s9")
    result = node.handle_batch([keyed(m) for m in (calibration(1), posterior(), known, unknown)])
    assert [state.segment for state in result.states] == ["s1"]
    ((key, reason, _),) = result.rejected
    assert key == keyed(unknown)[0]
    assert reason == "TrcRecord: segment L1/s9 is not in the network demo.geojson"
    assert set(node.tracker.histories) == {("L1", "s1")} and node.store.count_events() == 1
    node.store.close()


def keyed(msg) -> tuple[str, bytes]:
    """The key a message is published on (namespace "tf") and its payload."""
    return keys.key_of("tf", msg), encode(msg)


# --- mixture weights: the likelihood of the segment's own on-board data -------------------


def test_no_onboard_data_means_equal_weights():
    tracker, states = run([*MODELS, trc(0.0), tamping(30.0)])
    state = tracker.histories[("L1", "s1")].state
    np.testing.assert_array_equal(state.log_w, np.zeros(NS))
    np.testing.assert_array_equal(state_weights(state), np.full(NS, 1 / NS))
    equal = summarize(state.z, state.P, LIMITS.for_line("L1"))  # the paper's 1 / Ns
    np.testing.assert_allclose(states[-1].mean.array(), equal.mean, atol=1e-14)
    np.testing.assert_allclose(states[-1].ci_high_mm.array(), equal.ci_high_mm, rtol=1e-12)
    np.testing.assert_allclose(states[-1].p_exceed.array(), equal.p_exceed, atol=1e-14)
    # a tamping that starts a segment starts it with equal weights too
    tracker, _ = run([*MODELS, index(1.0, 2.0, 2.0), tamping(3.0)])
    np.testing.assert_array_equal(tracker.histories[("L1", "s1")].state.log_w, 0.0)


def test_trc_restart_resets_and_tamping_keeps_the_weights():
    tracker, _ = run([*MODELS, trc(0.0), index(3.0, 2.0, 2.0), index(9.0, 2.6, 2.0)])
    before = tracker.histories[("L1", "s1")].state.log_w.copy()
    assert np.ptp(before) > 0
    tracker.step(tamping(10.0))
    np.testing.assert_array_equal(tracker.histories[("L1", "s1")].state.log_w, before)
    tracker.step(trc(20.0))
    np.testing.assert_array_equal(tracker.histories[("L1", "s1")].state.log_w, 0.0)


def test_fold_with_weights_is_deterministic_under_late_and_duplicate_events():
    rng = np.random.default_rng(12)
    events = history(rng)
    in_order = sorted(events, key=lambda m: getattr(m, "t", getattr(m, "t_start", 0.0)))
    reference, _ = run(MODELS + in_order)
    for hist in reference.histories.values():
        assert effective_sample_size(state_weights(hist.state)) < NS - 1  # weights in play
    for seed in range(3):
        late = list(events)
        np.random.default_rng(seed).shuffle(late)
        late = late + late[::4]  # duplicates, arriving after everything else
        tracker, _ = run(late[:5] + MODELS + late[5:])
        assert_same_states(reference, tracker)  # log_w and the published states, bit for bit
    # one more step on the current state equals a replay of the whole log
    tracker, _ = run(MODELS + in_order[:-1])
    tracker.step(in_order[-1])
    assert_same_states(reference, tracker)


def test_nis_is_weighted_by_the_predictive_weights():
    post = posterior()
    tracker, _ = run([calibration(), post, trc(0.0), index(5.0, 2.0, 2.0), index(9.0, 2.4, 2.0)])
    first = tracker.histories[("L1", "s1")].state
    tracker.step(index(40.0, 2.6, 2.1))
    state = tracker.histories[("L1", "s1")].state
    z = first.z + post.mu.array() * 31.0
    P = first.P + post.sigma.array() * 31.0
    _, _, nis = update(z, P, np.log([2.6, 2.1]), H, B, R)
    np.testing.assert_allclose(state.nis, weights_from_log(first.log_w) @ nis, rtol=1e-12)
    assert abs(state.nis - nis.mean()) > 1e-6  # not the equal-weight mean


def test_store_rebuild_restores_the_weights(tmp_path):
    rng = np.random.default_rng(13)
    events = history(rng)[:30]
    db = tmp_path / "filtering-weights.sqlite"
    first = feed(db, [*MODELS, *events])
    second = PersistentTracker(new_tracker(), Store(db))  # after a SIGKILL: replay the store
    second.rebuild()
    assert_same_states(first.tracker, second.tracker)
    for hist in second.tracker.histories.values():
        assert np.ptp(hist.state.log_w) > 0
    second.store.close()


def test_a_trc_record_at_a_tampings_time_wins_whatever_the_order():
    """A TRC record is exact (P = 0): a tamping at the same time is ordered before it."""
    post = posterior()
    before = [calibration(), post, trc(0.0), index(5.0, 2.0, 2.0)]
    for last_two in ([tamping(10.0), trc(10.0, 4.0, 3.0)], [trc(10.0, 4.0, 3.0), tamping(10.0)]):
        tracker, _ = run([*before, *last_two])
        state = tracker.histories[("L1", "s1")].state
        np.testing.assert_array_equal(state.z, np.broadcast_to(np.log([4.0, 3.0]), (NS, 2)))
        np.testing.assert_array_equal(state.P, 0.0)
        assert state.last_trc_t == T0 + 10 * DAY_S
    # and the tamping still counts for what follows: the next index degrades from the record
    tracker, _ = run([*before, trc(10.0, 4.0, 3.0), tamping(10.0), index(12.0, 3.9, 2.9)])
    alone, _ = run([*before, trc(10.0, 4.0, 3.0), index(12.0, 3.9, 2.9)])
    np.testing.assert_array_equal(
        tracker.histories[("L1", "s1")].state.z, alone.histories[("L1", "s1")].state.z
    )


def correction(report: MaintenanceEvent, t_start_days: float, t_end_days=None, revision=0):
    t_end_days = t_start_days if t_end_days is None else t_end_days
    return MaintenanceEvent(
        line=report.line,
        segment=report.segment,
        event_id=report.event_id,
        t_start=T0 + t_start_days * DAY_S,
        t_end=T0 + t_end_days * DAY_S,
        revision=revision,
    )


@pytest.mark.parametrize(
    "corrected",
    [
        pytest.param(lambda r: correction(r, 13.0), id="interval corrected to a known time"),
        pytest.param(lambda r: correction(r, 9.0, 11.0), id="narrower interval"),
        pytest.param(lambda r: correction(r, 16.0, 19.0, revision=1), id="higher revision"),
    ],
)
def test_a_tamping_correction_replaces_the_report_whatever_the_order(corrected):
    report = tamping(8.0, 14.0)
    fixed = corrected(report)
    base = [*MODELS, trc(0.0), index(5.0, 2.0, 2.0), index(20.0, 2.2, 2.1)]
    truth, _ = run([*base, fixed])  # what the correction alone gives
    first, _ = run([*base, report, fixed])
    second, _ = run([*base, fixed, report])
    assert_same_states(first, truth)
    assert_same_states(second, truth)
    assert first.step(report).reason == "duplicate"  # after the correction: not replacing it
    # one row per event_id in the store, the correction, whatever the order
    for order in ([report, fixed], [fixed, report]):
        node = PersistentTracker(new_tracker(), Store(":memory:"))
        for msg in [*base, *order]:
            node.handle(*keyed(msg))
        node.handle(*keyed(base[-1]))  # a duplicate index: refused, not stored again
        kinds = node.store._db.execute("SELECT kind, COUNT(*) FROM events GROUP BY kind")
        assert dict(kinds.fetchall()) == {"trc": 1, "index": 2, "maintenance": 1}
        rebuilt = PersistentTracker(new_tracker(), node.store)
        rebuilt.rebuild()
        assert_same_states(rebuilt.tracker, truth)
        node.store.close()


def test_a_correction_before_the_latest_trc_record_takes_the_tamping_out_of_the_state():
    """The report put the tamping after the TRC record; the correction puts it before, where
    the record already measured it: the state is the one without the tamping, and the
    correction stays in the log before the record, so that the report coming again (or
    first) is outranked whatever the order."""
    report = tamping(15.0, 25.0)  # placed at day 20, after the record of day 18
    fixed = correction(report, 16.0)
    base = [*MODELS, trc(0.0), trc(18.0, 2.5, 2.2), index(22.0, 2.4, 2.2)]
    tracker, _ = run([*base, report])
    assert report.event_id in {e.identity[1] for e in tracker.histories[("L1", "s1")].log}
    assert tracker.step(fixed).accepted
    log = tracker.histories[("L1", "s1")].log
    assert [e.identity[0] for e in log] == ["maintenance", "trc", "index"]
    assert log[0].t_s == fixed.t_start
    a, b = tracker.histories[("L1", "s1")].state, run(base)[0].histories[("L1", "s1")].state
    for name in ("z", "P", "log_w", "t_s", "n_updates", "nis", "cusum"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True)
    assert tracker.step(report).reason == "duplicate"  # outranked by the correction
    other_order, _ = run([*base, fixed, report])
    assert_same_states(tracker, other_order)


def test_an_interval_only_tamping_sits_at_the_middle_of_the_reported_interval():
    """Eq. 2's mid-interval rule on the report's interval: the same state as a tamping known
    at the middle, whatever other events fall inside the interval."""
    base = [*MODELS, trc(0.0), index(5.0, 2.0, 2.0), index(11.0, 2.1, 2.0)]
    after = [index(25.0, 2.3, 2.1)]
    interval = MaintenanceEvent(
        line="L1", segment="s1", event_id="m", t_start=T0 + 4 * DAY_S, t_end=T0 + 20 * DAY_S
    )
    known = MaintenanceEvent(
        line="L1", segment="s1", event_id="m", t_start=T0 + 12 * DAY_S, t_end=T0 + 12 * DAY_S
    )
    a, _ = run([*base, interval, *after])
    b, _ = run([*base, known, *after])
    assert_same_states(a, b)
    assert [e.t_s for e in a.histories[("L1", "s1")].log if e.identity[0] == "maintenance"] == [
        T0 + 12 * DAY_S  # not the middle of the filter interval (11, 25]: day 18
    ]


def onboard_days(rng, days, z0, mu, t_tamp=None, z_plus=None):
    """Daily on-board indices y = H z + b + e of a segment degrading at ``mu`` from ``z0``,
    tamped (to ``z_plus``) at day ``t_tamp`` if given."""
    out = []
    chol = np.linalg.cholesky(R)
    for day in days:
        z = z0 + mu * day
        if t_tamp is not None and day > t_tamp:
            z = z_plus + mu * (day - t_tamp)
        y = H @ z + B + chol @ rng.standard_normal(2)
        out.append(index(float(day), *np.exp(y).tolist()))
    return out


Z_WORN = np.log([4.5, 3.5])
MU = np.array([7e-4, 4e-4])
Z_PLUS = np.log([2.0, 1.8])


def test_an_unreported_tamping_is_detected_and_the_segment_restarts_there():
    rng = np.random.default_rng(7)
    record = trc(0.0, *np.exp(Z_WORN).tolist())
    passes = onboard_days(rng, np.arange(1, 90), Z_WORN, MU, t_tamp=50.3, z_plus=Z_PLUS)
    tracker = new_tracker()
    found = []
    for msg in [*MODELS, record, *passes]:
        found.extend(tracker.step(msg).detected)
    assert len(found) == 1, found
    (detected,) = found
    assert detected.detected and detected.t_start <= T0 + 50.3 * DAY_S <= detected.t_end
    assert detected.t_end - detected.t_start == DAY_S  # between two daily passes
    delay = max(m.t for m in passes if m.t <= T0 + 53 * DAY_S) - T0 - 50.3 * DAY_S
    assert delay <= 3 * DAY_S
    # the state is the one a reported tamping at the detected interval gives
    reported = replace_msg(detected, event_id="m1", detected=False)
    with_report, _ = run([*MODELS, record, *passes[:50], reported, *passes[50:]])
    a, b = tracker.histories[("L1", "s1")].state, with_report.histories[("L1", "s1")].state
    for name in ("z", "P", "log_w"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # and it does not raise a second time
    assert not any(tracker.step(m).detected for m in onboard_days(rng, [90, 91], Z_PLUS, MU))


def replace_msg(msg, **changes):
    import msgspec

    return msgspec.structs.replace(msg, **changes)


def test_a_year_of_honest_indices_gives_no_detection():
    rng = np.random.default_rng(8)
    tracker = new_tracker()
    for msg in [*MODELS, trc(0.0, *np.exp(Z_PLUS).tolist())]:
        tracker.step(msg)
    reasons, _, detected, _ = tracker.step_events(onboard_days(rng, np.arange(1, 366), Z_PLUS, MU))
    assert not any(reasons) and detected == []


def test_a_reported_tamping_supersedes_a_detected_one_whatever_the_order(tmp_path):
    rng = np.random.default_rng(7)
    record = trc(0.0, *np.exp(Z_WORN).tolist())
    passes = onboard_days(rng, np.arange(1, 70), Z_WORN, MU, t_tamp=50.3, z_plus=Z_PLUS)
    report = tamping(50.0, 51.0)  # a maintenance record arriving late (interval: mid 50.5)
    truth, _ = run([*MODELS, record, report, *passes])  # the report first: nothing detected
    assert not any(e.message.detected for e in truth.histories[("L1", "s1")].log if e.kind == 0)
    db = tmp_path / "f.sqlite"
    node = PersistentTracker(new_tracker(), Store(db))
    detected = []
    for msg in [*MODELS, record, *passes]:
        detected.extend(node.handle(*keyed(msg)).detected)
    assert len(detected) == 1
    step = node.handle(*keyed(report))  # late report: replaces the detection
    assert step.accepted and step.withdrawn == (detected[0],)
    assert_same_states(node.tracker, truth)
    rebuilt = PersistentTracker(new_tracker(), Store(db))
    rebuilt.rebuild()
    assert_same_states(rebuilt.tracker, truth)  # the detected row is gone from the store
    # a detection coming back (its own echo from the bus) is no input
    assert node.handle(*keyed(detected[0])).reason == DERIVED
    # nor is its withdrawal, whether the instance detects or not
    gone = msgspec.structs.replace(detected[0], revision=1, withdrawn=True)
    assert node.handle(*keyed(gone)).reason == WITHDRAWAL
    plain = Tracker(LIMITS.for_line, LIMITS.levels, detect_maintenance=False)
    for msg in [*MODELS, record]:
        plain.step(msg)
    assert plain.step(gone).reason == WITHDRAWAL
    for n in (node, rebuilt):
        n.store.close()


def unit_calibration(train: str, unit: str, version: int = 1, shift=(0.1, -0.05)) -> Calibration:
    return Calibration(
        version=version,
        t=T0,
        indicators=["top6", "align10"],
        indices=["top6", "align10"],
        H=NDArray.of(H * 1.05),
        b=NDArray.of(B + np.asarray(shift)),
        R=NDArray.of(R * 0.8),
        n_pairs=20,
        r2=NDArray.of([0.8, 0.7]),
        train=train,
        unit=unit,
    )


def test_an_index_is_read_with_its_units_model_else_the_fleets():
    own = unit_calibration("T2", "u1")
    fleet_like_own = replace_msg(own, train="", unit="")
    passes = [index(d, 2.0 + 0.01 * d, 1.9, train="T2") for d in (3.0, 9.0, 15.0)]
    with_unit, _ = run([calibration(), own, posterior(), trc(0.0), *passes])
    as_fleet, _ = run([fleet_like_own, posterior(), trc(0.0), *passes])
    a, b = with_unit.histories[("L1", "s1")].state, as_fleet.histories[("L1", "s1")].state
    for name in ("z", "P", "log_w"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # T1 has no model of its own: its index is read with the fleet's
    others = [index(d, 2.0, 1.9, train="T1") for d in (3.0, 9.0)]
    fleet_only, _ = run([calibration(), posterior(), trc(0.0), *others])
    mixed, _ = run([calibration(), own, posterior(), trc(0.0), *others])
    assert_same_states(fleet_only, mixed)


def test_a_units_model_reruns_only_the_segments_it_read_and_matches_one_by_one():
    rng = np.random.default_rng(3)
    base = [calibration(), posterior(), trc(0.0), trc(0.0, segment="s2")]
    msgs = []
    for d in range(1, 40):
        msgs.append(index(float(d), *np.exp(rng.normal(0.7, 0.1, 2)).tolist(), train="T2"))
        msgs.append(index(d + 0.5, *np.exp(rng.normal(0.7, 0.1, 2)).tolist(), segment="s2"))
    tracker, _ = run([*base, *msgs])
    update = tracker.update_models([unit_calibration("T2", "u1")])
    assert [(s.line, s.segment) for s in update.states] == [("L1", "s1")]  # s2: T1 only
    one_by_one, _ = run([*base, unit_calibration("T2", "u1"), *msgs])
    assert_same_states(tracker, one_by_one)
    # a newer version replaces it; an older one is ignored, by the unit's own name
    assert tracker.update_models([unit_calibration("T2", "u1", 2, (0.2, 0.0))]).accepted
    assert tracker.update_models([unit_calibration("T2", "u1", 1)]).ignored


def test_a_units_calibration_key_carries_its_ids():
    own = unit_calibration("T2", "u1")
    assert keys.key_of("tf", own) == "tf/model/calibration/T2/u1"
    keys.check_key("tf/model/calibration/T2/u1", own)
    with pytest.raises(SchemaError, match="key says T3/u1"):
        keys.check_key("tf/model/calibration/T3/u1", own)
    with pytest.raises(SchemaError):
        keys.check_key(keys.calibration("tf"), own)  # a unit's model on the fleet's key
    with pytest.raises(SchemaError, match="both given or both empty"):
        Calibration(**{**msgspec.structs.asdict(own), "unit": ""})


def test_the_state_carries_its_mixture_weights_after_on_board_updates_only():
    """``log_weights`` softmax to the weights the summary used; a TRC restart makes them equal
    again (None)."""
    tracker, states = run([*MODELS, trc(0.0), index(3.0, 2.0, 2.0), index(6.0, 2.6, 1.9)])
    assert states[0].log_weights is None  # the TRC record: equal weights
    carried = states[-1].log_weights.array().astype(float)
    assert carried.max() == 0.0 and carried.shape == (NS,)
    w = np.exp(carried) / np.exp(carried).sum()
    used = state_weights(tracker.histories[("L1", "s1")].state)
    np.testing.assert_allclose(w, used, rtol=1e-5, atol=1e-9)
    (after,) = tracker.step(trc(20.0, 4.0, 3.0)).states
    assert after.log_weights is None
