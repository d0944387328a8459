"""Alerting core: every alert kind raises and clears, hysteresis, stale, the plan, and a
restart from the SQLite store; states built directly with schemas."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from schemas import DAY_S, Alert, MaintenanceEvent, SegmentState, TrcRecord
from services.alerting.core import (
    AlertingConfig,
    AlertingCore,
    Hysteresis,
    TrcSchedule,
    horizon_probability,
)
from services.alerting.service import DEFAULT_ALERTING_FILE, load_alerting_config
from services.alerting.store import AlertStore
from services.alerting.testing import (
    HORIZONS,
    LIMITS_MM,
    T0,
    forecast_top6,
    make_limits,
    make_state,
    p_top6,
)


@pytest.fixture
def core() -> AlertingCore:
    return AlertingCore(AlertingConfig(), make_limits())


def summary(alerts: list[Alert]) -> list[tuple[str, str, str, str]]:
    return [(a.kind, a.status, a.indicator, a.level) for a in alerts]


# --- exceedance ------------------------------------------------------------------------------


def test_exceedance_raises_once_and_clears_with_operator_message(core):
    raised = core.on_state(make_state(T0, p_exceed=p_top6(1, 0.72)))
    assert summary(raised) == [("exceedance", "raised", "top6", "intervention")]
    assert (
        raised[0].message
        == "Top6 likely above intervention limit 8.0 mm (p=0.72), speed class 80<v<=120 (default)"
    )
    assert raised[0].probability == pytest.approx(0.72)
    assert raised[0].speed_class == "80<v<=120"
    assert core.on_state(make_state(T0 + DAY_S, p_exceed=p_top6(1, 0.9))) == []  # no repeat
    assert core.raised_alerts() == raised

    cleared = core.on_state(make_state(T0 + 2 * DAY_S, p_exceed=p_top6(1, 0.1)))
    assert summary(cleared) == [("exceedance", "cleared", "top6", "intervention")]
    assert cleared[0].message == (
        "Top6 back below intervention limit 8.0 mm (p=0.10), speed class 80<v<=120 (default)"
    )
    assert cleared[0].speed_class == "80<v<=120"
    assert core.raised_alerts() == []


def test_exceedance_uses_and_names_the_speed_class_of_its_line():
    """L1 is named in the file, L2 takes its class from the network's line speed; the slower
    class's looser limit is the one compared with and said."""
    slow = LIMITS_MM * 1.5
    limits = replace(
        make_limits(),
        speed_classes={"v<=80": slow, "80<v<=120": LIMITS_MM},
        lines={"L1": "80<v<=120"},
        line_speeds_kmh={"L2": 60.0},
    )
    core = AlertingCore(AlertingConfig(), limits)
    fast = core.on_state(make_state(T0, line="L1", p_exceed=p_top6(1, 0.9)))
    assert [a.speed_class for a in fast] == ["80<v<=120"]
    assert fast[0].message.endswith("limit 8.0 mm (p=0.90), speed class 80<v<=120")
    # the state was computed on other limits: alerting recomputes against L2's class
    mean_mm = (9.0, 3.0)  # above 8.0 (80<v<=120), below 12.0 (v<=80)
    out = core.on_state(make_state(T0, line="L2", mean_mm=mean_mm, p_exceed=p_top6(1, 0.9)))
    assert [a for a in out if a.level == "intervention"] == []
    assert {r.line: r.speed_class for r in core.plan()} == {"L1": "80<v<=120", "L2": "v<=80"}


def test_exceedance_per_indicator_and_level(core):
    p = np.array([[0.8, 0.6], [0.55, 0.1]])  # alert: both; intervention: top6 only
    out = core.on_state(make_state(T0, p_exceed=p))
    assert summary(out) == [
        ("exceedance", "raised", "top6", "alert"),
        ("exceedance", "raised", "align10", "alert"),
        ("exceedance", "raised", "top6", "intervention"),
    ]
    assert "Align10 likely above alert limit 5.0 mm" in out[1].message


