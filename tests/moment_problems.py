"""Level hierarchies whose limit distribution is known, for the variance and CDF estimators.

``Q_l = Z + c 2^(-l) W`` with ``Z`` standard normal or gamma distributed and
``W`` an independent standard normal: the level-``l`` sample returns ``Q_l``
and ``Q_{l-1}`` of the same ``(Z, W)``, so ``Q_l -> Z`` with
``Var(Q_l) - Var(Z) = c^2 4^-l`` and ``F_l(s) - F_Z(s) = O(4^-l)``. The
randomness of sample ``i`` on level ``l`` is a pure function of
``(seed, level, i)`` (:func:`mlmc_problems.indexed_normals`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mlmc_problems import indexed_normals
from scipy import stats
from scipy.special import gammaincinv, ndtr


@dataclass(frozen=True)
class PerturbedLimit:
    """``Q_l = Z + scale 2^(-l) W``; ``Z ~ N(0, 1)`` or ``Gamma(shape, 1)``; cost ``2^(gamma l)``."""

    kind: str = "gaussian"
    shape: float = 2.0
    scale: float = 1.0
    gamma: float = 1.0
    seed: int = 0

    @property
    def limit(self):
        """The distribution of ``Z`` (a frozen scipy distribution)."""
        return stats.norm() if self.kind == "gaussian" else stats.gamma(self.shape)

    def variance(self, level: int | None = None) -> float:
        """``Var(Q_l)``; ``Var(Z)`` for ``level=None``."""
        extra = 0.0 if level is None else self.scale**2 * 4.0**-level
        return float(self.limit.var()) + extra

    def values(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Z, W)`` of the given samples."""
        normals = indexed_normals(self.seed, level, indices, 2)
        z = normals[:, 0]
        if self.kind == "gamma":
            z = gammaincinv(self.shape, ndtr(z))
        return z, normals[:, 1]

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z, w = self.values(level, indices)
        fine = z + self.scale * 2.0**-level * w
        coarse = np.zeros_like(fine) if level == 0 else z + self.scale * 2.0 ** (1 - level) * w
        return fine, coarse, np.full(len(fine), 2.0 ** (self.gamma * level))
