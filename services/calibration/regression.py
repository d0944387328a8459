"""Observation model calibration: least squares fit of ``y = H z + b + e`` (paper Eq. 3-6).

Pure core: numpy only, no I/O. ``z`` are ln TRC indicators (n), ``y`` ln on-board indices (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.drift_diffusion import CalibrationError, as_finite

__all__ = ["ObservationFit", "fit_observation"]


@dataclass(frozen=True)
class ObservationFit:
    """Fitted observation model ``y = H z + b + e``, ``e ~ N(0, R)``.

    Attributes
    ----------
    H : ndarray, shape (m, n)
        Sensitivity of the on-board indices to the TRC indicators.
    b : ndarray, shape (m,)
        Bias.
    R : ndarray, shape (m, m)
        Maximum-likelihood residual covariance ``E^T E / N`` (paper: zero-mean MVN fit).
    n_pairs : int
        Number N of (z, y) pairs used.
    r2 : ndarray, shape (m,)
        Coefficient of determination of each on-board index.
    resid_std : ndarray, shape (m,)
        ``sqrt(diag R)``, residual standard deviation of each index (ln units).
    condition : float
        Condition number of the centred, unit-variance indicator matrix (1 = uncorrelated
        indicators; large = nearly collinear, H badly determined).
    z_min, z_max : ndarray, shape (n,)
        Range of the calibration data; predictions outside it are extrapolations.
    se_H : ndarray, shape (m, n)
        Least-squares standard error of each element of ``H``.
    se_b : ndarray, shape (m,)
        Least-squares standard error of each element of ``b``.
    se_R : ndarray, shape (m, m)
        Sampling standard error of each element of ``R`` (Wishart, ``N - n - 1`` degrees of
        freedom); on the diagonal, ``R_ii sqrt(2 / (N - n - 1))``.
    """

    H: np.ndarray
    b: np.ndarray
    R: np.ndarray
    n_pairs: int
    r2: np.ndarray
    resid_std: np.ndarray
    condition: float
    z_min: np.ndarray
    z_max: np.ndarray
    se_H: np.ndarray
    se_b: np.ndarray
    se_R: np.ndarray

    def predict(self, z) -> np.ndarray:
        """Mean on-board indices ``H z + b`` for ``z`` of shape (..., n)."""
        return np.asarray(z, dtype=np.float64) @ self.H.T + self.b


def fit_observation(
    Z, Y, *, min_pairs: int = 10, max_condition: float = 1e4, rel_tol: float = 1e-10
) -> ObservationFit:
    r"""Fit ``H``, ``b`` and ``R`` by multivariate least squares with intercept (Eq. 5-6).

    .. math::

        \mathbf{Y} = \tilde{\mathbf{Z}}\tilde{\mathbf{H}} + \mathbf{E},\quad
        \tilde{\mathbf{Z}} = [\mathbf{Z}\ \mathbf{1}],\quad
        \tilde{\mathbf{H}} = (\tilde{\mathbf{Z}}^T\tilde{\mathbf{Z}})^{-1}
        \tilde{\mathbf{Z}}^T\mathbf{Y} = \begin{bmatrix}\mathbf{H}^T\\ \mathbf{b}\end{bmatrix},
        \quad \mathbf{R} = \frac{1}{N}\mathbf{E}^T\mathbf{E}

    Standard errors (what the calibration service's publication rule measures a change
    against), with :math:`\mathbf S = \mathbf E^T\mathbf E/(N - n - 1)` and
    :math:`\mathbf G = (\mathbf Z_c^T\mathbf Z_c)^{-1}` on the centred indicators:

    .. math::

        \operatorname{se}(H_{ij}) = \sqrt{S_{ii} G_{jj}},\quad
        \operatorname{se}(b_i) = \sqrt{S_{ii}\,(1/N + \bar{\mathbf z}^T\mathbf G
        \bar{\mathbf z})},\quad
        \operatorname{se}(R_{ij}) = \sqrt{(R_{ij}^2 + R_{ii}R_{jj})/(N - n - 1)}

    The normal equations are never formed: the slopes come from an SVD least squares solve
    on the centred data and :math:`\mathbf{b} = \bar{\mathbf{y}} - \mathbf{H}\bar{\mathbf{z}}`,
    which is algebraically the same estimate with better numerics.

    Parameters
    ----------
    Z : array_like, shape (N, n)
        ln TRC indicators (1-D is taken as n = 1).
    Y : array_like, shape (N, m)
        ln on-board indices paired row by row with ``Z`` (1-D is taken as m = 1).
    min_pairs : int
        Smallest N accepted; the fit also needs ``N >= n + 1 + m`` (and ``n + 2``) so that
        the residuals have at least m degrees of freedom and ``R`` can be nonsingular.
    max_condition : float
        Largest accepted condition number of the standardised ``Z`` (collinearity guard).
    rel_tol : float
        ``R`` is refused as singular when its smallest eigenvalue is below ``rel_tol``
        times the largest variance of ``Y``, and a ``Z`` column is constant when its std is below
        ``rel_tol * max(1, |mean|)``.

    Returns
    -------
    ObservationFit

    Raises
    ------
    ValueError
        NaN/inf, wrong dimensionality or mismatched row counts (message names the argument).
    CalibrationError
        Too few pairs, a constant or collinear indicator, or a singular ``R`` (exact fit).
    """
    Z = as_finite("Z", Z, 2)
    Y = as_finite("Y", Y, 2)
    if Z.shape[0] != Y.shape[0]:
        raise ValueError(f"Z and Y: row counts differ ({Z.shape[0]} vs {Y.shape[0]} pairs)")
    (N, n), m = Z.shape, Y.shape[1]
    need = max(min_pairs, n + 2, n + 1 + m)
    if need > N:
        raise CalibrationError(
            f"too few (TRC, on-board) pairs: {N}; need at least {need} "
            f"(n={n} indicators, m={m} indices, min_pairs={min_pairs})"
        )
    zbar, ybar = Z.mean(axis=0), Y.mean(axis=0)
    Zc, Yc = Z - zbar, Y - ybar
    cond = _condition(Zc, zbar, max_condition, rel_tol)
    Ht, *_ = np.linalg.lstsq(Zc, Yc, rcond=None)  # (n, m) = H^T
    H = Ht.T
    b = ybar - zbar @ Ht
    E = Yc - Zc @ Ht
    R = E.T @ E / N
    R = 0.5 * (R + R.T)
    var_y = (Yc**2).mean(axis=0)
    _check_residuals(R, var_y, rel_tol)
    r2 = 1.0 - np.diag(R) / var_y
    dof = N - n - 1
    s_ii = np.diag(E.T @ E) / dof
    _, sv_c, vt = np.linalg.svd(Zc, full_matrices=False)
    G = (vt.T / sv_c**2) @ vt  # (Zc^T Zc)^-1 without forming it
    se_H = np.sqrt(np.outer(s_ii, np.diag(G)))
    se_b = np.sqrt(s_ii * (1.0 / N + zbar @ G @ zbar))
    se_R = _se_R(R, dof)
    return _observation_fit(Z, H, b, R, r2, cond, (se_H, se_b, se_R))


def _condition(Zc: np.ndarray, zbar: np.ndarray, max_condition: float, rel_tol: float) -> float:
    """Condition number of the standardised centred indicators ``Zc``; CalibrationError when
    an indicator is constant or they are collinear (H could not be told apart per indicator).
    It measures collinearity between indicators only: centring handles the intercept."""
    zsd = np.sqrt((Zc**2).mean(axis=0))
    const = np.flatnonzero(zsd <= rel_tol * np.maximum(1.0, np.abs(zbar)))
    if const.size:
        raise CalibrationError(
            f"TRC indicator column(s) {const.tolist()} are constant over the {len(Zc)} pairs; "
            "H cannot be identified: need pairs spanning a range of each indicator"
        )
    sv = np.linalg.svd(Zc / zsd, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    if cond > max_condition:
        raise CalibrationError(
            f"TRC indicators are (nearly) collinear: condition number {cond:.3g} > "
            f"{max_condition:.3g}; H cannot be separated per indicator: need pairs where "
            "the indicators vary independently, or fit fewer indicators"
        )
    return cond


def _check_residuals(R: np.ndarray, var_y: np.ndarray, rel_tol: float) -> None:
    """CalibrationError when ``R`` is not positive definite, judged against the spread of Y
    itself (``var_y``): an exact fit leaves round-off residuals whose own eigenvalue ratio
    can look harmless."""
    tiny = np.finfo(float).tiny
    ev = np.linalg.eigvalsh(R)
    if ev[0] <= rel_tol * max(var_y.max(), tiny):
        exact = np.flatnonzero(np.diag(R) <= rel_tol * np.maximum(var_y, tiny))
        what = (
            f"on-board index column(s) {exact.tolist()} are fitted exactly"
            if exact.size
            else "a combination of on-board indices is fitted exactly (collinear indices)"
        )
        raise CalibrationError(
            f"residual covariance R is not positive definite (eigenvalues {ev.tolist()}): "
            f"{what}; need noisy, non-duplicated on-board indices"
        )


def _observation_fit(Z, H, b, R, r2, condition: float, se: tuple) -> ObservationFit:
    """The fit of ``H``, ``b``, ``R`` on the pairs of ``Z``; ``se``: those of H, b, R."""
    se_H, se_b, se_R = se
    return ObservationFit(
        H=H,
        b=b,
        R=R,
        n_pairs=len(Z),
        r2=r2,
        resid_std=np.sqrt(np.diag(R)),
        condition=condition,
        z_min=Z.min(axis=0),
        z_max=Z.max(axis=0),
        se_H=se_H,
        se_b=se_b,
        se_R=se_R,
    )


def _se_R(R: np.ndarray, dof: float) -> np.ndarray:
    """Sampling standard error of each element of ``R`` (Wishart, ``dof`` degrees of freedom)."""
    return np.sqrt((R**2 + np.outer(np.diag(R), np.diag(R))) / dof)


def fit_unit_observation(Z, Y, *, H0, b0, R0, design, shrink_pairs: float) -> ObservationFit:
    r"""One on-board unit's ``H, b, R``, shrunk towards the fleet's ``H0, b0, R0``.

    Each index's row :math:`\theta_i = [H_i\ b_i]` has a Gaussian prior centred on the
    fleet's row with the precision of ``shrink_pairs`` (:math:`k`) pairs of the fleet's
    design :math:`\mathbf D` (``design``: the mean of :math:`\tilde z \tilde z^T`,
    :math:`\tilde z = [z\ 1]`, over all pairs), so that

    .. math::

        \theta_i = (\tilde{\mathbf Z}^T\tilde{\mathbf Z} + k\mathbf D)^{-1}
                   (\tilde{\mathbf Z}^T \mathbf y_i + k\mathbf D\,\theta_{0,i}), \qquad
        \mathbf R = \frac{\mathbf E^T\mathbf E + k\,\mathbf R_0}{N + k},

    with :math:`\mathbf E` the unit's residuals: a unit with few pairs keeps close to the
    fleet's model, one with many gets its own least-squares fit (as :math:`N/k` grows). A
    unit whose pairs span a narrow range of ``z`` (one segment, one run) still gets a
    well-posed fit, its slopes held by the prior. Standard errors: :math:`\operatorname{se}
    (\theta_{ij}) = \sqrt{R_{ii} [(\tilde{\mathbf Z}^T\tilde{\mathbf Z} + k\mathbf D)^{-1}]
    _{jj}}`; ``se_R`` as in :func:`fit_observation` with :math:`N + k` pairs. ``r2`` is on the
    unit's own pairs (can be negative for a unit that reads little of the track's changes).

    ``Y`` may be NaN where a unit did not measure an index (a vertical-only sensor): each
    row of H, b is then fitted on the pairs that have its index (the fleet's row when none
    has it), and each element of R on the pairs that have both of its indices, with the
    same prior (:func:`_fit_unit_rows`).
    """
    Z = as_finite("Z", Z, 2)
    Y = np.asarray(Y, dtype=np.float64)
    missing = np.isnan(Y)
    if missing.any():
        if Y.ndim != 2 or not np.isfinite(Y[~missing]).all():
            raise ValueError("Y: must be (N, m) of finite numbers, or NaN where not measured")
        return _fit_unit_rows(Z, Y, H0, b0, R0, design, shrink_pairs)
    Y = as_finite("Y", Y, 2)
    if Z.shape[0] != Y.shape[0] or Z.shape[0] < 1:
        raise ValueError(f"Z and Y: need the same number >= 1 of rows, got {len(Z)}, {len(Y)}")
    if not shrink_pairs > 0:
        raise ValueError(f"shrink_pairs: must be > 0, got {shrink_pairs}")
    N, n = Z.shape
    X = np.hstack([Z, np.ones((N, 1))])
    theta0 = np.hstack([np.asarray(H0, float), np.asarray(b0, float)[:, None]])  # (m, n + 1)
    D = np.asarray(design, dtype=np.float64)
    A = X.T @ X + shrink_pairs * D
    try:
        A_inv = np.linalg.inv(A)
    except np.linalg.LinAlgError as exc:
        raise CalibrationError(f"unit fit: singular design ({exc})") from None
    theta = (A_inv @ (X.T @ Y + shrink_pairs * D @ theta0.T)).T  # (m, n + 1)
    H, b = theta[:, :n], theta[:, n]
    E = Y - X @ theta.T
    R = (E.T @ E + shrink_pairs * np.asarray(R0, float)) / (N + shrink_pairs)
    R = 0.5 * (R + R.T)
    dof = max(N + shrink_pairs - n - 1, 1.0)
    se = np.sqrt(np.outer(np.diag(R), np.diag(A_inv)))  # (m, n + 1)
    sst = ((Y - Y.mean(axis=0)) ** 2).sum(axis=0)
    r2 = 1.0 - (E**2).sum(axis=0) / np.where(sst > 0, sst, np.inf)
    cond = float(np.linalg.cond(A))
    return _observation_fit(Z, H, b, R, r2, cond, (se[:, :n], se[:, n], _se_R(R, dof)))


def _fit_unit_rows(Z, Y, H0, b0, R0, design, shrink_pairs: float) -> ObservationFit:
    r""":func:`fit_unit_observation` of pairs with indices missing (``Y`` NaN there): row
    :math:`i` on the pairs :math:`P_i` that have index :math:`i`,

    .. math::

        \theta_i = (\tilde{\mathbf Z}_{P_i}^T\tilde{\mathbf Z}_{P_i} + k\mathbf D)^{-1}
                   (\tilde{\mathbf Z}_{P_i}^T \mathbf y_{P_i,i} + k\mathbf D\,\theta_{0,i}),
        \qquad
        R_{ij} = \frac{\sum_{P_i \cap P_j} e_i e_j + k R_{0,ij}}{|P_i \cap P_j| + k}.
    """
    if Z.shape[0] != Y.shape[0] or Z.shape[0] < 1:
        raise ValueError(f"Z and Y: need the same number >= 1 of rows, got {len(Z)}, {len(Y)}")
    if not shrink_pairs > 0:
        raise ValueError(f"shrink_pairs: must be > 0, got {shrink_pairs}")
    k = shrink_pairs
    N, n = Z.shape
    m = Y.shape[1]
    have = ~np.isnan(Y)
    X = np.hstack([Z, np.ones((N, 1))])
    theta0 = np.hstack([np.asarray(H0, float), np.asarray(b0, float)[:, None]])
    D = np.asarray(design, dtype=np.float64)
    theta, se_theta, conds = np.empty((m, n + 1)), np.empty((m, n + 1)), []
    for i in range(m):
        Xi, yi = X[have[:, i]], Y[have[:, i], i]
        A = Xi.T @ Xi + k * D
        try:
            A_inv = np.linalg.inv(A)
        except np.linalg.LinAlgError as exc:
            raise CalibrationError(f"unit fit: singular design ({exc})") from None
        theta[i] = A_inv @ (Xi.T @ yi + k * D @ theta0[i])
        se_theta[i] = np.diag(A_inv)
        conds.append(float(np.linalg.cond(A)))
    H, b = theta[:, :n], theta[:, n]
    E = np.where(have, Y - X @ theta.T, 0.0)
    both = have.T.astype(float) @ have.astype(float)  # pairs with indices i and j
    R = (E.T @ E + k * np.asarray(R0, float)) / (both + k)
    R = 0.5 * (R + R.T)
    se = np.sqrt(np.diag(R)[:, None] * se_theta)
    dof = max(float(have.sum(axis=0).min()) + k - n - 1, 1.0)
    counts = have.sum(axis=0)
    means = np.where(have, Y, 0.0).sum(axis=0) / np.maximum(counts, 1)
    sst = (np.where(have, Y - means, 0.0) ** 2).sum(axis=0)
    r2 = 1.0 - (E**2).sum(axis=0) / np.where(sst > 0, sst, np.inf)
    return _observation_fit(Z, H, b, R, r2, max(conds), (se[:, :n], se[:, n], _se_R(R, dof)))
