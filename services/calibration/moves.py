"""How far a model moved, in standard errors: the publication rule's materiality test
(:func:`calibration_change`, :func:`posterior_change`) and the pooled posteriors' move bound."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from schemas import Calibration, DegradationPosterior
from services.calibration.regression import ObservationFit

Move = tuple[float, str]  # (largest move in standard errors, what moved and how)


def largest_move(moves: Iterable[tuple[str, Any, Any, Any]]) -> Move:
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
    return largest_move(
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
    return largest_move(moves)
