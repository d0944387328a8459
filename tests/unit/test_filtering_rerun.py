"""The tracker's batched re-run and model updates: the same bits as one segment at a time."""

from __future__ import annotations

from dataclasses import replace

import msgspec
import numpy as np
import pytest
from test_filtering_tracker import (  # tests/unit is on sys.path (rootdir conftest)
    LIMITS,
    assert_same_states,
    calibration,
    index,
    new_tracker,
    posterior,
    run,
    tamping,
    trc,
)

from schemas import NDArray, SchemaError, encode
from services.filtering import banks as banks_module
from services.filtering import tracker as tracker_module
from services.filtering.events import TAMPING as TAMPING_KIND
from services.filtering.histories import SegmentHistory
from services.filtering.segment import replay, replay_many
from services.filtering.tracker import Tracker


def assert_bit_identical(a: SegmentHistory, b: SegmentHistory, tracker: Tracker) -> None:
    assert (a.line, a.segment, a.group) == (b.line, b.segment, b.group)
    assert (a.state is None) == (b.state is None)
    if a.state is not None:
        for name in ("z", "P", "log_w"):
            assert np.array_equal(getattr(a.state, name), getattr(b.state, name)), name
        for name in ("t_s", "last_trc_t", "n_updates", "nis"):
            assert getattr(a.state, name) == getattr(b.state, name), name
    sa, sb = tracker.segment_state(a), tracker.segment_state(b)
    assert (sa is None) == (sb is None)
    if sa is not None:
        assert encode(sa) == encode(sb)


def mixed_events(rng: np.random.Generator) -> list:
    """Segments on two lines and their own group, with every kind of log."""
    events = []
    for k in range(24):
        line, seg = ("L1", "L2", "L3")[k % 3], f"s{k}"
        length = int(rng.integers(1, 30))  # logs of different lengths
        if k % 5 != 4:
            events.append(trc(float(k % 3), 2.5 + 0.1 * k, 2.0, line=line, segment=seg))
        else:  # no TRC: indices before the first start, then a tamping starts the state
            events.append(index(0.5, 2.0, 1.9, line=line, segment=seg))
            events.append(tamping(1.5, 2.5, line=line, segment=seg))
        for week in range(1, length):
            top6, align10 = np.exp(rng.normal([0.8, 0.5], 0.1)).tolist()
            events.append(index(3.0 * week + 0.1 * k, top6, align10, line=line, segment=seg))
        if k % 4 == 1:
            events.append(tamping(40.0, line=line, segment=seg))  # at a known time
        if k % 4 == 2:
            events.append(tamping(30.0, 44.0, line=line, segment=seg))  # in an interval
        if k % 6 == 3:
            events.append(trc(50.0, 2.1, 1.8, line=line, segment=seg))
            events.append(index(50.0, 2.0, 1.9, line=line, segment=seg))  # tie with it
    events.append(index(1.0, 2.0, 2.0, line="L1", segment="only-indices"))
    events.append(index(9.0, 2.1, 2.0, line="L1", segment="only-indices"))
    return events


# L3 has no posterior of its own and there is no net: its segments stay unpublishable;
# line.L2 has fewer samples than line.L1 (a re-run batch per sample count).
MODELS = [
    calibration(),
    posterior("line.L1", seed=1),
    posterior("line.L2", seed=2, ns=24),
    posterior("seg.L1.s3", seed=3),
]


