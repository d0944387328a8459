"""TRC profile exports: parse a sampled run, align it to the previous run, compute the indices.

A Track Recording Car exports its run as rail profiles sampled every 0.25 m. This module is
the pure core of ``trackfusion import-trc --profile`` (no I/O: text in, arrays and values
out); the archive of earlier runs and the publishing live in
:mod:`services.tools.trc_import`.

File format (CSV, UTF-8)
------------------------
* Lines starting with ``#`` and blank lines are comments, skipped (line numbers still
  count them).
* The first other line is the header. Columns, in any order:

  - ``chainage_m`` (required): position along the line in metres, the line's chainage
    as the TRC recorded it. Ascending or descending (the car may run either way), one
    sample every 0.25 m: each step must be 0.25 m within ``SPACING_TOLERANCE_M`` (jitter
    of the position encoder, rounding); a gap, a duplicate or a step back is refused.
  - ``level_left_mm``, ``level_right_mm``: longitudinal level (vertical profile) of each
    rail in mm.
  - ``align_left_mm``, ``align_right_mm``: alignment (lateral profile) of each rail in mm.
  - One of these four at least: a car that records longitudinal level only gives records
    of Top6 only (TrcRecord ``indicators``), one that records alignment only of Align10;
    one rail is enough for either.
  - ``lat``, ``lon`` (optional, both or neither): WGS84 degrees. Checked, not used: the
    chainage is the position.
  - any other column is ignored (and named in the report, so a misspelt one is seen).

* Every cell of those columns is a finite number; an empty or non-numeric cell is refused.

A bad file is refused as a whole, with every problem's line number (a profile with a hole
cannot give a segment statistic): :class:`ProfileFileError`.

Left and right are as the export gives them; nothing here depends on which is which
(see :func:`segment_values` and :func:`alignment_signal`).

What is computed
----------------
The on-board chain's definition (``services/extraction/pipeline.py``) and the simulator's
TRC value (``simulators/profile.py``), both built on :mod:`track.versine`:

.. math::

    \\text{Top6} = \\min_{r \\in \\text{rails}} s\\big(v_{6}(p^{level}_r)\\big), \\qquad
    \\text{Align10} = \\min_{r \\in \\text{rails}} s\\big(v_{10}(p^{align}_r)\\big)

with ``v_L`` the mid-chord versine of chord ``L`` and ``s`` the segment statistic (the
standard deviation over the chord centres in ``[start + L/2 + 1 m, end - L/2 - 1 m)``),
the minimum over the rails the file gives (of a single rail, that rail's); an indicator
whose profile the file does not have gets no value. The simulator scales each rail so that both
give ``exp(z)``; the on-board chain takes ``min(left, right)``: the same rule. The
profile is first interpolated (cubic spline) onto the on-board chain's grid ``x_j = j *
0.25 m`` from chainage 0, so the chord centres are the same points. A segment whose
centres and chords are not all inside the run gets no value.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.interpolate import make_interp_spline

from track.segments import LineSegments
from track.versine import (
    ALIGN_CHORD_M,
    TOP_CHORD_M,
    chord_versine,
    half_chord_samples,
    segment_statistic,
    statistic_centres,
)

SPACING_M = 0.25  # the export's sampling step and the on-board chain's grid
SPACING_TOLERANCE_M = 0.02  # a step may differ this much from SPACING_M (encoder jitter)
LEVEL_COLUMNS = ("level_left_mm", "level_right_mm")
ALIGN_COLUMNS = ("align_left_mm", "align_right_mm")
PROFILE_COLUMNS = LEVEL_COLUMNS + ALIGN_COLUMNS
CHAINAGE_COLUMN = "chainage_m"
POSITION_COLUMNS = ("lat", "lon")
MAX_PROBLEMS = 20  # problems listed per file; the count says how many more there were

WINDOW_M = 400.0  # alignment window
WINDOW_STEP_M = 200.0  # windows overlap by half
MAX_OFFSET_M = 20.0  # search range of the offset, either way
MIN_PEAK = 0.5  # a window whose best correlation is lower is not used
OUTLIER_M = 1.0  # a window further than this from its neighbours' median is not used


# --- parsing ---------------------------------------------------------------------------------


class ProfileFileError(ValueError):
    """A profile file that cannot be used; ``problems`` are ``(line number, reason)``."""

    def __init__(self, problems: list[tuple[int, str]], more: int = 0) -> None:
        self.problems = problems
        self.more = more
        first_line, first_reason = problems[0]
        extra = len(problems) - 1 + more
        super().__init__(
            f"line {first_line}: {first_reason}"
            + (f" (and {extra} more problem{'s' * (extra > 1)})" if extra else "")
        )


@dataclass(frozen=True)
class TrcProfile:
    """A parsed run, in increasing chainage whatever the direction it was recorded in."""

    chainage_m: np.ndarray  # (n,), increasing
    channels: dict[str, np.ndarray]  # name in PROFILE_COLUMNS -> (n,) mm
    descending: bool  # recorded in decreasing chainage
    lonlat: np.ndarray | None = None  # (n, 2) degrees, when the file has lat, lon
    ignored_columns: tuple[str, ...] = ()

    @property
    def n_samples(self) -> int:
        return len(self.chainage_m)

    @property
    def direction(self) -> str:
        return "descending" if self.descending else "ascending"


def parse_profile_csv(text: str, spacing_m: float = SPACING_M) -> TrcProfile:
    """Parse a TRC profile export (format in the module docstring).

    Raises
    ------
    ProfileFileError
        Listing up to ``MAX_PROBLEMS`` problems with their line numbers (1-based, as an
        editor shows them).
    """
    rows = [
        (n, line)
        for n, line in enumerate(text.splitlines(), 1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise ProfileFileError([(1, "no header: the file is empty or only comments")])
    header_no, header_line = rows[0]
    header = [h.strip() for h in next(csv.reader([header_line]))]
    wanted = [CHAINAGE_COLUMN, *PROFILE_COLUMNS, *POSITION_COLUMNS]
    problems = [(header_no, why) for why in _header_problems(header, wanted)]
    if problems:
        raise ProfileFileError(problems)
    used = [h for h in wanted if h in header]
    index = {h: header.index(h) for h in used}
    ignored = tuple(h for h in header if h not in wanted)

    problems: list[tuple[int, str]] = []
    values = np.full((len(rows) - 1, len(used)), np.nan)
    line_nos = np.array([n for n, _ in rows[1:]], dtype=np.int64)
    for i, (n, line) in enumerate(rows[1:]):
        cells = next(csv.reader([line]))
        if len(cells) != len(header):
            problems.append((n, f"{len(cells)} cells, the header has {len(header)}"))
            continue
        for c, name in enumerate(used):
            cell = cells[index[name]].strip()
            try:
                value = float(cell)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                problems.append((n, f"{name}: {cell!r} is not a finite number"))
            values[i, c] = value
    if len(values) < 2:
        problems.append((header_no, "fewer than 2 samples"))
    if problems:
        raise ProfileFileError(problems[:MAX_PROBLEMS], max(0, len(problems) - MAX_PROBLEMS))

    x = values[:, 0]
    sign = 1.0 if x[-1] >= x[0] else -1.0  # the run's direction, whatever a bad row does
    problems = [(int(line_nos[k + 1]), why) for k, why in _spacing_problems(x, sign, spacing_m)]
    if problems:
        raise ProfileFileError(problems[:MAX_PROBLEMS], max(0, len(problems) - MAX_PROBLEMS))

    if POSITION_COLUMNS[0] in index:
        lat, lon = values[:, used.index("lat")], values[:, used.index("lon")]
        bad = np.flatnonzero((np.abs(lat) > 90) | (np.abs(lon) > 180))
        if bad.size:
            raise ProfileFileError(
                [
                    (int(line_nos[k]), "lat, lon outside [-90, 90], [-180, 180]")
                    for k in bad[:MAX_PROBLEMS]
                ],
                max(0, bad.size - MAX_PROBLEMS),
            )
    order = slice(None, None, -1) if sign < 0 else slice(None)
    return TrcProfile(
        chainage_m=x[order].copy(),
        channels={
            name: values[order, used.index(name)].copy() for name in used if name in PROFILE_COLUMNS
        },
        descending=sign < 0,
        lonlat=(
            np.stack([values[order, used.index("lon")], values[order, used.index("lat")]], -1)
            if "lat" in index
            else None
        ),
        ignored_columns=ignored,
    )


def _header_problems(header: list[str], wanted: list[str]) -> list[str]:
    """What is wrong with a profile file's header (nothing: [])."""
    problems = []
    duplicated = sorted({h for h in header if header.count(h) > 1 and h in wanted})
    if duplicated:
        problems.append(f"header repeats column(s) {duplicated}")
    if CHAINAGE_COLUMN not in header:
        problems.append(f"header lacks column {CHAINAGE_COLUMN!r}")
    if not set(PROFILE_COLUMNS) & set(header):
        problems.append(f"header has no profile column: need one of {PROFILE_COLUMNS}")
    if (POSITION_COLUMNS[0] in header) != (POSITION_COLUMNS[1] in header):
        problems.append("header has one of lat, lon: give both or neither")
    return problems


