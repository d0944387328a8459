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

from schemas import DAY_S, Message
from simulators.fleet import Fleet
from simulators.index_model import index_pass_events
from simulators.profile import LineProfile
from simulators.train import TrainSimulator
from simulators.trc import trc_events
from simulators.truth import Truth, truth_events
from track.network import Network


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
                if not dropped:  # a lost chunk's seq is skipped: ingestion sees a gap
                    messages.append(chunk)
            messages.extend(train.gps_fixes(t, t + 1.0))
        yield t, messages


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