@pytest.mark.parametrize("block_filters", [8192, 100])
@pytest.mark.parametrize("models", [MODELS, MODELS[1:]], ids=["calibrated", "uncalibrated"])
def test_batched_rerun_equals_replaying_each_segment_alone(monkeypatch, block_filters, models):
    monkeypatch.setattr(banks_module, "BLOCK_FILTERS", block_filters)  # several blocks
    rng = np.random.default_rng(21)
    events = mixed_events(rng)
    tracker = new_tracker()
    states = tracker.load(models, events)  # one batched re-run of every segment
    published = {(s.line, s.segment) for s in states}
    assert 0 < len(published) < len(tracker.histories)
    for sid, hist in tracker.histories.items():
        alone = replay(replace_state(hist), tracker.models)
        assert_bit_identical(hist, alone, tracker)
        assert (tracker.segment_state(hist) is not None) == (sid in published)
    # L3 has no posterior; the segment of indices only has nothing to start from
    assert tracker.histories[("L3", "s2")].state is None
    assert tracker.histories[("L1", "only-indices")].state is None
    if len(models) == len(MODELS):
        assert tracker.histories[("L2", "s4")].state.last_trc_t is None  # started by a tamping
        assert tracker.histories[("L1", "s3")].group == "seg.L1.s3"
    else:  # without a calibration, only states without an update since their start
        assert all(t.state is None or t.state.n_updates == 0 for t in tracker.histories.values())


def replace_state(hist: SegmentHistory) -> SegmentHistory:
    return SegmentHistory(hist.line, hist.segment, hist.log, hist.trc_t)


def test_live_steps_continue_bit_identically_from_a_rerun():
    rng = np.random.default_rng(22)
    events = mixed_events(rng)
    in_order = sorted(events, key=lambda m: getattr(m, "t", getattr(m, "t_start", 0.0)))
    stepped, _ = run(MODELS + in_order)  # the live path: one incremental step per event
    loaded = new_tracker()
    loaded.load(MODELS, events)  # the restart path: one batched re-run
    for sid, hist in stepped.histories.items():
        assert_bit_identical(hist, loaded.histories[sid], stepped)
    late = [index(90.0, 2.4, 2.1, line=line, segment=seg) for line, seg in stepped.histories]
    for msg in late:
        a, b = stepped.step(msg), loaded.step(msg)
        assert [encode(s) for s in a.states] == [encode(s) for s in b.states]


def test_replay_many_of_one_track_is_replay():
    rng = np.random.default_rng(23)
    tracker, _ = run(MODELS + mixed_events(rng))
    hists = list(tracker.histories.values())
    many = replay_many(hists, tracker.models)
    for hist, again in zip(hists, many, strict=True):
        assert_bit_identical(again, replay(hist, tracker.models), tracker)


def bad_calibration(version: int, **changes) -> object:
    good = calibration(version)
    fields = {f: getattr(good, f) for f in good.__struct_fields__}
    return type(good)(**{**fields, **changes})


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"R": NDArray.of([[0.01, 0.02], [0.02, 0.01]])}, "Calibration.R: not positive definite"),
        ({"R": NDArray.of([[0.01, 0.0], [0.001, 0.03]])}, "Calibration.R: not symmetric"),
        ({"indices": ["align10", "top6"]}, "Calibration.indices"),
        ({"indicators": ["a", "b"]}, "Calibration.indicators"),
    ],
)
def test_a_refused_calibration_never_replaces_the_good_one(changes, reason):
    rng = np.random.default_rng(24)
    events = mixed_events(rng)
    half = len(events) // 2
    reference, _ = run([*MODELS, *events])
    tracker, _ = run([*MODELS, *events[:half]])
    held = tracker.models
    bad = bad_calibration(2, **changes)
    with pytest.raises(ValueError, match=reason.replace(".", r"\.")):
        tracker.step(bad)
    update = tracker.update_models([bad])
    assert update.accepted == [] and update.refused[0][0] is bad
    assert update.refused[0][1].startswith(reason)
    assert tracker.models is held
    for msg in events[half:]:  # later events still fold to the states without the bad one
        tracker.step(msg)
    for sid, hist in reference.histories.items():
        assert_bit_identical(tracker.histories[sid], hist, tracker)


