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

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


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