def _spacing_problems(x: np.ndarray, sign: float, spacing_m: float) -> list[tuple[int, str]]:
    """``(k, why)`` for every step ``x[k] -> x[k + 1]`` of the chainage that is not one
    sample spacing in the run's direction ``sign``."""
    step = np.diff(x)
    problems = []
    for k in np.flatnonzero(np.abs(step * sign - spacing_m) > SPACING_TOLERANCE_M):
        d = step[k] * sign
        if step[k] == 0:
            reason = f"chainage {x[k + 1]:g} repeats the previous row's (a duplicate)"
        elif d < 0:
            reason = (
                f"chainage {x[k + 1]:g} goes back after {x[k]:g}: a run is monotone "
                f"({'descending' if sign < 0 else 'ascending'} from its first to its last row)"
            )
        elif d > spacing_m:
            reason = f"gap of {d:g} m after chainage {x[k]:g} (samples every {spacing_m:g} m)"
        else:
            reason = f"step of {d:g} m after chainage {x[k]:g}, expected {spacing_m:g} m"
        problems.append((int(k), reason))
    return problems


# --- the grid ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class GridProfile:
    """Channels on the grid ``x_j = j * spacing_m``, ``j = first_index ... first_index + n - 1``."""

    first_index: int
    spacing_m: float
    channels: dict[str, np.ndarray]  # name -> (n,) mm

    def __post_init__(self) -> None:
        sizes = {len(v) for v in self.channels.values()}
        if len(sizes) != 1:
            raise ValueError(f"channels must have one length each, got {sorted(sizes)}")

    @property
    def n_samples(self) -> int:
        return len(next(iter(self.channels.values())))

    @property
    def chainage_m(self) -> np.ndarray:
        return (self.first_index + np.arange(self.n_samples)) * self.spacing_m

    @property
    def extent_m(self) -> tuple[float, float]:
        return self.first_index * self.spacing_m, (
            self.first_index + self.n_samples - 1
        ) * self.spacing_m