@pytest.mark.parametrize(
    ("kind", "raise_at", "clear_at"),
    [("exceedance", 0.5, 0.3), ("predicted_exceedance", 0.3, 0.18)],  # the defaults
)
def test_hysteresis_prevents_flapping(core, kind, raise_at, clear_at):
    def state(i: int, p: float) -> SegmentState:
        if kind == "exceedance":
            return make_state(T0 + i * DAY_S, p_exceed=p_top6(1, p))
        return make_state(T0 + i * DAY_S, forecast=forecast_top6(0.0, p, p))

    below, above = raise_at - 0.05, raise_at + 0.05
    sequence = [below, above] * 10 + [below, clear_at + 0.01, clear_at + 0.05]
    sequence += [clear_at - 0.01, above]
    out = [a for i, p in enumerate(sequence) for a in core.on_state(state(i, p))]
    assert [(a.kind, a.status) for a in out] == [
        (kind, "raised"),  # at the first value above raise
        (kind, "cleared"),  # only at or below clear
        (kind, "raised"),  # the last value above raise
    ]
    assert out[0].t == T0 + 1 * DAY_S and out[1].t == T0 + 23 * DAY_S


def test_hysteresis_needs_clear_below_raise():
    with pytest.raises(ValueError, match="clear < raise"):
        Hysteresis(raise_at=0.5, clear_at=0.5)


def test_approximates_probabilities_when_state_limits_differ(core):
    # the state was computed against other limits: recompute ours from the log-normal summary
    state = make_state(T0, mean_mm=(8.5, 3.0), sd_log=(0.1, 0.1), limits_mm=LIMITS_MM * 2)
    out = core.on_state(state)
    expected = stats.norm.sf((np.log(8.0) - np.log(8.5)) / 0.1)
    top6_int = [a for a in out if a.level == "intervention" and a.indicator == "top6"]
    assert top6_int and top6_int[0].probability == pytest.approx(expected)
    assert core.approximated > 0


# --- predicted exceedance --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("forecast", "horizon", "p"),
    [((0.2, 0.6, 0.9), 90.0, 0.6), ((0.4, 0.8, 0.9), 30.0, 0.4), ((0.1, 0.25, 0.95), None, None)],
)
def test_predicted_exceedance_reports_first_horizon_within(core, forecast, horizon, p):
    out = core.on_state(make_state(T0, forecast=forecast_top6(*forecast)))
    if horizon is None:  # above raise (0.3) only at 180 days, beyond within_days = 90
        assert out == []
        return
    assert summary(out) == [("predicted_exceedance", "raised", "top6", "intervention")]
    assert out[0].horizon_days == horizon and out[0].probability == pytest.approx(p)
    assert out[0].message == (
        f"Top6 likely above intervention limit 8.0 mm within {horizon:g} days (p={p:.2f}), "
        "speed class 80<v<=120 (default)"
    )
    assert core.on_state(make_state(T0 + DAY_S, forecast=forecast_top6(0.1, 0.2, 0.9))) == []
    cleared = core.on_state(make_state(T0 + 2 * DAY_S, forecast=forecast_top6(0.1, 0.15, 0.9)))
    assert summary(cleared) == [("predicted_exceedance", "cleared", "top6", "intervention")]


# --- sudden change ---------------------------------------------------------------------------


def test_nis_threshold_is_chi_square_quantile():
    assert AlertingConfig().nis_threshold == pytest.approx(13.8155, abs=1e-4)
    assert AlertingConfig(nis_tail_probability=0.99).nis_threshold == pytest.approx(9.2103, 1e-4)


def test_sudden_change_raises_and_clears_after_k_normal_updates(core):
    t = iter(T0 + i * DAY_S for i in range(100))
    raised = core.on_state(make_state(next(t), nis=25.0))
    assert summary(raised) == [("sudden_change", "raised", "", "")]
    assert "NIS 25.0 > 13.8" in raised[0].message
    assert raised[0].probability == pytest.approx(stats.chi2.cdf(25.0, 2))
    assert core.on_state(make_state(next(t), nis=30.0)) == []  # still abnormal, no repeat
    assert core.on_state(make_state(next(t), nis=1.0)) == []
    assert core.on_state(make_state(next(t), nis=None)) == []  # a TRC restart: not an update
    assert core.on_state(make_state(next(t), nis=2.0)) == []
    same_t = core.segments[("L1", "s1")].state.t
    assert core.on_state(make_state(same_t, nis=2.0)) == []  # re-run, not a new update
    cleared = core.on_state(make_state(next(t), nis=0.5))  # third normal update
    assert summary(cleared) == [("sudden_change", "cleared", "", "")]


