"""MLMC screening: per-level statistics, rate fits and the sample plan.

This module turns samples of a level hierarchy into the numbers SPEC section 5
works with. It needs only numpy and the standard library and has no state.

Conventions
-----------
Levels are numbered ``l = 0, 1, 2, ...`` with mesh size ``h_l = h_0 2^-l``.
All rate models are written against the *relative* mesh size
``h_l / h_0 = 2^-l``, i.e. they are fitted by least squares on ``log2`` values
against the level index ``l`` (``log2(h_l/h_0) = -l``); the constants are the
model values at ``l = 0``. With ``n_qoi`` quantities of interest, every QoI
has its own ``alpha`` and ``beta``; the cost is shared (``gamma``).

Symbols (SPEC section 5):

``Q_l``
    The quantity of interest on level ``l`` (``fine`` samples of level ``l``;
    ``coarse`` samples of level ``l`` are ``Q_{l-1}`` of the same random input,
    zero on level 0).
``Y_l = Q_l - Q_{l-1}``
    The level difference (``Y_0 = Q_0``); ``V_l = Var(Y_l)``.
``alpha``
    Bias rate: ``|E[Y_l]| ~ C_alpha 2^(-alpha l)``.
``beta``
    Variance rate: ``V_l ~ C_beta 2^(-beta l)``.
``gamma``
    Cost rate: ``C_l ~ C_gamma 2^(gamma l)``, ``C_l`` the mean cost of one
    level-``l`` sample (both solves on ``l >= 1``).
``eps``
    Tolerance on the root-mean-square error, ``MSE <= eps^2``.
``theta``
    Bias share of ``eps^2``: the bias must stay below ``sqrt(theta) eps`` and
    the estimator variance below ``(1 - theta) eps^2`` (default 1/2).

Fitting alpha
-------------
The bias rate matters beyond the data (the tail sum below), so it is fitted
on the levels whose means look asymptotic: the window starts with the two
finest usable levels, provided their means have one sign and decay, and
extends to coarser levels while the next pair has the same sign, decays, and
its local rate ``log2 |E[Y_l-1] / E[Y_l]|`` agrees with the window's fitted
rate within ``RATIO_LOG2_TOLERANCE`` plus two standard errors. The levels
before the window are pre-asymptotic: their different early decay would pull
the rate away from the asymptotic one (a faster one makes the predicted bias
of the finest levels too optimistic).
When the two finest means change sign or do not decay, no window can be
anchored and every usable level is fitted, as a plain least-squares line
(``Rates.levels_alpha`` says which levels were used).

Remaining bias
--------------
The bias of an estimator whose finest level is ``L`` is
``E[Q] - E[Q_L] = sum_{l > L} E[Y_l]``. Under the ``alpha`` model this is the
geometric tail ``|E[Y_L]| / (2^alpha - 1)`` (Giles 2015, section 3.1); this
module calls that the *remaining bias* (:func:`remaining_bias`).

Which ``|E[Y_L]|`` goes into it (:func:`estimated_bias`, used by :func:`plan`
and by the MLMC driver alike): the largest of the fitted model ``c_alpha
2^(-alpha L)``, the measured ``|mean(Y_L)|`` where level ``L`` was sampled,
and the measured means of the two levels below it scaled to level ``L``,
``|mean(Y_{L-1})| 2^-alpha`` and ``|mean(Y_{L-2})| 2^(-2 alpha)`` (levels
``>= 1`` only; Giles' rule). The model, a least-squares line through the
means of all fitted levels, is not fooled by a finest mean that happens to
lie near 0; the measured means catch a model that falls short of the finest
levels. The coarser means matter where the differences change sign: there the
finest mean is small because the hierarchy is pre-asymptotic, not because the
bias is. The classic cluster count (mean of the 4- and 8-connected counts) has
level means 61.2, 13.2, -0.67, -1.26, -0.46 on 384^2 ... 6144^2: on 1536^2 its
bias is about 1.7-2.0 per unit area (the 6144^2 level of the reference
hierarchy), the model and the finest mean gave 0.65, Giles' term from 768^2
2.0 (README, "The classic study"). An earlier version left Giles' terms out
because they looked driven by the top of the rise; the finer level showed
they were right.

Coarsest useful level
---------------------
The telescoping sum may start on any level ``b``: ``E[Q_L] = E[Q_b] + sum_{b<l<=L}
E[Y_l]``, the base level sampled as ``Q_b`` alone. A level ``l`` with
``Var(Y_l) >= Var(Q_l)`` makes everything below it useless: sampling ``Q_l``
directly is cheaper than sampling ``Y_l`` plus the coarser levels. In
general the MLMC cost is proportional to ``S(b)^2``,
``S(b) = sqrt(Var(Q_b) C_b) + sum_{l>b} sqrt(V_l C_l)`` (SPEC section 5 with
the base level's variance ``Var(Q_b)``); :func:`choose_coarsest_level` picks
the screened ``b`` that minimises it (worst QoI, relative to ``b = 0``) and
drops the levels below ``b`` when the predicted saving is at least
``DROP_MARGIN`` (10 %: the screening's variances carry sampling noise of that
order). ``C_b`` is the cost of a screened (coupled) level-``b`` sample, since
the estimators draw the base level's samples from the same coupled sampler
and ignore the coarse value, so the prediction is what a run pays.

Richardson extrapolation
------------------------
Where ``E[Y_l] = c 2^(-alpha l)`` holds, ``E[Q] - E[Q_L]`` is the geometric
tail ``E[Y_L] / (2^alpha - 1)``, so

    R_L = sum_{l<L} mean(Y_l) + w mean(Y_L),    w = 2^alpha / (2^alpha - 1),

removes the leading bias term (Giles 2015, section 3.1; Lemaire & Pages,
multilevel Richardson-Romberg). Its variance is ``sum_{l<L} V_l / N_l + w^2
V_L / N_L``, so the allocation treats the finest level as having variance
``w^2 V_L`` (:func:`optimal_samples` with scaled ``V_L``). What remains is the
next term of the expansion; this module estimates it from the change of the
extrapolated value between successive finest levels,

    D_L = R_L - R_{L-1} = w E[Y_L] - E[Y_{L-1}] / (2^alpha - 1),

and, if the next term decays like ``2^(-alpha2 l)``, the remaining bias is
``|D_L| / (2^alpha2 - 1)`` (:func:`richardson_bias`; as for the plain bias the
maximum with the same tail taken from ``D_{L-1}`` guards against a ``D_L``
that happens to be near 0). ``alpha`` itself is fitted, and on
pre-asymptotic levels it differs from the local rate of the two finest
levels; the extrapolation then leaves part of the leading term, about
``|w - w_L| |E[Y_L]|`` with ``w_L`` the weight of the local ratio, and the
reported remaining bias is the larger of the two. ``alpha2`` is not fitted
(it would need four or more levels with small noise): it is taken as
``min(2 alpha, alpha + 1)``, the next order of an expansion in powers of
``h^alpha`` or in integer powers of ``h``, whichever decays more slowly (the
conservative choice).

Extrapolation is only sound where the ratios ``E[Y_l] / E[Y_{l-1}]`` are
stable; :func:`ratio_instability` says why they are not (too few levels, a
mean indistinguishable from zero, a change of sign, no decay, or successive
ratios differing by more than a factor ``2^RATIO_LOG2_TOLERANCE`` beyond
their noise), and callers fall back to plain MLMC.

The plan
--------
:func:`plan` goes in steps, one function each: the finest level is the first
whose remaining bias (``_BiasModel``, as ``bias_from`` says) is within
``sqrt(theta) eps`` (``_finest_level``); with ``richardson`` the extrapolated
estimate may need fewer levels (``_richardson_level``); the base level is
given or chosen (``_plan_base``, :func:`choose_coarsest_level`); ``V_l`` and
``C_l`` come from the explicit arguments, the screening or the rate models
(``_level_inputs``); then the allocation (``_allocate``,
:func:`optimal_samples`) and the prediction for plain MC (``_mc_samples``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from rough_uq.errors import EstimationError, EstimationWarning, InvalidParameterError

__all__ = [
    "CONSISTENCY_CHECK_SAMPLES",
    "DROP_MARGIN",
    "KURTOSIS_LIMIT",
    "RATIO_LOG2_TOLERANCE",
    "RICHARDSON_MIN_LEVELS",
    "EstimationWarning",
    "LevelStatistics",
    "CoarsestLevel",
    "DroppedLevel",
    "Plan",
    "Rates",
    "choose_coarsest_level",
    "diagnose",
    "estimated_bias",
    "fine_cost_share",
    "fit_rates",
    "giles_prediction",
    "level_statistics",
    "optimal_samples",
    "plan",
    "ratio_instability",
    "remaining_bias",
    "richardson_bias",
    "richardson_weight",
    "second_order_rate",
]

#: Kurtosis of ``Y_l`` above which ``V_l`` is considered unreliable (Giles' ``mlmc_test`` value).
KURTOSIS_LIMIT = 100.0

#: Fewest samples on both levels for the statistical consistency check
#: (:attr:`LevelStatistics.consistency`). Its bound, three times the sum of
#: the standard deviations of the three means, uses sample standard
#: deviations; from two samples each they are so noisy that a consistent
#: hierarchy fails the check 2.7-3.7 % of the time per level and QoI, against
#: 0.4-0.7 % with three samples and 0.05-0.1 % with five (simulated for
#: Gaussian, Student-t(3), lognormal and exponential QoIs with coupled coarse
#: values). An estimation run at a loose tolerance has two samples on most
#: levels, so these false alarms reached users (one of the 20 MLMC runs of the
#: classic study); its screening checks the same levels with more samples.
#: With fewer samples only a gap with no spread at all is reported.
CONSISTENCY_CHECK_SAMPLES = 5

# Relative size of a difference of means that is rounding, not statistics.
_ROUNDING = 64 * np.finfo(float).eps

# Largest sample count a plan may ask for; keeps float -> int conversions exact.
_MAX_COUNT = 2.0**52

#: Smallest predicted saving (fraction of the MLMC cost) for which coarse levels are dropped.
DROP_MARGIN = 0.1

#: Levels ``>= 1`` (two ratios of successive means) needed before Richardson extrapolation is trusted.
RICHARDSON_MIN_LEVELS = 3

#: Largest ``|log2 r_l - log2 r_{l-1}|`` of successive mean ratios, beyond two standard errors, still "stable".
RATIO_LOG2_TOLERANCE = 0.5


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.array(array)
    array.setflags(write=False)
    return array


# --------------------------------------------------------------------------
# Per-level statistics
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LevelStatistics:
    """Per-level sample statistics, Giles' ``mlmc_test`` screening table.

    Every QoI array has shape ``(n_levels, n_qoi)`` (a scalar QoI has
    ``n_qoi = 1``); per-level scalars have shape ``(n_levels,)``. Variances
    use the ``n - 1`` normalisation and are 0 on levels with fewer than two
    samples (where they are unknown).

    Attributes
    ----------
    levels : ndarray of int, shape (n_levels,)
        Level indices, increasing.
    n_samples : ndarray of int, shape (n_levels,)
        Number of samples per level.
    mean_fine, var_fine : ndarray, shape (n_levels, n_qoi)
        Mean and variance of ``Q_l``.
    mean_coarse, var_coarse : ndarray, shape (n_levels, n_qoi)
        Mean and variance of the coarse values ``Q_{l-1}`` of the level-``l``
        samples (0 on level 0).
    mean_diff, var_diff : ndarray, shape (n_levels, n_qoi)
        Mean and variance ``V_l`` of ``Y_l = Q_l - Q_{l-1}``.
    kurtosis : ndarray, shape (n_levels, n_qoi)
        Kurtosis ``E[(Y - EY)^4] / Var(Y)^2`` of ``Y_l`` (population moments,
        as in ``mlmc_test``; 3 for a Gaussian). 0 where undefined (fewer than
        two samples or all ``Y_l`` equal).
    var_delta : ndarray, shape (n_levels, n_qoi)
        Unbiased estimate of ``Var(Q_l) - Var(Q_{l-1})`` from the paired
        samples: sample variance of ``fine`` minus sample variance of
        ``coarse`` (computed as the sample covariance of ``fine - coarse`` and
        ``fine + coarse``, which is the same number without cancellation).
    var_delta_se : ndarray, shape (n_levels, n_qoi)
        Standard error of ``var_delta`` (see :func:`level_statistics`).
    mean_cost, var_cost : ndarray, shape (n_levels,)
        Mean and variance of the per-sample cost.
    consistency : ndarray, shape (n_levels, n_qoi)
        ``|E[Y_l] - (E[Q_l] - E[Q_{l-1}])|`` divided by three standard
        deviations; above 1 the telescoping sum is broken. 0 on level 0 and
        where it cannot be checked (predecessor level missing, fewer than two
        samples, or fewer than :data:`CONSISTENCY_CHECK_SAMPLES` on either
        level unless every variance is zero); ``inf`` if all variances are
        zero and the means differ.
    coupling_ratio : ndarray, shape (n_levels, n_qoi)
        ``V_l / Var(Q_l)``: how much the coupling reduces the variance; 1 on
        level 0 by definition. Above 1 on a level ``l >= 1`` the coarse
        sample is not coupled to the fine one (MLMC cannot beat MC there).
        Where ``Var(Q_l) = 0``: ``inf`` if ``V_l > 0``, else 0.
    base_level : int
        The level the hierarchy starts on (0 unless an estimation run dropped
        coarse levels): its ``Y`` is ``Q`` itself (coarse values 0), and
        like level 0 it has coupling ratio 1 and is not checked for coupling.
    """

    levels: np.ndarray
    n_samples: np.ndarray
    mean_fine: np.ndarray
    var_fine: np.ndarray
    mean_coarse: np.ndarray
    var_coarse: np.ndarray
    mean_diff: np.ndarray
    var_diff: np.ndarray
    kurtosis: np.ndarray
    var_delta: np.ndarray
    var_delta_se: np.ndarray
    mean_cost: np.ndarray
    var_cost: np.ndarray
    consistency: np.ndarray
    coupling_ratio: np.ndarray
    base_level: int = 0

    @property
    def n_levels(self) -> int:
        """Number of levels."""
        return len(self.levels)

    @property
    def n_qoi(self) -> int:
        """Number of quantities of interest."""
        return int(self.mean_fine.shape[1])

    @property
    def is_consistent(self) -> np.ndarray:
        """Boolean, shape (n_levels, n_qoi): the consistency check passes."""
        return self.consistency <= 1.0

    @property
    def is_coupled(self) -> np.ndarray:
        """Boolean, shape (n_levels, n_qoi): ``V_l < Var(Q_l)`` (always True on level 0)."""
        return (self.levels[:, None] <= self.base_level) | (self.coupling_ratio < 1.0)

    def index(self, level: int) -> int | None:
        """Row of ``level`` in the arrays, or None if the level is absent."""
        hits = np.flatnonzero(self.levels == level)
        return int(hits[0]) if hits.size else None


@dataclass(frozen=True, eq=False)
class _Moments:
    """Statistics of one level, computed once per change of its samples."""

    n: int
    mean_fine: np.ndarray
    var_fine: np.ndarray
    mean_coarse: np.ndarray
    var_coarse: np.ndarray
    mean_diff: np.ndarray
    var_diff: np.ndarray
    kurtosis: np.ndarray
    var_delta: np.ndarray
    var_delta_se: np.ndarray
    mean_cost: float
    var_cost: float


def _as_samples(values: object, *, name: str, level: int) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2:
        raise EstimationError(f"{name} of level {level} must have shape (n,) or (n, n_qoi), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise EstimationError(f"{name} of level {level} contains non-finite values")
    return array


def _sample_variance(centred: np.ndarray, n: int) -> np.ndarray:
    if n < 2:
        return np.zeros(centred.shape[1:])
    return np.sum(centred**2, axis=0) / (n - 1)


def _kurtosis(centred: np.ndarray) -> np.ndarray:
    # Scaling by the largest deviation keeps z in [-1, 1]: no overflow in z^4, no
    # underflow of m2^2, and m2 >= 1/n whenever the scale is positive.
    scale = np.max(np.abs(centred), axis=0)
    z = np.divide(centred, scale, out=np.zeros_like(centred), where=scale > 0)
    m2 = np.mean(z**2, axis=0)
    m4 = np.mean(z**4, axis=0)
    return np.divide(m4, m2**2, out=np.zeros_like(m2), where=m2 > 0)


def _covariance_se(dx: np.ndarray, dy: np.ndarray, cov: np.ndarray, n: int) -> np.ndarray:
    """Standard error of the unbiased sample covariance of centred samples ``dx``, ``dy``.

    Exact variance of the unbiased sample covariance of ``n`` i.i.d. pairs:
    ``mu22/n - (n-2)/(n(n-1)) sigma_xy^2 + sigma_x^2 sigma_y^2/(n(n-1))`` with
    ``mu22 = E[(X-EX)^2 (Y-EY)^2]``; with ``X = Y`` it is the familiar
    ``(mu4 - (n-3)/(n-1) sigma^4)/n`` of the sample variance. The moments are
    replaced by their sample values (plug-in), so the error is itself an
    estimate, reliable when the kurtosis of the level is moderate.
    """
    if n < 2:
        return np.zeros(dx.shape[1:])
    mu22 = np.mean(dx**2 * dy**2, axis=0)
    var_x = np.sum(dx**2, axis=0) / (n - 1)
    var_y = np.sum(dy**2, axis=0) / (n - 1)
    variance = (mu22 - (n - 2) / (n - 1) * cov**2 + var_x * var_y / (n - 1)) / n
    return np.sqrt(np.maximum(variance, 0.0))


def _centre(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and deviations; shifting by the first sample makes both exact for constant data."""
    shifted = values - values[:1]
    mean_shift = np.mean(shifted, axis=0)
    return values[0] + mean_shift, shifted - mean_shift


