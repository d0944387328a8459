r"""Live calibration core: pairs TRC records with on-board indices, fits the observation model
and builds the degradation posteriors per group. Pure: no Zenoh, no clock, no I/O.

Conventions shared with the other services: time in days (epoch s / 86400) inside the maths,
``z = ln([top6_mm, align10_mm])`` of a TRC record, ``y = ln`` of an on-board index's values.

Use::

    core = Calibrator(CalibratorConfig(), state=store.load())   # or state=None when new
    outputs = core.step([trc, index, tamping, ...])   # new Calibration / DegradationPosterior
    store.apply(core.drain_changes())                  # persist what changed, one transaction

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
    as is a second TRC record of a segment at the same instant. A pair's time is the index's.

Observation model and the swap rule
    Once ``min_pairs`` pairs exist, H, b, R are fitted (:func:`fit_observation`, paper Eq. 5-6)
    on all pairs; a refit is tried every ``refit_every`` further pairs. The first fit is
    accepted when the regression succeeds (it replaces an initial prior model, which has no
    pairs). A refit **replaces the current model only if it is not worse**, judged on the
    ``n_old`` pairs the current model was fitted on (the pairs are kept in arrival order, so
    these are the first ``n_old`` of the candidate's pairs, held by both):

    1. R² of every on-board index drops by at most ``max_r2_drop`` (default 0.10), and
    2. the mean Gaussian log-likelihood per pair of those ``n_old`` pairs,
       :math:`\frac{1}{n}\sum_i \log N(\mathbf y_i;\ \mathbf H\mathbf z_i + \mathbf b,\ \mathbf R)`,
       under the candidate is at most ``max_loglik_drop`` nats (default 0.25) below that under
       the current model.

    The current model is the maximum-likelihood fit of those pairs, so the candidate is never
    better on them; for good new pairs the gap is small (about 0.04 nats per pair at 30 -> 40
    pairs), while pairs from a faulty sensor or a broken pairing inflate R and bend H and cost
    nats per pair. A rejected refit is counted (``stats["fits_rejected"]``), its reason is kept
    in :attr:`Calibrator.rejections` and logged; the current model stays, and the pairs added
    since it (the evidence of the fault) are quarantined: kept, so that their indices stay
    recognised as duplicates, but left out of every later fit (``stats["pairs_quarantined"]``).
    Without that, one burst of bad pairs would block every later refit. The "current model"
    here is the newest *accepted* fit, published or not (see the publication rule).

Degradation posteriors
    Per segment, the TRC history (``z`` at record times) and the tampings (known time, or the
    middle of the interval: the paper's mid-interval rule) give increments that do not span a
    tamping and post-tamping levels (:func:`history_to_increments`). Groups:

    * ``seg.{line}.{segment}`` when the segment alone has ``>= segment_min_increments``;
    * ``line.{line}`` pooling the increments of the line's segments;
    * ``net`` pooling every segment.

    Post-tamping levels come from the group itself when it has ``>= min_levels``, else from
    its line, else from the network; when even the network has fewer, ``(z+, Σz+)`` are drawn
    from the level prior alone (``n_levels = 0``) so that drift and diffusion are published
    before any tamping has been recorded. ``samples`` draws of :func:`sample_degradation_posterior`
    use a generator seeded from ``(seed, group, version)``: re-running gives identical samples.
    A group is rebuilt when a fingerprint of its inputs (increments, levels, and the settings
    that shape the draws) changed; when the core raises :class:`CalibrationError` (too little
    data) the old posterior stays and the refusal is counted.

Publication rule (issue 12: model updates without storms)
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
    limit, whether or not anything was refitted since. The swap rule is unchanged: it judges
    each refit against the newest accepted fit, so a worse fit is never held nor published.
    With ``material_se = 0`` and ``min_publish_interval_days = 0`` every accepted change is
    published at once (the behaviour before the rule). Counted: ``changes_immaterial``,
    ``publications_delayed``, ``calibrations_published``, ``posteriors_published``. The held
    candidates, the publication time of each model in force and event time are persisted.

Robustness (issue 14)
    Every model is checked (:func:`robust.check_model`: finite, SPD covariances) before it is
    held and again before it is published; TRC records that the data blame (a spike, a newest
    record beyond the physical rate bound, a post-tamping level far off the network's, a
    record dated far after event time) are left out of the increments and levels
    (:func:`robust.screen_segment`); a pooled posterior moved beyond ``max_move_sd`` by one
    segment alone is held; a few wild pairs are quarantined before the swap rule judges a
    refit. What is left out is logged, counted and returned by
    :meth:`Calibrator.drain_quarantined` (the adapter's dead letters). See the README.
"""

from __future__ import annotations