def test_abnormal_update_resets_the_calm_count(core):
    nis = [20.0, 1.0, 1.0, 20.0, 1.0, 1.0, 1.0]
    out = [a for i, x in enumerate(nis) for a in core.on_state(make_state(T0 + i, nis=x))]
    assert [a.status for a in out] == ["raised", "cleared"]
    assert out[1].t == T0 + 6


# --- stale -----------------------------------------------------------------------------------


def test_stale_raised_against_event_time_and_cleared_by_data(core):
    core.on_state(make_state(T0, segment="s1"))
    core.on_state(make_state(T0 + 10 * DAY_S, segment="s2"))
    assert core.check_stale(T0 + 21 * DAY_S) == []  # not beyond 21 days yet
    out = core.check_stale(T0 + 22 * DAY_S)
    assert summary(out) == [("stale", "raised", "", "")] and out[0].segment == "s1"
    assert out[0].message == "No data for 22 days (stale after 21)"
    assert core.check_stale(T0 + 25 * DAY_S) == []  # no repeat
    assert [a.segment for a in core.check_stale(T0 + 32 * DAY_S)] == ["s2"]

    cleared = core.on_state(make_state(T0 + 40 * DAY_S, segment="s1"))
    assert summary(cleared) == [("stale", "cleared", "", "")]
    assert cleared[0].message == "Data again after 40 days"
    assert [a.segment for a in core.raised_alerts()] == ["s2"]


def _network_of(core, n: int, t: float) -> None:
    for i in range(n):
        core.on_state(make_state(t, segment=f"s{i}"))


def test_one_trc_record_dated_far_ahead_does_not_make_every_segment_stale(core):
    """The adapter checks stale against ``newest_t``: a watermark one record cannot move.
    (Year 3000 itself is refused by the schemas now; 2099 is inside their range.)"""
    _network_of(core, 20, T0)
    year_2099 = 4_070_908_800.0
    record = TrcRecord(line="L1", segment="s3", t=year_2099, top6_mm=3, align10_mm=2, run_id="x")
    core.on_trc(record)
    assert core.newest_t == T0
    assert core.check_stale(core.newest_t) == []


def test_one_or_two_far_future_states_do_not_move_the_watermark(core):
    _network_of(core, 20, T0)
    core.on_state(make_state(T0 + 400 * DAY_S, segment="s1"))
    core.on_state(make_state(T0 + 500 * DAY_S, segment="s2"))
    assert core.newest_t == T0
    assert core.check_stale(core.newest_t) == []


def test_the_watermark_moves_when_a_quorum_of_segments_agrees(core):
    """Three segments (the quorum) moving on are the network's time: the others go stale."""
    _network_of(core, 20, T0)
    for i in range(3):
        core.on_state(make_state(T0 + 30 * DAY_S + i, segment=f"s{i}"))
    assert core.newest_t == T0 + 30 * DAY_S
    stale = core.check_stale(core.newest_t)
    assert sorted(a.segment for a in stale) == sorted(f"s{i}" for i in range(3, 20))


def test_late_state_is_ignored(core):
    core.on_state(make_state(T0 + DAY_S, p_exceed=p_top6(1, 0.1)))
    assert core.on_state(make_state(T0, p_exceed=p_top6(1, 0.9))) == []
    assert core.segments[("L1", "s1")].state.t == T0 + DAY_S


def test_random_sequence_only_transitions(core):
    rng = np.random.default_rng(1)
    out: list[Alert] = []
    for i in range(300):
        seg = f"s{rng.integers(3)}"
        t = T0 + i * DAY_S
        state = make_state(
            t,
            segment=seg,
            p_exceed=rng.uniform(size=(2, 2)),
            forecast=rng.uniform(size=(3, 2, 2)),
            nis=float(rng.choice([1.0, 20.0])),
        )
        out += core.on_state(state) + core.check_stale(t)
    last: dict = {}
    for a in out:
        key = (a.line, a.segment, a.kind, a.indicator, a.level)
        assert last.get(key, "cleared") != a.status, f"repeated {a.status} for {key}"
        last[key] = a.status
    assert {k for k, s in last.items() if s == "raised"} == set(core.raised)


# --- plan ------------------------------------------------------------------------------------


