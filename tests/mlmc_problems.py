"""Cheap MLMC test problems with known answers, as level samplers.

Each problem is a level sampler ``problem(level, indices) -> (fine, coarse,
cost)`` whose randomness is a pure function of ``(seed, level, index)``: the
normals of sample ``i`` on level ``l`` come from a Philox stream keyed by
``(seed, level)`` at counter ``i * (width / 4)`` (Philox yields four 64-bit
words per counter step, one per uniform double), so any sample can be
recomputed alone and batches need no per-sample generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri


def indexed_normals(seed: int, level: int, indices: np.ndarray, n_per_sample: int) -> np.ndarray:
    """Standard normals of shape (len(indices), n_per_sample), a pure function of each index."""
    indices = np.asarray(indices, dtype=np.int64)
    width = 4 * -(-n_per_sample // 4)
    out = np.empty((len(indices), n_per_sample))
    # Contiguous runs of indices are drawn from one stream position.
    breaks = np.flatnonzero(np.diff(indices) != 1) + 1
    for run in np.split(np.arange(len(indices)), breaks):
        if run.size == 0:
            continue
        start = int(indices[run[0]])
        bit_generator = np.random.Philox(
            key=np.array([seed, level], dtype=np.uint64),
            counter=np.array([start * (width // 4), 0, 0, 0], dtype=np.uint64),
        )
        uniforms = np.random.Generator(bit_generator).random(run.size * width).reshape(run.size, width)
        # random() lies on the grid k 2^-53 including 0; shift half a step into (0, 1).
        out[run] = ndtri(uniforms[:, :n_per_sample] + 2.0**-54)
    return out


def sample_levels(sampler, levels, n: int) -> dict[str, list]:
    """Draw samples 0..n-1 on each level; keyword arguments for ``level_statistics``."""
    drawn = [sampler(level, np.arange(n)) for level in levels]
    return {
        "fine": [d[0] for d in drawn],
        "coarse": [d[1] for d in drawn],
        "cost": [d[2] for d in drawn],
        "levels": list(levels),
    }


def shifted_screening(shifts, *, seed: int, n: int = 20, noise: float = 0.01):
    """A screening table of ``n`` samples per level whose level means ``E[Y_l]`` are ``shifts[l]`` (``l >= 1``).

    ``Q ~ 20 + N(0, 1)``; a difference ``Y_l`` is ``shifts[l] + noise N(0, 1)``; the cost of level ``l`` is
    ``2^l``. Keyword arguments of ``level_statistics``.
    """
    rng = np.random.default_rng(seed)
    fine, coarse = [], []
    for level, shift in enumerate(shifts):
        q = 20 + rng.normal(size=n)
        fine.append(q)
        coarse.append(q - shift + noise * rng.normal(size=n) if level else np.zeros(n))
    return {"fine": fine, "coarse": coarse, "cost": [np.full(n, 2.0**level) for level in range(len(shifts))]}


@dataclass(frozen=True)
class Synthetic:
    """Hierarchy with prescribed rates: ``Y_l = a 2^(-alpha l) + b 2^(-alpha2 l) + sqrt(v1 2^(-beta l)) Z_l``.

    ``Q_0 = mu0 + s0 Z_0`` and ``Q_l = Q_{l-1} + Y_l`` with independent
    standard normals ``Z_0, Z_1, ...`` of one sample; a level-``l`` sample
    draws ``Z_0..Z_l`` and returns ``Q_l`` and ``Q_{l-1}``. The cost of a
    level-``l`` sample is ``2^(gamma l)``. With ``scales`` the QoI is a
    vector ``scales * Q`` (one column per scale). ``b`` (default 0) adds a
    second-order bias term, the one Richardson extrapolation leaves. On the
    ``loose_levels`` the coarse value comes from an independent draw (as for
    ``coupled=False`` on every level): consistent, but ``V_l > Var(Q_l)``.
    """

    alpha: float = 1.0
    beta: float = 2.0
    gamma: float = 1.0
    a: float = 1.0
    v1: float = 1.0
    mu0: float = 1.0
    s0: float = 1.0
    seed: int = 0
    scales: tuple[float, ...] | None = None
    coupled: bool = True
    b: float = 0.0
    alpha2: float = 2.0
    loose_levels: tuple[int, ...] = ()

    def mean_diff(self, level: int) -> float:
        """``E[Y_l]``."""
        if level == 0:
            return self.mu0
        return self.a * 2.0 ** (-self.alpha * level) + self.b * 2.0 ** (-self.alpha2 * level)

    def var_diff(self, level: int) -> float:
        """``V_l``."""
        return self.s0**2 if level == 0 else self.v1 * 2.0 ** (-self.beta * level)

    def mean(self, level: int | None = None) -> float:
        """``E[Q_l]``; the limit ``E[Q]`` for ``level=None``."""
        if level is None:
            r, r2 = 2.0 ** (-self.alpha), 2.0 ** (-self.alpha2)
            return self.mu0 + self.a * r / (1.0 - r) + self.b * r2 / (1.0 - r2)
        return sum(self.mean_diff(k) for k in range(level + 1))

    def variance(self, level: int | None = None) -> float:
        """``Var(Q_l)``; the limit ``Var(Q)`` for ``level=None``."""
        if level is None:
            r = 2.0 ** (-self.beta)
            return self.s0**2 + self.v1 * r / (1.0 - r)
        return sum(self.var_diff(k) for k in range(level + 1))

    def cost(self, level: int) -> float:
        """Cost of one level-``level`` sample."""
        return 2.0 ** (self.gamma * level)

    def _paths(self, level: int, z: np.ndarray) -> np.ndarray:
        steps = np.arange(level + 1)
        drift = np.array([self.mean_diff(int(step)) for step in steps])
        spread = np.where(steps == 0, self.s0, np.sqrt(self.v1 * 2.0 ** (-self.beta * steps)))
        return np.cumsum(drift + spread * z, axis=1)

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z = indexed_normals(self.seed, level, indices, level + 1)
        paths = self._paths(level, z)
        fine = paths[:, level]
        if level == 0:
            coarse = np.zeros_like(fine)
        elif self.coupled and level not in self.loose_levels:
            coarse = paths[:, level - 1]
        else:
            # Broken coupling: the coarse value comes from an independent draw.
            other = indexed_normals(self.seed + 7919, level, indices, level + 1)
            coarse = self._paths(level, other)[:, level - 1]
        cost = np.full(len(indices), self.cost(level))
        if self.scales is not None:
            scales = np.asarray(self.scales)
            return fine[:, None] * scales, coarse[:, None] * scales, cost
        return fine, coarse, cost


@dataclass(frozen=True)
class GbmEuler:
    """Geometric Brownian motion ``dS = r S dt + sigma S dW`` by Euler-Maruyama.

    Level ``l`` uses ``2^l`` steps of ``h_l = 2^-l T``; the coarse path of a
    level-``l`` sample uses the pairwise sums of the fine Brownian increments.
    The QoI is ``S_T``. Cost: number of time steps (fine plus coarse).
    """

    s0: float = 1.0
    r: float = 1.0
    sigma: float = 0.5
    maturity: float = 1.0
    seed: int = 0

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n_steps = 2**level
        h = self.maturity / n_steps
        dw = indexed_normals(self.seed, level, indices, n_steps) * np.sqrt(h)
        fine = self.s0 * np.prod(1.0 + self.r * h + self.sigma * dw, axis=1)
        if level == 0:
            coarse = np.zeros_like(fine)
            cost = np.full(len(indices), 1.0)
        else:
            dw_coarse = dw[:, 0::2] + dw[:, 1::2]
            coarse = self.s0 * np.prod(1.0 + 2.0 * self.r * h + self.sigma * dw_coarse, axis=1)
            cost = np.full(len(indices), 1.5 * n_steps)
        return fine, coarse, cost

    def mean(self, level: int | None = None) -> float:
        """``E[S_T^(l)] = S0 (1 + r h_l)^(T/h_l)``; ``S0 e^(rT)`` for ``level=None``."""
        if level is None:
            return self.s0 * np.exp(self.r * self.maturity)
        h = self.maturity / 2**level
        return self.s0 * (1.0 + self.r * h) ** (2**level)

    def var_diff(self, level: int) -> float:
        """Exact ``V_l = Var(S_T^(l) - S_T^(l-1))`` (``Var(S_T^(0))`` on level 0).

        The Euler factors of disjoint coarse steps are independent, so second
        moments are products over the ``2^(l-1)`` coarse steps of the moments of
        one pair ``F = (1 + r h + sigma a)(1 + r h + sigma b)``,
        ``C = 1 + 2 r h + sigma (a + b)`` with ``a, b ~ N(0, h)``:
        ``E[F^2] = ((1+rh)^2 + sigma^2 h)^2``, ``E[C^2] = (1+2rh)^2 + 2 sigma^2 h``,
        ``E[FC] = (1+rh)^2 (1+2rh) + 2 (1+rh) sigma^2 h``.
        """
        h = self.maturity / 2**level
        r, s2 = self.r, self.sigma**2
        if level == 0:
            return self.s0**2 * (((1 + r * h) ** 2 + s2 * h) - (1 + r * h) ** 2)
        n_pairs = 2 ** (level - 1)
        second_fine = ((1 + r * h) ** 2 + s2 * h) ** 2
        second_coarse = (1 + 2 * r * h) ** 2 + 2 * s2 * h
        cross = (1 + r * h) ** 2 * (1 + 2 * r * h) + 2 * (1 + r * h) * s2 * h
        second_moment = second_fine**n_pairs + second_coarse**n_pairs - 2 * cross**n_pairs
        return self.s0**2 * second_moment - (self.mean(level) - self.mean(level - 1)) ** 2
