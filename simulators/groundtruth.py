"""The ground-truth file: what the world really was, for scoring estimates against.

One SQLite file (stdlib ``sqlite3``) per simulation. ``seg`` is the segment's position in
the network's order (``segments.seg``); ``line``/``segment`` are the wire ids; times are
epoch seconds; ``z_*`` are natural logs of mm; rates per day.

=========  ====================================================================================
table      columns
=========  ====================================================================================
meta       key, value (text): ``schema_version``, ``seed``, ``start_t``, ``days``,
           ``segment_length_m``, ``snapshot_every_days``, ``config`` (JSON of the simulator
           config), ``network`` (GeoJSON of the lines)
segments   seg, line, segment, idx, start_m, end_m, class, mu_top, mu_align, sigma_tt,
           sigma_ta, sigma_aa, zp_top, zp_align, szp_tt, szp_ta, szp_aa, limit_top_mm,
           limit_align_mm (true per-segment parameters; sigma = Sigma per day, szp = Sigma_z+)
truth      seg, line, segment, t, z_top, z_align, epoch: snapshots of every segment on the
           truth's grid (every ``snapshot_every_days``), the first at ``start_t``
tamping    seg, line, segment, t, t_start, t_end, event_id, epoch, cause, z_top_before,
           z_align_before, z_top_after, z_align_after, report, t_reported: every true
           tamping (t the true time, [t_start, t_end] what the MaintenanceEvent reported,
           ``report`` ``on_time``, ``late`` or ``never``, t_reported when it was published,
           NULL if never)
units      train, unit, vehicle_class, h_tt, h_ta, h_at, h_aa, b_top, b_align, gain,
           offset_top, offset_align, mount_deg: every in-service unit that published
           (``simulators/fleet.py``): its vehicle class, its sensor's gain and, in the
           fast mode, the observation model its indices follow (H, b of the class with the
           sensor's gain and mounting offset in b), in the raw mode its mounting tilt
trc        seg, line, segment, t, run_id, top6_mm, align10_mm, z_top, z_align: every
           published TrcRecord with the true z at its time
onboard    seg, line, segment, t, train, unit, run_id, top6_mm, align10_mm, z_top, z_align:
           every published OnboardIndex with the true z at its time
=========  ====================================================================================

The writer keeps its own replica of the truth (same network, config, start and seed as
the generators), advances it with the stream of published messages and reads the true z
at each message's time, so the publishing loop only has to hand it what it published::

    with GroundTruthWriter(path, network, config, start_t, days, seed) as gt:
        for t, msgs in heapq.merge(..., key=lambda e: e[0]):
            publish(msgs)
            gt.record(t, msgs)
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from schemas import DAY_S, Message, OnboardIndex, RawChunk, TrcRecord
from simulators.fleet import Fleet
from simulators.truth import Tamping, Truth
from track.network import Network

SCHEMA_VERSION = 2
_TEXT = {"line", "segment", "class", "run_id", "train", "unit", "event_id", "cause", "report"}
_TEXT |= {"vehicle_class"}
_TABLES = {
    "meta": "key TEXT PRIMARY KEY, value TEXT",
    "segments": (
        "seg INTEGER PRIMARY KEY, line TEXT, segment TEXT, idx INTEGER, start_m REAL, "
        "end_m REAL, class TEXT, mu_top REAL, mu_align REAL, sigma_tt REAL, sigma_ta REAL, "
        "sigma_aa REAL, zp_top REAL, zp_align REAL, szp_tt REAL, szp_ta REAL, szp_aa REAL, "
        "limit_top_mm REAL, limit_align_mm REAL"
    ),
    "truth": "seg INTEGER, line TEXT, segment TEXT, t REAL, z_top REAL, z_align REAL, epoch INT",
    "tamping": (
        "seg INTEGER, line TEXT, segment TEXT, t REAL, t_start REAL, t_end REAL, event_id TEXT, "
        "epoch INTEGER, cause TEXT, z_top_before REAL, z_align_before REAL, z_top_after REAL, "
        "z_align_after REAL, report TEXT, t_reported REAL"
    ),
    "trc": (
        "seg INTEGER, line TEXT, segment TEXT, t REAL, run_id TEXT, top6_mm REAL, "
        "align10_mm REAL, z_top REAL, z_align REAL"
    ),
    "onboard": (
        "seg INTEGER, line TEXT, segment TEXT, t REAL, train TEXT, unit TEXT, run_id TEXT, "
        "top6_mm REAL, align10_mm REAL, z_top REAL, z_align REAL"
    ),
    "units": (
        "train TEXT, unit TEXT, vehicle_class TEXT, h_tt REAL, h_ta REAL, h_at REAL, h_aa REAL, "
        "b_top REAL, b_align REAL, gain REAL, offset_top REAL, offset_align REAL, "
        "mount_deg REAL"
    ),
}


class GroundTruthWriter:
    """Writes the ground-truth file of one simulation (context manager; overwrites ``path``).

    Parameters
    ----------
    path : str or Path
    network, config, start_t, days, seed
        As given to the generators (``config`` is the simulator config dict).
    snapshot_every_days : float
        Truth snapshot interval (a multiple of the truth's step); thin it for big runs.
    batch_rows : int
        Rows buffered per table before an ``executemany``.
    """

    def __init__(
        self,
        path: str | Path,
        network: Network,
        config: Mapping,
        start_t: float,
        days: float,
        seed: int,
        *,
        snapshot_every_days: float = 1.0,
        batch_rows: int = 50_000,
    ):
        self.path = Path(path)
        self.truth = Truth(network, config, start_t, seed)
        self._fleet = Fleet.from_config(config, seed)
        self._units: set[tuple[str, str]] = set()
        self.end_t = start_t + days * DAY_S
        self._every = max(1, round(snapshot_every_days * DAY_S / self.truth.step_s))
        self._steps = 0
        self._batch = batch_rows
        self._rows: dict[str, list[tuple]] = {name: [] for name in _TABLES}
        self._index = {key: i for i, key in enumerate(self.truth.keys)}
        self.path.unlink(missing_ok=True)
        self._db = sqlite3.connect(self.path)
        self._db.execute("PRAGMA journal_mode=OFF")  # a scratch file: rewritten on every run
        self._db.execute("PRAGMA synchronous=OFF")
        for name, columns in _TABLES.items():
            self._db.execute(f"CREATE TABLE {name} ({columns})")
        meta = {
            "schema_version": SCHEMA_VERSION,
            "seed": int(seed),
            "start_t": float(start_t),
            "days": float(days),
            "segment_length_m": network.segment_length_m,
            "snapshot_every_days": self._every * self.truth.step_s / DAY_S,
            "config": json.dumps(config, default=str),
            "network": json.dumps(network.to_geojson(include_segments=False)),
        }
        self._rows["meta"] = [(k, str(v)) for k, v in meta.items()]
        tr = self.truth
        names = tr.class_names
        for i, (line, seg) in enumerate(network.segments()):
            s, zp = tr.sigma[i], tr.sigma_z_plus[i]
            lim = np.exp(tr.log_limits[i])
            self._rows["segments"].append(
                (i, line.id, seg.id, seg.index, seg.start_m, seg.end_m, names[tr.klass[i]])
                + (*tr.mu[i], s[0, 0], s[0, 1], s[1, 1], *tr.z_plus[i], zp[0, 0], zp[0, 1])
                + (zp[1, 1], *lim)
            )
        self._snapshot()
        self._flush()

    def __enter__(self) -> GroundTruthWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close(finish=exc[0] is None)

    def _snapshot(self) -> None:
        tr = self.truth
        z = tr.z.tolist()
        self._rows["truth"].extend(
            (i, line, seg, tr.t, z[i][0], z[i][1], int(tr.epoch[i]))
            for i, (line, seg) in enumerate(tr.keys)
        )

    def _add_tamping(self, taps: Iterable[Tamping]) -> None:
        self._rows["tamping"].extend(
            (tp.seg, tp.line, tp.segment, tp.t, tp.t_start, tp.t_end, tp.event_id, tp.epoch)
            + (tp.cause, *map(float, tp.z_before), *map(float, tp.z_after))
            + (tp.report, tp.t_reported)
            for tp in taps
        )

    def advance_to(self, t: float) -> None:
        """Step the truth replica to ``t``, writing snapshots and tampings on the way."""
        while self.truth.t < min(t, self.end_t):
            self._add_tamping(self.truth.step())
            self._steps += 1
            if self._steps % self._every == 0:
                self._snapshot()
        if sum(map(len, self._rows.values())) >= self._batch:
            self._flush()

    def record(self, t: float, msgs: Iterable[Message]) -> None:
        """Record published messages of time ``t`` (in time order across calls).

        TrcRecord and OnboardIndex rows get the true z at their time; MaintenanceEvents
        are skipped (the tamping table comes from the truth, with the same event ids).
        """
        self.advance_to(t)
        for m in msgs:
            if isinstance(m, RawChunk) and (m.train, m.unit) not in self._units:
                self._add_unit(m.train, m.unit)
            if not isinstance(m, TrcRecord | OnboardIndex):
                continue
            i = self._index[(m.line, m.segment)]
            z_top, z_align = self.truth.z_at(m.t, i).tolist()
            if isinstance(m, TrcRecord):
                row = (i, m.line, m.segment, m.t, m.run_id, m.top6_mm, m.align10_mm)
                self._rows["trc"].append(row + (z_top, z_align))
            else:
                row = (i, m.line, m.segment, m.t, m.train, m.unit, m.run_id)
                self._rows["onboard"].append(row + (m.top6_mm, m.align10_mm, z_top, z_align))
                if not m.run_id and (m.train, m.unit) not in self._units:
                    self._add_unit(m.train, m.unit)

    def _add_unit(self, train: str, unit: str) -> None:
        u = self._fleet.unit(train, unit)
        self._units.add((train, unit))
        self._rows["units"].append(
            (train, unit, u.vehicle_class, *u.model.H.ravel().tolist(), *u.model.b.tolist())
            + (u.gain, *u.offset.tolist(), float(np.rad2deg(u.mount_rad)))
        )

    def _flush(self) -> None:
        for name, rows in self._rows.items():
            if rows:
                marks = ",".join("?" * len(rows[0]))
                self._db.executemany(f"INSERT INTO {name} VALUES ({marks})", rows)
                rows.clear()
        self._db.commit()

    def close(self, finish: bool = True) -> None:
        """Advance to the end of the period (if ``finish``), write, index and close."""
        if self._db is None:
            return
        if finish:
            self.advance_to(self.end_t)
        self._flush()
        for name in ("truth", "tamping", "trc", "onboard"):
            self._db.execute(f"CREATE INDEX {name}_seg_t ON {name} (seg, t)")
        self._db.commit()
        self._db.close()
        self._db = None


def _columns(db: sqlite3.Connection, table: str, order: str) -> dict[str, list]:
    """A table as {column: values}, rows ordered by ``order``."""
    names = [c[1] for c in db.execute(f"PRAGMA table_info({table})")]
    rows = db.execute(f"SELECT * FROM {table} ORDER BY {order}").fetchall()
    return {name: [r[k] for r in rows] for k, name in enumerate(names)}


def load_truth(path: str | Path) -> dict:
    """Read a ground-truth file into numpy arrays.

    Returns
    -------
    dict
        ``meta`` (dict of str), per segment (S,): ``line``, ``segment``, ``class``,
        ``start_m``, ``end_m``, ``mu`` (S, 2), ``sigma`` (S, 2, 2), ``z_plus`` (S, 2),
        ``sigma_z_plus`` (S, 2, 2), ``limits_mm`` (S, 2); snapshots ``t`` (T,), ``z``
        (T, S, 2), ``epoch`` (T, S); and for ``tamping``, ``trc``, ``onboard`` one array
        per column named ``<table>_<column>`` (``seg``, ``t``, ...), plus ``trc_mm``,
        ``trc_z``, ``onboard_mm``, ``onboard_z`` (N, 2).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth file {path} not found")
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        out: dict = {"meta": dict(db.execute("SELECT key, value FROM meta"))}
        seg = _columns(db, "segments", "seg")
        f = {k: np.asarray(v, dtype=np.float64) for k, v in seg.items() if k not in _TEXT}
        for k in ("line", "segment", "class"):
            out[k] = np.asarray(seg[k], dtype=str)
        out["start_m"], out["end_m"] = f["start_m"], f["end_m"]
        out["mu"] = np.stack([f["mu_top"], f["mu_align"]], -1)
        out["z_plus"] = np.stack([f["zp_top"], f["zp_align"]], -1)
        out["limits_mm"] = np.stack([f["limit_top_mm"], f["limit_align_mm"]], -1)
        for name, p in (("sigma", "sigma_"), ("sigma_z_plus", "szp_")):
            tt, ta, aa = f[p + "tt"], f[p + "ta"], f[p + "aa"]
            out[name] = np.stack([np.stack([tt, ta], -1), np.stack([ta, aa], -1)], -2)
        n_seg = len(out["line"])
        rows = db.execute("SELECT t, z_top, z_align, epoch FROM truth ORDER BY t, seg").fetchall()
        snap = np.asarray(rows, dtype=np.float64).reshape(-1, n_seg, 4)
        out["t"], out["z"], out["epoch"] = snap[:, 0, 0], snap[..., 1:3], snap[..., 3].astype(int)
        for c, values in _columns(db, "units", "train, unit").items():
            out[f"units_{c}"] = np.asarray(values, dtype=str if c in _TEXT else np.float64)
        for table in ("tamping", "trc", "onboard"):
            for c, values in _columns(db, table, "t, seg").items():
                out[f"{table}_{c}"] = np.asarray(values, dtype=str if c in _TEXT else np.float64)
            out[f"{table}_seg"] = out[f"{table}_seg"].astype(np.int64)
        for table in ("trc", "onboard"):
            out[f"{table}_mm"] = np.stack([out[f"{table}_top6_mm"], out[f"{table}_align10_mm"]], -1)
            out[f"{table}_z"] = np.stack([out[f"{table}_z_top"], out[f"{table}_z_align"]], -1)
        out["tamping_epoch"] = out["tamping_epoch"].astype(np.int64)
        return out
    finally:
        db.close()