def test_horizon_probability_interpolates_linearly_from_now():
    p_now, horizons = np.array([0.1, 0.0]), np.array(HORIZONS)
    fc = np.array([[0.2, 0.0], [0.6, 0.3], [0.9, 0.4]])
    assert np.allclose(horizon_probability(0, p_now, horizons, fc), [0.1, 0.0])
    assert np.allclose(horizon_probability(15, p_now, horizons, fc), [0.15, 0.0])
    assert np.allclose(horizon_probability(60, p_now, horizons, fc), [0.4, 0.15])
    assert np.allclose(horizon_probability(400, p_now, horizons, fc), [0.9, 0.4])  # held
    assert np.allclose(horizon_probability(-5, p_now, horizons, fc), [0.1, 0.0])
    # not monotone (a tamping within the horizon): the maximum before h counts
    fc_down = np.array([[0.5, 0.0], [0.1, 0.0], [0.1, 0.0]])
    assert np.allclose(horizon_probability(90, p_now, horizons, fc_down), [0.5, 0.0])


def test_plan_ranks_segments_by_probability_before_next_run(core):
    def fc(top6, align10):
        out = np.zeros((3, 2, 2))
        out[:, 1, 0], out[:, 1, 1] = top6, align10
        return out

    core.on_state(make_state(T0, segment="a", forecast=fc((0.1, 0.2, 0.3), (0.0, 0.0, 0.0))))
    core.on_state(make_state(T0, segment="b", forecast=fc((0.0, 0.1, 0.2), (0.2, 0.8, 0.9))))
    core.on_state(make_state(T0, segment="c", forecast=fc((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))))
    core.on_state(make_state(T0, line="L2", segment="d", forecast=fc((0.5, 1, 1), (0, 0, 0))))

    rows = core.plan({"L1": T0 + 60 * DAY_S, "L2": T0 + 15 * DAY_S})
    assert [(r.line, r.segment) for r in rows] == [
        ("L1", "b"),
        ("L2", "d"),
        ("L1", "a"),
        ("L1", "c"),
    ]
    b = rows[0]
    assert b.indicator == "align10" and b.level == "intervention" and b.limit_mm == 7.0
    assert b.probability == pytest.approx(0.5) and b.horizon_days == pytest.approx(60)
    assert rows[1].probability == pytest.approx(0.25)  # halfway to 30 days
    assert b.estimate_mm == pytest.approx(3.0) and b.ci_low_mm < 3.0 < b.ci_high_mm
    assert [r.segment for r in core.plan({"L1": T0 + 60 * DAY_S}, line="L2")] == ["d"]


def test_trc_schedule_learns_median_interval_with_default():
    schedule = TrcSchedule(default_interval_days=70)
    assert schedule.next_run_t("L1") is None
    assert schedule.next_run_t("L1", fallback_last_t=T0) == T0 + 70 * DAY_S
    schedule.observe("L1", "r1", T0 + 3600)
    assert schedule.observe("L1", "r1", T0) is True  # earlier record of the same run
    assert schedule.observe("L1", "r1", T0 + 7200) is False
    assert schedule.next_run_t("L1") == T0 + 70 * DAY_S  # one run: the default interval
    schedule.observe("L1", "r2", T0 + 63 * DAY_S)
    schedule.observe("L1", "r3", T0 + 133 * DAY_S)
    assert schedule.interval_days("L1") == pytest.approx(66.5)
    assert schedule.next_run_t("L1") == pytest.approx(T0 + (133 + 66.5) * DAY_S)


def test_plan_uses_learnt_schedule_then_last_trc_of_states(core):
    core.on_state(make_state(T0 + 5 * DAY_S, last_trc_t=T0))
    assert core.next_trc_t("L1") == T0 + 70 * DAY_S  # no run seen: state's last TRC + 70 d
    for run, day in (("r1", 0), ("r2", 60)):
        core.on_trc(TrcRecord(line="L1", segment="s1", t=T0 + day * DAY_S, top6_mm=3,
                              align10_mm=2, run_id=run))  # fmt: skip
    assert core.next_trc_t("L1") == T0 + 120 * DAY_S
    (row,) = core.plan()
    assert row.next_trc_t == T0 + 120 * DAY_S and row.horizon_days == pytest.approx(115)
    # overdue: the run is expected now (the newest event time)
    core.on_state(make_state(T0 + 130 * DAY_S, segment="s2"))
    assert core.next_trc_t("L1") == T0 + 130 * DAY_S


# --- config ----------------------------------------------------------------------------------


