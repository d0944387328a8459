"""The simulated world: every generator of the simulator merged into one time-ordered stream.

``world_events`` yields ``(t, [message, …])`` in event-time order, where messages are the
wire Structs of ``schemas``: MaintenanceEvent (tamping), TrcRecord (and the campaign's
OnboardIndex), and either OnboardIndex of service passes (``fidelity="index"``: the
statistical sensor model) or RawChunk and GpsFix of every train (``fidelity="raw"``: the
full bogie physics). Publishing is a thin loop over it (``simulators/gateway.py``).

Every source keeps its own replica of the truth (same network, config, start and seed give
the same path), so merging never lets one source advance the truth under another.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import msgspec
import numpy as np

from schemas import DAY_S, SUPPLY_CHANNEL, Message, NDArray, OnboardIndex, RawChunk
from simulators.fleet import Fleet
from simulators.index_model import IndexSensorModel
from simulators.network import stable_rng
from simulators.profile import LineProfile
from simulators.train import TrainSimulator
from simulators.trc import trc_events
from simulators.truth import Truth, config_pair, truth_events
from track.network import Network

VERTICAL_CHANNELS = ("left_z", "right_z", SUPPLY_CHANNEL)  # what a vertical-only unit sends


@dataclass(frozen=True)
class WorldSpec:
    """What to simulate."""

    network: Network
    config: Mapping  # services/defaults/simulator.json5
    start_t: float  # epoch s
    days: float
    seed: int
    trains: int  # raw: trains running; index: service passes per line per day
    fidelity: str = "index"  # "index" | "raw"
    units: int = 1  # on-board units per train (raw)

    def __post_init__(self):
        if self.fidelity not in ("index", "raw"):
            raise ValueError(f"fidelity: {self.fidelity!r} is not 'index' or 'raw'")
        if self.days <= 0 or self.trains < 0 or self.units < 1:
            raise ValueError("days must be > 0, trains >= 0 and units >= 1")


def raw_train_events(spec: WorldSpec) -> Iterator[tuple[float, list[Message]]]:
    """RawChunk (one per unit, ~1 s) and GpsFix (1 Hz) of ``spec.trains`` trains.

    Trains are spread over the lines in turn (train i on line i mod L), each at its own
    phase of its route cycle; on a track that runs one way a train sends nothing while on
    its way back (:meth:`TrainSimulator.in_service`: that runs on the other track). Track
    profiles follow the truth day by day: a segment's amplitude is exp(z) of that day and
    its shape changes after a tamping (epoch).
    """
    truth = Truth(spec.network, spec.config, spec.start_t, spec.seed)
    lines = list(spec.network.lines.values())
    profiles = {
        line.id: LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], spec.seed)
        for line in lines
    }

    def refresh_profiles() -> None:
        for line_id, rows in truth.line_slices.items():
            profiles[line_id].update(truth.z[rows], truth.epoch[rows])

    refresh_profiles()
    fleet = Fleet.from_config(spec.config, spec.seed)

    def train(i: int) -> TrainSimulator:
        train_id, line = f"T{i:03d}", lines[i % len(lines)]
        units = [fleet.unit(train_id, f"u{u}") for u in range(spec.units)]
        return TrainSimulator(
            train_id,
            line,
            profiles[line.id],
            spec.seed,
            units=spec.units,
            start_t=spec.start_t,
            config=fleet.train_config(train_id),
            sensors=[(u.gain, u.mount_rad) for u in units],
        )

    trains = [train(i) for i in range(spec.trains)]
    vertical_only = {
        (t.train_id, u)
        for t in trains
        for u in range(spec.units)
        if fleet.unit(t.train_id, f"u{u}").vertical_only
    }
    day = 0
    for k in range(int(spec.days * DAY_S)):
        t = spec.start_t + k
        if int(k // DAY_S) != day:
            day = int(k // DAY_S)
            truth.advance_to(spec.start_t + day * DAY_S)
            refresh_profiles()
        messages: list[Message] = []
        for train in trains:
            if not train.in_service(t):
                continue
            for unit in range(spec.units):
                chunk, dropped = train.raw_chunk(k, unit)
                if (train.train_id, unit) in vertical_only:
                    chunk = vertical_channels(chunk)
                if not dropped:  # a lost chunk's seq is skipped: ingestion sees a gap
                    messages.append(chunk)
            messages.extend(train.gps_fixes(t, t + 1.0))
        yield t, messages


def vertical_channels(chunk: RawChunk) -> RawChunk:
    """``chunk`` as a unit with a vertical sensor only sends it."""
    cols = [chunk.channels.index(c) for c in VERTICAL_CHANNELS]
    samples = NDArray.of(chunk.samples.array()[:, cols], "f4")
    return msgspec.structs.replace(chunk, channels=list(VERTICAL_CHANNELS), samples=samples)


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
        top_only = {tr for tr in set(train.tolist()) if model is None and units[tr].vertical_only}
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
                align10_mm=None if train[j] in top_only else float(y[j, 1]),
                speed_mps=float(speed[j]),
                coverage=1.0,
                quality=1.0,
                indicators=["top6"] if train[j] in top_only else ["top6", "align10"],
            )
            yield float(t[j]), [msg]


def world_events(spec: WorldSpec) -> Iterator[tuple[float, list[Message]]]:
    """All sources of ``spec`` merged in event-time order."""
    sources = [
        truth_events(spec.network, spec.config, spec.start_t, spec.days, spec.seed),
        trc_events(
            spec.network, spec.config, spec.start_t, spec.days, spec.seed, fidelity=spec.fidelity
        ),
    ]
    if spec.fidelity == "index":
        truth = Truth(spec.network, spec.config, spec.start_t, spec.seed)
        sources.append(
            index_pass_events(
                spec.network, truth, spec.trains, spec.days, spec.seed, config=spec.config
            )
        )
    elif spec.trains:
        sources.append(raw_train_events(spec))
    end = spec.start_t + spec.days * DAY_S
    for t, messages in heapq.merge(*sources, key=lambda item: item[0]):
        if t >= end:
            break
        if messages:
            yield t, messages


def message_count(messages: list[Message]) -> dict[str, int]:
    """Messages per type name, for progress displays."""
    counts: dict[str, int] = {}
    for message in messages:
        name = type(message).__name__
        counts[name] = counts.get(name, 0) + 1
    return counts