def to_grid(chainage_m, channels: dict[str, np.ndarray], spacing_m: float = SPACING_M):
    """Interpolate samples at increasing chainages onto the grid points they span.

    A cubic interpolating spline through the samples (not linear: linear interpolation
    halfway between samples attenuates a 1 m wavelength by 30 %), evaluated at every
    ``x_j = j dx`` within ``[x_0, x_{n-1}]``.
    """
    x = np.asarray(chainage_m, dtype=np.float64)
    if x.ndim != 1 or len(x) < 4 or not np.all(np.diff(x) > 0):
        raise ValueError("chainage_m: need at least 4 strictly increasing positions")
    names = list(channels)
    spline = make_interp_spline(x, np.stack([channels[n] for n in names], -1), k=3)
    j0 = math.ceil(x[0] / spacing_m - 1e-9)
    j1 = math.floor(x[-1] / spacing_m + 1e-9)
    y = spline((j0 + np.arange(j1 - j0 + 1)) * spacing_m)
    return GridProfile(j0, spacing_m, {n: y[:, i] for i, n in enumerate(names)})


# --- alignment --------------------------------------------------------------------------------


SIGNALS = {"level": (LEVEL_COLUMNS, TOP_CHORD_M), "alignment": (ALIGN_COLUMNS, ALIGN_CHORD_M)}