def test_deploy_config_loads_with_documented_defaults():
    config = load_alerting_config(DEFAULT_ALERTING_FILE)
    assert config == AlertingConfig()


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ({"stale": {"days": 3}}, "unknown key"),
        ({"exceedence": {}}, "unknown section"),
        ({"exceedance": {"alert": {"raise": 0.3, "clear": 0.5}}}, "clear < raise"),
        ({"exceedance": {"alert": {"raise": 0.6}}}, "KeyError"),
        ({"stale": {"stale_days": 0}}, "positive"),
    ],
)
def test_bad_config_says_what_is_wrong(raw, match):
    with pytest.raises(ValueError, match=match):
        AlertingConfig.from_dict(raw)


def test_config_level_must_exist_in_limits():
    config = AlertingConfig(exceedance={"warning": Hysteresis(0.5, 0.3)})
    with pytest.raises(ValueError, match="'warning' not in limits"):
        AlertingCore(config, make_limits())


# --- persistence -----------------------------------------------------------------------------


def run_and_persist(core: AlertingCore, store: AlertStore, state: SegmentState) -> list[Alert]:
    alerts = core.on_state(state)
    store.save(alerts, core.segments[(state.line, state.segment)])
    return alerts


def test_restart_neither_reraises_nor_forgets(tmp_path):
    path = tmp_path / "var" / "alerting-test.sqlite"
    store = AlertStore(path)
    first = AlertingCore(AlertingConfig(), make_limits())
    raised = run_and_persist(first, store, make_state(T0, p_exceed=p_top6(1, 0.8), nis=20.0))
    run_and_persist(first, store, make_state(T0 + 1, segment="s2", nis=1.0))
    calm = make_state(T0 + 2, p_exceed=p_top6(1, 0.8), nis=1.0)
    assert run_and_persist(first, store, calm) == []  # one calm update
    first.on_trc(TrcRecord(line="L1", segment="s1", t=T0, top6_mm=3, align10_mm=2, run_id="r1"))
    store.save(run=("L1", "r1", T0))
    store.close()

    store = AlertStore(path)
    second = AlertingCore(AlertingConfig(), make_limits())
    second.restore(*store.load())
    assert second.raised_alerts() == first.raised_alerts() and len(raised) == 2
    assert second.segments == first.segments
    assert second.schedule.runs == first.schedule.runs and second.newest_t == T0 + 2
    # the same condition again: nothing new; the calm count went on where it stopped
    again = make_state(T0 + 3, p_exceed=p_top6(1, 0.8), nis=1.0)
    assert run_and_persist(second, store, again) == []
    cleared = run_and_persist(second, store, make_state(T0 + 4, nis=1.0))
    assert summary(cleared) == [
        ("exceedance", "cleared", "top6", "intervention"),
        ("sudden_change", "cleared", "", ""),
    ]
    assert store.load()[0] == []
    # stale detection still knows s2 after the restart
    assert [a.segment for a in second.check_stale(T0 + 30 * DAY_S)] == ["s1", "s2"]
    store.close()


def test_a_detected_tamping_waits_for_an_operator_and_a_report_confirms_it(core):
    t0 = 1_767_225_600.0
    detected = MaintenanceEvent(
        line="L1",
        segment="s7",
        event_id="detected-1",
        t_start=t0,
        t_end=t0 + DAY_S,
        detected=True,
    )
    (raised,) = core.on_maintenance(detected)
    assert (raised.kind, raised.status, raised.segment) == ("detected_maintenance", "raised", "s7")
    assert "2026-01-01 00:00" in raised.message and "confirm" in raised.message
    assert core.on_maintenance(detected) == []  # its echo raises nothing new
    far = MaintenanceEvent(
        line="L1", segment="s7", event_id="m0", t_start=t0 - 60 * DAY_S,
        t_end=t0 - 60 * DAY_S,
    )  # fmt: skip
    assert core.on_maintenance(far) == []  # another tamping, long before: not a confirmation
    report = MaintenanceEvent(
        line="L1", segment="s7", event_id="m1", t_start=t0 + 3600.0, t_end=t0 + 3600.0
    )
    (cleared,) = core.on_maintenance(report)
    assert cleared.status == "cleared" and cleared.message == "Reported: m1"
    assert core.raised_alerts() == []


