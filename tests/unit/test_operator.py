"""Pure parts of the operator commands: TRC CSV parsing, formatting, exports."""

from __future__ import annotations

import io
import json

import msgspec
import numpy as np
import pytest

from schemas import Alert, NDArray, SegmentState, TrcRecord
from services.limits import load_limits
from services.tools.operator import (
    ALERT_COLUMNS,
    STATE_COLUMNS,
    RowError,
    alert_row,
    format_state,
    parse_time,
    parse_trc_csv,
    state_row,
    to_csv,
    to_geojson,
)

GOOD = "line,segment,t,top6_mm,align10_mm,run_id\n"


def f8(values) -> NDArray:
    return NDArray.of(values, "f8")


def a_state() -> SegmentState:
    return SegmentState(
        line="L1",
        segment="s00001",
        t=1_767_225_600.0,
        indicators=["top6", "align10"],
        mean=f8(np.log([3.0, 2.0])),
        cov=f8(np.eye(2) * 0.01),
        ci_low_mm=f8([2.5, 1.6]),
        ci_high_mm=f8([3.6, 2.5]),
        width=0.01,
        limit_levels=["alert", "intervention"],
        limits_mm=f8([[6.0, 5.0], [8.0, 7.0]]),
        p_exceed=f8([[0.01, 0.0], [0.002, 0.0]]),
        horizons_days=f8([30, 90, 180]),
        forecast_mean=f8(np.log([[3.1, 2.0], [3.3, 2.1], [3.6, 2.2]])),
        forecast_ci_low_mm=f8(np.full((3, 2), 1.5)),
        forecast_ci_high_mm=f8(np.full((3, 2), 4.5)),
        forecast_p_exceed=f8(np.zeros((3, 2, 2))),
        last_trc_t=1_767_000_000.0,
        n_updates=3,
    )


def test_parse_time_accepts_epoch_and_iso():
    assert parse_time("1767225600") == 1_767_225_600.0
    assert parse_time("2026-01-01T00:00:00Z") == 1_767_225_600.0
    assert parse_time("2026-01-01T00:00:00") == 1_767_225_600.0  # no zone: UTC
    with pytest.raises(ValueError, match="'yesterday' is neither epoch seconds nor an ISO 8601"):
        parse_time("yesterday")


def test_bad_rows_are_reported_with_line_numbers_and_good_rows_kept():
    text = GOOD + (
        "L1,s00001,2026-01-01T00:00:00Z,4.1,3.0,run7\n"  # line 2: good
        "L1,s00002,yesterday,4.1,3.0,run7\n"  # line 3: bad time
        "L1,s00003,1767225600,-1,3.0,run7\n"  # line 4: negative mm
        "L1,s0*4,1767225600,4.0,3.0,run7\n"  # line 5: unsafe id
        "L1,s00005,1767225600,nan,3.0,run7\n"  # line 6: NaN
        "L2,s00006,1767225600,5.0,2.5,run8\n"  # line 7: good
    )
    items = list(parse_trc_csv(io.StringIO(text)))
    records = [i for i in items if isinstance(i, TrcRecord)]
    errors = [i for i in items if isinstance(i, RowError)]
    assert [(r.line, r.segment) for r in records] == [("L1", "s00001"), ("L2", "s00006")]
    assert [e.line_no for e in errors] == [3, 4, 5, 6]
    assert "top6_mm" in errors[1].reason and "forbidden" in errors[2].reason


def test_missing_columns_are_named():
    (error,) = list(parse_trc_csv(io.StringIO("line,segment,t\nL1,s1,0\n")))
    assert isinstance(error, RowError) and "align10_mm" in error.reason


def test_level_only_and_alignment_only_exports_are_records_of_what_they_measured():
    level = "line,segment,t,top6_mm,run_id\nL1,s1,1767225600,4.1,r1\n"
    (record,) = list(parse_trc_csv(io.StringIO(level)))
    assert record.indicators == ["top6"] and record.values_mm == (4.1, None)
    mixed = "line,segment,t,top6_mm,align10_mm,run_id\nL1,s1,0,,3.0,r1\nL1,s2,0,,,r1\n"
    items = list(parse_trc_csv(io.StringIO(mixed.replace(",0,", ",1767225600,"))))
    assert items[0].indicators == ["align10"] and items[0].align10_mm == 3.0
    assert isinstance(items[1], RowError) and "no value" in items[1].reason
    (error,) = list(parse_trc_csv(io.StringIO("line,segment,t,run_id\nL1,s1,0,r1\n")))
    assert isinstance(error, RowError) and "one or both of" in error.reason


def test_format_state_says_what_the_last_trc_record_measured():
    state = msgspec.structs.replace(a_state(), last_trc_t=1_767_225_600.0,
                                    last_trc_indicators=["top6"])  # fmt: skip
    assert "(last TRC 2026-01-01T00:00+00:00, measured top6)" in format_state(state)
    assert format_state(state, "Alassio – Albenga").startswith("L1/s00001 (Alassio – Albenga) at")


def test_format_state_reads_like_an_engineer_would():
    text = format_state(a_state())
    assert "L1/s00001" in text and "3.00 mm" in text and "95% [2.50, 3.60]" in text
    assert "P(>8.0 mm intervention)=0.00" in text and "in  180 d" in text


def test_format_state_says_the_speed_class_of_its_line_and_its_ial():
    limits = load_limits()
    text = format_state(a_state(), limits=limits)  # L1: 80<v<=120 in the default file
    assert "  limits of speed class 80<v<=120; immediate action top6 11.0 mm, align10 9.5 mm" in (
        text.splitlines()
    )
    other = msgspec.structs.replace(a_state(), line="X1", limits_mm=f8([[5.0, 4.0], [6.5, 5.5]]))
    text = format_state(other, limits=load_limits(line_speeds_kmh={"X1": 140.0}))
    assert "limits of speed class 120<v<=160 (line speed 140 km/h);" in text
    assert "not this class's" not in text
    assert "not this class's" in format_state(other, limits=limits)  # the default class


def test_exports():
    row = state_row(a_state())
    assert set(row) == set(STATE_COLUMNS) and row["top6_mm"] == 3.0
    csv_text = to_csv([row], STATE_COLUMNS)
    assert csv_text.splitlines()[0] == ",".join(STATE_COLUMNS)
    geo = to_geojson([row], {("L1", "s00001"): [[153.0, -27.5], [153.001, -27.5]]})
    assert json.loads(json.dumps(geo))["features"][0]["properties"]["segment"] == "s00001"
    assert to_geojson([row], {})["features"] == []
    assert "probability" in ALERT_COLUMNS
    alert = Alert(
        line="L3",
        segment="s1",
        t=1_767_225_600.0,
        kind="exceedance",
        status="raised",
        indicator="top6",
        level="alert",
        speed_class="v<=80",
    )
    assert alert_row(alert)["speed_class"] == "v<=80"


def test_a_value_that_is_not_a_number_is_named_by_its_column():
    text = "line,segment,t,top6_mm,align10_mm,run_id\nL1,s00002,2026-02-01,abc,0.8,r1\n"
    (error,) = list(parse_trc_csv(io.StringIO(text)))
    assert (error.line_no, error.reason) == (2, "top6_mm: 'abc' is not a number (mm)")
