r"""The observation model's refit: the swap rule and the outlying pairs. Pure.

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

"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from schemas import INDICATORS, ONBOARD_INDICES, Calibration
from services.calibration.config import CalibratorConfig
from services.calibration.regression import ObservationFit
from services.calibration.robust import reference
from services.calibration.state import Pair

_N = len(INDICATORS)
_RESIDUAL_SD_FLOOR = 1e-3  # ln: and that of (TRC, on-board) residuals
_MAX_OUTLIER_SHARE = 0.2  # more outlying pairs than this share are a burst: the swap rule's


def mean_loglik(H, b, R, Z, Y) -> float:
    r"""Mean Gaussian log-likelihood per pair, :math:`\frac1N\sum_i\log N(y_i; Hz_i + b, R)`."""
    H, b, R = (np.asarray(a, dtype=np.float64) for a in (H, b, R))
    E = np.asarray(Y, dtype=np.float64) - np.asarray(Z, dtype=np.float64) @ H.T - b
    L = np.linalg.cholesky(R)
    w = np.linalg.solve(L, E.T)  # (m, N)
    logdet = 2.0 * np.log(np.diag(L)).sum()
    m = R.shape[0]
    return float(-0.5 * (m * math.log(2 * math.pi) + logdet + (w**2).sum(axis=0).mean()))


def worse(
    old: Calibration, fit: ObservationFit, Z: np.ndarray, Y: np.ndarray, cfg: CalibratorConfig
) -> str | None:
    """The swap rule: why the candidate ``fit`` is worse than ``old``, or None."""
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


def outlying_pairs(
    pairs: Sequence[Pair], H: np.ndarray, b: np.ndarray, n_ref: int, cfg: CalibratorConfig
) -> list[tuple[int, str]]:
    """The pairs after the first ``n_ref`` whose residual ``y - (Hz + b)``
    under the fit ``H, b`` is beyond ``robust_k`` robust sd (1.4826 MAD) of the residuals
    of the first ``n_ref`` (all pairs when ``n_ref`` is 0: a first fit judged on its own
    pairs): ``(position, reason)`` of each. Only when they are a few (at most
    ``_MAX_OUTLIER_SHARE`` of the pairs judged, or one): single wild pairs (a wrong
    pairing, a glitch) go here, before the swap rule judges the rest, which would
    otherwise quarantine every new pair with them; a burst of bad pairs (a faulty unit)
    is left whole to the swap rule."""
    Z = np.array([p.z for p in pairs]).reshape(-1, _N)
    Y = np.array([p.y for p in pairs]).reshape(-1, len(ONBOARD_INDICES))
    E = Y - Z @ H.T - b
    ref = reference(
        E[:n_ref] if n_ref else E, min_count=cfg.robust_min_count, floor=_RESIDUAL_SD_FLOOR
    )
    if ref is None:
        return []
    out = [i for i in range(n_ref, len(E)) if ref.outlying(E[i], cfg.robust_k)]
    if len(out) > max(1.0, _MAX_OUTLIER_SHARE * (len(E) - n_ref)):
        return []
    found = []
    for i in out:
        p, d = pairs[i], np.abs(E[i] - ref.median) / ref.scale
        m = int(np.argmax(d))
        why = (
            f"pair of index {p.index_id} with TRC run {p.run_id} left out of the "
            f"observation model: residual of {ONBOARD_INDICES[m]} {E[i][m]:+.3f} ln is "
            f"{d[m]:.1f} robust sd (1.4826 MAD {ref.scale[m]:.3g}) from the fit's "
            f"(more than {cfg.robust_k:g})"
        )
        found.append((i, why))
    return found
