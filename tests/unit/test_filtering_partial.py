"""TRC records and on-board indices of some indicators only, against a per-sample
derivation straight from the equations (docs/science.md, Eq. 7-12, the exact observation of
a record's measured rows, the update with an index's observed rows of H, b, R)."""

from __future__ import annotations

import numpy as np

from schemas import DAY_S, OnboardIndex, TrcRecord, encode
from services.filtering.coordinator import PersistentTracker
from services.filtering.models import Models, with_model
from services.filtering.state import pack_state, unpack_state
from services.filtering.store import Store
from services.filtering.testing import T0, example_models
from services.filtering.tracker import Tracker
from services.limits import load_limits

NS = 30
LIMITS = load_limits()
MODELS = example_models(NS, seed=4)


def trc(day: float, top6: float | None, align10: float | None, run: str) -> TrcRecord:
    names = [n for n, v in (("top6", top6), ("align10", align10)) if v is not None]
    return TrcRecord(line="L1", segment="s1", t=T0 + day * DAY_S, top6_mm=top6,
                     align10_mm=align10, run_id=run, indicators=names)  # fmt: skip


def index(day: float, top6: float | None, align10: float | None) -> OnboardIndex:
    names = [n for n, v in (("top6", top6), ("align10", align10)) if v is not None]
    return OnboardIndex(line="L1", segment="s1", train="T1", unit="u1", t=T0 + day * DAY_S,
                        top6_mm=top6, align10_mm=align10, speed_mps=30.0, coverage=1.0,
                        indicators=names)  # fmt: skip


# a full record, indices, Top6 alone at day 20, an index, Align10 alone at day 40, an index
EVENTS = [
    trc(0.0, 2.0, 1.8, "r0"),
    index(5.0, 1.9, 1.5),
    index(12.0, 2.2, 1.6),
    trc(20.0, 2.6, None, "r1"),
    index(27.0, 2.3, 1.4),
    trc(40.0, None, 2.4, "r2"),
    index(45.0, 2.5, 1.9),
]


def reference(events):
    """Per sample j, in plain numpy: restart, predict, Joseph update, exact partial
    observation (conditional Gaussian); the log weights since the last full record."""
    models = Models()
    for msg in MODELS:
        models = with_model(models, msg)
    params, obs = models.params["net"], models.observation
    z, P, log_w, t = None, None, np.zeros(NS), None
    for msg in events:
        if isinstance(msg, TrcRecord) and len(msg.indicators) == 2:
            z = np.tile(np.log([msg.top6_mm, msg.align10_mm]), (NS, 1))
            P, log_w, t = np.zeros((NS, 2, 2)), np.zeros(NS), msg.t
            continue
        dt = (msg.t - t) / DAY_S
        t = msg.t
        for j in range(NS):
            zj = z[j] + params.mu[j] * dt
            Pj = P[j] + params.sigma[j] * dt
            if isinstance(msg, TrcRecord):
                o = [k for k, v in enumerate(msg.values_mm) if v is not None]
                zo = np.log([msg.values_mm[k] for k in o])
                gain = Pj[:, o] @ np.linalg.inv(Pj[np.ix_(o, o)])
                zj = zj + gain @ (zo - zj[o])
                Pj = Pj - gain @ Pj[o, :]
            else:  # the observed rows of H, b, R
                o = [k for k, v in enumerate(msg.values_mm) if v is not None]
                y = np.log([msg.values_mm[k] for k in o])
                H, b, R = obs.H[o], obs.b[o], obs.R[np.ix_(o, o)]
                S = H @ Pj @ H.T + R
                K = Pj @ H.T @ np.linalg.inv(S)
                nu = y - H @ zj - b
                zj = zj + K @ nu
                A = np.eye(2) - K @ H
                Pj = A @ Pj @ A.T + K @ R @ K.T
                log_w[j] += -0.5 * (nu @ np.linalg.solve(S, nu) + np.log(np.linalg.det(S)))
                log_w[j] -= 0.5 * len(o) * np.log(2 * np.pi)
            z[j], P[j] = zj, Pj
    return z, P, log_w


def tracker() -> Tracker:
    out = Tracker(LIMITS.for_line, LIMITS.levels)
    for msg in MODELS:
        out.step(msg)
    return out


