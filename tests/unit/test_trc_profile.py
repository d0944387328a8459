"""The TRC profile core: parsing a sampled export, the statistic per segment, the alignment.

Synthetic runs are the simulator's track (``simulators.profile.LineProfile``) sampled every
0.25 m with fresh measurement noise, their chainage shifted as a TRC's odometer shifts it.
"""

from __future__ import annotations

import numpy as np
import pytest

from simulators.profile import LineProfile
from track.segments import LineSegments
from track.trc_profile import (
    PROFILE_COLUMNS,
    ProfileFileError,
    TrcProfile,
    align_runs,
    parse_profile_csv,
    process_run,
    segment_values,
    to_grid,
)

DX = 0.25
N_SEGMENTS = 15  # 3 km of 200 m segments
NOISE_MM = 0.15


def profile_csv(x, channels: dict[str, np.ndarray], descending: bool = False) -> str:
    names = list(channels)
    rows = np.stack([x, *(channels[n] for n in names)], -1)
    if descending:
        rows = rows[::-1]
    body = "\n".join(",".join(f"{v:.6f}" for v in row) for row in rows)
    return "# a TRC export\n" + ",".join(["chainage_m", *names]) + "\n" + body + "\n"


@pytest.fixture(scope="module")
def line() -> LineSegments:
    starts = np.arange(N_SEGMENTS) * 200.0
    ids = tuple(f"s{i:05d}" for i in range(N_SEGMENTS))
    return LineSegments("L9", ids, starts, starts + 200.0)


def true_state(seed: int, n: int = N_SEGMENTS, spread: float = 0.4) -> np.ndarray:
    """``[ln Top6, ln Align10]`` per segment: segments of various quality (log sd ``spread``)."""
    rng = np.random.default_rng(seed)
    return np.stack([rng.normal(np.log(1.5), spread, n), rng.normal(np.log(1.2), spread, n)], -1)


def track(line: LineSegments, seed: int) -> LineProfile:
    """The simulator's track over ``line`` in the state ``true_state(seed)``."""
    profile = LineProfile(line.line, np.stack([line.starts, line.ends], -1), seed=seed)
    profile.update(true_state(seed), np.zeros(len(line.ids), dtype=np.int64))
    return profile


def trc_run(track: LineProfile, offset, seed: int, span=(100.0, 2900.0)) -> TrcProfile:
    """A run over true chainages ``span``, recorded at ``true - offset(true)``."""
    rng = np.random.default_rng(seed)
    true_m = np.arange(*span, DX)
    p = track.sample(true_m) + rng.normal(0.0, NOISE_MM, (4, true_m.size))
    return TrcProfile(true_m - offset(true_m), dict(zip(PROFILE_COLUMNS, p, strict=True)), False)


def true_offset_at(recorded_m: float, offset) -> float:
    """The offset at a recorded chainage (``recorded = true - offset(true)``, solved)."""
    true_m = np.arange(0.0, 3200.0, 0.01)
    return float(np.interp(recorded_m, true_m - offset(true_m), offset(true_m)))


# --- parsing -------------------------------------------------------------------------------


def test_an_ascending_and_a_descending_file_give_the_same_profile():
    x = np.arange(100.0, 110.0, DX)
    ch = {"level_left_mm": np.sin(x), "align_right_mm": np.cos(x)}
    up = parse_profile_csv(profile_csv(x, ch))
    down = parse_profile_csv(profile_csv(x, ch, descending=True))
    assert (up.direction, down.direction) == ("ascending", "descending")
    for run in (up, down):
        assert np.allclose(run.chainage_m, x)
        assert np.allclose(run.channels["level_left_mm"], np.sin(x), atol=1e-6)
        assert set(run.channels) == {"level_left_mm", "align_right_mm"}


def test_jitter_comments_lat_lon_and_other_columns_are_taken():
    text = (
        "# exported by the TRC\n\n"
        "chainage_m,level_right_mm,align_left_mm,speed_kmh,lat,lon\n"
        "10.000,1,2,80,-27.5,152.9\n"
        "# a comment inside\n"
        "10.252,1,2,80,-27.5,152.9\n"
        "10.498,1,2,80,-27.5,152.9\n"
    )
    run = parse_profile_csv(text)
    assert run.n_samples == 3 and run.ignored_columns == ("speed_kmh",)
    assert np.allclose(run.lonlat, [[152.9, -27.5]] * 3)