def _level_moments(fine: np.ndarray, coarse: np.ndarray, cost: np.ndarray) -> _Moments:
    n = fine.shape[0]
    mean_fine, d_fine = _centre(fine)
    mean_coarse, d_coarse = _centre(coarse)
    mean_diff, d_diff = _centre(fine - coarse)
    _, d_total = _centre(fine + coarse)
    # fine - coarse carries rounding errors of order eps |Q|; differences no larger than
    # that are zero (a level-independent QoI has Y_l = 0, not 1e-17), so that rate fits
    # see them as the zeros they are.
    rounding = _ROUNDING * np.maximum(np.max(np.abs(fine), axis=0), np.max(np.abs(coarse), axis=0))
    is_rounding = np.max(np.abs(d_diff), axis=0) <= rounding
    d_diff = np.where(is_rounding, 0.0, d_diff)
    mean_diff = np.where(np.abs(mean_diff) <= rounding, 0.0, mean_diff)
    var_delta = np.sum(d_diff * d_total, axis=0) / (n - 1) if n >= 2 else np.zeros(fine.shape[1])
    return _Moments(
        n=n,
        mean_fine=mean_fine,
        var_fine=_sample_variance(d_fine, n),
        mean_coarse=mean_coarse,
        var_coarse=_sample_variance(d_coarse, n),
        mean_diff=mean_diff,
        var_diff=_sample_variance(d_diff, n),
        kurtosis=_kurtosis(d_diff) if n >= 2 else np.zeros(fine.shape[1]),
        var_delta=var_delta,
        var_delta_se=_covariance_se(d_diff, d_total, var_delta, n),
        mean_cost=float(np.mean(cost)),
        var_cost=float(np.var(cost, ddof=1)) if n >= 2 else 0.0,
    )