def test_a_failing_rerun_keeps_the_models_and_histories_it_had(monkeypatch):
    tracker, _ = run([*MODELS, *mixed_events(np.random.default_rng(25))])
    models, hists = tracker.models, dict(tracker.histories)

    def failing(*args, **kwargs):
        raise ValueError("boom")

    monkeypatch.setattr(tracker_module, "replay_many", failing)
    monkeypatch.setattr(tracker_module, "replay_checked", failing)  # the detecting re-run
    update = tracker.update_models([calibration(2, scale=1.1)])
    assert update.accepted == [] and "re-run with this model failed: boom" in update.refused[0][1]
    assert tracker.models is models and tracker.histories == hists


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("mu", np.zeros((3, 2, 1)), "DegradationPosterior.mu: shape (3, 2, 1), expected (Ns, 2)"),
        ("z_plus", np.zeros((39, 2)), "DegradationPosterior.z_plus: shape (39, 2), expected"),
        ("sigma", np.zeros((40, 2, 2)) - np.eye(2), "sigma: not positive semi-definite"),
        ("sigma_z_plus", np.zeros((40, 2, 2)) + [[0, 1], [0, 0]], "sigma_z_plus: not symm"),
    ],
)
def test_a_bad_posterior_is_refused_naming_the_field(field, value, reason):
    tracker, _ = run([*MODELS, trc(0.0, line="L1", segment="s1")])
    before = encode(tracker.state_of("L1", "s1"))
    bad = posterior("line.L1", version=2, seed=9)
    # past the wire checks (a message built in-process skips decoding): the core's own
    msgspec.structs.force_setattr(bad, field, NDArray.of(value))
    update = tracker.update_models([bad])
    assert update.accepted == [] and update.states == ()
    assert reason in update.refused[0][1]
    assert tracker.models.posteriors["line.L1"].version == 1
    assert encode(tracker.state_of("L1", "s1")) == before


def test_update_models_equals_stepping_them_one_by_one():
    rng = np.random.default_rng(26)
    events = mixed_events(rng)
    m1 = calibration(2, scale=1.05)
    m2 = posterior("line.L1", version=2, seed=11)
    m3 = posterior("net", version=1, seed=12)  # L3 becomes publishable
    one_by_one, _ = run([*MODELS, *events])
    for msg in (m1, m2, m3):
        one_by_one.step(msg)
    batched, _ = run([*MODELS, *events])
    stale = posterior("line.L2", version=1, seed=13, ns=24)
    older = calibration(2, scale=0.9)  # superseded by m4 below
    m4 = calibration(3, scale=1.05)
    update = batched.update_models([older, m2, stale, m3, m4])
    assert update.accepted == [m2, m3, m4]
    assert [(m, r.split(" ")[0]) for m, r in update.ignored] == [
        (stale, "version"),
        (older, "superseded"),
    ]
    one_by_one.step(m4)
    assert len(update.states) == len({(s.line, s.segment) for s in update.states})
    for sid, hist in one_by_one.histories.items():
        assert_bit_identical(batched.histories[sid], hist, batched)
    assert {(s.line, s.segment) for s in update.states} == {
        sid for sid, t in batched.histories.items() if batched.segment_state(t) is not None
    }
    assert batched.state_of("L3", "s2") is not None


def test_a_batch_of_summaries_is_each_summary_alone_and_refuses_one_not_finite():
    """The summaries of a batch (the first built checked, the others copied from it with
    their arrays checked at once) are the messages of each segment summarised alone; a
    state whose numbers are not finite, anywhere in a batch, is refused with the reason."""
    tracker = new_tracker()
    tracker.load(MODELS, mixed_events(np.random.default_rng(22)))
    hists = [h for h in tracker.histories.values() if h.state is not None and h.line == "L1"]
    assert len(hists) >= 3
    batch = tracker.segment_states(hists)
    assert [encode(s) for s in batch] == [encode(tracker.segment_state(h)) for h in hists]
    state = hists[2].state
    huge = replace(hists[2], state=replace(state, z=state.z + 800.0))  # exp(800) mm: inf
    with np.errstate(over="ignore"), pytest.raises(SchemaError, match="NaN or inf"):
        tracker.segment_states([*hists[:2], huge])
    no_nis = replace(hists[2], state=replace(state, nis=float("inf")))
    with pytest.raises(SchemaError, match="nis: must be finite"):
        tracker.segment_states([*hists[:2], no_nis])