def common_signal(new: GridProfile, reference: GridProfile) -> tuple[str, tuple[str, ...]]:
    """What two runs are matched on: ``(family, rails)``, their level when both have it,
    else their alignment; of the rails both runs have (empty: each run's own rails, when
    they have none in common). ValueError when they share neither family."""
    for family, (names, _) in SIGNALS.items():
        if all(set(names) & set(grid.channels) for grid in (new, reference)):
            shared = tuple(n for n in names if n in new.channels and n in reference.channels)
            return family, shared
    raise ValueError(
        "the run and the previous run of the line share no profile (one has level only, "
        "the other alignment only): give --no-align to take the run as it is"
    )


def alignment_signal(
    grid: GridProfile, family: str = "level", rails: tuple[str, ...] = ()
) -> tuple[int, np.ndarray]:
    """The signal two runs are matched on: the 6 m versine of the mean level of the rails
    (``family`` "level"), or the 10 m versine of their mean alignment ("alignment"); of
    the ``rails`` named, else of every rail the run has.

    .. math::

        a(x) = v_6\\big(\\tfrac{1}{|R|}\\textstyle\\sum_{r \\in R} p^{level}_r\\big)(x)

    The versine is a band-pass (it removes the long wavelengths that dominate the profile
    and would make a broad peak), the mean of the rails does not change when a run calls
    the other rail left, and the vertical does not change sign with the car's direction
    (the lateral may: :func:`align_runs` matches alignment on the correlation's size).

    Returns
    -------
    first_index, signal
        ``signal[i]`` is at grid index ``first_index + i``.
    """
    names, chord = SIGNALS[family]
    profiles = [grid.channels[n] for n in rails or names if n in grid.channels]
    if not profiles:
        raise ValueError(f"no {family} channel to align on")
    h = half_chord_samples(grid.spacing_m, chord)
    return grid.first_index + h, chord_versine(np.mean(profiles, axis=0), grid.spacing_m, chord)


@dataclass(frozen=True)
class WindowOffset:
    """One alignment window of the new run: where it starts, what it found, whether used."""

    start_m: float  # in the new run's chainage
    end_m: float
    offset_m: float  # reference chainage = new chainage + offset (NaN when not found)
    peak: float  # Pearson correlation at the peak (NaN when not computed)
    used: bool
    reason: str = ""  # why not used

    @property
    def centre_m(self) -> float:
        return 0.5 * (self.start_m + self.end_m)


@dataclass(frozen=True)
class Alignment:
    """The offsets of the windows and the piecewise-linear correction they give."""

    windows: tuple[WindowOffset, ...] = ()
    identity: bool = False  # no reference: the run is taken as it is
    signal: str = "level"  # the profiles matched: "level" or "alignment" (SIGNALS)

    @property
    def used(self) -> list[WindowOffset]:
        return [w for w in self.windows if w.used]

    def correct(self, chainage_m) -> np.ndarray:
        """The reference's chainage of positions of the new run.

        .. math::

            x' = x + \\delta(x)

        with ``delta`` linear between the used windows' centres and constant beyond the
        first and last. ValueError when no window was used, or when the correction would
        fold the run back on itself.
        """
        x = np.asarray(chainage_m, dtype=np.float64)
        if self.identity:
            return x.copy()
        used = self.used
        if not used:
            raise ValueError("no alignment window was used")
        c = np.array([w.centre_m for w in used])
        d = np.array([w.offset_m for w in used])
        if len(c) > 1 and np.any(np.diff(d) / np.diff(c) <= -1.0):
            raise ValueError("the offsets fold the run back on itself")
        return x + np.interp(x, c, d)


