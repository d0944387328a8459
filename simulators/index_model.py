"""The fast mode's statistical on-board sensor (``--fidelity index``).

Instead of simulating bogie accelerations and extracting indices from them, the on-board
indices of a train pass are drawn from the paper's observation model (Eq. 3-4):

.. math::

    y = H z + b + e, \\qquad e \\sim N(0, R), \\qquad
    [\\text{Top6}, \\text{Align10}]_{\\text{on-board}} = \\exp(y)\\ \\text{mm},

with z the true state at the time of the pass. The numbers live in the ``index`` section
of ``services/defaults/simulator.json5`` (the study's observation model): on-board indices read low
(b < 0, H below 1 on the diagonal) and Align10 is noisier than Top6, as in the paper's
section 3.2. The calibration service should recover H, b, R from TRC-paired passes.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from schemas import DAY_S, OnboardIndex
from simulators.network import stable_rng
from simulators.truth import Truth, config_pair
from track.network import Network


@dataclass(frozen=True)
class IndexSensorModel:
    """Observation model ``y = H z + b + e``, ``e ~ N(0, R)`` in log space (2 x 2)."""

    H: np.ndarray
    b: np.ndarray
    R: np.ndarray

    def __post_init__(self):
        for name, shape in (("H", (2, 2)), ("b", (2,)), ("R", (2, 2))):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != shape or not np.isfinite(a).all():
                raise ValueError(f"index.{name}: expected finite {shape}, got {a.shape}")
            object.__setattr__(self, name, a)
        if not np.allclose(self.R, self.R.T) or np.linalg.eigvalsh(self.R)[0] <= 0:
            raise ValueError("index.R: must be symmetric positive definite")
        object.__setattr__(self, "_chol", np.linalg.cholesky(self.R))

    @classmethod
    def from_config(cls, config: Mapping) -> IndexSensorModel:
        """From the ``index`` section of the simulator config."""
        try:
            sec = config["index"]
            return cls(sec["H"], sec["b"], sec["R"])
        except KeyError as exc:
            raise ValueError(f"simulator config: index section needs {exc}") from None

    def log_indices(self, z, rng: np.random.Generator) -> np.ndarray:
        """``y = H z + b + e`` for states ``z`` (k, 2)."""
        z = np.asarray(z, dtype=np.float64)
        e = rng.standard_normal(z.shape) @ self._chol.T
        return z @ self.H.T + self.b + e

    def indices(self, z, rng: np.random.Generator) -> np.ndarray:
        """On-board [Top6, Align10] in mm, ``exp(y)``, shape (k, 2)."""
        return np.exp(self.log_indices(z, rng))


def index_pass_events(
    network: Network,
    truth: Truth,
    trains_per_line_per_day: int,
    days: float,
    seed: int,
    *,
    config: Mapping,
    model: IndexSensorModel | None = None,
) -> Iterator[tuple[float, list[OnboardIndex]]]:
    """On-board indices of in-service train passes, ``(t, [OnboardIndex])`` in time order.

    Every simulated day (from ``truth.t``, which must be the start) each line gets
    ``trains_per_line_per_day`` passes, departures evenly spread over the ``index.service_hours``
    with a random offset, alternating direction (even slots run up the chainage, odd
    down; every slot in the line's ``running`` direction on a track of double track). A
    pass runs at ``line_speed_mps * U(index.speed_factor)`` and reaches a segment's middle
    at ``departure + distance / speed``; its indices come from the
    observation model of the train's unit (:class:`simulators.fleet.Fleet`: its vehicle
    class and its sensor; ``model`` instead, if given, for every train) applied to the
    truth at that instant, and its speed factor is its vehicle class's. Train ids are
    ``T{line}-{slot}`` (the same timetable slot every day), the unit is ``index.unit``;
    coverage and quality are 1.

    ``truth`` is advanced by this generator: give it a replica of its own
    (:meth:`Truth.copy` or a new Truth with the same seed) when other generators read
    the truth too.
    """
    from simulators.fleet import Fleet  # fleet builds on this module's IndexSensorModel

    fleet = Fleet.from_config(config, seed)
    sec = config["index"]
    h0, h1 = config_pair(sec, "service_hours", "index")
    unit = str(sec.get("unit", "bogie1"))
    units = {}

    def unit_of(line_id: str, k: int):
        train = f"T{line_id}-{k:02d}"
        if train not in units:
            units[train] = fleet.unit(train, unit)
        return units[train]

    start, n = truth.t, int(trains_per_line_per_day)
    if n < 0:
        raise ValueError(f"trains_per_line_per_day: must be >= 0, got {n}")
    lines = list(network.lines.values())
    mids = {line.id: np.array([s.mid_m for s in line.segments]) for line in lines}
    for day in range(int(np.ceil(days - 1e-9))):
        day0 = start + day * DAY_S
        t_all, seg_all, meta = [], [], []
        for line in lines if n else ():  # no service passes: nothing to draw
            rng = stable_rng(seed, "index-passes", line.id, day)
            factor = np.array([unit_of(line.id, k).speed_factor for k in range(n)]).reshape(n, 2)
            speed = line.line_speed_mps * (
                factor[:, 0] + (factor[:, 1] - factor[:, 0]) * rng.random(n)
            )
            last = h1 * 3600 - line.length_m / speed.min()
            if last < h0 * 3600:
                raise ValueError(f"line {line.id}: a pass does not fit into service hours")
            slots = np.linspace(h0 * 3600, last, n + 1)[:-1] if n else np.zeros(0)
            dep = day0 + slots + rng.uniform(0, (last - h0 * 3600) / max(n, 1), n)
            sl = truth.line_slices[line.id]
            running = getattr(line, "running", "both")
            for k in range(n):
                up = running == "increasing" or (running == "both" and k % 2 == 0)
                dist = mids[line.id] if up else line.length_m - mids[line.id]
                t_all.append(dep[k] + dist / speed[k])
                seg_all.append(np.arange(sl.start, sl.stop))
                meta.append((line.id, k, speed[k], len(dist)))
        if not t_all:
            truth.advance_to(day0 + DAY_S)
            continue
        t, seg = np.concatenate(t_all), np.concatenate(seg_all)
        truth.advance_to(t.max())
        z = truth.z_at(t, seg)
        y = np.empty_like(z)
        lo = 0
        for line_id, k, _, m in meta:  # noise keyed per pass: independent of loop order
            y[lo : lo + m] = (model or unit_of(line_id, k).model).indices(
                z[lo : lo + m], stable_rng(seed, "index", line_id, day, k)
            )
            lo += m
        train = np.concatenate([[f"T{line_id}-{k:02d}"] * m for line_id, k, _, m in meta])
        speed = np.concatenate([[v] * m for _, _, v, m in meta])
        for j in np.argsort(t, kind="stable"):
            line_id, seg_id = truth.keys[seg[j]]
            msg = OnboardIndex(
                line=line_id,
                segment=seg_id,
                train=str(train[j]),
                unit=unit,
                t=float(t[j]),
                top6_mm=float(y[j, 0]),
                align10_mm=float(y[j, 1]),
                speed_mps=float(speed[j]),
                coverage=1.0,
                quality=1.0,
            )
            yield float(t[j]), [msg]
