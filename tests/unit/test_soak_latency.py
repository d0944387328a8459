"""bench.soak's latency figures on a hand-made pass: the sample an index needs is where
extraction completes it, 0.75 m (END_GUARD_M less one grid step) short of the segment end."""

from __future__ import annotations

import numpy as np
import pytest

from bench.soak import Probe, latency_figures
from schemas import OnboardIndex

T0 = 1_767_225_600.0
START, END = 200.0, 400.0
V = END / 17.01  # m/s from chainage 0 at T0: leaves the segment 10 ms into the 18th second
STATE_WALL = T0 + 18.5  # when the segment's state arrives (offset 0: wall = event time)


def probe() -> Probe:
    """One unit on L1, 1 s raw chunks each arriving at its end, a knot every second."""
    p = Probe({("L1", "s1"): (START, END)})
    t = np.arange(0.0, 31.0)
    p.raw_spans[("T1", "u0")] = [(T0 + a, T0 + a + 1.0, T0 + a + 1.0) for a in t[:-1]]
    p.trajectories[("T1", "u0")] = [("L1", T0 + t, V * t)]
    index = OnboardIndex(
        line="L1",
        segment="s1",
        train="T1",
        unit="u0",
        t=T0 + 0.5 * (START + END) / V,
        top6_mm=1.0,
        align10_mm=1.0,
        speed_mps=V,
        coverage=1.0,
    )
    p.latency.append((STATE_WALL, index, STATE_WALL - 0.01))
    return p


def test_latency_is_measured_from_the_chunks_of_the_leave_and_of_the_needed_sample():
    out = latency_figures(probe(), offset=0.0)
    leave = T0 + END / V
    assert out["latency_s"]["matched"] == 1 and out["latency_s"]["leave_not_found"] == 0
    # (a) from the leave moment; (b) from the chunk [17, 18) s holding the first sample past
    # the end, which arrives at 18 s
    assert out["latency_other_s"]["(a) from the leave moment"]["p50"] == pytest.approx(
        STATE_WALL - leave
    )
    assert out["latency_s"]["p50"] == pytest.approx(0.5)
    # (c) the index needed the sample at END - 0.75 m (+ 12 ms), 20 ms before 17 s: the chunk
    # [16, 17) s, arriving at 17 s, completed it
    assert (END - 0.75) / V + 0.012 < 17.0
    assert out["latency_other_s"]["(c) from the raw chunk the index needs"]["p50"] == pytest.approx(
        1.5
    )