def align_runs(
    new: GridProfile,
    reference: GridProfile,
    *,
    window_m: float = WINDOW_M,
    step_m: float = WINDOW_STEP_M,
    max_offset_m: float = MAX_OFFSET_M,
    min_peak: float = MIN_PEAK,
    outlier_m: float = OUTLIER_M,
) -> Alignment:
    """Piecewise cross-correlation of the new run against the reference run.

    For each window ``[a, a + W)`` of the new run (``W = window_m``, a new window every
    ``step_m``), the normalised cross-correlation of the alignment signals
    (:func:`alignment_signal`) at every whole-sample lag ``k`` with ``|k dx| <=
    max_offset_m`` for which the reference covers the shifted window:

    .. math::

        \\rho(k) = \\frac{\\sum_i (a_i - \\bar a)(r_{i+k} - \\bar r_k)}
        {\\sqrt{\\sum_i (a_i - \\bar a)^2 \\sum_i (r_{i+k} - \\bar r_k)^2}}

    The peak ``k*`` is refined to a fraction of a sample by the parabola through
    ``rho(k* - 1), rho(k*), rho(k* + 1)``:

    .. math::

        \\delta = \\frac{\\rho(k^*-1) - \\rho(k^*+1)}
        {2\\,(\\rho(k^*-1) - 2\\rho(k^*) + \\rho(k^*+1))}, \\qquad
        \\text{offset} = (k^* + \\delta)\\,dx

    A window is not used when the peak is below ``min_peak``, lies at the end of the lags
    searched (the true offset may be beyond), or when its offset is more than
    ``outlier_m`` from the median of its used neighbours (two each side): a repeated
    pattern (jointed track) or a tamped stretch. Offsets between the used windows'
    centres are interpolated linearly (:meth:`Alignment.correct`).
    """
    if new.spacing_m != reference.spacing_m:
        raise ValueError("the two runs must be on the same grid spacing")
    dx = new.spacing_m
    family, rails = common_signal(new, reference)
    n0, a = alignment_signal(new, family, rails)
    r0, r = alignment_signal(reference, family, rails)
    width = round(window_m / dx)
    stride = round(step_m / dx)
    max_lag = round(max_offset_m / dx)
    starts = list(range(0, max(len(a) - width, 0) + 1, stride))
    if len(a) >= width and starts[-1] + width < len(a):
        starts.append(len(a) - width)  # the run's tail gets a window of its own
    found: list[WindowOffset] = []
    for s in starts:
        seg = a[s : s + width]
        span = ((n0 + s) * dx, (n0 + s + len(seg) - 1) * dx)
        if len(seg) < width:
            found.append(WindowOffset(*span, math.nan, math.nan, False, "run shorter than W"))
            continue
        first = n0 + s - r0  # reference index of the window's first sample at lag 0
        lo, hi = max(-max_lag, -first), min(max_lag, len(r) - width - first)
        if hi - lo < 2:
            found.append(WindowOffset(*span, math.nan, math.nan, False, "no reference here"))
            continue
        rho = _pearson(seg, sliding_window_view(r[first + lo : first + hi + width], width))
        if family == "alignment":  # a run recorded the other way may see it mirrored
            rho = np.abs(rho)
        k = int(np.argmax(rho))
        peak = float(rho[k])
        if k == 0 or k == len(rho) - 1:
            why = "peak at the search limit"
            found.append(WindowOffset(*span, (k + lo) * dx, peak, False, why))
            continue
        c_m, c_0, c_p = rho[k - 1], rho[k], rho[k + 1]
        curvature = c_m - 2 * c_0 + c_p
        delta = 0.5 * (c_m - c_p) / curvature if curvature < 0 else 0.0
        offset = (k + lo + delta) * dx
        if peak < min_peak:
            found.append(WindowOffset(*span, offset, peak, False, f"peak < {min_peak:g}"))
            continue
        found.append(WindowOffset(*span, offset, peak, True))
    return Alignment(tuple(_reject_outliers(found, outlier_m)), signal=family)


def _pearson(seg: np.ndarray, windows: np.ndarray) -> np.ndarray:
    """Pearson correlation of ``seg`` with each row of ``windows``."""
    u = seg - seg.mean()
    w = windows - windows.mean(axis=1, keepdims=True)
    den = np.sqrt((u @ u) * np.einsum("ij,ij->i", w, w))
    return np.divide(w @ u, den, out=np.zeros(len(w)), where=den > 0)


def _reject_outliers(windows: list[WindowOffset], outlier_m: float) -> list[WindowOffset]:
    used = [i for i, w in enumerate(windows) if w.used]
    offsets = np.array([windows[i].offset_m for i in used])
    out = list(windows)
    for j, i in enumerate(used):
        near = np.r_[offsets[max(0, j - 2) : j], offsets[j + 1 : j + 3]]
        if near.size >= 2 and abs(offsets[j] - np.median(near)) > outlier_m:
            w = windows[i]
            out[i] = WindowOffset(
                w.start_m, w.end_m, w.offset_m, w.peak, False, "off its neighbours"
            )
    return out


# --- the statistic per segment ----------------------------------------------------------------