def follows_reference(events):
    """A tracker stepped through ``events``, its state checked against :func:`reference`
    after each."""
    live = tracker()
    for k, msg in enumerate(events):
        assert live.step(msg).accepted
        state = live.histories[("L1", "s1")].state
        z, P, log_w = reference(events[: k + 1])
        np.testing.assert_allclose(state.z, z, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(state.P, P, rtol=1e-7, atol=1e-15)
        np.testing.assert_allclose(state.log_w, log_w, rtol=1e-9)
    return live


def test_a_partial_record_observes_its_indicators_exactly_and_the_others_follow():
    live = follows_reference(EVENTS)
    summary = live.state_of("L1", "s1")
    assert summary.last_trc_indicators == ["align10"] and summary.last_trc_t == EVENTS[5].t
    after_top6 = tracker()
    for msg in EVENTS[:4]:
        after_top6.step(msg)
    partial = after_top6.histories[("L1", "s1")].state
    assert np.all(partial.z[:, 0] == np.log(2.6)) and np.all(partial.P[:, 0, :] == 0.0)
    assert np.all(partial.P[:, 1, 1] > 0.0)  # Align10 keeps its own uncertainty
    assert after_top6.state_of("L1", "s1").last_trc_indicators == ["top6"]


def test_a_partial_record_keeps_the_log_and_a_full_one_cuts_it():
    live = tracker()
    for msg in EVENTS:
        live.step(msg)
    assert len(live.histories[("L1", "s1")].log) == len(EVENTS)  # Align10 needs day 0 on
    assert live.step(index(3.0, 2.0, 1.6)).accepted  # before a partial record: still folded
    live.step(trc(50.0, 2.5, 2.0, "r3"))
    assert len(live.histories[("L1", "s1")].log) == 1
    assert live.state_of("L1", "s1").last_trc_indicators == ["top6", "align10"]


def test_shuffled_partial_records_give_the_in_order_bits():
    reference_tracker = tracker()
    for msg in EVENTS:
        reference_tracker.step(msg)
    want = encode(reference_tracker.state_of("L1", "s1"))
    for seed in range(3):
        shuffled = list(EVENTS)
        np.random.default_rng(seed).shuffle(shuffled)
        live = tracker()
        for msg in shuffled:
            live.step(msg)
        assert encode(live.state_of("L1", "s1")) == want
    state = reference_tracker.histories[("L1", "s1")].state
    restored = unpack_state(pack_state(state))  # a checkpoint keeps what the record measured
    assert restored.trc_absent == state.trc_absent == 1  # bit 0: Top6 not measured
    assert pack_state(restored) == pack_state(state)


def test_a_partial_record_without_a_state_does_not_start_the_segment():
    live = tracker()
    assert live.step(trc(0.0, 2.0, None, "r0")).accepted
    assert live.histories[("L1", "s1")].state is None
    live.step(trc(10.0, 2.1, 1.7, "r1"))
    assert live.histories[("L1", "s1")].state is not None


def keyed(msg) -> tuple[str, bytes]:
    if isinstance(msg, TrcRecord | OnboardIndex):
        kind = "trc" if isinstance(msg, TrcRecord) else "index"
        return f"tf/{kind}/{msg.line}/{msg.segment}", encode(msg)
    name = "calibration" if msg.__class__.__name__ == "Calibration" else f"degradation/{msg.group}"
    return f"tf/model/{name}", encode(msg)


def test_the_store_keeps_the_log_a_partial_record_needs(tmp_path):
    """A batch (the fold of many events at once), then a rebuild from the store: the same
    bits as one by one; a partial record prunes nothing, a full one prunes the rest."""
    live = tracker()
    for msg in EVENTS:
        live.step(msg)
    node = PersistentTracker(tracker(), Store(tmp_path / "f.sqlite"))
    node.handle_batch([keyed(m) for m in MODELS + EVENTS])
    assert node.store.count_events() == len(EVENTS)
    rebuilt = PersistentTracker(tracker(), Store(tmp_path / "f.sqlite"))
    rebuilt.rebuild()
    for other in (node, rebuilt):
        assert encode(other.tracker.state_of("L1", "s1")) == encode(live.state_of("L1", "s1"))
    node.handle_batch([keyed(trc(50.0, 2.5, 2.0, "r3"))])
    assert node.store.count_events() == 1
    for other in (node, rebuilt):
        other.store.close()


# a vertical-only unit's indices among full ones, and a partial record between them
MIXED = [
    trc(0.0, 2.0, 1.8, "r0"),
    index(3.0, 2.1, None),
    index(5.0, 1.9, 1.5),
    index(9.0, 2.3, None),
    trc(12.0, None, 1.9, "r1"),
    index(15.0, 2.4, None),
    index(18.0, None, 1.7),
]


def test_an_index_of_some_indicators_updates_with_its_rows_of_the_model():
    live = follows_reference(MIXED)
    state = live.histories[("L1", "s1")].state
    assert state.n_updates == 2  # since the Align10 record


def test_partial_indices_batched_shuffled_and_stored_give_the_in_order_bits(tmp_path):
    one_by_one = tracker()
    for msg in MIXED:
        one_by_one.step(msg)
    want = encode(one_by_one.state_of("L1", "s1"))
    shuffled = list(MIXED)
    np.random.default_rng(1).shuffle(shuffled)
    live = tracker()
    for msg in shuffled:
        live.step(msg)
    assert encode(live.state_of("L1", "s1")) == want
    node = PersistentTracker(tracker(), Store(tmp_path / "f.sqlite"))
    node.handle_batch([keyed(m) for m in MODELS + MIXED])
    rebuilt = PersistentTracker(tracker(), Store(tmp_path / "f.sqlite"))
    rebuilt.rebuild()
    for other in (node, rebuilt):
        assert encode(other.tracker.state_of("L1", "s1")) == want
        other.store.close()


def test_a_tamping_missed_before_a_level_only_record_is_still_detected():
    """The CUSUM goes on through a partial record, which is a step of it: after an
    unreported tamping a Top6-only record reads far below its prediction, the Align10
    indices after it read low too, and the tamping is found between the last index before
    the record and the record."""
    H, b = np.array([[0.9, 0.05], [0.05, 0.75]]), np.array([-0.25, -0.35])

    def reading(day: float, z) -> OnboardIndex:
        top6, align10 = np.exp(H @ np.log(z) + b)
        return index(day, float(top6), float(align10))

    before, after = (6.0, 5.0), (2.0, 1.8)  # the tamping at day 30 resets to about z+
    events = [trc(0.0, *before, "r0")]
    events += [reading(day, before) for day in range(2, 30, 2)]
    events += [trc(31.0, 2.0, None, "r1")]
    events += [reading(day, after) for day in range(33, 61, 2)]
    live = tracker()
    found = []
    for msg in events:
        step = live.step(msg)
        found += step.detected
    assert len(found) == 1 and found[0].detected
    assert (found[0].t_start - T0, found[0].t_end - T0) == (28 * DAY_S, 31 * DAY_S)
    align10_mm = float(np.exp(live.state_of("L1", "s1").mean.array()[1]))
    assert abs(align10_mm - 1.8) < 0.3  # Align10 follows the tamping, not its old level
