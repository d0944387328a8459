"""The published trajectory of a train (its chainage over time): the knots its
PositionedChunks carry. Pure.

The knots a chunk goes out with are the **published trajectory**
(:func:`publish_trajectory`): what went out is never revised, so every chunk of a train (and
of each of its units) continues the previous one. When a later fix moves the trajectory
away from a dead-reckoned position, the correction (usually well under a metre: the fused
knots take in 0.3 of the GPS error) is spread linearly over ``correction_s``; one larger
than ``correction_ok_m`` (a stop inside a tunnel, a reversal at a terminus found 12 m late)
is jumped, as the fix knots themselves jump, and marked poor for ``correction_s``.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right

from services.ingestion.matching import Positioner
from services.ingestion.train import Knot, TrainState

STANDING_MPS = 0.5  # slower than this, a train of unknown direction is taken as standing
_DR_STEP_S = 0.5  # knot spacing of a dead-reckoned stretch with acceleration (a parabola)


class _FixTrajectory:
    """The fix knots of one line as a function of time: linear between knots, dead-reckoned
    past the last one (its speed, and the acceleration between the last two knots)."""

    def __init__(self, st: TrainState, line: str, pos: Positioner) -> None:
        cfg = pos.cfg
        self.knots = [k for k in st.knots if k.line == line]
        self.t = [k.t for k in self.knots]
        self.line, self.cfg = line, cfg
        self.length_m = pos.lines[line].length_m
        self.direction = st.direction if line == st.line else 0
        self.last_good_t = st.last_good_t
        self.accel = 0.0
        if len(self.knots) >= 2 and self.direction:
            k0, k1 = self.knots[-2], self.knots[-1]
            dt = k1.t - k0.t
            if 0 < dt <= cfg.dead_reckon_s:
                bound = cfg.extrapolate_accel_max_mps2
                self.accel = min(max((k1.speed_mps - k0.speed_mps) / dt, -bound), bound)

    def at(self, t: float) -> Knot:
        ks = self.knots
        i = bisect_right(self.t, t)
        if i == 0:  # before the line's first knot (a line change): its first position
            return Knot(t, self.line, ks[0].chainage_m, ks[0].speed_mps, False)
        a = ks[i - 1]
        if a.t == t:
            return a
        if i < len(ks):
            b = ks[i]
            f = (t - a.t) / (b.t - a.t)
            return Knot(
                t,
                self.line,
                a.chainage_m + f * (b.chainage_m - a.chainage_m),
                a.speed_mps + f * (b.speed_mps - a.speed_mps),
                a.ok and b.ok,
            )
        return self.reckon(t)

    def reckon(self, t: float) -> Knot:
        r"""Dead reckoning from the last knot ``r`` over ``tau = t - t_r``:

        .. math::

            c = c_r + d\,(v_r \tau + \tfrac{1}{2} a \tau^2), \qquad v = v_r + a \tau

        until the speed reaches 0 (a stop), never past a line end. Trusted (ok) while ``tau``
        is within ``extrapolate_s`` and the last good fix within ``dead_reckon_s``.
        """
        cfg, r = self.cfg, self.knots[-1]
        tau, v, a = t - r.t, r.speed_mps, self.accel
        if a < 0 and v + a * tau < 0:
            tau_stop = -v / a
            dist, speed = v * tau_stop + 0.5 * a * tau_stop**2, 0.0
        else:
            dist, speed = v * tau + 0.5 * a * tau**2, v + a * tau
        chain = r.chainage_m + self.direction * dist  # not past a line end (nor back from r)
        chain = min(max(chain, min(0.0, r.chainage_m)), max(self.length_m, r.chainage_m))
        ok = (
            r.ok
            and tau <= cfg.extrapolate_s
            and self.last_good_t is not None
            and t - self.last_good_t <= cfg.dead_reckon_s
        )
        return Knot(t, self.line, chain, speed, ok)


def can_extrapolate(st: TrainState, pos: Positioner, t_last: float) -> bool:
    """Whether a chunk ending at ``t_last`` can go out now, its tail dead-reckoned."""
    cfg = pos.cfg
    if cfg.extrapolate_s <= 0 or st.line is None:
        return False
    last = next((k for k in reversed(st.knots) if k.line == st.line), None)
    if last is None or t_last - last.t > cfg.extrapolate_s:
        return False
    return st.direction != 0 or last.speed_mps <= STANDING_MPS


def publish_trajectory(st: TrainState, pos: Positioner, t_to: float, *, extrapolate=False) -> None:
    """Extend the published trajectory (``st.pub``) towards ``t_to``.

    It takes the fix knots after its end up to the first one at or after ``t_to`` and, with
    ``extrapolate``, dead-reckons from the last fix knot to ``t_to`` when no knot reaches it.
    What was published stays. Where the fix knots have since moved the trajectory away from
    the published end (a dead-reckoned position that a later fix corrects), that correction is
    spread linearly over the next ``correction_s`` (each new correction on its own schedule,
    added to those still running), so the published chainage is continuous: a correction
    never reads as a jump, or backwards as a reversal, in the extraction. A correction larger
    than ``correction_ok_m`` is no dead-reckoning error (a stop inside a tunnel, where the
    fix knots themselves were reckoned on): the trajectory jumps to the fix knots, as they do,
    and its knots for ``correction_s`` are marked poor. It never steps backwards
    while the fix knots move forwards (a spread correction never reverses it). Without dead
    reckoning there is nothing to correct and the published trajectory is the fix knots.
    """
    cfg = pos.cfg
    pub, end = st.pub, (st.pub[-1] if st.pub else None)
    t_end = -math.inf if end is None else end.t
    i = bisect_right(st.knot_t, t_end)
    j = bisect_left(st.knot_t, t_to, lo=i)
    new = st.knots[i : j + 1]  # up to the first knot at or after t_to, if there is one
    fixes: _FixTrajectory | None = None
    if extrapolate and j >= len(st.knot_t) and st.line is not None:
        fixes = _FixTrajectory(st, st.line, pos)
        if fixes.knots and t_to > max(fixes.t[-1], t_end):
            r = fixes.t[-1]
            steps = []
            if fixes.accel:
                steps = [r + _DR_STEP_S * m for m in range(1, int((t_to - r) / _DR_STEP_S) + 1)]
            new += [fixes.reckon(t) for t in [*steps, t_to] if t_end < t < t_to or t == t_to]
    if not new:
        return
    prev_base = None
    if end is None or not any(k.line == end.line for k in st.knots):
        st.corrections = []
    else:
        ref = (
            fixes
            if fixes is not None and fixes.line == end.line
            else _FixTrajectory(st, end.line, pos)
        )
        if ref.t[0] > end.t:  # the knots around the end are gone (a long pause)
            st.corrections = []
        else:
            prev_base = ref.at(end.t).chainage_m
            st.corrections = [c for c in st.corrections if c[2] > end.t]
            residual = end.chainage_m - prev_base - _correction(st, end.t)
            st.stats.max_correction_m = max(st.stats.max_correction_m, abs(residual))
            if abs(residual) > cfg.correction_ok_m:
                # not a dead-reckoning error to smooth over (a stop in a tunnel, a reversal
                # found late): jump to the fixes' trajectory, as they do, and mark it poor
                st.corrections, prev_base = [], None
                st.poor_until = end.t + cfg.correction_s
            elif abs(residual) > 1e-9 and cfg.correction_s > 0:
                st.corrections.append((end.t, residual, end.t + cfg.correction_s))
            times = {k.t for k in new}
            for _, _, until in st.corrections:  # where a correction ends: a knot
                if new[0].t < until < new[-1].t and until not in times:
                    new.append(ref.at(until))
                    times.add(until)
            new.sort(key=lambda k: k.t)
    for k in new:
        if end is not None and k.line != end.line:  # no blending across a line change
            st.corrections, prev_base, end = [], None, None
        offset = _correction(st, k.t)
        chain = k.chainage_m + offset
        poor = k.t < st.poor_until
        if pub and pub[-1].line == k.line and prev_base is not None and st.direction:
            d, last = st.direction, pub[-1].chainage_m
            if d * (chain - last) < 0 <= d * (k.chainage_m - prev_base):
                chain = last  # the correction would step back: hold until the fixes pass
        prev_base = k.chainage_m
        pub.append(Knot(k.t, k.line, chain, k.speed_mps, k.ok and not poor))
        st.pub_t.append(k.t)


def _correction(st: TrainState, t: float) -> float:
    """The sum of the corrections still being spread at ``t`` (m)."""
    return sum(
        offset * (until - t) / (until - since)
        for since, offset, until in st.corrections
        if t < until
    )
