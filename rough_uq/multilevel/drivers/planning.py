"""Rates and allocation of a run: the rates it plans with, and the costs and variances it allocates with."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rough_uq.multilevel.rates import RATE_FLOOR, RateLine, Rates, alpha_line, beta_line, gamma_line
from rough_uq.multilevel.statistics import LevelStatistics


def _floor_rates(n_qoi: int) -> Rates:
    """Rates before anything is known: every rate at the floor, no bias or variance model."""
    return Rates(
        alpha=np.full(n_qoi, RATE_FLOOR),
        beta=np.full(n_qoi, RATE_FLOOR),
        gamma=RATE_FLOOR,
        c_alpha=np.zeros(n_qoi),
        c_beta=np.zeros(n_qoi),
        c_gamma=1.0,
    )


def planning_rates(screening: LevelStatistics, *, gamma_beyond: float | None = None) -> Rates:
    """The rates an MLMC run started from ``screening`` plans with: fitted on levels >= 1, floored at RATE_FLOOR.

    The fits of :func:`~rough_uq.multilevel.rates.fit_rates` with every rate
    raised to :data:`RATE_FLOOR` (0.5, as in Giles' code; the constants stay
    those of the fits), and the floor where a rate cannot be fitted. A
    fitted ``alpha`` near 0 (level means at the noise of the screening)
    would make the tail sum ``|E[Y_L]| / (2^alpha - 1)`` of the bias many
    times the level means themselves. Forecasts and the plain MC level
    chosen from a screening plan with these rates, so that they predict
    what the run does. ``gamma_beyond``: the problem's least cost rate
    beyond the screened levels (:attr:`~rough_uq.multilevel.rates.Rates.gamma_beyond`).
    """
    return replace(_lenient_rates(screening, None), gamma_beyond=gamma_beyond)


def _lenient_rates(
    statistics: LevelStatistics,
    fallback: Rates | None,
    min_level: int = 1,
    bias_statistics: LevelStatistics | None = None,
) -> Rates:
    """Rates for the driver: fitted on levels >= 1 where possible (floored), else the fallback.

    ``alpha`` is fitted on ``bias_statistics`` if given (the run's means pooled
    with the screening's), ``beta`` and ``gamma`` on ``statistics``. A rate
    that cannot be fitted keeps the fallback's value (the screening rates, or
    the floor), with its standard error and empty ``levels_*``.
    """
    means = statistics if bias_statistics is None else bias_statistics
    base = fallback if fallback is not None else _floor_rates(statistics.n_qoi)
    qois = range(statistics.n_qoi)
    alpha = _lenient_fit(
        [alpha_line(means, q, min_level)[0] for q in qois], base.alpha, base.c_alpha, base.alpha_se, base.levels_alpha
    )
    beta = _lenient_fit(
        [beta_line(statistics, q, min_level)[0] for q in qois], base.beta, base.c_beta, base.beta_se, base.levels_beta
    )
    gamma = _lenient_gamma(statistics, base, min_level, is_anchored=fallback is None)
    return Rates(
        alpha=alpha.rate,
        beta=beta.rate,
        gamma=gamma.rate,
        c_alpha=alpha.constant,
        c_beta=beta.constant,
        c_gamma=gamma.constant,
        alpha_se=alpha.se,
        beta_se=beta.se,
        gamma_se=gamma.se,
        levels_alpha=alpha.levels,
        levels_beta=beta.levels,
        levels_gamma=gamma.levels,
        gamma_beyond=base.gamma_beyond,
    )


@dataclass(frozen=True, eq=False)
class _QoiRates:
    """A per-QoI rate model: rates, constants and standard errors of shape (n_qoi,), and the levels fitted."""

    rate: np.ndarray
    constant: np.ndarray
    se: np.ndarray
    levels: tuple[tuple[int, ...], ...]


def _lenient_fit(
    lines: list[RateLine | None],
    rate: np.ndarray,
    constant: np.ndarray,
    se: np.ndarray,
    levels: tuple[tuple[int, ...], ...],
) -> _QoiRates:
    """The fitted ``lines`` (one per QoI, rates floored), the fallback's values where a line is None."""
    rate, constant, se = np.array(rate), np.array(constant), np.array(se)
    fitted_levels = list(levels) or [()] * len(lines)
    for q, line in enumerate(lines):
        if line is not None:
            rate[q], constant[q], se[q] = max(line.rate, RATE_FLOOR), line.constant, line.se
            fitted_levels[q] = line.levels
    return _QoiRates(rate=rate, constant=constant, se=se, levels=tuple(fitted_levels))