HEADER = "chainage_m,level_left_mm,align_left_mm\n"


@pytest.mark.parametrize(
    ("text", "line_no", "words"),
    [
        (HEADER + "0,1,2\n0.25,x,2\n0.5,1,2\n", 3, "level_left_mm: 'x'"),
        (HEADER + "0,1,2\n0.25,,2\n0.5,1,2\n", 3, "level_left_mm: ''"),
        (HEADER + "0,1,2\n0.25,nan,2\n", 3, "not a finite number"),
        (HEADER + "0,1,2\n0.25,1\n", 3, "2 cells, the header has 3"),
        ("# c\nlevel_left_mm,align_left_mm\n1,2\n", 2, "lacks column 'chainage_m'"),
        ("chainage_m,lat,lon\n0,2,1\n0.25,2,1\n", 1, "no profile column"),
        (HEADER.replace("\n", ",lat\n") + "0,1,2,3\n0.25,1,2,3\n", 1, "lat, lon"),
        (HEADER + "0,1,2\n0.25,1,2\n0.75,1,2\n1.0,1,2\n", 4, "gap of 0.5 m after chainage 0.25"),
        (HEADER + "0,1,2\n0.25,1,2\n0.25,1,2\n0.5,1,2\n", 4, "repeats the previous row's"),
        (HEADER + "0,1,2\n0.25,1,2\n0.5,1,2\n0.25,1,2\n0.5,1,2\n0.75,1,2\n", 5, "goes back"),
        (HEADER + "# x\n5,1,2\n4.75,1,2\n4.6,1,2\n4.35,1,2\n", 5, "step of 0.15 m"),
        (HEADER + "0,1,2\n", 1, "fewer than 2 samples"),
        ("# only a comment\n", 1, "no header"),
    ],
    ids=[
        "non-numeric",
        "empty cell",
        "nan",
        "short row",
        "no chainage",
        "no profile",
        "lat without lon",
        "gap",
        "duplicate",
        "not monotone",
        "wrong step, descending",
        "one row",
        "empty",
    ],
)
def test_a_bad_file_is_refused_with_the_line_number_of_each_problem(text, line_no, words):
    with pytest.raises(ProfileFileError) as refused:
        parse_profile_csv(text)
    problems = refused.value.problems
    assert any(n == line_no and words in reason for n, reason in problems), problems
    assert str(refused.value).startswith(f"line {problems[0][0]}: ")
    assert ("more problem" in str(refused.value)) == (len(problems) > 1)


def test_every_problem_is_listed_up_to_a_bound_and_counted_beyond():
    rows = "".join(f"{i * DX},x,2\n" for i in range(30))
    with pytest.raises(ProfileFileError) as refused:
        parse_profile_csv(HEADER + rows)
    assert [n for n, _ in refused.value.problems] == list(range(2, 22))
    assert "(and 29 more problems)" in str(refused.value)


# --- the statistic -------------------------------------------------------------------------


def test_each_segment_gets_the_simulators_trc_value_exactly(line):
    """Built of the segments' own profiles, a run gives exp(z) of each segment: the value
    the simulator defines a TRC record by (both rails scaled to it, min of the two)."""
    sim = track(line, seed=1)
    parts = [sim.segment_profile(k) for k in range(N_SEGMENTS)]
    x = np.concatenate([xk[inner] for xk, _, inner in parts])
    p = np.concatenate([pk[:, inner] for _, pk, inner in parts], axis=1)
    grid = to_grid(x, dict(zip(PROFILE_COLUMNS, p, strict=True)))
    values, partial, outside = segment_values(grid, line)
    assert [v.segment for v in values] == list(line.ids)
    assert partial == outside == []
    got = np.array([[v.top6_mm, v.align10_mm] for v in values])
    want = np.array([sim.segment_statistics(k)[[0, 2]] for k in range(N_SEGMENTS)])
    assert np.allclose(got, want, rtol=1e-9)
    assert np.allclose(got, np.exp(true_state(1)), rtol=1e-9)