@dataclass(frozen=True)
class SegmentValue:
    """A segment's TRC value from the run: min over the rails of each statistic (None for
    an indicator whose profile the run does not have)."""

    segment: str
    start_m: float
    end_m: float
    top6_mm: float | None
    align10_mm: float | None
    top6_by_rail_mm: dict[str, float] = field(default_factory=dict)
    align10_by_rail_mm: dict[str, float] = field(default_factory=dict)


def segment_values(
    grid: GridProfile, segments: LineSegments
) -> tuple[list[SegmentValue], list[str], list[str]]:
    """Top6 and Align10 (those the run has a profile for) of every segment it covers
    entirely.

    A segment is covered when every chord centre of the statistic (``[start + L/2 + g,
    end - L/2 - g)`` on the grid, :func:`track.versine.statistic_centres`) and both ends
    of its chord are inside the run, for each chord it has a profile for.

    Returns
    -------
    values, partial, outside
        The covered segments' values; the ids of the segments the run overlaps without
        covering them; the ids of the segments it does not reach at all.
    """
    dx = grid.spacing_m
    lo_m, hi_m = grid.extent_m
    families = (
        (TOP_CHORD_M, [n for n in LEVEL_COLUMNS if n in grid.channels]),
        (ALIGN_CHORD_M, [n for n in ALIGN_COLUMNS if n in grid.channels]),
    )
    if not any(names for _, names in families):
        raise ValueError("no level or alignment channel")
    versines = {}
    for chord, names in families:
        h = half_chord_samples(dx, chord)
        for name in names:
            versines[name] = (h, chord_versine(grid.channels[name], dx, chord))
    values, partial, outside = [], [], []
    for k, seg in enumerate(segments.ids):
        start, end = float(segments.starts[k]), float(segments.ends[k])
        if end <= lo_m or start >= hi_m:
            outside.append(seg)
            continue
        stats: list[dict[str, float]] = []
        for chord, names in families:
            if not names:
                stats.append({})
                continue
            j_lo, j_hi = statistic_centres(start, end, dx, chord)  # as the on-board chain
            by_rail = {}
            for name in names:
                h, v = versines[name]
                i_lo, i_hi = j_lo - grid.first_index - h, j_hi - grid.first_index - h
                if i_lo < 0 or i_hi > len(v) or i_hi <= i_lo:
                    break
                by_rail[name] = float(segment_statistic(v[i_lo:i_hi]))
            else:
                stats.append(by_rail)
        if len(stats) < 2:
            partial.append(seg)
            continue
        top, align = stats
        top6 = min(top.values()) if top else None
        align10 = min(align.values()) if align else None
        values.append(SegmentValue(seg, start, end, top6, align10, top, align))
    return values, partial, outside


# --- one run ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunResult:
    """What importing one run gives: its aligned profile, the alignment, the values."""

    grid: GridProfile  # aligned, on the network grid: what the archive keeps
    alignment: Alignment
    values: list[SegmentValue]
    partial: list[str]  # segments overlapped, not covered
    outside: list[str]  # segments not reached


def process_run(
    profile: TrcProfile,
    segments: LineSegments,
    reference: GridProfile | None,
    *,
    align: bool = True,
    max_offset_m: float = MAX_OFFSET_M,
    spacing_m: float = SPACING_M,
) -> RunResult:
    """Align ``profile`` to ``reference`` (when given and ``align``), then compute its values.

    The new run's samples keep their own spacing (its encoder's); they are put on the grid
    for the correlation, their chainages corrected by :meth:`Alignment.correct`, and put
    on the grid again from the corrected chainages (one interpolation of the data).
    ValueError, saying what to do, when a reference exists and no window could be used.
    """
    raw = to_grid(profile.chainage_m, profile.channels, spacing_m)
    if reference is None or not align:
        alignment = Alignment(identity=True)
    else:
        alignment = align_runs(raw, reference, max_offset_m=max_offset_m)
        if not alignment.used:
            raise ValueError(
                "no alignment window matches the previous run of the line (is --line right? "
                "is the track renewed? give a larger --max-offset, or --no-align to take "
                "the run as it is)"
            )
    corrected = alignment.correct(profile.chainage_m)
    if not np.all(np.diff(corrected) > 0):
        raise ValueError("the aligned chainages are not increasing")
    grid = to_grid(corrected, profile.channels, spacing_m)
    values, partial, outside = segment_values(grid, segments)
    return RunResult(grid, alignment, values, partial, outside)