def _assemble(levels: Sequence[int], moments: Sequence[_Moments], base_level: int = 0) -> LevelStatistics:
    """Stack per-level moments and add the cross-level checks (``base_level``: see :class:`LevelStatistics`)."""
    levels_array = np.asarray(levels, dtype=np.int64)

    def stack(name: str) -> np.ndarray:
        return np.array([getattr(m, name) for m in moments], dtype=float)

    table = {
        name: stack(name)
        for name in (
            "mean_fine",
            "var_fine",
            "mean_coarse",
            "var_coarse",
            "mean_diff",
            "var_diff",
            "kurtosis",
            "var_delta",
            "var_delta_se",
            "mean_cost",
            "var_cost",
        )
    }
    n_samples = np.array([m.n for m in moments], dtype=np.int64)
    consistency = np.zeros_like(table["mean_fine"])
    for row in range(1, len(moments)):
        below = row - 1
        fewest = min(n_samples[row], n_samples[below])
        if levels_array[below] != levels_array[row] - 1 or fewest < 2:
            continue
        # E[Y_l] - (E[Q_l] - E[Q_{l-1}]) equals mean_fine[l-1] - mean_coarse[l] (the fine
        # means cancel); computed that way it is exactly 0 for a deterministic problem.
        gap = np.abs(table["mean_fine"][below] - table["mean_coarse"][row])
        # Giles' mlmc_test bound: the sum of the standard deviations of the three means.
        spread = 3.0 * (
            np.sqrt(table["var_diff"][row] / n_samples[row])
            + np.sqrt(table["var_fine"][row] / n_samples[row])
            + np.sqrt(table["var_fine"][below] / n_samples[below])
        )
        # Below the rounding level of the means a gap or a spread is no information.
        rounding = _ROUNDING * (np.abs(table["mean_fine"][below]) + np.abs(table["mean_coarse"][row]))
        has_spread = spread > rounding
        # Standard deviations of fewer samples make the bound noise (CONSISTENCY_CHECK_SAMPLES);
        # a gap with no spread at all is a broken coupling however few the samples.
        ratio = np.divide(gap, spread, out=np.zeros_like(gap), where=has_spread)
        if fewest < CONSISTENCY_CHECK_SAMPLES:
            ratio[:] = 0.0
        consistency[row] = np.where(~has_spread & (gap > rounding), np.inf, ratio)
    # Where Q_l never varies, V_l > 0 means the coarse value adds all the variance
    # (ratio inf, not coupled); V_l = 0 as well means there is nothing to reduce (0).
    coupling = np.divide(
        table["var_diff"],
        table["var_fine"],
        out=np.where(table["var_diff"] > 0, np.inf, 0.0),
        where=table["var_fine"] > 0,
    )
    coupling[levels_array <= base_level] = 1.0
    return LevelStatistics(
        base_level=int(base_level),
        levels=_readonly(levels_array),
        n_samples=_readonly(n_samples),
        consistency=_readonly(consistency),
        coupling_ratio=_readonly(coupling),
        **{name: _readonly(value) for name, value in table.items()},
    )


def level_statistics(
    *,
    fine: Sequence[np.ndarray],
    coarse: Sequence[np.ndarray],
    cost: Sequence[np.ndarray],
    levels: Sequence[int] | None = None,
) -> LevelStatistics:
    """Screening table of a level hierarchy (Giles' ``mlmc_test``).

    Parameters
    ----------
    fine, coarse : sequence of ndarray, each shape (n_l,) or (n_l, n_qoi)
        Per level, ``Q_l`` and ``Q_{l-1}`` of the same samples (``coarse`` is
        zero on level 0).
    cost : sequence of ndarray, each shape (n_l,)
        Per level, the cost of each sample (seconds or model units, >= 0).
    levels : sequence of int, optional
        Level index of each entry, increasing; default ``0, 1, 2, ...``.

    Returns
    -------
    LevelStatistics
        Means, variances, kurtosis, variance differences with standard
        errors, costs, the consistency check and the coupling ratio.

    Raises
    ------
    EstimationError
        On mismatched shapes, an empty level, non-finite values, negative
        cost, or a nonzero ``coarse`` on level 0.

    Warns
    -----
    EstimationWarning
        For levels with a single sample (their variances are unknown and
        reported as 0).

    Notes
    -----
    ``var_delta_se`` is the standard error of the variance difference
    ``s^2(fine) - s^2(coarse) = cov(fine - coarse, fine + coarse)``, from the
    exact variance of an unbiased sample covariance with plug-in fourth-order
    moments (on level 0 it reduces to ``(m4 - (n-3)/(n-1) s^4)/n``).
    """
    if not (len(fine) == len(coarse) == len(cost)):
        raise EstimationError(
            f"fine, coarse and cost need one entry per level, got {len(fine)}, {len(coarse)}, {len(cost)}"
        )
    if len(fine) == 0:
        raise EstimationError("level_statistics needs at least one level")
    levels = list(range(len(fine))) if levels is None else [int(level) for level in levels]
    if len(levels) != len(fine) or any(b <= a for a, b in zip(levels, levels[1:])) or levels[0] < 0:
        raise EstimationError(f"levels must be increasing non-negative integers, one per entry, got {levels}")
    moments = []
    n_qoi = None
    for level, f, c, k in zip(levels, fine, coarse, cost):
        f = _as_samples(f, name="fine", level=level)
        c = _as_samples(c, name="coarse", level=level)
        k = np.asarray(k, dtype=float)
        if f.shape != c.shape or k.shape != (f.shape[0],):
            raise EstimationError(
                f"level {level}: fine {f.shape}, coarse {c.shape} and cost {k.shape} do not match"
            )
        if f.shape[0] == 0:
            raise EstimationError(f"level {level} has no samples")
        if n_qoi is not None and f.shape[1] != n_qoi:
            raise EstimationError(f"level {level} has {f.shape[1]} QoIs, the levels below have {n_qoi}")
        n_qoi = f.shape[1]
        if not np.all(np.isfinite(k)) or np.any(k < 0):
            raise EstimationError(f"cost of level {level} must be finite and non-negative")
        if level == 0 and np.any(c != 0):
            raise EstimationError("coarse values on level 0 must be zero (there is no coarser level)")
        if f.shape[0] < 2:
            warnings.warn(
                f"level {level} has a single sample: its variances are unknown and reported as 0",
                EstimationWarning,
                stacklevel=2,
            )
        moments.append(_level_moments(f, c, k))
    return _assemble(levels, moments)


COUPLING_CHECK_SAMPLES = 10
"""Fewest samples on a level for the coupling check of :func:`diagnose`."""


def diagnose(statistics: LevelStatistics, *, kurtosis_limit: float = KURTOSIS_LIMIT) -> tuple[str, ...]:
    """The failed MLMC checks of a screening table, as one message each.

    Checks (SPEC section 5): the consistency check (ratio above 1; below
    ``CONSISTENCY_CHECK_SAMPLES`` samples on a level only a gap with no spread), the
    kurtosis of ``Y_l`` (above ``kurtosis_limit``: ``V_l`` unreliable), the
    coupling (``V_l >= Var(Q_l)`` on a level ``l >= 1`` with at least
    ``COUPLING_CHECK_SAMPLES`` samples: the ratio of two variances from a few
    samples is noise, and MLMC runs started from a screening often have only
    two samples on their fine levels), levels ``l >= 1``
    whose ``Y_l`` never varied although ``Q_l`` does (rare differences missed),
    and levels with fewer than two samples.

    Parameters
    ----------
    statistics : LevelStatistics
        The table to check.
    kurtosis_limit : float
        Largest acceptable kurtosis (default 100, as in ``mlmc_test``).

    Returns
    -------
    tuple of str
        Empty when every check passes.
    """
    messages = []
    for row, level in enumerate(statistics.levels):
        n = statistics.n_samples[row]
        if n < 2:
            messages.append(f"level {level}: {n} sample(s), variance unknown")
            continue
        bad = np.flatnonzero(statistics.consistency[row] > 1.0)
        if bad.size:
            worst = float(np.max(statistics.consistency[row]))
            messages.append(
                f"level {level}: consistency check failed for QoI {bad.tolist()} "
                f"(|E[Q_l - Q_l-1] - (E[Q_l] - E[Q_l-1])| = {worst:.3g} x 3 standard deviations); "
                "the coarse sample of level l does not match the fine sample of level l-1"
            )
        heavy = np.flatnonzero(statistics.kurtosis[row] > kurtosis_limit)
        if heavy.size:
            messages.append(
                f"level {level}: kurtosis {float(np.max(statistics.kurtosis[row])):.3g} of Q_l - Q_l-1 "
                f"for QoI {heavy.tolist()} exceeds {kurtosis_limit:g}; its variance estimate is unreliable"
            )
        if level > statistics.base_level:
            frozen = np.flatnonzero((statistics.var_diff[row] == 0) & (statistics.var_fine[row] > 0))
            if frozen.size:
                messages.append(
                    f"level {level}: Q_l - Q_l-1 is the same in all {n} samples for QoI {frozen.tolist()} "
                    "although Q_l varies; if the differences are rare events (integer QoIs), this level's "
                    "mean and variance are underestimated -- use more samples per level"
                )
            loose = np.flatnonzero(statistics.coupling_ratio[row] >= 1.0)
            if loose.size and n >= COUPLING_CHECK_SAMPLES:
                messages.append(
                    f"level {level}: Var(Q_l - Q_l-1) >= Var(Q_l) for QoI {loose.tolist()} "
                    f"(ratio {float(np.max(statistics.coupling_ratio[row])):.3g}); the coarse sample "
                    "is not coupled to the fine one"
                )
    return tuple(messages)