def test_the_value_is_the_smaller_rail_and_one_rail_is_enough(line):
    sim = track(line, seed=2)
    x = np.arange(0.0, 1000.0, DX)
    p = sim.sample(x)
    both = dict(zip(PROFILE_COLUMNS, p, strict=True))
    louder = {**both, "level_right_mm": 2 * both["level_right_mm"]}
    louder["align_left_mm"] = 3 * both["align_left_mm"]
    one = {"level_left_mm": both["level_left_mm"], "align_right_mm": both["align_right_mm"]}
    a, b, c = (segment_values(to_grid(x, ch), line)[0] for ch in (both, louder, one))
    for va, vb, vc in zip(a, b, c, strict=True):
        rails = va.top6_by_rail_mm
        assert vb.top6_mm == pytest.approx(min(rails["level_left_mm"], 2 * rails["level_right_mm"]))
        assert vb.align10_mm == pytest.approx(va.align10_by_rail_mm["align_right_mm"])
        assert vc.top6_mm == pytest.approx(va.top6_by_rail_mm["level_left_mm"])
        assert vc.align10_mm == pytest.approx(va.align10_by_rail_mm["align_right_mm"])


def test_a_level_only_or_alignment_only_run_gives_values_of_what_it_measured(line):
    sim = track(line, seed=6)
    first = process_run(trc_run(sim, lambda x: 0 * x, seed=1), line, None)
    second = trc_run(sim, lambda x: np.full_like(x, 5.0), seed=2)
    level = {n: v for n, v in second.channels.items() if n.startswith("level")}
    one_rail = {"level_right_mm": second.channels["level_right_mm"]}
    align = {n: v for n, v in second.channels.items() if n.startswith("align")}
    full = process_run(second, line, first.grid)
    for channels, signal in ((level, "level"), (one_rail, "level"), (align, "alignment")):
        run = TrcProfile(second.chainage_m, channels, False)
        result = process_run(run, line, first.grid)
        assert result.alignment.signal == signal
        assert all(abs(w.offset_m - 5.0) < 0.05 for w in result.alignment.used)
        assert len(result.alignment.used) >= 10
        for got, want in zip(result.values, full.values, strict=True):
            if signal == "alignment":
                assert got.top6_mm is None
                assert got.align10_mm == pytest.approx(want.align10_mm, rel=1e-3)
            elif len(channels) == 2:  # aligned on the same signal: the same numbers
                assert got.align10_mm is None and got.top6_mm == pytest.approx(want.top6_mm)
            else:  # aligned on one rail: within the alignment's centimetres
                rail = want.top6_by_rail_mm["level_right_mm"]
                assert got.align10_mm is None and got.top6_mm == pytest.approx(rail, rel=1e-3)
    level_first = process_run(TrcProfile(second.chainage_m, level, False), line, None)
    with pytest.raises(ValueError, match="share no profile"):
        process_run(TrcProfile(second.chainage_m, align, False), line, level_first.grid)


def test_a_segment_the_run_does_not_cover_gets_no_value(line):
    sim = track(line, seed=3)
    x = np.arange(150.0, 653.0, DX)  # s00000 and s00003 partly, s00004.. not at all
    run = TrcProfile(x, dict(zip(PROFILE_COLUMNS, sim.sample(x), strict=True)), False)
    result = process_run(run, line, None)
    assert [v.segment for v in result.values] == ["s00001", "s00002"]
    assert result.partial == ["s00000", "s00003"]
    assert result.outside == list(line.ids[4:])


# --- alignment -----------------------------------------------------------------------------


OFFSETS = {
    "5 m": lambda x: np.full_like(x, 5.0),
    "5 m drifting 0.5 m over 2 km": lambda x: 5.0 + 0.5 * (x - 100.0) / 2000.0,
    "-12 m": lambda x: np.full_like(x, -12.0),
}