def tamping(revision, *, withdrawn=False, event_id="detected-1", segment="s7", day=0.0):
    """Filtering's detection (or withdrawal) of a tamping in the day after ``day``."""
    t = T0 + day * DAY_S
    return MaintenanceEvent(
        line="L1", segment=segment, event_id=event_id, t_start=t, t_end=t + DAY_S,
        detected=True, revision=revision, withdrawn=withdrawn,
    )  # fmt: skip


def raised_after(*events):
    core = AlertingCore(AlertingConfig(), make_limits())
    for event in events:
        core.on_maintenance(event)
    return [(a.segment, a.kind) for a in core.raised_alerts()]


def test_a_withdrawn_detection_clears_its_alert_and_raises_nothing_arriving_first():
    found, gone, again = tamping(1), tamping(2, withdrawn=True), tamping(3)
    core = AlertingCore(AlertingConfig(), make_limits())
    core.on_maintenance(found)
    (cleared,) = core.on_maintenance(gone)
    assert (cleared.kind, cleared.status) == ("detected_maintenance", "cleared")
    assert "no longer show detected-1" in cleared.message
    assert raised_after(found, gone) == raised_after(gone, found) == []
    assert raised_after(gone, found, gone, found) == []  # duplicates change nothing
    # found again after its withdrawal: raised again, in any order
    assert (
        raised_after(found, gone, again) == raised_after(again, gone, found) == raised_after(found)
    )
    assert raised_after(found) == [("s7", "detected_maintenance")]
    # another detection of the segment still held keeps the alert
    other = tamping(4, event_id="detected-2", day=40.0)
    assert (
        raised_after(found, other, gone) == raised_after(gone, other, found) == raised_after(other)
    )


def test_shuffled_detections_and_withdrawals_end_in_the_same_raised_alerts():
    rng = np.random.default_rng(3)
    for _ in range(30):
        messages = [
            tamping(
                int(rng.integers(1, 5)), withdrawn=bool(rng.random() < 0.5),
                event_id=f"detected-{rng.integers(3)}", segment=f"s{rng.integers(2)}",
                day=float(rng.integers(0, 100)),
            )
            for _ in range(6)
        ]  # fmt: skip
        # what holds: per event_id the highest rank; raised where a detection is held
        held = {}
        for m in messages:
            key = (m.segment, m.event_id)
            if key not in held or m.rank > held[key].rank:
                held[key] = m
        expected = sorted(
            {(s, "detected_maintenance") for (s, _), m in held.items() if not m.withdrawn}
        )
        for _ in range(6):
            order = [messages[j] for j in rng.permutation(len(messages))]
            assert raised_after(*order) == expected


def test_the_detections_held_survive_a_restart(tmp_path):
    path = tmp_path / "alerting.sqlite"
    store = AlertStore(path)
    first = AlertingCore(AlertingConfig(), make_limits())
    gone = tamping(2, withdrawn=True)
    store.save(first.on_maintenance(gone), detection=gone)
    store.close()
    store = AlertStore(path)
    second = AlertingCore(AlertingConfig(), make_limits())
    second.restore(*store.load())
    assert second.on_maintenance(tamping(1)) == []  # withdrawn before the restart
    assert second.on_maintenance(tamping(3)) != []  # found again since
    store.close()


def test_what_a_state_implies_agrees_with_the_raised_set_after_any_path():
    """Random paths of states of one segment: after each, every alert the newest state
    implies (True or False) is what the core holds; the band in between is left open."""
    from services.alerting.core import alert_key

    rng = np.random.default_rng(11)
    for _ in range(30):
        core = AlertingCore(AlertingConfig(), make_limits())
        for i in range(12):
            p, f = rng.uniform(0, 1, 2)
            state = make_state(
                T0 + i * DAY_S, p_exceed=p_top6(1, p), forecast=forecast_top6(0, f, f)
            )
            core.on_state(state)
            raised = {alert_key(a) for a in core.raised_alerts()}
            implied = core.implied(state)
            assert implied  # the exceedance and predicted keys of the segment
            for key, must in implied.items():
                if must is not None:
                    assert (key in raised) == must, (key, p, f)
    middle = make_state(T0, p_exceed=p_top6(1, 0.4))
    key = (middle.line, middle.segment, "exceedance", "top6", "intervention")
    assert core.implied(middle)[key] is None  # between clear 0.3 and raise 0.5