def test_limits_of_each_line_in_one_batch():
    tracker = new_tracker()
    tracker.load(
        MODELS[:2] + [posterior("line.L2", seed=2)],
        [trc(0.0, line="L1", segment="a"), trc(0.0, line="L2", segment="b")],
    )
    for line, seg in (("L1", "a"), ("L2", "b")):
        state = tracker.state_of(line, seg)
        assert state.limits_mm.array().tolist() == LIMITS.for_line(line).tolist()


def test_an_event_whose_state_cannot_be_summarised_changes_nothing(monkeypatch):
    tracker, _ = run([*MODELS, trc(0.0, line="L1", segment="s1")])
    hists = dict(tracker.histories)

    def failing(*args, **kwargs):
        raise ValueError("boom")

    monkeypatch.setattr(tracker_module, "summarize_states", failing)
    with pytest.raises(ValueError, match="boom"):
        tracker.step(index(3.0, 2.0, 2.0, line="L1", segment="s1"))
    assert tracker.histories == hists


def test_update_models_applies_the_good_and_refuses_the_bad():
    events = mixed_events(np.random.default_rng(27))
    good = posterior("line.L1", version=2, seed=14)
    bad = bad_calibration(2, R=NDArray.of([[0.01, 0.02], [0.02, 0.01]]))
    tracker, _ = run([*MODELS, *events])
    update = tracker.update_models([bad, good])
    assert update.accepted == [good] and [m for m, _ in update.refused] == [bad]
    reference, _ = run([*MODELS, *events, good])
    assert tracker.models.calibration.version == 1
    for sid, hist in reference.histories.items():
        assert_bit_identical(tracker.histories[sid], hist, tracker)


def detected_tampings(tracker: Tracker) -> list:
    return sorted(
        e.message.event_id
        for hist in tracker.histories.values()
        for e in hist.log
        if e.kind == TAMPING_KIND and e.message.detected
    )


def test_a_model_change_finds_and_withdraws_detections_as_a_fresh_fold_would():
    """Whether the on-board data show an unreported tamping depends on the observation
    model: events folded under one calibration, then a new one, must end as the same events
    folded under the new one from the start (states and detected tampings), whichever way
    the change goes."""
    rng = np.random.default_rng(3)
    events = [trc(0.0, 3.0, 2.5)]
    for day in range(1, 60):
        level = (3.0, 2.5) if day < 30 else (1.8, 1.5)  # an unreported tamping on day 30
        top6, align10 = np.exp(np.log(level) + rng.normal(0.0, 0.05, 2)).tolist()
        events.append(index(day + 0.5, top6, align10))
    flips = 0
    for first, second in [(1.0, 0.6), (0.6, 1.0), (1.0, 2.0), (2.0, 0.45)]:
        changed, _ = run([calibration(1, first), posterior(), *events])
        before = detected_tampings(changed)
        update = changed.update_models([calibration(2, second)])
        fresh, _ = run([calibration(2, second), posterior(), *events])
        assert detected_tampings(changed) == detected_tampings(fresh)
        assert_same_states(changed, fresh)
        found = sorted(m.event_id for m in update.detected)
        withdrawn = sorted(m.event_id for m in update.withdrawn)
        assert found == sorted(set(detected_tampings(fresh)) - set(before))
        assert withdrawn == sorted(set(before) - set(detected_tampings(fresh)))
        flips += bool(found or withdrawn)
    assert flips, "no model change here changed a detection: the test checks nothing"