@pytest.mark.parametrize("offset", list(OFFSETS.values()), ids=list(OFFSETS))
def test_a_known_offset_is_recovered_within_a_grid_step_in_every_used_window(line, offset):
    sim = track(line, seed=4)
    first = process_run(trc_run(sim, lambda x: 0 * x, seed=1), line, None)
    second = trc_run(sim, offset, seed=2)
    alignment = align_runs(to_grid(second.chainage_m, second.channels), first.grid)
    used = alignment.used
    assert len(used) >= 10  # of 13 windows over 2.8 km
    errors = [w.offset_m - true_offset_at(w.centre_m, offset) for w in used]
    assert np.max(np.abs(errors)) < 0.25, errors
    assert np.max(np.abs(errors)) < 0.05  # what it does: a few cm


def agreement(a, b) -> np.ndarray:
    """Per-segment differences (Top6, Align10) of two runs' values, common segments."""
    va = {v.segment: v for v in a.values}
    return np.array(
        [[v.top6_mm - va[v.segment].top6_mm, v.align10_mm - va[v.segment].align10_mm]
         for v in b.values if v.segment in va]
    )  # fmt: skip


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_two_aligned_runs_of_unchanged_track_agree_and_would_not_unaligned(line, seed):
    sim = track(line, seed=seed)
    first = process_run(trc_run(sim, lambda x: 0 * x, seed=10 + seed), line, None)
    assert len(first.values) == 13
    for shift_m in (5.0, 10.0):
        second = trc_run(sim, lambda x, s=shift_m: np.full_like(x, s), seed=20 + seed)
        aligned = agreement(first, process_run(second, line, first.grid))
        unaligned = agreement(first, process_run(second, line, first.grid, align=False))
        assert len(aligned) == 13
        assert np.all(aligned.std(axis=0) < 0.1) and np.abs(aligned).max() < 0.1
        assert np.all(aligned.std(axis=0) < 0.02)  # measurement noise alone
        assert np.all(unaligned.std(axis=0) > 1.5 * aligned.std(axis=0))
        if shift_m == 10.0:
            assert np.abs(unaligned).max() > 0.1


def test_a_descending_run_is_aligned_too(line):
    sim = track(line, seed=5)
    first = process_run(trc_run(sim, lambda x: 0 * x, seed=1), line, None)
    second = trc_run(sim, lambda x: np.full_like(x, 7.0), seed=2)
    text = profile_csv(second.chainage_m, second.channels, descending=True)
    run = parse_profile_csv(text)
    assert run.descending
    result = process_run(run, line, first.grid)
    assert all(abs(w.offset_m - 7.0) < 0.25 for w in result.alignment.used)
    assert np.abs(agreement(first, result)).max() < 0.1


def test_a_renewed_stretch_is_rejected_and_bridged(line):
    """Tamped or renewed track between two runs: its windows do not correlate; the offset
    there is interpolated from the windows around it."""
    sim = track(line, seed=6)
    first = process_run(trc_run(sim, lambda x: 0 * x, seed=1), line, None)
    second = trc_run(sim, lambda x: np.full_like(x, 4.0), seed=2)
    renewed = (second.chainage_m > 1200) & (second.chainage_m < 1900)
    rng = np.random.default_rng(9)
    for p in second.channels.values():
        p[renewed] = np.convolve(rng.normal(0, 2, renewed.sum()), np.ones(20) / 20, "same")
    alignment = align_runs(to_grid(second.chainage_m, second.channels), first.grid)
    rejected = [w for w in alignment.windows if not w.used and 1200 < w.centre_m < 1900]
    assert rejected and all("peak" in w.reason or "neighbours" in w.reason for w in rejected)
    assert all(abs(w.offset_m - 4.0) < 0.25 for w in alignment.used)
    assert np.allclose(alignment.correct([1500.0]), [1504.0], atol=0.25)


def test_another_lines_run_does_not_align(line):
    first = process_run(trc_run(track(line, seed=7), lambda x: 0 * x, seed=1), line, None)
    other = trc_run(track(line, seed=8), lambda x: 0 * x, seed=2)
    with pytest.raises(ValueError, match="no alignment window matches"):
        process_run(other, line, first.grid)