import bisect
import hashlib
import logging
import math
from collections import Counter, deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from schemas import (
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
from services.calibration.posterior import (
    NIWPosterior,
    NIWPrior,
    SegmentIncrements,
    history_to_increments,
    posterior_drift_diffusion,
    sample_degradation_posterior,
)
from services.calibration.regression import (
    CalibrationError,
    ObservationFit,
    fit_observation,
    fit_unit_observation,
)
from services.calibration.robust import Rules, check_model, raw_pieces, reference, screen_segment

__all__ = [
    "CALIBRATION_KEY",
    "Calibrator",
    "CalibratorConfig",
    "Changes",
    "Event",
    "ModelEntry",
    "Model",
    "Pair",
    "Quarantine",
    "StoredState",
    "calibration_change",
    "initial_models",
    "mean_loglik",
    "posterior_change",
]

log = logging.getLogger(__name__)

DAY_S = 86400.0
_AHEAD = "dated "  # how robust.screen_segment's reason for a record ahead of event time begins
_INCREMENT_SD_FLOOR = 1e-3  # ln mm / sqrt(day): the robust sd of increments is at least this
_LEVEL_SD_FLOOR = 1e-2  # ln mm: and that of post-tamping levels
_RESIDUAL_SD_FLOOR = 1e-3  # ln: and that of (TRC, on-board) residuals
_MAX_OUTLIER_SHARE = 0.2  # more outlying pairs than this share are a burst: the swap rule's
CALIBRATION_KEY = "calibration"  # ModelEntry.key of the Calibration; posteriors use their group


def unit_key(train: str, unit: str) -> str:
    """ModelEntry.key of a unit's own Calibration."""
    return f"{CALIBRATION_KEY}/{train}/{unit}"


def is_calibration_key(key: str) -> bool:
    """The fleet's or a unit's Calibration (a posterior group never has a ``/``)."""
    return key == CALIBRATION_KEY or key.startswith(CALIBRATION_KEY + "/")


_N = len(INDICATORS)

Event = TrcRecord | OnboardIndex | MaintenanceEvent
Model = Calibration | DegradationPosterior
Segment = tuple[str, str]  # (line, segment)


@dataclass(frozen=True)
class CalibratorConfig:
    """Settings of :class:`Calibrator` (see the module docstring for what each one rules)."""

    min_pairs: int = 30  # pairs before the first fit
    refit_every: int = 10  # new pairs between fit attempts
    tolerance_days: float | None = 1.0  # time pairing of indices without run_id; None: off
    index_window_days: float = 30.0  # an unpaired index waits this long (segment's TRC time)
    max_pending_per_segment: int = 500  # unpaired indices kept per segment (newest by t)
    min_quality: float = 0.5  # indices below are not used for calibration
    min_coverage: float = 0.5
    max_r2_drop: float = 0.10  # swap rule 1
    max_loglik_drop: float = 0.25  # swap rule 2, nats per pair
    segment_min_increments: int = 6  # k: a segment gets its own posterior group
    min_increments: int = _N + 2  # pooled groups (line, net)
    min_levels: int = _N + 2  # post-tamping levels for (z+, Σz+) from data
    max_level_age_days: float | None = 120.0  # older post-tamping levels are not used
    samples: int = 200  # Ns
    seed: int = 0
    material_se: float = 1.0  # publication rule: a change is material beyond this many SEs
    min_publish_interval_days: float = 1.0  # event time between two versions of one model
    # robustness (issue 14; robust.py)
    max_rate_per_day: float = 1.0 / 30.0  # hard bound on |dz|/dt between records, ln mm/day
    max_jump: float = 0.5  # ... plus this much, ln mm (diffusion and TRC noise over short dt)
    robust_k: float = 8.0  # outliers: beyond this many robust sd (1.4826 MAD)
    robust_min_count: int = 20  # samples before a median/MAD reference is used
    max_move_sd: float = 8.0  # a pooled posterior moved beyond this (sd of the one in force)
    event_time_quorum: int = 3  # event time: the newest time this many segments have reached
    max_ahead_days: float = 180.0  # TRC records later than event time + this: left out for now
    # per-unit observation models (issue 18): shrunk towards the fleet's by this many pairs
    unit_models: bool = True
    unit_min_pairs: int = 5  # a unit's pairs before its first own model
    unit_shrink_pairs: float = 20.0
    drift_prior: NIWPrior | None = None  # None: NIWPrior.default_drift
    level_prior: NIWPrior | None = None  # None: NIWPrior.default_level

    def __post_init__(self) -> None:
        if self.min_pairs < 1 or self.refit_every < 1:
            raise ValueError(
                f"min_pairs and refit_every must be >= 1, got {self.min_pairs}, {self.refit_every}"
            )
        if self.tolerance_days is not None and not self.tolerance_days >= 0:
            raise ValueError(f"tolerance_days: must be >= 0 or None, got {self.tolerance_days}")
        if not self.index_window_days >= 0:
            raise ValueError(f"index_window_days: must be >= 0, got {self.index_window_days}")
        if self.samples < 1:
            raise ValueError(f"samples: must be >= 1, got {self.samples}")
        if self.seed < 0:
            raise ValueError(f"seed: must be >= 0, got {self.seed}")
        if self.segment_min_increments < 1 or self.min_increments < 1 or self.min_levels < 1:
            raise ValueError("segment_min_increments, min_increments, min_levels must be >= 1")
        if not (
            self.max_rate_per_day > 0
            and self.max_jump >= 0
            and self.robust_k > 0
            and self.max_move_sd > 0
            and self.max_ahead_days >= 0
        ):
            raise ValueError(
                "max_rate_per_day, robust_k, max_move_sd must be > 0, max_jump and "
                "max_ahead_days >= 0"
            )
        if self.event_time_quorum < 1 or self.robust_min_count < 3:
            raise ValueError("event_time_quorum must be >= 1 and robust_min_count >= 3")
        if not self.material_se >= 0 or not self.min_publish_interval_days >= 0:
            raise ValueError(
                "material_se and min_publish_interval_days: must be >= 0, got "
                f"{self.material_se}, {self.min_publish_interval_days}"
            )


@dataclass(frozen=True)
class Pair:
    """One (TRC record, on-board index) pair: ``z`` and ``y`` in ln mm, ``t`` the index's (s)."""

    line: str
    segment: str
    run_id: str  # the TRC record's
    index_id: str
    t: float
    z: tuple[float, float]
    y: tuple[float, float]

    @property
    def unit(self) -> tuple[str, str]:
        """``(train, unit)`` of the index (from its id, :func:`index_id`)."""
        parts = self.index_id.split("/")
        return parts[2], parts[3]


@dataclass(frozen=True)
class Quarantine:
    """Something left out of a fit or a posterior, to report (a dead letter): ``kind`` is the
    key kind of what caused it (``trc`` or ``index``), ``message`` the record when kept."""

    kind: str
    line: str
    segment: str
    reason: str
    message: TrcRecord | None = None


@dataclass(frozen=True)
class ModelEntry:
    """A model as stored: ``key`` is ``"calibration"`` or the posterior's group.

    A model in force carries the event time it was published at (None for an initial model,
    or one stored before publication times were kept: the next version is not rate-limited);
    a held candidate (accepted, not published) carries None.
    """

    key: str
    message: Model
    fingerprint: str = ""  # of the posterior's inputs; "" for the calibration
    prior: bool = False  # an initial model (no data behind it)
    published_at: float | None = None  # epoch s of event time


@dataclass
class StoredState:
    """Everything a :class:`Calibrator` needs to continue: what a store loads."""

    trc: list[TrcRecord] = field(default_factory=list)
    maintenance: list[MaintenanceEvent] = field(default_factory=list)
    pending: list[OnboardIndex] = field(default_factory=list)  # unpaired, in arrival order
    pairs: list[Pair] = field(default_factory=list)  # in arrival order
    quarantined: list[Pair] = field(default_factory=list)  # left out of fits
    models: list[ModelEntry] = field(default_factory=list)  # in force (published)
    held: list[ModelEntry] = field(default_factory=list)  # accepted, not (yet) published
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class Changes:
    """What changed since the last :meth:`Calibrator.drain_changes`: what a store writes."""

    trc: list[TrcRecord] = field(default_factory=list)
    maintenance: list[MaintenanceEvent] = field(default_factory=list)
    pending_added: list[OnboardIndex] = field(default_factory=list)
    pending_removed: list[str] = field(default_factory=list)  # index ids
    pairs: list[Pair] = field(default_factory=list)
    quarantined: list[str] = field(default_factory=list)  # index ids of pairs set aside
    models: list[ModelEntry] = field(default_factory=list)  # published, in order
    held: dict[str, ModelEntry | None] = field(default_factory=dict)  # key -> held now, or None
    meta: dict[str, Any] | None = None  # the whole meta when it changed

    def __bool__(self) -> bool:
        return bool(
            self.trc
            or self.maintenance
            or self.pending_added
            or self.pending_removed
            or self.pairs
            or self.quarantined
            or self.models
            or self.held
            or self.meta is not None
        )


def trc_id(rec: TrcRecord) -> str:
    return f"{rec.line}/{rec.segment}/{rec.run_id}"


def index_id(idx: OnboardIndex) -> str:
    return f"{idx.line}/{idx.segment}/{idx.train}/{idx.unit}/{idx.t!r}"


def maintenance_id(ev: MaintenanceEvent) -> str:
    return f"{ev.line}/{ev.segment}/{ev.event_id}"


def _z(msg: TrcRecord | OnboardIndex) -> tuple[float, float]:
    return (math.log(msg.top6_mm), math.log(msg.align10_mm))


def mean_loglik(H, b, R, Z, Y) -> float:
    r"""Mean Gaussian log-likelihood per pair, :math:`\frac1N\sum_i\log N(y_i; Hz_i + b, R)`."""
    H, b, R = (np.asarray(a, dtype=np.float64) for a in (H, b, R))
    E = np.asarray(Y, dtype=np.float64) - np.asarray(Z, dtype=np.float64) @ H.T - b
    L = np.linalg.cholesky(R)
    w = np.linalg.solve(L, E.T)  # (m, N)
    logdet = 2.0 * np.log(np.diag(L)).sum()
    m = R.shape[0]
    return float(-0.5 * (m * math.log(2 * math.pi) + logdet + (w**2).sum(axis=0).mean()))


Move = tuple[float, str]  # (largest move in standard errors, what moved and how)


def _largest_move(moves: Iterable[tuple[str, Any, Any, Any]]) -> Move:
    """The largest ``|new - old| / se`` over named arrays, and where it is."""
    best: Move = (0.0, "nothing")
    for name, new, old, se in moves:
        new, old, se = (np.asarray(a, dtype=np.float64) for a in (new, old, se))
        d = np.abs(new - old)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(d > 0, d / se, 0.0)  # a zero se: any move is infinitely many
        i = np.unravel_index(int(np.argmax(z)), z.shape) if z.size else ()
        if z.size and z[i] > best[0]:
            where = f"[{','.join(str(k) for k in i)}]" if i else ""
            best = (
                float(z[i]),
                f"{name}{where} {float(old[i]):.4g} -> {float(new[i]):.4g} "
                f"({float(z[i]):.2f} SE of {float(se[i]):.3g})",
            )
    return best


def calibration_change(fit: ObservationFit, old: Calibration) -> Move:
    r"""How far the fit ``fit`` moved from the model ``old``, in the fit's standard errors.

    .. math::

        \max\Big(\max_{ij}\frac{|H_{ij} - H^{old}_{ij}|}{\operatorname{se}(H_{ij})},\
        \max_i\frac{|b_i - b^{old}_i|}{\operatorname{se}(b_i)},\
        \max_{ij}\frac{|R_{ij} - R^{old}_{ij}|}{\operatorname{se}(R_{ij})}\Big)

    with the least-squares standard errors of :func:`fit_observation` (for ``R``, its
    sampling error: relative :math:`\sqrt{2/(N - n - 1)}` on the diagonal).
    """
    return _largest_move(
        [
            ("H", fit.H, old.H.array(), fit.se_H),
            ("b", fit.b, old.b.array(), fit.se_b),
            ("R", fit.R, old.R.array(), fit.se_R),
        ]
    )


def posterior_change(new: DegradationPosterior, old: DegradationPosterior) -> Move:
    r"""How far the posterior ``new`` moved from ``old``, in posterior standard deviations.

    For each parameter :math:`\theta` of :math:`(\boldsymbol\mu, \boldsymbol\Sigma,
    \mathbf z^+, \boldsymbol\Sigma_{z^+})`, element by element, the move of the posterior mean
    over the posterior sd, both from the draws the filter runs on:

    .. math::

        \max_\theta \frac{|\bar\theta_{new} - \bar\theta_{old}|}{\operatorname{sd}(\theta_{new})}

    (the draws of two versions come from different seeds, so the Monte Carlo part of a move is
    about :math:`\sqrt{2/N_s}` sd: 0.1 sd at Ns = 200).
    """
    moves = []
    for name in ("mu", "sigma", "z_plus", "sigma_z_plus"):
        a_new, a_old = getattr(new, name).array(), getattr(old, name).array()
        moves.append((name, a_new.mean(axis=0), a_old.mean(axis=0), a_new.std(axis=0)))
    return _largest_move(moves)


def group_rng(seed: int, group: str, version: int) -> np.random.Generator:
    """The generator of a posterior's draws: a pure function of (seed, group, version)."""
    g = int.from_bytes(hashlib.sha256(group.encode()).digest()[:8], "little")
    return np.random.default_rng(np.random.SeedSequence([seed, g, version]))


def _arr(x: Any) -> NDArray:
    return NDArray.of(np.asarray(x, dtype=np.float64))


def _prior_from_spec(spec: Mapping[str, Any], what: str, weight: str, cov: str) -> NIWPrior:
    """NIW prior from ``{mean, <weight>, <cov> (prior mean of the covariance), dof}``."""
    try:
        dof = float(spec["dof"])
        cov_mean = np.asarray(spec[cov], dtype=np.float64)
        n = cov_mean.shape[0]
        if not dof > n + 1:
            raise ValueError(f"{what}.dof: must be > n + 1 = {n + 1} (finite mean), got {dof}")
        return NIWPrior(
            m0=np.asarray(spec["mean"], dtype=np.float64),
            lambda0=float(spec[weight]),
            Psi0=cov_mean * (dof - n - 1),  # so that E[Σ] = Psi0 / (nu0 - n - 1) = cov_mean
            nu0=dof,
        )
    except KeyError as e:
        raise ValueError(f"{what}: missing {e.args[0]!r}") from None


def _sample_prior(prior: NIWPrior, ns: int, rng: np.random.Generator):
    """Draws of (mean, cov) from the NIW prior itself (no data)."""
    return NIWPosterior(
        m=prior.m0, lam=prior.lambda0, Psi=prior.Psi0, nu=prior.nu0, n_obs=0
    ).sample(ns, rng)


def initial_models(
    spec: Mapping[str, Any], *, samples: int, seed: int
) -> tuple[Calibration | None, list[DegradationPosterior]]:
    """Version-1 models from a prior specification (``services/defaults/initial-models.json5``).

    ``spec["calibration"]``: ``H``, ``b``, ``R``, optionally ``r2`` (default 0) and ``n_pairs``
    (default 1: the schema needs > 0; the pairs behind a prior model are not ours). ``t`` is 0.
    ``spec["degradation"]``: ``{group: {drift: {...}, level: {...}}}`` where ``drift`` is
    ``{mean (ln mm/day), weight_days, sigma (prior mean of Σ, ln mm²/day), dof}`` and
    ``level`` is ``{mean (ln mm), weight_levels, cov (prior mean of Σz+), dof}``; the
    ``samples`` draws come from these Normal-Inverse-Wishart priors, seeded by
    ``(seed, group, 1)``. Raises ValueError naming what is wrong.
    """
    calibration = None
    if (cal := spec.get("calibration")) is not None:
        try:
            H, b, R = (np.asarray(cal[k], dtype=np.float64) for k in ("H", "b", "R"))
        except KeyError as e:
            raise ValueError(f"calibration: missing {e.args[0]!r}") from None
        m = len(ONBOARD_INDICES)
        if H.shape != (m, _N) or b.shape != (m,) or R.shape != (m, m):
            raise ValueError(
                f"calibration: H {H.shape}, b {b.shape}, R {R.shape}; need ({m}, {_N}), "
                f"({m},), ({m}, {m})"
            )
        if not np.allclose(R, R.T) or np.linalg.eigvalsh(R)[0] <= 0:
            raise ValueError("calibration.R: must be symmetric positive definite")
        calibration = Calibration(
            version=1,
            t=0.0,
            indicators=list(INDICATORS),
            indices=list(ONBOARD_INDICES),
            H=_arr(H),
            b=_arr(b),
            R=_arr(R),
            n_pairs=int(cal.get("n_pairs", 1)),
            r2=_arr(cal.get("r2", np.zeros(m))),
        )
    posteriors = []
    for group, gspec in sorted(dict(spec.get("degradation") or {}).items()):
        drift = _prior_from_spec(gspec.get("drift", {}), f"{group}.drift", "weight_days", "sigma")
        level = _prior_from_spec(gspec.get("level", {}), f"{group}.level", "weight_levels", "cov")
        rng = group_rng(seed, group, 1)
        mu, sigma = _sample_prior(drift, samples, rng)
        z_plus, sigma_z_plus = _sample_prior(level, samples, rng)
        posteriors.append(
            DegradationPosterior(
                group=group,
                version=1,
                t=0.0,
                indicators=list(INDICATORS),
                mu=_arr(mu),
                sigma=_arr(sigma),
                z_plus=_arr(z_plus),
                sigma_z_plus=_arr(sigma_z_plus),
                n_increments=0,
                n_levels=0,
            )
        )
    return calibration, posteriors


@dataclass(frozen=True)
class _GroupInput:
    dz: np.ndarray
    dt: np.ndarray
    level: np.ndarray
    age: np.ndarray
    level_source: str  # the group whose levels are used, or "prior"
    t_newest: float  # epoch s of the newest TRC record used of the group's segments
    members: tuple[Segment, ...] = ()  # segments whose increments are pooled


class Calibrator:
    """The calibration service's state and rules; see the module docstring.

    Feed events with :meth:`ingest` (or :meth:`step`), call :meth:`flush` to fit/rebuild,
    persist :meth:`drain_changes`. Single-threaded by design.
    """

    def __init__(self, config: CalibratorConfig | None = None, state: StoredState | None = None):
        self.config = config or CalibratorConfig()
        self.stats: Counter[str] = Counter()
        self.rejections: deque[str] = deque(maxlen=100)  # reasons of rejected refits, newest last
        self._trc: dict[Segment, dict[str, TrcRecord]] = {}
        self._trc_times: dict[Segment, list[tuple[float, str]]] = {}  # sorted (t, run_id)
        self._maint: dict[Segment, dict[str, MaintenanceEvent]] = {}
        self._pending: dict[Segment, dict[str, OnboardIndex]] = {}
        self._pairs: list[Pair] = []
        self._quarantined: list[Pair] = []
        self._paired: set[str] = set()
        self._models: dict[str, ModelEntry] = {}  # in force: published
        self._held: dict[str, ModelEntry] = {}  # newest accepted, not published (yet)
        self._material: set[str] = set()  # held keys that differ materially from in force
        self._now = -math.inf  # event time (epoch s): see _note_time
        # newest event time of the event_time_quorum segments furthest ahead: (t, line, seg)
        self._clock_top: list[tuple[float, str, str]] = []
        self._history: dict[Segment, tuple[list[TrcRecord], np.ndarray, np.ndarray, list]] = {}
        self._raw: dict[Segment, tuple[np.ndarray, np.ndarray]] = {}  # robust.raw_pieces
        self._screened: dict[Segment, dict[str, str]] = {}  # run_id -> why it is left out
        self._reported: set[str] = set()  # trc ids reported left out (and still left out)
        self._newest_used: dict[Segment, float] = {}  # epoch s of the newest record used
        self._outbox: list[Quarantine] = []  # to report (dead letters), see drain_quarantined
        self._screened_now = -math.inf  # event time at the last screening
        self._refused: dict[str, str] = {}  # group -> fingerprint whose build failed
        self._increments: dict[Segment, SegmentIncrements] = {}
        self._dirty: set[Segment] = set()
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
            self._maint.setdefault((ev.line, ev.segment), {})[maintenance_id(ev)] = ev
        for idx in state.pending:
            self._pending.setdefault((idx.line, idx.segment), {})[index_id(idx)] = idx
        for pair in state.pairs:
            self._pairs.append(pair)
            self._paired.add(pair.index_id)
        for pair in state.quarantined:
            self._quarantined.append(pair)
            self._paired.add(pair.index_id)
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
        self.stats.update(state.meta.get("stats", {}))
        self.rejections.extend(state.meta.get("rejections", []))
        self._dirty = set(self._trc) | set(self._maint)
        self._update_increments()
        self._dirty.clear()

    def _meta(self) -> dict[str, Any]:
        return {
            "attempt_at": self._attempt_at,
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

    def _note_time(self, seg: Segment, t: float) -> None:
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

    def _oldest_waiting(self, seg: Segment) -> float:
        """Indices of ``seg`` older than this (epoch s) no longer wait for a TRC record."""
        times = self._trc_times.get(seg)
        return times[-1][0] - self.config.index_window_days * DAY_S if times else -math.inf

    def _drop_pending(self, seg: Segment, iid: str) -> None:
        del self._pending[seg][iid]
        self._changes.pending_removed.append(iid)
        self.stats["index_expired"] += 1

    def _match(self, idx: OnboardIndex) -> TrcRecord | None:
        """The TRC record ``idx`` pairs with among those known, if any."""
        seg = (idx.line, idx.segment)
        records = self._trc.get(seg)
        if not records:
            return None
        if idx.run_id:
            return records.get(idx.run_id)
        tol = self.config.tolerance_days
        if tol is None:
            return None
        times = self._trc_times[seg]
        i = bisect.bisect_left(times, (idx.t, ""))
        best: tuple[float, str] | None = None
        for t, run_id in times[max(0, i - 1) : i + 1]:
            d = abs(t - idx.t)
            if d <= tol * DAY_S and (best is None or d < best[0]):
                best = (d, run_id)
        return records[best[1]] if best is not None else None

    def _add_pair(self, idx: OnboardIndex, iid: str, rec: TrcRecord) -> None:
        pair = Pair(idx.line, idx.segment, rec.run_id, iid, idx.t, _z(rec), _z(idx))
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
        if mid in known:
            self.stats["maintenance_duplicates"] += 1
            return False
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
            reason = self._worse(old, fit, Z[: old.n_pairs], Y[: old.n_pairs])
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
                H=_arr(fit.H),
                b=_arr(fit.b),
                R=_arr(fit.R),
                n_pairs=n,
                r2=_arr(fit.r2),
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
        """Each unit's own model (:func:`fit_unit_observation`), shrunk towards the fleet's
        model in force or held, once the unit has ``unit_min_pairs`` pairs and again every
        ``refit_every`` more; held and published by the same rule as the fleet's. A unit's
        pairs include those quarantined from the fleet's fit: a unit that reads the track
        differently from the fleet is what its own model is for."""
        cfg = self.config
        fleet = self._current(CALIBRATION_KEY)
        pairs = self._pairs + self._quarantined
        if not cfg.unit_models or fleet is None or not pairs:
            return
        by_unit: dict[tuple[str, str], list[Pair]] = {}
        for p in pairs:
            by_unit.setdefault(p.unit, []).append(p)
        due = {
            u: ps
            for u, ps in by_unit.items()
            if len(ps) >= cfg.unit_min_pairs
            and (u not in self._unit_fit_at or len(ps) - self._unit_fit_at[u] >= cfg.refit_every)
        }
        if not due:
            return
        X = np.hstack([np.array([p.z for p in pairs]), np.ones((len(pairs), 1))])
        design = X.T @ X / len(X)
        base: Calibration = fleet.message  # type: ignore[assignment]
        for (train, unit), ps in sorted(due.items()):
            self._unit_fit_at[(train, unit)] = len(ps)
            try:
                fit = fit_unit_observation(
                    np.array([p.z for p in ps]),
                    np.array([p.y for p in ps]),
                    H0=base.H.array(),
                    b0=base.b.array(),
                    R0=base.R.array(),
                    design=design,
                    shrink_pairs=cfg.unit_shrink_pairs,
                )
                key = unit_key(train, unit)
                cal = Calibration(
                    version=self._next_version(key),
                    t=max(p.t for p in ps),
                    indicators=list(INDICATORS),
                    indices=list(ONBOARD_INDICES),
                    H=_arr(fit.H),
                    b=_arr(fit.b),
                    R=_arr(fit.R),
                    n_pairs=len(ps),
                    r2=_arr(fit.r2),
                    train=train,
                    unit=unit,
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
        """Quarantine the pairs after the first ``n_ref`` whose residual ``y - (Hz + b)``
        under the fit ``H, b`` is beyond ``robust_k`` robust sd (1.4826 MAD) of the residuals
        of the first ``n_ref`` (all pairs when ``n_ref`` is 0: a first fit judged on its own
        pairs); the number left out. Only when they are a few (at most
        ``_MAX_OUTLIER_SHARE`` of the pairs judged, or one): single wild pairs (a wrong
        pairing, a glitch) go here, before the swap rule judges the rest, which would
        otherwise quarantine every new pair with them; a burst of bad pairs (a faulty unit)
        is left whole to the swap rule."""
        cfg = self.config
        Z = np.array([p.z for p in self._pairs]).reshape(-1, _N)
        Y = np.array([p.y for p in self._pairs]).reshape(-1, len(ONBOARD_INDICES))
        E = Y - Z @ H.T - b
        ref = reference(
            E[:n_ref] if n_ref else E, min_count=cfg.robust_min_count, floor=_RESIDUAL_SD_FLOOR
        )
        if ref is None:
            return 0
        out = [i for i in range(n_ref, len(E)) if ref.outlying(E[i], cfg.robust_k)]
        if len(out) > max(1.0, _MAX_OUTLIER_SHARE * (len(E) - n_ref)):
            return 0
        for i in out:
            p, d = self._pairs[i], np.abs(E[i] - ref.median) / ref.scale
            m = int(np.argmax(d))
            why = (
                f"pair of index {p.index_id} with TRC run {p.run_id} left out of the "
                f"observation model: residual of {ONBOARD_INDICES[m]} {E[i][m]:+.3f} ln is "
                f"{d[m]:.1f} robust sd (1.4826 MAD {ref.scale[m]:.3g}) from the fit's "
                f"(more than {cfg.robust_k:g})"
            )
            log.warning("%s", why)
            self._outbox.append(Quarantine("index", p.line, p.segment, why))
        dropped = set(out)
        self._quarantined.extend(self._pairs[i] for i in out)
        self._changes.quarantined.extend(self._pairs[i].index_id for i in out)
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

    def _worse(self, old: Calibration, fit, Z: np.ndarray, Y: np.ndarray) -> str | None:
        """The swap rule: why the candidate ``fit`` is worse than ``old``, or None."""
        cfg = self.config
        drop = old.r2.array() - fit.r2
        if np.any(drop > cfg.max_r2_drop):
            i = int(np.argmax(drop))
            return (
                f"R² of {ONBOARD_INDICES[i]} drops {old.r2.array()[i]:.3f} -> {fit.r2[i]:.3f} "
                f"(more than {cfg.max_r2_drop})"
            )
        ll_old = mean_loglik(old.H.array(), old.b.array(), old.R.array(), Z, Y)
        ll_new = mean_loglik(fit.H, fit.b, fit.R, Z, Y)
        if ll_new < ll_old - cfg.max_loglik_drop:
            return (
                f"log-likelihood per pair on the {len(Z)} pairs of version {old.version} drops "
                f"{ll_old:.3f} -> {ll_new:.3f} (more than {cfg.max_loglik_drop} nats)"
            )
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
            z = np.array([_z(r) for r in records]).reshape(len(records), _N)
            tamping = sorted(
                0.5 * (e.t_start + e.t_end) / DAY_S for e in self._maint.get(seg, {}).values()
            )
            self._history[seg] = (records, t, z, tamping)
            self._raw[seg] = raw_pieces(t, z, tamping)
        raw = [self._raw[s] for s in sorted(self._raw)]
        empty = np.empty((0, _N))
        increments = reference(
            np.concatenate([x for x, _ in raw] or [empty]),
            min_count=cfg.robust_min_count,
            floor=_INCREMENT_SD_FLOOR,
        )
        levels = reference(
            np.concatenate([lv for _, lv in raw] or [empty]),
            min_count=cfg.robust_min_count,
            floor=_LEVEL_SD_FLOOR,
        )
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
            self._increments[seg] = history_to_increments(
                t[keep], z[keep], tamping, max_age=cfg.max_level_age_days
            )
            self._newest_used[seg] = float(t[keep].max()) * DAY_S

    def _report_screening(self, seg: Segment, left: dict[str, str]) -> None:
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

    def _group_inputs(self) -> dict[str, _GroupInput]:
        """Inputs of every group that exists now (deterministic order of pooling)."""
        cfg = self.config
        segs = sorted(self._increments)
        newest = self._newest_used

        def pool(members: list[Segment]):
            incs = [self._increments[s] for s in members]
            return (
                np.concatenate([i.dz for i in incs]).reshape(-1, _N),
                np.concatenate([i.dt for i in incs]),
                np.concatenate([i.level for i in incs]).reshape(-1, _N),
                np.concatenate([i.age for i in incs]),
                max(newest[s] for s in members),
                tuple(members),
            )

        net = pool(segs)
        lines: dict[str, list[Segment]] = {}
        for s in segs:
            lines.setdefault(s[0], []).append(s)
        line_pool = {line: pool(members) for line, members in lines.items()}

        def make(own, chain: list[tuple[str, tuple]]) -> _GroupInput:
            dz, dt, _, _, t_newest, members = own
            for source, (_, _, level, age, _, _) in chain:
                if len(level) >= cfg.min_levels:
                    return _GroupInput(dz, dt, level, age, source, t_newest, members)
            return _GroupInput(dz, dt, net[2][:0], net[3][:0], "prior", t_newest, members)

        out: dict[str, _GroupInput] = {"net": make(net, [("net", net)])}
        for line, lp in line_pool.items():
            out[f"line.{line}"] = make(lp, [(f"line.{line}", lp), ("net", net)])
        for s in segs:
            if len(self._increments[s].dt) >= cfg.segment_min_increments:
                own = pool([s])
                group = f"seg.{s[0]}.{s[1]}"
                out[group] = make(
                    own, [(group, own), (f"line.{s[0]}", line_pool[s[0]]), ("net", net)]
                )
        return out

    def _fingerprint(self, group: str, g: _GroupInput) -> str:
        cfg = self.config
        h = hashlib.sha256()
        settings = (
            group,
            g.level_source,
            cfg.samples,
            cfg.seed,
            cfg.min_increments,
            cfg.min_levels,
        )
        h.update(repr(settings).encode())
        for prior in (cfg.drift_prior, cfg.level_prior):
            if prior is not None:
                h.update(
                    repr(
                        (prior.m0.tolist(), prior.lambda0, prior.Psi0.tolist(), prior.nu0)
                    ).encode()
                )
        for a in (g.dz, g.dt, g.level, g.age):
            h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
            h.update(repr(a.shape).encode())
        return h.hexdigest()

    def _rebuild_posteriors(self) -> None:
        if not self._increments:
            return
        for group, g in sorted(self._group_inputs().items()):
            fp = self._fingerprint(group, g)
            entry = self._current(group)
            if (entry is not None and entry.fingerprint == fp) or self._refused.get(group) == fp:
                continue
            in_force = self._models.get(group)
            version = self._next_version(group)
            try:
                post = self._build(group, g, version)
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
            if in_force is not None and (why := self._one_segment_move(g, post, in_force)):
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

    def _one_segment_move(
        self, g: _GroupInput, post: DegradationPosterior, in_force: ModelEntry
    ) -> str | None:
        r"""The move bound: why the pooled posterior ``post`` moved too far on the strength of
        one segment, or None.

        The move is :math:`\max |\bar\theta_{new} - \bar\theta_{old}| / sd(\theta_{old})`
        over the elements of ``mu`` and ``Sigma``, in the posterior sd of the version in force
        (from its draws). Beyond ``max_move_sd`` the conjugate posterior means are computed
        again without each member segment in turn; when leaving out one segment brings the
        move back within the bound (or the group has one segment only and a prior in force),
        that segment alone moved it: the candidate is held (not published) and the segment's
        newest record reported. Segment groups, and a pooled group of one segment whose
        version in force came from data, are not judged (their data are one segment's own).
        """
        if post.group.startswith("seg."):
            return None
        old: DegradationPosterior = in_force.message  # type: ignore[assignment]
        o_mu, o_sigma = old.mu.array(), old.sigma.array()
        ref = (o_mu.mean(axis=0), o_mu.std(axis=0), o_sigma.mean(axis=0), o_sigma.std(axis=0))

        def move(mu, sigma) -> Move:
            return _largest_move([("mu", mu, ref[0], ref[1]), ("sigma", sigma, ref[2], ref[3])])

        bound = self.config.max_move_sd
        moved = move(post.mu.array().mean(axis=0), post.sigma.array().mean(axis=0))
        if moved[0] <= bound:
            return None
        members = [s for s in g.members if len(self._increments[s].dt)]
        if len(members) == 1 and old.n_increments > 0:
            return None  # a one-segment group from data: it moves with its segment
        culprit: Segment | None = members[0] if len(members) == 1 else None
        if culprit is None:
            best = (math.inf, members[0])
            for s in members:
                rest = [self._increments[m] for m in members if m != s]
                try:
                    p = posterior_drift_diffusion(
                        np.concatenate([i.dz for i in rest]).reshape(-1, _N),
                        np.concatenate([i.dt for i in rest]),
                        self.config.drift_prior,
                        min_increments=1,
                    )
                except CalibrationError:
                    continue
                without = move(p.m, p.mean_sigma())[0]
                best = min(best, (without, s))
            if best[0] <= bound:
                culprit = best[1]
        if culprit is None:
            return None  # several segments agree: a real change
        why = (
            f"posterior {post.group} not published: moved {moved[1]} of version "
            f"{old.version} in force (more than {bound:g}) on the strength of segment "
            f"{culprit[0]}/{culprit[1]} alone"
        )
        records = self._history[culprit][0]
        rec = records[-1]
        self._outbox.append(Quarantine("trc", rec.line, rec.segment, why, rec))
        return why

    def _build(self, group: str, g: _GroupInput, version: int) -> DegradationPosterior:
        cfg = self.config
        rng = group_rng(cfg.seed, group, version)
        min_inc = cfg.segment_min_increments if group.startswith("seg.") else cfg.min_increments
        if g.level_source != "prior":
            s = sample_degradation_posterior(
                g.dz,
                g.dt,
                g.level,
                g.age,
                ns=cfg.samples,
                rng=rng,
                drift_prior=cfg.drift_prior,
                level_prior=cfg.level_prior,
                min_increments=min_inc,
                min_levels=cfg.min_levels,
            )
            mu, sigma, z_plus, sigma_z_plus = s.mu, s.sigma, s.z_plus, s.sigma_z_plus
        else:
            post = posterior_drift_diffusion(g.dz, g.dt, cfg.drift_prior, min_increments=min_inc)
            mu, sigma = post.sample(cfg.samples, rng)
            level_prior = cfg.level_prior or NIWPrior.default_level(_N)
            z_plus, sigma_z_plus = _sample_prior(level_prior, cfg.samples, rng)
        return DegradationPosterior(
            group=group,
            version=version,
            t=g.t_newest,
            indicators=list(INDICATORS),
            mu=_arr(mu),
            sigma=_arr(sigma),
            z_plus=_arr(z_plus),
            sigma_z_plus=_arr(sigma_z_plus),
            n_increments=len(g.dt),
            n_levels=len(g.age),
        )
