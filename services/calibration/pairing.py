r"""Which TRC record an on-board index pairs with, and how long an unpaired one waits. Pure.

The waiting indices and the pairs themselves are kept by
:class:`~services.calibration.calibrator.Calibrator`; the rules are these.

Pairing
    An on-board index and a TRC record of the same (line, segment) pair up

    * when the index carries a non-empty ``run_id`` equal to the record's (the on-board unit
      rode the TRC: the paper's campaign, section 3.2). Such an index pairs by ``run_id`` only;
    * otherwise, when ``tolerance_days`` is set, when ``|t_trc - t_index| <= tolerance_days``;
      the nearest record known at that moment wins.

    An index pairs at most once and a pair is never undone; a record may pair with several
    indices (several passes within the tolerance). An index that has not paired waits for its
    record while it is within ``index_window_days`` of the newest TRC record of its segment,
    and while it is among the ``max_pending_per_segment`` newest waiting indices of that
    segment (a memory bound). The window is measured against the segment's own TRC records,
    not against the newest event seen anywhere: TRC records and indices come on different
    keys, and a replay or an import of a year of records arrives in any interleaving.
    Duplicates (same identity: TRC ``(line, segment, run_id)``, index
    ``(line, segment, train, unit, t)``, tamping ``(line, segment, event_id)``) are ignored,
    as is a second TRC record of a segment at the same instant, except that a tamping report
    that outranks the one held (``MaintenanceEvent.rank``: a correction) replaces it, as in
    filtering, whatever the order. A pair's time is the index's.

Records of some indicators
    By time an index pairs with a record of every indicator only. One that pairs by
    ``run_id`` with a record of some indicators only makes no pair
    (:func:`partial_record_reason`): every row of H weighs every indicator (H is full), so
    without ``z_k`` each row of ``y = H z + b + e`` has an unknown term ``H_ik z_k`` and the
    pair fits no element of H, b or R.

"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping

from schemas import DAY_S, INDICATORS, OnboardIndex, TrcRecord


def ln_mm(msg: TrcRecord | OnboardIndex) -> tuple[float, ...]:
    """``ln`` of a record's or an index's values (``z`` or ``y``), NaN for one not measured."""
    return tuple(math.nan if v is None else math.log(v) for v in msg.values_mm)


def match_record(
    records: Mapping[str, TrcRecord] | None,
    times: list[tuple[float, str]],
    idx: OnboardIndex,
    tolerance_days: float | None,
) -> TrcRecord | None:
    """The TRC record ``idx`` pairs with among ``records`` of its segment (by run id;
    ``times`` sorted ``(t, run_id)`` of the same records), if any."""
    if not records:
        return None
    if idx.run_id:
        return records.get(idx.run_id)
    tol = tolerance_days
    if tol is None:
        return None
    i = bisect.bisect_left(times, (idx.t, ""))
    best: tuple[float, str] | None = None
    for t, run_id in times[max(0, i - 1) : i + 1]:
        d = abs(t - idx.t)
        if d <= tol * DAY_S and (best is None or d < best[0]):
            best = (d, run_id)
    return records[best[1]] if best is not None else None


def oldest_waiting(times: list[tuple[float, str]] | None, index_window_days: float) -> float:
    """Indices of a segment older than this (epoch s) no longer wait for a TRC record
    (``times``: the segment's sorted ``(t, run_id)``)."""
    return times[-1][0] - index_window_days * DAY_S if times else -math.inf


def partial_record_reason(iid: str, rec: TrcRecord) -> str | None:
    """Why index ``iid`` makes no pair with ``rec`` (a record of some indicators only), or
    None (see the module docstring)."""
    if len(rec.indicators) == len(INDICATORS):
        return None
    return (
        f"on-board index {iid} not paired: its TRC record {rec.line}/{rec.segment}/"
        f"{rec.run_id} measured {rec.indicators} only, and every row of the observation "
        f"model weighs {list(INDICATORS)}"
    )
