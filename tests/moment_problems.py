"""Level hierarchies whose limit distribution is known, for the variance and CDF estimators.

``Q_l = Z + c 2^(-l) W`` with ``Z`` standard normal or gamma distributed and
``W`` an independent standard normal: the level-``l`` sample returns ``Q_l``
and ``Q_{l-1}`` of the same ``(Z, W)``, so ``Q_l -> Z`` with
``Var(Q_l) - Var(Z) = c^2 4^-l`` and ``F_l(s) - F_Z(s) = O(4^-l)``. The
randomness of sample ``i`` on level ``l`` is a pure function of
``(seed, level, i)`` (:func:`mlmc_problems.indexed_normals`).
"""

from __future__ import annotations

import math
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


@dataclass(frozen=True)
class RoundedLimit:
    """A discrete QoI: ``Q_l = round(sigma X + 2^(-rate l) W)``, ``X``, ``W`` standard normal; cost ``2^l``.

    Few pairs of a level differ, and often in opposite directions: the
    unbiased variance of a level's ``h2`` difference comes out negative.
    """

    sigma: float = 2.0
    rate: float = 0.5
    seed: int = 0

    def variance(self) -> float:
        """``Var(round(sigma X))``, the limit's variance (summed over the integers)."""
        k = np.arange(-60, 61)
        p = ndtr((k + 0.5) / self.sigma) - ndtr((k - 0.5) / self.sigma)
        return float(np.sum(k**2 * p) - np.sum(k * p) ** 2)

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        normals = indexed_normals(self.seed, level, indices, 2)
        x, w = self.sigma * normals[:, 0], normals[:, 1]
        fine = np.round(x + 2.0 ** (-self.rate * level) * w)
        coarse = np.zeros_like(fine) if level == 0 else np.round(x + 2.0 ** (-self.rate * (level - 1)) * w)
        return fine, coarse, np.full(len(fine), 2.0**level)


@dataclass(frozen=True)
class RareJumps:
    """``Q_l = Z + sum_{k=1..l} J (B_k - p_k)``: level ``k`` adds a jump ``J`` with probability ``p_k = p0 2^-k``.

    ``Var(Q_l) = 1 + sum_k J^2 p_k (1 - p_k)``, ``J^2 = 1 / p0``; a level's
    differences are 0 but for a rare jump, which a level's first samples may
    all miss. Cost ``2^l``.
    """

    p0: float = 0.2
    seed: int = 0

    def variance(self, levels: int = 60) -> float:
        """``Var(Q_levels)`` (the limit by default, to rounding)."""
        p = self.p0 * 2.0 ** -np.arange(1, levels + 1)
        return float(1.0 + np.sum(p * (1.0 - p)) / self.p0)

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        normals = indexed_normals(self.seed, level, indices, level + 1)
        p = self.p0 * 2.0 ** -np.arange(1, level + 1)
        jumps = ((ndtr(normals[:, 1:]) < p) - p) / math.sqrt(self.p0)
        fine = normals[:, 0] + np.sum(jumps, axis=1)
        coarse = np.zeros_like(fine) if level == 0 else fine - jumps[:, -1]
        return fine, coarse, np.full(len(fine), 2.0**level)