def _lenient_gamma(statistics: LevelStatistics, base: Rates, min_level: int, *, is_anchored: bool) -> RateLine:
    """``gamma`` fitted (floored), else the fallback's; ``is_anchored``: put a fallback's ``c_gamma`` on the data."""
    line, _ = gamma_line(statistics, min_level)
    if line is not None:
        # A floored rate goes through the fit at its finest level, where the models of finer levels start
        # (Rates.cost_model): with the fit's own constant, costs 0.01, 0.005, 0.002 on levels 0..2 priced level 3
        # at 59 times level 2.
        top = max(line.levels)
        rate = max(line.rate, RATE_FLOOR)
        return RateLine(rate=rate, constant=line.constant * 2.0 ** ((line.rate - rate) * top), se=line.se,
                        levels=line.levels)
    c_gamma = base.c_gamma
    known = np.flatnonzero(statistics.mean_cost > 0)
    if is_anchored and known.size:
        # Anchor the cost model at the finest level with a measured cost, so that
        # extrapolated costs stay on the scale of the measured ones.
        top = known[-1]
        c_gamma = statistics.mean_cost[top] * 2.0 ** (-base.gamma * statistics.levels[top])
    return RateLine(rate=base.gamma, constant=c_gamma, se=base.gamma_se, levels=base.levels_gamma)


def fill_costs(mean_cost: np.ndarray, has_data: np.ndarray, gamma: float) -> np.ndarray:
    """Positive ``C_l`` for every level: measured where positive, else from the nearest measured level."""
    known = np.flatnonzero(has_data & (mean_cost > 0))
    levels = np.arange(len(mean_cost))
    if known.size == 0:
        # Only relative costs matter for the allocation; use the model shape.
        return 2.0 ** (gamma * levels)
    costs = np.array(mean_cost, dtype=float)
    for level in np.flatnonzero(~(has_data & (mean_cost > 0))):
        nearest = known[np.argmin(np.abs(known - level))]
        costs[level] = mean_cost[nearest] * 2.0 ** (gamma * (level - nearest))
    return costs


#: ``V_l`` decreases with the level (``2^(-beta l)``, ``beta > 0``): a level whose sampled ``V_l`` is below this
#: share of the sampled ``V_{l+1}`` has most likely not yet seen a rare event of its differences (a jump of
#: ``Q_l - Q_{l-1}`` in a tenth of the samples was absent from the 32 of level 1 of a variance run, which then
#: kept its 32 samples and reported an RMSE of 0.034 at an error of 0.46). The allocation takes that share as
#: the level's ``V``: a few more samples on a cheaper level, and the event shows up if it is there.
_FLOOR_FROM_ABOVE = 0.5


def planning_variances(var_diff: np.ndarray, has_data: np.ndarray, beta: np.ndarray, base: int = 0) -> np.ndarray:
    """``V_l`` for the allocation: sample values, extrapolated where missing, floored from below and above.

    Levels below ``base`` get 0; the base level's ``V`` is ``Var(Q_base)``, so
    it is neither extrapolated from nor used as a floor of the level above.
    A sampled level ``>= base + 1`` is also floored at half the sampled ``V``
    of the level above it (:data:`_FLOOR_FROM_ABOVE`).
    """
    variances = np.array(var_diff, dtype=float)
    variances[:base] = 0.0
    for level in range(len(variances) - 2, base, -1):
        if has_data[level] and has_data[level + 1]:
            variances[level] = np.maximum(variances[level], _FLOOR_FROM_ABOVE * variances[level + 1])
    for level in range(base, len(variances)):
        extrapolated = variances[level - 1] * 2.0 ** (-beta) if level >= base + 1 else None
        if not has_data[level]:
            variances[level] = extrapolated if extrapolated is not None else 0.0
        elif level >= base + 2:
            variances[level] = np.maximum(variances[level], 0.5 * extrapolated)
    return variances


def _pooled_variance(run_var: np.ndarray, n_run: int, prior_var: np.ndarray, n_prior: int) -> np.ndarray:
    """Variance pooled from two independent sample sets of one distribution (``n - 1`` weights)."""
    dof_run = max(n_run - 1, 0)
    return (dof_run * run_var + (n_prior - 1) * prior_var) / (dof_run + n_prior - 1)