# --------------------------------------------------------------------------
# Rates
# --------------------------------------------------------------------------


def _as_qoi_array(value: object) -> np.ndarray:
    return _readonly(np.atleast_1d(np.asarray(value, dtype=float)))


@dataclass(frozen=True, eq=False)
class Rates:
    """Fitted (or prescribed) rate models of a level hierarchy.

    ``|E[Y_l]| = c_alpha 2^(-alpha l)``, ``V_l = c_beta 2^(-beta l)``,
    ``C_l = c_gamma 2^(gamma l)`` (module docstring). Scalars given for the
    per-QoI fields are stored as arrays of shape (1,).

    Attributes
    ----------
    alpha, beta : ndarray, shape (n_qoi,)
        Bias and variance rates.
    gamma : float
        Cost rate.
    c_alpha, c_beta : ndarray, shape (n_qoi,)
        Constants of the bias and variance models (model values at ``l = 0``).
    c_gamma : float
        Constant of the cost model.
    alpha_se, beta_se : ndarray, shape (n_qoi,)
        Standard errors of the rates (0 if prescribed).
    gamma_se : float
        Standard error of ``gamma``.
    levels_alpha, levels_beta : tuple of tuple of int
        Per QoI, the levels the fit used (empty if prescribed).
    levels_gamma : tuple of int
        Levels the cost fit used.
    """

    alpha: np.ndarray
    beta: np.ndarray
    gamma: float
    c_alpha: np.ndarray
    c_beta: np.ndarray
    c_gamma: float
    alpha_se: np.ndarray = field(default_factory=lambda: np.zeros(1))
    beta_se: np.ndarray = field(default_factory=lambda: np.zeros(1))
    gamma_se: float = 0.0
    levels_alpha: tuple[tuple[int, ...], ...] = ()
    levels_beta: tuple[tuple[int, ...], ...] = ()
    levels_gamma: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        n_qoi = max(np.size(self.alpha), np.size(self.beta), np.size(self.c_alpha), np.size(self.c_beta))
        for name in ("alpha", "beta", "c_alpha", "c_beta", "alpha_se", "beta_se"):
            value = _as_qoi_array(getattr(self, name))
            if value.shape == (1,) and n_qoi > 1:
                value = _readonly(np.repeat(value, n_qoi))
            if value.shape != (n_qoi,):
                raise InvalidParameterError(f"Rates.{name}", getattr(self, name), f"a scalar or {n_qoi} values")
            object.__setattr__(self, name, value)
        for name in ("gamma", "c_gamma", "gamma_se"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def n_qoi(self) -> int:
        """Number of quantities of interest."""
        return len(self.alpha)

    def bias_model(self, level: int) -> np.ndarray:
        """Model ``|E[Y_l]|``, shape (n_qoi,)."""
        return self.c_alpha * 2.0 ** (-self.alpha * level)

    def variance_model(self, level: int) -> np.ndarray:
        """Model ``V_l``, shape (n_qoi,)."""
        return self.c_beta * 2.0 ** (-self.beta * level)

    def cost_model(self, level: int) -> float:
        """Model cost ``C_l`` of one level-``level`` sample."""
        return self.c_gamma * 2.0 ** (self.gamma * level)


@dataclass(frozen=True, eq=False)
class _Line:
    rate: float
    constant: float
    se: float
    levels: tuple[int, ...]


def _fit_line(levels: np.ndarray, values: np.ndarray, rel_se: np.ndarray, sign: float) -> _Line | None:
    """Least-squares fit ``log2 value = log2 constant + sign * rate * level``.

    ``rel_se`` is the standard error of each value relative to the value; it
    is propagated through the fit so that a two-point fit still gets an error.
    Returns None with fewer than two points.
    """
    if len(levels) < 2:
        return None
    x = levels.astype(float)
    y = np.log2(values)
    x_mean = x.mean()
    sxx = float(np.sum((x - x_mean) ** 2))
    slope = float(np.sum((x - x_mean) * (y - y.mean())) / sxx)
    intercept = float(y.mean() - slope * x_mean)
    # Propagated sampling error: var(log2 v) ~ (se(v)/v)^2 / ln(2)^2.
    weights = (x - x_mean) / sxx
    se_sampling = math.sqrt(float(np.sum(weights**2 * (rel_se / math.log(2.0)) ** 2)))
    se = se_sampling
    if len(levels) > 2:
        residual = y - (intercept + slope * x)
        se_residual = math.sqrt(float(np.sum(residual**2)) / (len(levels) - 2) / sxx)
        # The residual error also sees model misfit (pre-asymptotic levels); keep the larger.
        se = max(se_sampling, se_residual)
    return _Line(rate=sign * slope, constant=2.0**intercept, se=se, levels=tuple(int(level) for level in levels))


def _asymptotic_window(levels: np.ndarray, means: np.ndarray, rel_se: np.ndarray) -> np.ndarray:
    """Indices of the levels the bias rate is fitted on (module docstring, "Fitting alpha").

    ``levels`` increasing, ``means`` the signed ``mean(Y_l)`` (nonzero),
    ``rel_se`` their standard errors relative to ``|mean|``.
    """
    rows = np.arange(len(levels))

    def is_decaying_pair(coarse: int, fine: int) -> bool:
        return (
            levels[fine] - levels[coarse] == 1
            and np.sign(means[fine]) == np.sign(means[coarse])
            and abs(means[fine]) < abs(means[coarse])
        )

    if len(rows) < 3 or not is_decaying_pair(len(rows) - 2, len(rows) - 1):
        return rows  # nothing to leave out, or no asymptotic pair to anchor a window on
    finest = len(rows) - 1
    start = finest - 1
    while start > 0 and is_decaying_pair(start - 1, start):
        window = slice(start, finest + 1)
        rate = -np.polyfit(levels[window], np.log2(np.abs(means[window])), 1)[0]
        local = math.log2(abs(means[start - 1]) / abs(means[start]))
        noise = math.hypot(rel_se[start - 1], rel_se[start]) / math.log(2.0)
        if abs(local - rate) > RATIO_LOG2_TOLERANCE + 2.0 * noise:
            break
        start -= 1
    return rows[start:]


def _fit_alpha(statistics: LevelStatistics, q: int, min_level: int) -> tuple[_Line | None, str]:
    use = (statistics.levels >= min_level) & (statistics.n_samples >= 2)
    mean = np.abs(statistics.mean_diff[:, q])
    usable = use & (mean > 0)
    rel_se = np.sqrt(statistics.var_diff[usable, q] / statistics.n_samples[usable]) / mean[usable]
    window = _asymptotic_window(statistics.levels[usable], statistics.mean_diff[usable, q], rel_se)
    line = _fit_line(statistics.levels[usable][window], mean[usable][window], rel_se[window], -1.0)
    zero = statistics.levels[use & (mean == 0)].tolist()
    return line, f"levels with E[Q_l - Q_l-1] = 0 (unusable): {zero}" if zero else ""


def _fit_beta(statistics: LevelStatistics, q: int, min_level: int) -> tuple[_Line | None, str]:
    use = (statistics.levels >= min_level) & (statistics.n_samples >= 2)
    var = statistics.var_diff[:, q]
    usable = use & (var > 0)
    n = statistics.n_samples[usable]
    # Var(s^2)/sigma^4 = (kurtosis - (n-3)/(n-1))/n; the kurtosis is >= 1, the bracket > 0.
    rel_var = np.maximum(statistics.kurtosis[usable, q] - (n - 3) / (n - 1), 0.0) / n
    line = _fit_line(statistics.levels[usable], var[usable], np.sqrt(rel_var), -1.0)
    zero = statistics.levels[use & (var == 0)].tolist()
    return line, f"levels with Var(Q_l - Q_l-1) = 0 (unusable): {zero}" if zero else ""


def _fit_gamma(statistics: LevelStatistics, min_level: int) -> tuple[_Line | None, str]:
    use = statistics.levels >= min_level
    cost = statistics.mean_cost
    usable = use & (cost > 0)
    rel_se = np.sqrt(statistics.var_cost[usable] / statistics.n_samples[usable]) / cost[usable]
    line = _fit_line(statistics.levels[usable], cost[usable], rel_se, 1.0)
    zero = statistics.levels[use & (cost <= 0)].tolist()
    return line, f"levels with zero cost (unusable): {zero}" if zero else ""


def fit_rates(statistics: LevelStatistics, *, min_level: int = 1) -> Rates:
    """Fit ``alpha``, ``beta``, ``gamma`` and their constants by least squares.

    Ordinary least squares of ``log2 |E[Y_l]|``, ``log2 V_l`` and
    ``log2 C_l`` against the level index ``l`` (equivalently against
    ``log2(h_l/h_0) = -l``), over the levels ``l >= min_level``; for
    ``alpha``, over those of them whose means look asymptotic (module
    docstring, "Fitting alpha").

    Parameters
    ----------
    statistics : LevelStatistics
        Screening table (:func:`level_statistics`).
    min_level : int
        Coarsest level used (default 1). Level 0 is excluded by default
        because ``Y_0 = Q_0`` follows none of the models, and because a
        level-0 sample has no coarse solve, so its cost is off the ``gamma``
        model too.

    Returns
    -------
    Rates
        Rates, constants, standard errors and the levels used.

    Raises
    ------
    EstimationError
        If any rate has fewer than two usable levels. A level is unusable
        for ``alpha`` if ``E[Y_l] = 0``, for ``beta`` if ``V_l = 0``, for
        both if it has fewer than two samples, and for ``gamma`` if its mean
        cost is 0 (a logarithm of 0 is never taken).

    Notes
    -----
    The standard error of each rate is the larger of the residual-based OLS
    error (needs three or more levels) and the sampling error of the
    ``log2`` values propagated through the fit: ``se(E[Y_l]) = sqrt(V_l /
    N_l)``, ``Var(s^2)/sigma^4 = (kurtosis - (N-3)/(N-1))/N`` for ``V_l``
    and ``se(C_l) = sd(cost)/sqrt(N_l)``.
    """
    alpha, beta = [], []
    for q in range(statistics.n_qoi):
        for name, fit, out in (("alpha", _fit_alpha, alpha), ("beta", _fit_beta, beta)):
            line, note = fit(statistics, q, min_level)
            if line is None:
                raise EstimationError(
                    f"cannot fit {name} for QoI {q}: needs at least two usable levels >= {min_level} "
                    f"with two or more samples each; screened levels {statistics.levels.tolist()}"
                    + (f"; {note}" if note else "")
                )
            out.append(line)
    gamma, note = _fit_gamma(statistics, min_level)
    if gamma is None:
        raise EstimationError(
            f"cannot fit gamma: needs at least two levels >= {min_level} with positive cost; "
            f"screened levels {statistics.levels.tolist()}" + (f"; {note}" if note else "")
        )
    return Rates(
        alpha=np.array([line.rate for line in alpha]),
        beta=np.array([line.rate for line in beta]),
        gamma=gamma.rate,
        c_alpha=np.array([line.constant for line in alpha]),
        c_beta=np.array([line.constant for line in beta]),
        c_gamma=gamma.constant,
        alpha_se=np.array([line.se for line in alpha]),
        beta_se=np.array([line.se for line in beta]),
        gamma_se=gamma.se,
        levels_alpha=tuple(line.levels for line in alpha),
        levels_beta=tuple(line.levels for line in beta),
        levels_gamma=gamma.levels,
    )


# --------------------------------------------------------------------------
# Plan
# --------------------------------------------------------------------------


def remaining_bias(mean_diff: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Remaining bias ``|E[Y_L]| / (2^alpha - 1)`` of an estimator with finest level ``L``.

    Parameters
    ----------
    mean_diff : ndarray, shape (n_qoi,)
        ``E[Y_L]`` (measured or modelled).
    alpha : ndarray, shape (n_qoi,)
        Bias rate; must be positive.

    Returns
    -------
    ndarray, shape (n_qoi,)
        ``inf`` where the tail sum exceeds the float range (``alpha`` near 0).

    Raises
    ------
    EstimationError
        If some ``alpha <= 0`` (or NaN): the bias does not decay.
    """
    alpha = np.asarray(alpha, dtype=float)
    # expm1 keeps 2^alpha - 1 = alpha ln 2 exact for small alpha, where 2.0**alpha - 1
    # rounds to 0 (alpha < 1.6e-16) and the division would be 0/0 or x/0.
    denominator = np.expm1(alpha * math.log(2.0))
    if np.any(~(denominator > 0)):
        rates_text = ", ".join(f"{value:.3g}" for value in alpha.ravel())
        raise EstimationError(
            f"the bias does not decay with the level (alpha = {rates_text}); no finest level can meet a bias tolerance"
        )
    # A rate so small that the tail sum exceeds the float range is an infinite bias.
    with np.errstate(over="ignore"):
        return np.abs(mean_diff) / denominator


def estimated_bias(
    *, rates: Rates, level: int, mean_diff: np.ndarray | None = None, coarser: np.ndarray | None = None
) -> np.ndarray:
    """Remaining bias of an estimator whose finest level is ``level`` (module docstring).

    Parameters
    ----------
    rates : Rates
        Bias model ``c_alpha 2^(-alpha l)`` and rate ``alpha`` (positive).
    level : int
        Finest level ``L``.
    mean_diff : ndarray, shape (n_qoi,), optional
        Measured ``mean(Y_L)`` (pooled over every sample of level ``L``);
        None where the level was not sampled.
    coarser : ndarray, shape (k, n_qoi), optional
        Measured ``mean(Y_l)`` of the ``k <= 2`` levels just below ``L``
        (``L - k .. L - 1``, in that order; levels ``l >= 1`` only, whose
        ``Y_l`` is a difference); NaN where a level was not sampled.

    Returns
    -------
    ndarray, shape (n_qoi,)
        ``max(c_alpha 2^(-alpha L), |mean(Y_L)|, |mean(Y_{L-1})| 2^-alpha,
        |mean(Y_{L-2})| 2^(-2 alpha)) / (2^alpha - 1)`` over the terms
        given, in the QoI's unit.
    """
    expected = rates.bias_model(level)
    if mean_diff is not None or coarser is not None:
        unknown = np.full(rates.n_qoi, np.nan)
        finest = unknown if mean_diff is None else np.asarray(mean_diff, dtype=float)
        below = np.empty((0, rates.n_qoi)) if coarser is None else np.asarray(coarser, dtype=float)[-2:]
        expected = np.fmax(expected, giles_prediction(np.vstack([below, finest]), rates.alpha))
    return remaining_bias(expected, rates.alpha)


def giles_prediction(means: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``|E[Y_L]|`` as Giles' rule predicts it from the (up to) three finest level means.

    ``means`` has shape (k, n): rows the levels ``L - k + 1 .. L``, each a
    difference (levels ``>= 1``), NaN where unknown. Returns, shape (n,), the
    largest of ``|mean(Y_l)| 2^(-(L - l) alpha)`` over the last three rows
    (NaN only where all of them are unknown).
    """
    rows = np.abs(np.asarray(means, dtype=float))[-3:]
    steps = np.arange(len(rows) - 1, -1, -1)[:, None]
    return np.fmax.reduce(rows * 2.0 ** (-steps * np.asarray(alpha, dtype=float)), axis=0)


@dataclass(frozen=True)
class DroppedLevel:
    """A coarse level left out of the hierarchy, and why."""

    level: int
    reason: str


@dataclass(frozen=True)
class CoarsestLevel:
    """The coarsest useful level (:func:`choose_coarsest_level`).

    Attributes
    ----------
    level : int
        ``b``: the hierarchy starts here (0 when nothing is dropped).
    dropped : tuple of DroppedLevel
        The levels ``0..b-1``, each with its reason.
    cost_factor : float
        Predicted MLMC cost starting at ``b`` relative to starting at 0 (worst QoI).
    """

    level: int
    dropped: tuple[DroppedLevel, ...]
    cost_factor: float


def choose_coarsest_level(statistics: LevelStatistics, *, margin: float = DROP_MARGIN) -> CoarsestLevel:
    """The screened level the hierarchy should start on (module docstring, "Coarsest useful level").

    Parameters
    ----------
    statistics : LevelStatistics
        Screening table; only the levels ``0, 1, 2, ...`` screened with two
        or more samples and a positive cost are candidates.
    margin : float
        Drop levels only if that saves at least this fraction of the cost.

    Returns
    -------
    CoarsestLevel
    """
    rows: list[int] = []
    for row in range(statistics.n_levels):
        if statistics.levels[row] != len(rows) or statistics.n_samples[row] < 2 or statistics.mean_cost[row] <= 0:
            break
        rows.append(row)
    if len(rows) < 2:
        return CoarsestLevel(level=0, dropped=(), cost_factor=1.0)
    cost = statistics.mean_cost[rows]
    var_q = statistics.var_fine[rows]
    corrections = np.sqrt(statistics.var_diff[rows] * cost[:, None])
    # S(b) per QoI: base term plus the corrections above b (over the screened levels).
    totals = np.array([np.sqrt(var_q[b] * cost[b]) + np.sum(corrections[b + 1 :], axis=0) for b in range(len(rows))])
    reference = totals[0]
    relative = np.divide(totals, reference, out=np.ones_like(totals), where=reference > 0) ** 2
    worst = np.max(relative, axis=1)
    best = int(np.argmin(worst))
    if best == 0 or worst[best] > 1.0 - margin:
        return CoarsestLevel(level=0, dropped=(), cost_factor=1.0)
    dropped = []
    for level in range(best):
        above = level + 1
        loose = np.flatnonzero(statistics.var_diff[rows[above]] >= var_q[above])
        if loose.size:
            q = int(loose[0])
            reason = (
                f"Var(Y_{above}) = {statistics.var_diff[rows[above], q]:.3g} is not below "
                f"Var(Q_{above}) = {var_q[above, q]:.3g}: level {level} does not reduce the variance of "
                f"level {above}, it only adds cost"
            )
        else:
            factor = float(np.max(relative[best] / np.where(relative[level] > 0, relative[level], 1.0)))
            reason = (
                f"a hierarchy starting at level {best} is predicted to cost {factor:.2f} x one starting at "
                f"level {level} (sqrt(Var(Q_b) C_b) + sum_l>b sqrt(V_l C_l), screened levels)"
            )
        dropped.append(DroppedLevel(level=level, reason=reason))
    return CoarsestLevel(level=best, dropped=tuple(dropped), cost_factor=float(worst[best]))


def richardson_weight(alpha: np.ndarray) -> np.ndarray:
    """Weight ``w = 2^alpha / (2^alpha - 1)`` of the finest level in the extrapolated estimate.

    Parameters
    ----------
    alpha : ndarray, shape (n_qoi,)
        Bias rate, positive.

    Returns
    -------
    ndarray, shape (n_qoi,)
    """
    alpha = np.asarray(alpha, dtype=float)
    remaining_bias(np.zeros_like(alpha), alpha)  # alpha <= 0: raises the explanatory error
    return -1.0 / np.expm1(-alpha * math.log(2.0))


def second_order_rate(alpha: np.ndarray) -> np.ndarray:
    """Assumed rate ``alpha2 = min(2 alpha, alpha + 1)`` of the bias left by extrapolation (module docstring)."""
    alpha = np.asarray(alpha, dtype=float)
    return np.minimum(2.0 * alpha, alpha + 1.0)


def richardson_bias(mean_diff: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Remaining bias of the extrapolated estimate from the change ``D_L`` of the extrapolated values.

    Parameters
    ----------
    mean_diff : ndarray, shape (n, n_qoi)
        ``E[Y_l]`` of consecutive levels ``l >= 1`` (not the base level, whose
        ``Y = Q``), the finest last; ``n >= 2``.
    alpha : ndarray, shape (n_qoi,)
        Bias rate of the extrapolation.

    Returns
    -------
    ndarray, shape (n_qoi,)
        The larger of the next-order tail ``max(|D_L|, |D_{L-1}| 2^-alpha2) /
        (2^alpha2 - 1)`` (``alpha2`` from :func:`second_order_rate`; the
        ``D_{L-1}`` term only with ``n >= 3``) and the sensitivity to the rate,
        ``|w - w_L| |E[Y_L]|`` with ``w_L = 1 / (1 - r_L)`` the weight of the
        local ratio ``r_L = E[Y_L] / E[Y_{L-1}]`` (where ``0 < r_L < 1``).

    Raises
    ------
    EstimationError
        With fewer than two levels (no ``D_L``) or a non-positive ``alpha``.
    """
    mean_diff = np.asarray(mean_diff, dtype=float)
    if mean_diff.ndim != 2 or mean_diff.shape[0] < 2:
        raise EstimationError("Richardson's remaining bias needs the means of two levels >= 1")
    weight = richardson_weight(alpha)
    alpha2 = second_order_rate(alpha)
    changes = weight * mean_diff[1:] - (weight - 1.0) * mean_diff[:-1]  # D_l; w - 1 = 1 / (2^alpha - 1)
    terms = [np.abs(changes[-1])]
    if len(changes) >= 2:
        terms.append(np.abs(changes[-2]) * 2.0 ** (-alpha2))
    next_order = remaining_bias(np.max(terms, axis=0), alpha2)
    # A fitted alpha off the local rate of the two finest levels leaves part of the leading
    # term; the difference of the two extrapolations measures it.
    finest, below = mean_diff[-1], mean_diff[-2]
    ratio = np.divide(finest, below, out=np.zeros_like(finest), where=below != 0)
    has_local = (ratio > 0) & (ratio < 1)
    local_weight = np.divide(1.0, 1.0 - ratio, out=np.ones_like(ratio), where=has_local)
    rate_error = np.where(has_local, np.abs(local_weight - weight) * np.abs(finest), 0.0)
    return np.maximum(next_order, rate_error)


def ratio_instability(
    mean_diff: np.ndarray,
    mean_se: np.ndarray,
    levels: Sequence[int],
    *,
    min_levels: int = RICHARDSON_MIN_LEVELS,
    window: int = 3,
) -> str:
    """Why the ratios of successive level means are not stable enough to extrapolate ("" if they are).

    Parameters
    ----------
    mean_diff, mean_se : ndarray, shape (n, n_qoi)
        ``E[Y_l]`` and its standard error ``sqrt(V_l / N_l)`` of consecutive
        levels ``l >= 1``, the finest last.
    levels : sequence of int, length n
        The level indices (for the message).
    min_levels : int
        Fewest levels needed (two ratios by default).
    window : int
        Number of finest ratios checked.

    Returns
    -------
    str
        The first failed check for some QoI, or "" when, on the ``window``
        finest levels, every mean is at least two standard errors from 0, all
        have the same sign, every ratio ``r_l = E[Y_l] / E[Y_{l-1}]`` is below
        1, and successive ratios agree: ``|log2 r_l - log2 r_{l-1}| <=
        RATIO_LOG2_TOLERANCE`` plus two standard errors of that difference.
    """
    mean_diff = np.asarray(mean_diff, dtype=float)
    mean_se = np.asarray(mean_se, dtype=float)
    levels = [int(level) for level in levels]
    if len(levels) < min_levels:
        return (
            f"needs the means of {min_levels} levels >= 1 to check the ratios of successive means, "
            f"has {len(levels)} ({levels})"
        )
    rows = slice(max(0, len(levels) - window - 1), len(levels))
    means, errors, names = mean_diff[rows], mean_se[rows], levels[rows]
    for q in range(means.shape[1]):
        m, se = means[:, q], errors[:, q]
        tag = f" (QoI {q})" if means.shape[1] > 1 else ""
        weak = np.flatnonzero(np.abs(m) < 2.0 * se)
        if weak.size:
            row = int(weak[0])
            return (
                f"the mean of Y_{names[row]} = {m[row]:.3g} is within two standard errors ({se[row]:.2g}) of 0"
                f"{tag}: its ratio to the next level is noise"
            )
        ratios = m[1:] / m[:-1]
        for k, ratio in enumerate(ratios):
            if ratio <= 0:
                return (
                    f"the level means change sign between levels {names[k]} and {names[k + 1]} "
                    f"({m[k]:.3g}, {m[k + 1]:.3g}){tag}: the bias is not in its asymptotic regime"
                )
            if ratio >= 1:
                return (
                    f"the level means do not decay between levels {names[k]} and {names[k + 1]} "
                    f"({m[k]:.3g}, {m[k + 1]:.3g}){tag}"
                )
        rel = se / np.abs(m)
        log_ratios = np.log2(ratios)
        for k in range(1, len(ratios)):
            spread = abs(log_ratios[k] - log_ratios[k - 1])
            noise = math.sqrt(rel[k + 1] ** 2 + 4.0 * rel[k] ** 2 + rel[k - 1] ** 2) / math.log(2.0)
            if spread > RATIO_LOG2_TOLERANCE + 2.0 * noise:
                return (
                    f"the ratios of successive level means are not stable: E[Y_l] / E[Y_l-1] = "
                    f"{ratios[k - 1]:.3g} at level {names[k]} and {ratios[k]:.3g} at level {names[k + 1]}{tag}"
                )
    return ""


def optimal_samples(variances: np.ndarray, costs: np.ndarray, budget: np.ndarray) -> np.ndarray:
    """Real-valued optimal ``N_l`` per QoI for a variance budget.

    ``N_l = sqrt(V_l / C_l) * sum_k sqrt(V_k C_k) / budget`` (SPEC section 5
    with ``budget = (1 - theta) eps^2``).

    Parameters
    ----------
    variances : ndarray, shape (n_levels, n_qoi)
        ``V_l`` (>= 0).
    costs : ndarray, shape (n_levels,)
        ``C_l`` (> 0).
    budget : ndarray, shape (n_qoi,)
        Allowed estimator variance per QoI (> 0).

    Returns
    -------
    ndarray, shape (n_levels, n_qoi)
    """
    if np.any(~(np.asarray(costs) > 0)):
        # C_l = 0 would divide by zero in sqrt(V_l / C_l).
        raise InvalidParameterError("costs", costs, "positive costs C_l")
    costs = costs[:, None]
    total = np.sum(np.sqrt(variances * costs), axis=0)
    return np.minimum(np.sqrt(variances / costs) * total / budget, _MAX_COUNT)


@dataclass(frozen=True, eq=False)
class Plan:
    """Finest level, optimal sample numbers and predicted costs for a tolerance.

    Attributes
    ----------
    tol : ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error, per QoI.
    theta : float
        Bias share of ``eps^2``.
    finest_level : int
        ``L``; the plan covers levels ``0..L``.
    n_samples : ndarray of int, shape (L+1,)
        ``N_l`` (maximum over the QoIs; at least 1).
    variances : ndarray, shape (L+1, n_qoi)
        ``V_l`` the plan used.
    costs : ndarray, shape (L+1,)
        ``C_l`` the plan used.
    is_extrapolated : ndarray of bool, shape (L+1,)
        True where ``V_l`` or ``C_l`` came from the rate models.
    bias : ndarray, shape (n_qoi,)
        Predicted remaining bias on level ``L``.
    is_bias_met : bool
        Whether ``bias <= sqrt(theta) eps`` for every QoI (False only when
        ``max_level`` capped the finest level).
    stat_variance : ndarray, shape (n_qoi,)
        Predicted estimator variance ``sum_l V_l / N_l``.
    cost : float
        Predicted MLMC cost ``sum_l N_l C_l``.
    mc_n_samples : int
        Samples plain MC on level ``L`` needs: ``(1-theta)^-1 eps^-2 Var(Q_L)``.
    mc_cost : float
        Predicted cost of plain MC, ``mc_n_samples`` times the cost of one fine
        solve on level ``L``.
    is_richardson : bool
        The plan is for the Richardson-extrapolated estimate (``richardson=True``
        and it needs fewer levels than plain MLMC): ``bias`` is its remaining
        bias, ``n_samples`` and ``stat_variance`` weight ``V_L`` by ``w^2``.
    richardson_note : str
        Why a requested extrapolation was not planned ("" otherwise).
    coarsest_level : int
        ``b``, the level the hierarchy starts on (its ``V_b`` is ``Var(Q_b)``;
        ``n_samples`` and ``variances`` are 0 below it).
    dropped_levels : tuple of DroppedLevel
        The levels below ``b`` and why they were dropped.
    """

    tol: np.ndarray
    theta: float
    finest_level: int
    n_samples: np.ndarray
    variances: np.ndarray
    costs: np.ndarray
    is_extrapolated: np.ndarray
    bias: np.ndarray
    is_bias_met: bool
    stat_variance: np.ndarray
    cost: float
    mc_n_samples: int
    mc_cost: float
    is_richardson: bool = False
    richardson_note: str = ""
    coarsest_level: int = 0
    dropped_levels: tuple[DroppedLevel, ...] = ()

    @property
    def levels(self) -> np.ndarray:
        """Level indices ``0..L``."""
        return np.arange(self.finest_level + 1)

    @property
    def work_ratio(self) -> float:
        """Predicted cost of plain MC over that of MLMC."""
        return self.mc_cost / self.cost if self.cost > 0 else math.inf


def _check_fraction(name: str, value: float) -> float:
    value = float(value)
    if not 0.0 < value < 1.0:
        raise InvalidParameterError(name, value, "a number strictly between 0 and 1")
    return value


def _check_tol(tol: object, n_qoi: int | None) -> np.ndarray:
    """Tolerance as a positive array of shape (n_qoi,) (a scalar is broadcast)."""
    array = np.atleast_1d(np.asarray(tol, dtype=float))
    if array.ndim != 1 or not np.all(np.isfinite(array)) or np.any(array <= 0):
        raise InvalidParameterError("tol", tol, "a positive number or a 1-d array of positive numbers")
    if n_qoi is not None:
        if array.size == 1:
            array = np.repeat(array, n_qoi)
        elif array.size != n_qoi:
            raise InvalidParameterError("tol", tol, f"a scalar or {n_qoi} values (one per QoI)")
    return array


def fine_cost_share(gamma: float, level: int) -> float:
    """Fraction of a level-``level`` sample's cost spent on the fine solve.

    A sample on ``l >= 1`` solves on ``h_l`` and ``h_{l-1}``; under the cost
    model the coarse solve costs ``2^-gamma`` of the fine one, so plain MC
    (fine solve only) pays ``1 / (1 + 2^-gamma)`` of ``C_l``.
    """
    return 1.0 if level == 0 else 1.0 / (1.0 + 2.0 ** (-gamma))


def plan(
    *,
    tol: float | np.ndarray,
    rates: Rates,
    statistics: LevelStatistics | None = None,
    variances: np.ndarray | None = None,
    costs: np.ndarray | None = None,
    theta: float = 0.5,
    finest_level: int | None = None,
    max_level: int | None = None,
    bias_from: str = "both",
    richardson: bool = False,
    coarsest_level: int | None = 0,
) -> Plan:
    """Finest level and optimal ``N_l`` for a tolerance (SPEC section 5).

    Parameters
    ----------
    tol : float or ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error (one per QoI, or one for all).
    rates : Rates
        Rate models, used for the bias and to extrapolate ``V_l``, ``C_l``
        beyond the data.
    statistics : LevelStatistics, optional
        Screening table; ``V_l``, ``C_l`` of screened levels (with two or more
        samples) come from it, and ``Var(Q_L)`` for the MC prediction.
    variances : ndarray, shape (n_levels,) or (n_levels, n_qoi), optional
        Explicit ``V_0, V_1, ...`` (override ``statistics``).
    costs : ndarray, shape (n_levels,), optional
        Explicit ``C_0, C_1, ...`` (override ``statistics``).
    theta : float
        Bias share of ``eps^2``, in (0, 1).
    finest_level : int, optional
        Use this ``L`` instead of choosing it from the bias.
    max_level : int, optional
        Largest admissible ``L``; if the bias needs a finer level, the plan
        stops there with ``is_bias_met = False``.
    bias_from : {"both", "model", "data"}
        ``|E[Y_L]|`` from the largest of the fitted model ``c_alpha
        2^(-alpha L)`` and the screened means of levels ``L``, ``L - 1`` and
        ``L - 2`` (levels ``>= 1``, scaled to level ``L``) where screened
        (default, :func:`estimated_bias`), from the model alone, or from the
        screened mean of level ``L`` where available (the model elsewhere).
    richardson : bool
        Plan the Richardson-extrapolated estimate (module docstring) if the
        screened means allow it and it needs fewer levels than plain MLMC;
        otherwise plan plain MLMC and say why in ``richardson_note``.
    coarsest_level : int or None
        Level the hierarchy starts on (default 0); None chooses it with
        :func:`choose_coarsest_level` from ``statistics`` (0 without). It is
        capped at the finest level.

    Returns
    -------
    Plan

    Notes
    -----
    ``L`` is the smallest level whose remaining bias
    ``|E[Y_L]| / (2^alpha - 1)`` is at most ``sqrt(theta) eps``, maximised
    over the QoIs (``|E[Y_L]|`` as ``bias_from`` says). ``N_l =
    ceil((1-theta)^-1 eps^-2 sqrt(V_l/C_l) sum_k sqrt(V_k C_k))``, maximised
    over the QoIs, at least 1. Plain MC needs
    ``(1-theta)^-1 eps^-2 Var(Q_L)`` samples of cost ``C_L / (1 + 2^-gamma)``
    (the fine solve only, see :func:`fine_cost_share`); ``Var(Q_L)`` comes
    from the screening at ``L`` or, beyond it, from the finest screened level
    (``Var(Q_l)`` converges), or is ``V_0 = Var(Q_0)`` without screening.
    """
    theta = _check_fraction("theta", theta)
    if bias_from not in ("both", "model", "data"):
        raise InvalidParameterError("bias_from", bias_from, '"both", "model" or "data"')
    n_qoi = rates.n_qoi
    if statistics is not None and statistics.n_qoi != n_qoi:
        raise EstimationError(f"rates have {n_qoi} QoIs, the statistics {statistics.n_qoi}")
    tol = _check_tol(tol, n_qoi)
    variances = _explicit_variances(variances, n_qoi)
    costs = _explicit_costs(costs)
    bias_model = _BiasModel(rates=rates, statistics=statistics, bias_from=bias_from)
    bias_limit = math.sqrt(theta) * tol
    if finest_level is None:
        finest_level = _finest_level(bias_model, bias_limit, max_level)
    finest_level = int(finest_level)
    if finest_level < 0:
        raise InvalidParameterError("finest_level", finest_level, "a non-negative integer")
    bias = bias_model.at(finest_level)
    is_richardson, richardson_note = False, ""
    if richardson:
        is_plain_met = bool(np.all(bias <= bias_limit))
        extrapolated = _richardson_level(statistics, rates, bias_limit, finest_level, is_plain_met)
        if isinstance(extrapolated, str):
            richardson_note = extrapolated
        else:
            finest_level, bias = extrapolated
            is_richardson = True
    base, dropped = _plan_base(statistics, coarsest_level, finest_level)
    inputs = _level_inputs(
        statistics=statistics, rates=rates, variances=variances, costs=costs, finest_level=finest_level, base=base
    )
    budget = (1.0 - theta) * tol**2
    weighted = np.array(inputs.variances)
    if is_richardson:
        weighted[-1] *= richardson_weight(rates.alpha) ** 2
    n_samples, stat_variance = _allocate(weighted, inputs.costs, budget, base)
    mc_n = _mc_samples(statistics, inputs.variances, finest_level, budget)
    mc_cost = mc_n * inputs.costs[finest_level] * fine_cost_share(rates.gamma, finest_level)
    return Plan(
        tol=_readonly(tol),
        theta=theta,
        finest_level=finest_level,
        n_samples=_readonly(n_samples),
        variances=_readonly(inputs.variances),
        costs=_readonly(inputs.costs),
        is_extrapolated=_readonly(inputs.is_extrapolated),
        bias=_readonly(bias),
        is_bias_met=bool(np.all(bias <= bias_limit)),
        stat_variance=_readonly(stat_variance),
        cost=float(np.sum(n_samples * inputs.costs)),
        mc_n_samples=mc_n,
        mc_cost=float(mc_cost),
        is_richardson=is_richardson,
        richardson_note=richardson_note,
        coarsest_level=base,
        dropped_levels=dropped,
    )


def _explicit_variances(variances: np.ndarray | None, n_qoi: int) -> np.ndarray | None:
    """``variances`` given to :func:`plan` as shape (n_levels, n_qoi), checked."""
    if variances is None:
        return None
    variances = np.asarray(variances, dtype=float)
    variances = variances[:, None] if variances.ndim == 1 else variances
    if variances.ndim != 2 or variances.shape[1] != n_qoi or np.any(variances < 0):
        raise InvalidParameterError("variances", variances, f"non-negative values of shape (n_levels, {n_qoi})")
    return variances


def _explicit_costs(costs: np.ndarray | None) -> np.ndarray | None:
    """``costs`` given to :func:`plan`, checked."""
    if costs is None:
        return None
    costs = np.asarray(costs, dtype=float)
    if costs.ndim != 1 or np.any(costs <= 0):
        raise InvalidParameterError("costs", costs, "positive values of shape (n_levels,)")
    return costs


def _screened_row(statistics: LevelStatistics | None, level: int) -> int | None:
    """Row of ``level`` in the screening if it was screened with two or more samples, else None."""
    if statistics is None:
        return None
    row = statistics.index(level)
    return row if row is not None and statistics.n_samples[row] >= 2 else None


@dataclass(frozen=True, eq=False)
class _BiasModel:
    """The remaining bias :func:`plan` predicts for a finest level (``bias_from``: see :func:`plan`)."""

    rates: Rates
    statistics: LevelStatistics | None
    bias_from: str

    def at(self, level: int) -> np.ndarray:
        """Remaining bias, shape (n_qoi,), of an estimator whose finest level is ``level``."""
        row = _screened_row(self.statistics, level) if level >= 1 else None
        if self.bias_from == "data" and row is not None:
            return remaining_bias(self.statistics.mean_diff[row], self.rates.alpha)
        if self.bias_from != "both":
            return estimated_bias(rates=self.rates, level=level)
        measured = None if row is None else self.statistics.mean_diff[row]
        return estimated_bias(rates=self.rates, level=level, mean_diff=measured, coarser=self._coarser(level))

    def _coarser(self, level: int) -> np.ndarray | None:
        """Screened means of the (up to) two levels ``>= 1`` below ``level``, NaN where not screened."""
        below = range(max(level - 2, 1), level)
        if self.statistics is None or not below:
            return None
        rows = [_screened_row(self.statistics, lower) for lower in below]
        nan = np.full(self.statistics.n_qoi, np.nan)
        return np.array([nan if row is None else self.statistics.mean_diff[row] for row in rows])


def _finest_level(bias_model: _BiasModel, bias_limit: np.ndarray, max_level: int | None) -> int:
    """The smallest level whose remaining bias is within ``bias_limit`` (``max_level`` if none is)."""
    rates, statistics = bias_model.rates, bias_model.statistics
    if np.any(rates.alpha <= 0):
        remaining_bias(rates.c_alpha, rates.alpha)  # raises the explanatory error
    # Beyond the data the model bias halves every 1/alpha levels, so this cap is never binding
    # for sane inputs; it only keeps a runaway search finite.
    top = (0 if statistics is None else int(statistics.levels[-1])) + 200
    cap = top if max_level is None else int(max_level)
    for level in range(cap + 1):
        if np.all(bias_model.at(level) <= bias_limit):
            return level
    return cap


def _plan_base(
    statistics: LevelStatistics | None, coarsest_level: int | None, finest_level: int
) -> tuple[int, tuple[DroppedLevel, ...]]:
    """The level :func:`plan`'s hierarchy starts on, and the dropped levels below it."""
    dropped: tuple[DroppedLevel, ...] = ()
    if coarsest_level is None:
        choice = choose_coarsest_level(statistics) if statistics is not None else CoarsestLevel(0, (), 1.0)
        coarsest_level, dropped = choice.level, choice.dropped
    base = min(int(coarsest_level), finest_level)
    if base < 0 or (base > 0 and _screened_row(statistics, base) is None):
        raise InvalidParameterError("coarsest_level", coarsest_level, "0 or a screened level")
    return base, tuple(d for d in dropped if d.level < base)


@dataclass(frozen=True, eq=False)
class _LevelInputs:
    """``V_l`` (shape (L+1, n_qoi)), ``C_l`` (shape (L+1,)) and where they are extrapolated, for :func:`plan`."""

    variances: np.ndarray
    costs: np.ndarray
    is_extrapolated: np.ndarray


def _level_inputs(
    *,
    statistics: LevelStatistics | None,
    rates: Rates,
    variances: np.ndarray | None,
    costs: np.ndarray | None,
    finest_level: int,
    base: int,
) -> _LevelInputs:
    """``V_l`` and ``C_l`` of levels ``0..L``: given, else screened, else from the rate models."""
    level_variances = np.zeros((finest_level + 1, rates.n_qoi))
    level_costs = np.empty(finest_level + 1)
    is_extrapolated = np.zeros(finest_level + 1, dtype=bool)
    for level in range(finest_level + 1):
        row = _screened_row(statistics, level)
        if level < base:
            pass  # below the base level: no samples, V_l stays 0 (the cost is still filled in)
        elif level == base and base > 0:
            level_variances[level] = statistics.var_fine[row]
        elif variances is not None and level < len(variances):
            level_variances[level] = variances[level]
        elif row is not None:
            level_variances[level] = statistics.var_diff[row]
        else:
            level_variances[level] = rates.variance_model(level)
            is_extrapolated[level] = True
        if costs is not None and level < len(costs):
            level_costs[level] = costs[level]
        elif row is not None and statistics.mean_cost[row] > 0:
            level_costs[level] = statistics.mean_cost[row]
        else:
            level_costs[level] = rates.cost_model(level)
            is_extrapolated[level] = True
    if np.any(level_costs <= 0):
        raise EstimationError(
            f"plan needs positive costs; got C_l = {level_costs.tolist()} (check the rates' c_gamma)"
        )
    return _LevelInputs(variances=level_variances, costs=level_costs, is_extrapolated=is_extrapolated)


def _allocate(
    variances: np.ndarray, costs: np.ndarray, budget: np.ndarray, base: int
) -> tuple[np.ndarray, np.ndarray]:
    """``N_l`` (maximum over QoIs, at least 1 from ``base`` on, 0 below) and the predicted ``sum_l V_l / N_l``."""
    n_real = np.zeros_like(variances)
    n_real[base:] = optimal_samples(variances[base:], costs[base:], budget)
    n_samples = np.maximum(np.ceil(np.max(n_real, axis=1)), 1.0).astype(np.int64)
    n_samples[:base] = 0
    return n_samples, np.sum(variances[base:] / n_samples[base:, None], axis=0)


def _mc_samples(
    statistics: LevelStatistics | None, variances: np.ndarray, finest_level: int, budget: np.ndarray
) -> int:
    """Samples plain MC on level ``L`` needs (:func:`plan`, Notes).

    ``Var(Q_L)`` is that of the finest level screened up to ``L``, else ``V_0``.
    """
    var_q = variances[0]
    if statistics is not None:
        rows = [row for row in range(statistics.n_levels) if statistics.levels[row] <= finest_level]
        rows = [row for row in rows if statistics.n_samples[row] >= 2]
        if rows:
            var_q = statistics.var_fine[rows[-1]]
    return int(np.max(np.minimum(np.ceil(var_q / budget), _MAX_COUNT)))


def _richardson_level(
    statistics: LevelStatistics | None,
    rates: Rates,
    bias_limit: np.ndarray,
    plain_level: int,
    is_plain_met: bool,
) -> tuple[int, np.ndarray] | str:
    """Finest level and remaining bias of the extrapolated estimate, or why there is none (:func:`plan`)."""
    if statistics is None:
        return "Richardson extrapolation needs screened level means"
    rows = [r for r in range(statistics.n_levels) if statistics.levels[r] >= 1 and statistics.n_samples[r] >= 2]
    levels = [int(statistics.levels[r]) for r in rows]
    if len(rows) < 2 or levels != list(range(1, len(rows) + 1)):
        return f"Richardson extrapolation needs the screened means of levels 1 and 2 at least (has {levels})"
    means = statistics.mean_diff[rows]
    errors = np.sqrt(statistics.var_diff[rows] / statistics.n_samples[rows][:, None])
    reason = ratio_instability(means, errors, levels, min_levels=2)
    if reason:
        return f"Richardson extrapolation refused: {reason}"
    alpha = rates.alpha
    if np.any(alpha <= 0):
        return f"Richardson extrapolation refused: the bias does not decay (alpha = {alpha.tolist()})"
    top = levels[-1]
    alpha2 = second_order_rate(alpha)
    # Worth it only with fewer levels than plain MLMC, or on the same levels if plain MLMC
    # cannot meet the bias there (capped by max_level).
    cap = plain_level + 1 if not is_plain_met else plain_level
    for level in range(RICHARDSON_MIN_LEVELS, cap):
        if level <= top:
            bias = richardson_bias(means[:level], alpha)
        else:
            bias = richardson_bias(means, alpha) * 2.0 ** (-alpha2 * (level - top))
        if np.all(bias <= bias_limit):
            return level, bias
    return f"Richardson extrapolation needs as many levels as plain MLMC here (L = {plain_level}); plain MLMC planned"
