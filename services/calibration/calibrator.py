r"""Live calibration core: pairs TRC records with on-board indices, fits the observation model
and builds the degradation posteriors per group. Pure: no Zenoh, no clock, no I/O.

Conventions shared with the other services: time in days (epoch s / DAY_S) inside the maths,
``z = ln([top6_mm, align10_mm])`` of a TRC record, ``y = ln`` of an on-board index's values.

Use::

    core = Calibrator(CalibratorConfig(), state=store.load())   # or state=None when new
    outputs = core.step([trc, index, tamping, ...])   # new Calibration / DegradationPosterior
    store.apply(core.drain_changes())                  # persist what changed, one transaction

The rules live in modules of their own, each with its docstring: :mod:`.pairing` (which
record an index pairs with), :mod:`.refit` (the observation model's refit, the swap rule,
outlying pairs), :mod:`.units` (per-unit models), :mod:`.groups` (posterior groups),
:mod:`.initial` (initial models), :mod:`.moves` (how far a model moved); :mod:`.state` holds
what a store persists. This module keeps the state, the bookkeeping of events and pairs, and
the publication rule.

Publication rule (model updates without storms)
    Every new version makes the filtering service re-run the segments it applies to, so an
    accepted fit or a rebuilt posterior (a *candidate*) is **held**, and replaces the model in
    force (is published, version in force + 1) only when both hold:

    1. **it differs materially** from the model in force: some parameter moved by more than
       ``material_se`` (default 1) of its standard errors. For the Calibration
       (:func:`calibration_change`) the least-squares standard errors of ``H`` and ``b`` and
       the sampling error of ``R`` (relative ``sqrt(2 / (N - n - 1))`` on the diagonal), all
       of the candidate's fit; for a posterior (:func:`posterior_change`) the posterior mean of
       any element of ``mu``, ``Sigma``, ``z+`` or ``Sigma_z+`` moved by more than the
       candidate's posterior sd of it (both from the draws). A model with nothing in force
       (the first fit without initial models, a new group) always differs; an initial model
       is replaced by the first candidate that differs from it by this rule;
    2. **the rate limit** lets it out: at least ``min_publish_interval_days`` (default 1) of
       event time since the version in force was published. Event time is the newest time
       (TRC ``t``, index ``t``, tamping ``t_end``) that ``event_time_quorum`` segments have
       reached (:attr:`Calibrator.now`), never the clock. An initial model is not rate-limited.

    Both are judged against the model **in force**, not the previous candidate, so many small
    moves that add up to a material one are published. Nothing is lost while held: the pairs
    and increments stay and the next candidate is fitted on all of them; a newer candidate
    replaces the held one (material or not, judged afresh); a material candidate held by the
    rate limit is published at the first :meth:`Calibrator.flush` once event time passes the
    limit, whether or not anything was refitted since. The swap rule judges each refit
    against the newest accepted fit, so a worse fit is never held nor published. With
    ``material_se = 0`` and ``min_publish_interval_days = 0`` every accepted change is
    published at once (no publication rule). Counted: ``changes_immaterial``,
    ``publications_delayed``, ``calibrations_published``, ``posteriors_published``. The held
    candidates, the publication time of each model in force and event time are persisted.

Robustness (one outlier cannot blow up a model)
    Every model is checked (:func:`robust.check_model`: finite, SPD covariances) before it is
    held and again before it is published; TRC records that the data blame (a spike, a newest
    record beyond the physical rate bound, a post-tamping level far off the network's, a
    record dated far after event time) are left out of the increments and levels
    (:func:`robust.screen_segment`); a pooled posterior moved beyond ``max_move_sd`` by one
    segment alone is held; a few wild pairs are quarantined before the swap rule judges a
    refit. What is left out is logged, counted and returned by
    :meth:`Calibrator.drain_quarantined` (the adapter's dead letters). See
    services/calibration/README.md.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import numpy as np

from schemas import (
    DAY_S,
    INDICATORS,
    ONBOARD_INDICES,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    NDArray,
    OnboardIndex,
    SchemaError,
    TrcRecord,
)
from schemas.keys import SegmentId
from services.calibration.config import CalibratorConfig
from services.calibration.groups import (
    build_posterior,
    fingerprint,
    group_inputs,
    one_segment_move,
)
from services.calibration.moves import Move, calibration_change, posterior_change
from services.calibration.pairing import ln_mm, match_record, oldest_waiting, partial_record_reason
from services.calibration.posterior import SegmentIncrements, segment_increments
from services.calibration.refit import outlying_pairs, worse
from services.calibration.regression import fit_observation
from services.calibration.robust import (
    Rules,
    check_model,
    network_references,
    raw_pieces,
    screen_segment,
)
from services.calibration.state import (
    CALIBRATION_KEY,
    Changes,
    Event,
    Model,
    ModelEntry,
    Pair,
    Quarantine,
    StoredState,
    index_id,
    is_calibration_key,
    maintenance_id,
    trc_id,
    unit_key,
)
from services.calibration.units import pair_design, unit_calibration, units_due
from services.drift_diffusion import CalibrationError

log = logging.getLogger(__name__)

_AHEAD = "dated "  # how robust.screen_segment's reason for a record ahead of event time begins
_N = len(INDICATORS)


class Calibrator:
    """The calibration service's state and rules; see the module docstring.

    Feed events with :meth:`ingest` (or :meth:`step`), call :meth:`flush` to fit/rebuild,
    persist :meth:`drain_changes`. Single-threaded by design.
    """

    def __init__(self, config: CalibratorConfig | None = None, state: StoredState | None = None):
        self.config = config or CalibratorConfig()
        self.stats: Counter[str] = Counter()
        self.rejections: deque[str] = deque(maxlen=100)  # reasons of rejected refits, newest last
        self._trc: dict[SegmentId, dict[str, TrcRecord]] = {}
        self._trc_times: dict[SegmentId, list[tuple[float, str]]] = {}  # sorted (t, run_id)
        self._complete_times: dict[SegmentId, list[tuple[float, str]]] = {}  # of all indicators
        self._maint: dict[SegmentId, dict[str, MaintenanceEvent]] = {}
        self._pending: dict[SegmentId, dict[str, OnboardIndex]] = {}
        self._pairs: list[Pair] = []
        self._partial_pairs: list[Pair] = []  # of indices of some indices (units' fits only)
        self._quarantined: list[Pair] = []
        self._paired: set[str] = set()
        self._models: dict[str, ModelEntry] = {}  # in force: published
        self._held: dict[str, ModelEntry] = {}  # newest accepted, not published (yet)
        self._material: set[str] = set()  # held keys that differ materially from in force
        self._now = -math.inf  # event time (epoch s): see _note_time
        # newest event time of the event_time_quorum segments furthest ahead: (t, line, seg)
        self._clock_top: list[tuple[float, str, str]] = []
        self._history: dict[SegmentId, tuple[list[TrcRecord], np.ndarray, np.ndarray, list]] = {}
        self._raw: dict[SegmentId, tuple[np.ndarray, np.ndarray]] = {}  # robust.raw_pieces
        self._screened: dict[SegmentId, dict[str, str]] = {}  # run_id -> why it is left out
        self._reported: set[str] = set()  # trc ids reported left out (and still left out)
        self._newest_used: dict[SegmentId, float] = {}  # epoch s of the newest record used
        self._outbox: list[Quarantine] = []  # to report (dead letters), see drain_quarantined
        self._screened_now = -math.inf  # event time at the last screening
        self._refused: dict[str, str] = {}  # group -> fingerprint whose build failed
        self._increments: dict[SegmentId, SegmentIncrements] = {}
        self._dirty: set[SegmentId] = set()
        self._attempt_at = 0  # number of pairs at the last fit attempt
        self._unit_fit_at: dict[tuple[str, str], int] = {}  # a unit's pairs at its last fit
        self._changes = Changes()
        if state is not None:
            self._restore(state)

    # --- state ---------------------------------------------------------------------------

    def _restore(self, state: StoredState) -> None:
        for rec in state.trc:
            self._add_trc(rec)
        for ev in state.maintenance:
            known = self._maint.setdefault((ev.line, ev.segment), {})
            held = known.get(maintenance_id(ev))
            if held is None or ev.rank > held.rank:
                known[maintenance_id(ev)] = ev
        for idx in state.pending:
            self._pending.setdefault((idx.line, idx.segment), {})[index_id(idx)] = idx
        stored = (self._pairs, state.pairs), (self._quarantined, state.quarantined)
        for kept, pairs in (*stored, (self._partial_pairs, state.partial_pairs)):
            kept.extend(pairs)
            self._paired.update(pair.index_id for pair in pairs)
        for entry in state.models:
            self._models[entry.key] = entry
        for entry in state.held:
            self._held[entry.key] = entry
        self._material = set(state.meta.get("material", [])) & set(self._held)
        now = state.meta.get("now")
        self._now = -math.inf if now is None else float(now)
        self._clock_top = [(float(t), line, seg) for t, line, seg in state.meta.get("clock", [])]
        self._reported = set(state.meta.get("reported", []))
        self._attempt_at = int(state.meta.get("attempt_at", 0))
        # kept, or a restart refits every unit: versions an undisturbed run never publishes
        self._unit_fit_at = {(t, u): int(n) for t, u, n in state.meta.get("unit_fit_at", [])}
        self.stats.update(state.meta.get("stats", {}))
        self.rejections.extend(state.meta.get("rejections", []))
        self._dirty = set(self._trc) | set(self._maint)
        self._update_increments()
        self._dirty.clear()

    def _meta(self) -> dict[str, Any]:
        return {
            "attempt_at": self._attempt_at,
            "unit_fit_at": [[t, u, n] for (t, u), n in sorted(self._unit_fit_at.items())],
            "now": self._now if math.isfinite(self._now) else None,
            "clock": [list(c) for c in self._clock_top],
            "reported": sorted(self._reported),
            "material": sorted(self._material),
            "stats": dict(self.stats),
            "rejections": list(self.rejections),
        }

    def drain_changes(self) -> Changes:
        """What to persist since the last call (the store applies it in one transaction)."""
        changes, self._changes = self._changes, Changes()
        if changes:
            changes.meta = self._meta()
        return changes

    @property
    def pairs(self) -> list[Pair]:
        """The pairs fits use, in arrival order."""
        return list(self._pairs)

    @property
    def quarantined(self) -> list[Pair]:
        """Pairs set aside by rejected refits."""
        return list(self._quarantined)

    @property
    def calibration(self) -> Calibration | None:
        entry = self._models.get(CALIBRATION_KEY)
        return entry.message if entry is not None else None  # type: ignore[return-value]

    @property
    def unit_calibrations(self) -> dict[tuple[str, str], Calibration]:
        """The units' own Calibrations in force, by ``(train, unit)``."""
        return {
            (e.message.train, e.message.unit): e.message  # type: ignore[union-attr]
            for k, e in sorted(self._models.items())
            if k != CALIBRATION_KEY and is_calibration_key(k)
        }

    @property
    def posteriors(self) -> dict[str, DegradationPosterior]:
        return {
            k: e.message  # type: ignore[misc]
            for k, e in sorted(self._models.items())
            if not is_calibration_key(k)
        }

    def models(self) -> list[Model]:
        """The models in force: the fleet's Calibration (if any) first, then the units', then
        posteriors by group."""
        cal = self.calibration
        units = list(self.unit_calibrations.values())
        return ([cal] if cal is not None else []) + units + list(self.posteriors.values())

    @property
    def held(self) -> dict[str, Model]:
        """Accepted models not published (yet), by key: an immaterial change, or a material
        one waiting for the rate limit."""
        return {k: e.message for k, e in sorted(self._held.items())}

    @property
    def published_at(self) -> dict[str, float | None]:
        """Event time (epoch s) each model in force was published at (None: initial model)."""
        return {k: e.published_at for k, e in sorted(self._models.items())}

    @property
    def now(self) -> float:
        """Event time (epoch s; -inf before any event): the newest time that
        ``event_time_quorum`` segments have reached (with fewer segments known, the oldest of
        their newest times), never going back. One segment's events, however late they are
        dated (a record dated 2099), cannot move it: the publication rate limit runs on it."""
        return self._now

    def drain_quarantined(self) -> list[Quarantine]:
        """What was left out since the last call, with reasons (the adapter's dead letters)."""
        out, self._outbox = self._outbox, []
        return out

    def _note_time(self, seg: SegmentId, t: float) -> None:
        top = self._clock_top
        for i, (tt, line, segment) in enumerate(top):
            if (line, segment) == seg:
                if t > tt:
                    top[i] = (t, line, segment)
                break
        else:
            top.append((t, *seg))
        top.sort(reverse=True)
        del top[self.config.event_time_quorum :]
        self._now = max(self._now, top[-1][0])

    def n_pending(self) -> int:
        return sum(len(p) for p in self._pending.values())

    # --- events ----------------------------------------------------------------------------

    def step(self, events: Iterable[Event]) -> list[Model]:
        """Ingest ``events`` in order, then :meth:`flush`: the new models, if any."""
        for event in events:
            self.ingest(event)
        return self.flush()

    def ingest(self, event: Event) -> bool:
        """Take one event; False if it was a duplicate or otherwise not used.

        Every event taken (used or not) counts for event time (:attr:`now`); an event that
        raises does not.
        """
        match event:
            case TrcRecord():
                used, t = self._ingest_trc(event), event.t
            case OnboardIndex():
                used, t = self._ingest_index(event), event.t
            case MaintenanceEvent():
                used, t = self._ingest_maintenance(event), event.t_end
            case _:
                raise TypeError(f"not a calibration input: {type(event).__name__}")
        self._note_time((event.line, event.segment), t)
        return used

    def install_initial(
        self, calibration: Calibration | None, posteriors: Iterable[DegradationPosterior]
    ) -> list[Model]:
        """Install initial (prior) models where no model exists yet; returns those installed."""
        installed: list[Model] = []
        if calibration is not None and CALIBRATION_KEY not in self._models:
            self._set_model(ModelEntry(CALIBRATION_KEY, calibration, prior=True))
            installed.append(calibration)
        for post in posteriors:
            if post.group not in self._models:
                self._set_model(ModelEntry(post.group, post, fingerprint="prior", prior=True))
                installed.append(post)
        return installed

    def _add_trc(self, rec: TrcRecord) -> None:
        seg = (rec.line, rec.segment)
        self._trc.setdefault(seg, {})[rec.run_id] = rec
        bisect.insort(self._trc_times.setdefault(seg, []), (rec.t, rec.run_id))
        if len(rec.indicators) == _N:
            bisect.insort(self._complete_times.setdefault(seg, []), (rec.t, rec.run_id))

    def _ingest_trc(self, rec: TrcRecord) -> bool:
        seg = (rec.line, rec.segment)
        known = self._trc.get(seg, {})
        if rec.run_id in known:
            self.stats["trc_duplicates"] += 1
            if known[rec.run_id] != rec:
                log.warning("TRC record %s differs from the one kept; ignored", trc_id(rec))
            return False
        if any(r.t == rec.t for r in known.values()):
            self.stats["trc_duplicates"] += 1
            log.warning("TRC record %s: segment already has a record at t=%r", trc_id(rec), rec.t)
            return False
        self._add_trc(rec)
        self._changes.trc.append(rec)
        self.stats["trc"] += 1
        if len(rec.indicators) < _N:  # used by the posteriors on what it measured (.groups)
            self.stats["trc_partial"] += 1
        self._dirty.add(seg)
        # pending indices of the segment that this record completes
        pending = self._pending.get(seg, {})
        for iid, idx in list(pending.items()):
            match = self._match(idx)
            if match is not None and match.run_id == rec.run_id:
                del pending[iid]
                self._changes.pending_removed.append(iid)
                self._add_pair(idx, iid, rec)
        oldest = self._oldest_waiting(seg)
        for iid in [iid for iid, idx in pending.items() if idx.t < oldest]:
            self._drop_pending(seg, iid)
        return True

    def _oldest_waiting(self, seg: SegmentId) -> float:
        """Indices of ``seg`` older than this (epoch s) no longer wait for a TRC record."""
        return oldest_waiting(self._trc_times.get(seg), self.config.index_window_days)

    def _drop_pending(self, seg: SegmentId, iid: str) -> None:
        del self._pending[seg][iid]
        self._changes.pending_removed.append(iid)
        self.stats["index_expired"] += 1

    def _match(self, idx: OnboardIndex) -> TrcRecord | None:
        """The TRC record ``idx`` pairs with among those known, if any: by time, a record of
        every indicator only (one of some would make no pair, see :meth:`_add_pair`)."""
        seg = (idx.line, idx.segment)
        return match_record(
            self._trc.get(seg), self._complete_times.get(seg, []), idx, self.config.tolerance_days
        )

    def _add_pair(self, idx: OnboardIndex, iid: str, rec: TrcRecord) -> None:
        if (why := partial_record_reason(iid, rec)) is not None:
            self._paired.add(iid)
            self.stats["index_record_partial"] += 1
            log.info("%s", why)
            self._outbox.append(Quarantine("index", idx.line, idx.segment, why))
            return
        pair = Pair(idx.line, idx.segment, rec.run_id, iid, idx.t, ln_mm(rec), ln_mm(idx))
        if len(idx.indicators) < len(ONBOARD_INDICES):  # for its unit's model only
            self._partial_pairs.append(pair)
            self._paired.add(iid)
            self._changes.partial_pairs.append(pair)
            self.stats["pairs_partial"] += 1
            return
        self._pairs.append(pair)
        self._paired.add(iid)
        self._changes.pairs.append(pair)
        self.stats["pairs"] += 1

    def _ingest_index(self, idx: OnboardIndex) -> bool:
        iid = index_id(idx)
        seg = (idx.line, idx.segment)
        if iid in self._paired or iid in self._pending.get(seg, {}):
            self.stats["index_duplicates"] += 1
            return False
        if idx.quality < self.config.min_quality or idx.coverage < self.config.min_coverage:
            self.stats["index_low_quality"] += 1
            return False
        rec = self._match(idx)
        if rec is not None:
            self._add_pair(idx, iid, rec)
            return True
        if idx.t < self._oldest_waiting(seg):
            self.stats["index_expired"] += 1
            return False
        pending = self._pending.setdefault(seg, {})
        pending[iid] = idx
        self._changes.pending_added.append(idx)
        if len(pending) > self.config.max_pending_per_segment:
            self._drop_pending(seg, min(pending, key=lambda i: (pending[i].t, i)))
        return True

    def _ingest_maintenance(self, ev: MaintenanceEvent) -> bool:
        seg = (ev.line, ev.segment)
        mid = maintenance_id(ev)
        known = self._maint.setdefault(seg, {})
        if mid in known and ev.rank <= known[mid].rank:
            self.stats["maintenance_duplicates"] += 1
            return False
        if mid in known:  # a correction or a withdrawal (MaintenanceEvent.rank) replaces it
            self.stats["maintenance_corrections"] += 1
        known[mid] = ev
        self._changes.maintenance.append(ev)
        self.stats["maintenance"] += 1
        self._dirty.add(seg)
        return True

    # --- models ------------------------------------------------------------------------------

    def flush(self) -> list[Model]:
        """Fit or rebuild what the new data calls for, then publish what the publication
        rule lets through; the models published, the Calibration first, then by group."""
        self._maybe_fit()
        self._maybe_fit_units()
        ahead_due = self._screened_now != self._now and any(
            r.startswith(_AHEAD) for left in self._screened.values() for r in left.values()
        )
        if self._dirty or ahead_due:
            self._update_increments()
            self._dirty.clear()
            self._rebuild_posteriors()
        return self._publish_due()

    def _set_model(self, entry: ModelEntry) -> None:
        self._models[entry.key] = entry
        self._changes.models.append(entry)

    def _current(self, key: str) -> ModelEntry | None:
        """The newest accepted model of ``key``: held if any, else the one in force."""
        return self._held.get(key) or self._models.get(key)

    def _next_version(self, key: str) -> int:
        in_force = self._models.get(key)
        return in_force.message.version + 1 if in_force is not None else 1

    def _due(self, key: str) -> bool:
        """Whether the rate limit lets a new version of ``key`` out now."""
        in_force = self._models.get(key)
        if in_force is None or in_force.published_at is None:
            return True
        return self._now >= in_force.published_at + self.config.min_publish_interval_days * DAY_S

    def _invalid(self, entry: ModelEntry) -> str | None:
        """Why ``entry`` must never be published (:func:`robust.check_model`), logged and
        counted, or None."""
        reason = check_model(entry.message)
        if reason is None:
            return None
        self.stats["models_invalid"] += 1
        msg = f"{entry.key} version {entry.message.version} invalid, not published: {reason}"
        self.rejections.append(msg)
        log.error("%s", msg)
        return msg

    def _hold(self, entry: ModelEntry, change: Move | None) -> None:
        """Keep an accepted model; mark it for publication if it differs materially from the
        one in force (``change`` None: there is none)."""
        key = entry.key
        self._held[key] = entry
        self._changes.held[key] = entry
        if change is None or change[0] > self.config.material_se:
            self._material.add(key)
            if not self._due(key):
                self.stats["publications_delayed"] += 1
                log.info(
                    "%s version %d held by the rate limit: %s",
                    key,
                    entry.message.version,
                    "new" if change is None else change[1],
                )
        else:
            self._material.discard(key)
            self.stats["changes_immaterial"] += 1
            log.debug("%s: change not material, not published: %s", key, change[1])

    def _publish_due(self) -> list[Model]:
        out: list[Model] = []
        at = self._now if math.isfinite(self._now) else None
        for key in sorted(self._material, key=lambda k: (k != CALIBRATION_KEY, k)):
            if not self._due(key):
                continue
            if self._invalid(self._held[key]) is not None:  # checked when held: never here
                self._material.discard(key)
                continue
            entry = replace(self._held.pop(key), published_at=at)
            self._material.discard(key)
            self._changes.held[key] = None
            self._set_model(entry)
            kind = "calibrations" if is_calibration_key(key) else "posteriors"
            self.stats[f"{kind}_published"] += 1
            out.append(entry.message)
        return out

    def _maybe_fit(self) -> Calibration | None:
        """Fit when due; the accepted candidate (held until :meth:`_publish_due`), or None."""
        cfg, n = self.config, len(self._pairs)
        if n < cfg.min_pairs:
            return None
        current = self._current(CALIBRATION_KEY)
        fitted = current is not None and not current.prior
        if fitted and n - self._attempt_at < cfg.refit_every:
            return None
        if not fitted and self._attempt_at and n - self._attempt_at < cfg.refit_every:
            return None  # the last first-fit attempt failed: wait for more pairs
        self._attempt_at = n
        self._changes.meta = {}  # mark meta as changed
        if fitted:  # a few wild new pairs go before the swap rule judges the rest
            cur: Calibration = current.message  # type: ignore[union-attr,assignment]
            if self._drop_outlying_pairs(cur.H.array(), cur.b.array(), cur.n_pairs):
                n = self._attempt_at = len(self._pairs)
                if n == cur.n_pairs:
                    return None
        fitted_pairs = self._fit_pairs()
        if fitted_pairs is None:
            return None
        fit, Z, Y = fitted_pairs
        if fitted:
            old: Calibration = current.message  # type: ignore[union-attr,assignment]
            reason = worse(old, fit, Z[: old.n_pairs], Y[: old.n_pairs], self.config)
            if reason is not None:
                self.stats["fits_rejected"] += 1
                held = "" if current is self._models.get(CALIBRATION_KEY) else " (held)"
                msg = f"refit on {n} pairs rejected against version {old.version}{held}: {reason}"
                self.rejections.append(msg)
                log.warning("%s; %d new pairs quarantined", msg, n - old.n_pairs)
                new = self._pairs[old.n_pairs :]
                del self._pairs[old.n_pairs :]
                self._quarantined.extend(new)
                self._changes.quarantined.extend(p.index_id for p in new)
                self.stats["pairs_quarantined"] += len(new)
                self._attempt_at = old.n_pairs
                return None
        if not fitted and self._drop_outlying_pairs(fit.H, fit.b, 0):  # on its own residuals
            n = self._attempt_at = len(self._pairs)
            fitted_pairs = self._fit_pairs()
            if fitted_pairs is None:
                return None
            fit, Z, Y = fitted_pairs
        in_force = self._models.get(CALIBRATION_KEY)
        version = self._next_version(CALIBRATION_KEY)
        try:
            cal = Calibration(
                version=version,
                t=max(p.t for p in self._pairs),
                indicators=list(INDICATORS),
                indices=list(ONBOARD_INDICES),
                H=NDArray.of(fit.H),
                b=NDArray.of(fit.b),
                R=NDArray.of(fit.R),
                n_pairs=n,
                r2=NDArray.of(fit.r2),
            )
        except SchemaError as e:  # NaN/inf or out of the wire's bounds: never published
            self.stats["models_invalid"] += 1
            self.rejections.append(f"calibration fit on {n} pairs invalid, not published: {e}")
            log.error("%s", self.rejections[-1])
            return None
        entry = ModelEntry(CALIBRATION_KEY, cal)
        if self._invalid(entry) is not None:
            return None
        self.stats["fits_accepted"] += 1
        change = None
        if in_force is not None:
            change = calibration_change(fit, in_force.message)  # type: ignore[arg-type]
        log.info(
            "calibration fit on %d pairs accepted, R² %s; against version %s in force: %s",
            n,
            np.round(fit.r2, 3),
            None if in_force is None else in_force.message.version,
            "none" if change is None else change[1],
        )
        self._hold(entry, change)
        return cal

    def _maybe_fit_units(self) -> None:
        """Each unit's own model when it is due (:mod:`.units`), held and published by the
        same rule as the fleet's."""
        cfg = self.config
        fleet = self._current(CALIBRATION_KEY)
        pairs = self._pairs + self._quarantined
        if not cfg.unit_models or fleet is None or not (pairs or self._partial_pairs):
            return
        due = units_due(pairs + self._partial_pairs, self._unit_fit_at, cfg)
        if not due:
            return
        design = pair_design(pairs or self._partial_pairs)
        base: Calibration = fleet.message  # type: ignore[assignment]
        for (train, unit), ps in sorted(due.items()):
            self._unit_fit_at[(train, unit)] = len(ps)
            self._changes.meta = {}  # part of meta
            key = unit_key(train, unit)
            try:
                fit, cal = unit_calibration(
                    train, unit, ps, base, design, self._next_version(key), cfg
                )
            except (CalibrationError, SchemaError, ValueError) as e:
                self.stats["unit_fit_errors"] += 1
                log.warning("unit %s/%s: fit on %d pairs refused: %s", train, unit, len(ps), e)
                continue
            entry = ModelEntry(key, cal)
            if self._invalid(entry) is not None:
                continue
            in_force = self._models.get(key)
            change = None if in_force is None else calibration_change(fit, in_force.message)
            self.stats["unit_fits"] += 1
            self._hold(entry, change)

    def _drop_outlying_pairs(self, H: np.ndarray, b: np.ndarray, n_ref: int) -> int:
        """Quarantine the pairs :func:`refit.outlying_pairs` finds under the fit ``H, b``
        judged against the first ``n_ref`` (all when 0); the number left out."""
        out = outlying_pairs(self._pairs, H, b, n_ref, self.config)
        for i, why in out:
            p = self._pairs[i]
            log.warning("%s", why)
            self._outbox.append(Quarantine("index", p.line, p.segment, why))
        dropped = {i for i, _ in out}
        self._quarantined.extend(self._pairs[i] for i, _ in out)
        self._changes.quarantined.extend(self._pairs[i].index_id for i, _ in out)
        self._pairs = [p for i, p in enumerate(self._pairs) if i not in dropped]
        self.stats["pairs_outliers"] += len(out)
        return len(out)

    def _fit_pairs(self):
        """``(fit, Z, Y)`` of H, b, R on every pair held (Eq. 5-6), or None (counted and
        logged) when the fit is refused."""
        Z = np.array([p.z for p in self._pairs])
        Y = np.array([p.y for p in self._pairs])
        try:
            return fit_observation(Z, Y, min_pairs=self.config.min_pairs), Z, Y
        except CalibrationError as e:
            self.stats["fit_errors"] += 1
            log.warning("calibration fit on %d pairs refused: %s", len(Z), e)
            return None

    def _update_increments(self) -> None:
        """Screen every segment's TRC history (:func:`robust.screen_segment`: the reference
        is the whole network's, so a new record anywhere may change a verdict) and rebuild
        the increments of the segments whose records used changed."""
        cfg = self.config
        for seg in self._dirty:
            records = sorted(self._trc.get(seg, {}).values(), key=lambda r: r.t)
            if not records:
                for d in (self._history, self._raw, self._increments, self._newest_used):
                    d.pop(seg, None)
                continue
            t = np.array([r.t / DAY_S for r in records])
            z = np.array([ln_mm(r) for r in records]).reshape(len(records), _N)
            held = self._maint.get(seg, {}).values()  # a withdrawn detection splits nothing
            tamping = sorted(0.5 * (e.t_start + e.t_end) / DAY_S for e in held if not e.withdrawn)
            self._history[seg] = (records, t, z, tamping)
            self._raw[seg] = raw_pieces(t, z, tamping)
        raw = [self._raw[s] for s in sorted(self._raw)]
        increments, levels = network_references(raw, _N, cfg.robust_min_count)
        rules = Rules(cfg.max_rate_per_day, cfg.max_jump, cfg.robust_k, cfg.max_ahead_days)
        now_days = self._now / DAY_S if math.isfinite(self._now) else math.inf
        self._screened_now = self._now
        for seg in sorted(self._history):
            records, t, z, tamping = self._history[seg]
            out = screen_segment(
                t, z, tamping, now_days=now_days, rules=rules, increments=increments, levels=levels
            )
            left = {records[i].run_id: reason for i, reason in out.items()}
            if seg not in self._dirty and left == self._screened.get(seg, {}):
                continue
            self._report_screening(seg, left)
            keep = np.array([i not in out for i in range(len(records))])
            if not keep.any():
                self._increments.pop(seg, None)
                self._newest_used.pop(seg, None)
                continue
            self._increments[seg] = segment_increments(
                t[keep], z[keep], tamping, max_age=cfg.max_level_age_days
            )
            self._newest_used[seg] = float(t[keep].max()) * DAY_S

    def _report_screening(self, seg: SegmentId, left: dict[str, str]) -> None:
        """Log, count and report (once) the records of ``seg`` newly left out; forget those
        taken back (a step confirmed by a later record, event time reaching a record)."""
        before = self._screened.get(seg, {})
        if left:
            self._screened[seg] = left
        else:
            self._screened.pop(seg, None)
        records = self._trc[seg]
        for run_id in sorted(set(before) - set(left)):
            self._reported.discard(trc_id(records[run_id]))
            self.stats["trc_taken_back"] += 1
            log.info("TRC record %s used again", trc_id(records[run_id]))
        for run_id, reason in sorted(left.items()):
            rec = records[run_id]
            tid = trc_id(rec)
            if tid in self._reported:
                continue
            self._reported.add(tid)
            self.stats["trc_quarantined"] += 1
            why = f"TRC record {tid} left out of the degradation posteriors: {reason}"
            log.warning("%s", why)
            self._outbox.append(Quarantine("trc", rec.line, rec.segment, why, rec))
        self._changes.meta = {}  # the reported set is part of meta

    def _rebuild_posteriors(self) -> None:
        if not self._increments:
            return
        inputs = group_inputs(self._increments, self._newest_used, self.config)
        self.stats["trc_partial_left_out"] = inputs["net"].left_out
        for group, g in sorted(inputs.items()):
            fp = fingerprint(group, g, self.config)
            entry = self._current(group)
            if (entry is not None and entry.fingerprint == fp) or self._refused.get(group) == fp:
                continue
            if g.left_out:  # records that did not measure the group's j (see .groups)
                log.info("posterior %s: %d partial TRC records left out", group, g.left_out)
            in_force = self._models.get(group)
            version = self._next_version(group)
            try:
                post = build_posterior(group, g, version, self.config)
            except SchemaError as e:  # NaN/inf or out of the wire's bounds: never published
                self._refused[group] = fp
                self.stats["models_invalid"] += 1
                self.rejections.append(f"{group} version {version} invalid, not published: {e}")
                log.error("%s", self.rejections[-1])
                continue
            except CalibrationError as e:
                self._refused[group] = fp
                self.stats["posteriors_refused"] += 1
                log.info("posterior %s not rebuilt: %s", group, e)
                continue
            entry = ModelEntry(group, post, fingerprint=fp)
            if self._invalid(entry) is not None:
                self._refused[group] = fp
                continue
            moved = None
            if in_force is not None:
                moved = one_segment_move(g, post, in_force, self._increments, self.config)
            if moved is not None:
                why, culprit = moved
                rec = self._history[culprit][0][-1]
                self._outbox.append(Quarantine("trc", rec.line, rec.segment, why, rec))
                self._refused[group] = fp
                self.stats["posteriors_held_move"] += 1
                self.rejections.append(why)
                log.warning("%s", why)
                continue
            self._refused.pop(group, None)
            self.stats["posteriors_built"] += 1
            change = None
            if in_force is not None:
                change = posterior_change(post, in_force.message)  # type: ignore[arg-type]
            self._hold(entry, change)
