"""MLMC for targets beyond the mean: telescoping sums of per-level statistics.

The mean driver (:mod:`rough_uq.multilevel.drivers`) telescopes sample means
of ``Y_l = Q_l - Q_{l-1}``. Other targets telescope other statistics of the
same coupled pairs: the variance telescopes ``h2(Q_l) - h2(Q_{l-1})``
(:mod:`rough_uq.multilevel.moments`), the distribution function telescopes
smoothed indicators (:mod:`rough_uq.multilevel.distribution`). This module is
the part they share: the per-level term, the telescoping estimate with its
errors, and an adaptive driver.

Symbols
-------
Levels and the sampler contract are those of
:mod:`rough_uq.multilevel.drivers` (``sampler(level, indices) -> (fine,
coarse, cost)``; contiguous indices from 0 per level). A *target* has
``n_components`` components (one per QoI for the variance, one per threshold
for the distribution function), grouped into ``n_groups`` *groups* that each
carry one tolerance (one per QoI for the variance, a single group for a
distribution function, whose tolerance is on the maximum over thresholds).

``T_l``
    The level-``l`` term, a vector of shape ``(n_components,)``: an unbiased
    (or consistent) estimate from the ``N_l`` level-``l`` pairs of
    ``E[t_l] = theta_l - theta_{l-1}`` (``theta_l`` the target on level ``l``;
    on the base level ``T_0`` estimates ``theta_0`` itself).
``W_l``
    The per-sample variance of the term, ``W_l = N_l Var(T_l)`` (the role
    ``V_l`` plays for the mean; for a sample mean they coincide).
``alpha``, ``beta``, ``gamma``
    ``|E[T_l]| ~ 2^(-alpha l)`` (every component of a group alike),
    ``W_l ~ 2^(-beta l)`` (maximum over a group's components),
    ``C_l ~ 2^(gamma l)``; all floored at ``RATE_FLOOR`` (0.5) as in the
    mean driver.

Estimate and errors
-------------------
The estimate of ``theta_L`` is ``sum_l T_l`` with statistical variance
``sum_l Var(T_l)`` per component (independent levels).

A group with many components (a CDF on a grid) makes the mean driver's bias
logic unreliable: the maximum over the components of ``|T_l|`` is, on the
finer levels, mostly the maximum of the noise. So each level's terms are
summarised by ``r2_l = mean_c (T_c^2 - Var(T_c))``, an unbiased estimate of
the mean square of ``E[T_l]`` over the group, pooled over all its components.
A level is *detected* when ``r2_l`` exceeds its standard error (for a single
component about ``|T_l| > 2.5 sd(T_l)``); ``alpha`` is the weighted
least-squares slope of ``log2 sqrt(r2_l)`` over the detected levels ``>= 1``
(weights: inverse variances, so noisy levels hardly count; the floor with
fewer than two). The remaining bias is the geometric tail of the ``alpha``
model from the three finest levels, ``max_i b_{L-i} 2^(-i alpha) / (2^alpha
- 1)`` (:func:`_tail_bias`), with ``b_l =
max_c |T_c|`` up to the finest detected level ``k`` and, above it, the
smaller of that and the model ``b_k 2^(-alpha (l - k))``: where the terms
are noise, the data bound the bias only loosely, and the model extrapolated
from measured terms is the better estimate (as :func:`~rough_uq.multilevel.allocation.plan`
uses the model by default). A group meets its
tolerance ``eps`` when ``max_c Var_c + bias^2 <= eps^2``, the maximum over
its components: for a distribution function that is the supremum over the
thresholds of the pointwise mean-square error (not the mean of the squared
supremum, which is larger; see :mod:`rough_uq.multilevel.distribution`).

Adaptive driver
---------------
:func:`adaptive_mlmc` follows the mean driver's algorithm without screening,
Richardson extrapolation or coarse-level dropping: levels ``0..min_finest_level``
with ``n_initial`` samples each; after each round of samples (drawn in
batches of at most ``batch_size``) the terms are recomputed, the rates refitted (floored at ``RATE_FLOOR``), and
``N_l = ceil((1-theta)^-1 eps^-2 sqrt(W_l/C_l) sum_k sqrt(W_k C_k))``
(maximum over the components; never fewer than drawn or than ``n_initial``);
once every level has (within 1 %) its samples, the bias test adds level
``L+1`` or stops (``"tol_met"``, ``"max_level"``); ``"max_cost"`` stops
before a batch would exceed ``max_cost``. A round draws level after level;
where ``max_cost`` cannot pay what the round misses (at the costs per
sample measured so far), it draws on each level the share of its missing
samples that the budget left pays
(:func:`~rough_uq.multilevel.drivers.loop.round_counts`), so that a run the
budget stops has its levels in about the planned ratio (level by level, a
variance run stopped by ``max_cost = 1`` had 953 / 32 / 32 samples where its
plan asked for some 4150 / 970 / 280). The terms are recomputed only once a
round is drawn, so the order changes no result of a run the budget does not
stop.

The ``n_initial`` samples of a level are one unit, which a batch cap only
splits: a level is started only if ``max_cost`` pays for all of them (level
0 always: no cost is known before its first sample) and then gets all of
them, so a level's term never rests on fewer. The total can therefore exceed
``max_cost`` by the initial samples of level 0 and by a misprediction of a
level's cost (extrapolated from the nearest sampled level with ``gamma``).

The bias is *estimated* only once levels ``0..min_finest_level`` have their
samples (``TargetEstimate.is_bias_estimated``): the driver never tests the
bias with fewer levels, and level 0 alone has no difference to measure it
from. A run that ``max_cost`` stops earlier reports the bias as 0, not
estimated, and does not meet its tolerance, however small its statistical
error: its RMS error is unknown. A run stopped later meets it when its
statistical error and estimated bias do (``sum Var + bias^2 <= eps^2``), as
one that stops with ``"tol_met"`` does.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import EstimationError, InvalidParameterError, checked_integer, warn_at_caller
from rough_uq.multilevel.allocation import check_fraction, check_tol, optimal_samples
from rough_uq.multilevel.drivers import (
    RATE_FLOOR,
    Sampler,
    affordable_count,
    budget_share,
    call_sampler,
    check_finest_levels,
    check_optional_positive,
    checked_batch_cap,
    fill_costs,
    planning_variances,
    refuse_large_plan,
    refuse_large_start,
    round_counts,
)
from rough_uq.multilevel.rates import giles_prediction, rate_line, remaining_bias, tail_rate
from rough_uq.multilevel.statistics import (
    ESTIMATE_DIGITS,
    KURTOSIS_LIMIT,
    EstimationWarning,
    ExactTotal,
    checked_names,
    diagnose,
    errors_summary,
    level_statistics,
    names_summary,
    readonly_array,
    units_summary,
    values_summary,
)

__all__ = [
    "LevelTerm",
    "TargetEstimate",
    "TermFunction",
    "adaptive_mlmc",
    "sample_plan",
    "telescope",
]


@dataclass(frozen=True, eq=False)
class LevelTerm:
    """The level-``l`` term ``T_l`` of a telescoping sum, with its variance.

    Attributes
    ----------
    mean : ndarray, shape (n_components,)
        ``T_l`` (an estimate of ``theta_l - theta_{l-1}``, of ``theta_0`` on
        the base level), in the unit of the target.
    variance : ndarray, shape (n_components,)
        Estimated ``Var(T_l)``, >= 0, in the unit of the target squared.
    n_samples : int
        ``N_l``, the number of pairs the term was computed from.
    groups : ndarray of int, shape (n_components,)
        Tolerance group of each component (``0..n_groups-1``).
    is_bound : bool
        ``variance`` is an upper bound that falls like ``1 / N_l^2``, not a
        measurement (a CDF level whose pairs changed no indicator,
        :mod:`rough_uq.multilevel.distribution`): the allocation at most
        doubles such a level's samples per round (:func:`_targets`).
    """

    mean: np.ndarray
    variance: np.ndarray
    n_samples: int
    groups: np.ndarray
    is_bound: bool = False

    @property
    def per_sample_variance(self) -> np.ndarray:
        """``W_l = N_l Var(T_l)``, shape (n_components,)."""
        return self.n_samples * self.variance

    @property
    def n_groups(self) -> int:
        """Number of tolerance groups."""
        return int(np.max(self.groups)) + 1


TermFunction = Callable[[np.ndarray, "np.ndarray | None", int], LevelTerm]
"""``term(fine, coarse, level) -> LevelTerm``; ``fine``, ``coarse`` shape (n, n_qoi), ``coarse`` None on level 0."""


def _group_max(values: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Maximum over each group's components along the last axis: shape (..., n_groups)."""
    n_groups = int(np.max(groups)) + 1
    return np.stack([np.max(values[..., groups == g], axis=-1) for g in range(n_groups)], axis=-1)


@dataclass(frozen=True, eq=False)
class TargetEstimate:
    """MLMC estimate of a target with its errors.

    Attributes
    ----------
    estimate : ndarray, shape (n_components,)
        ``sum_l T_l``, the estimate of the target on the finest level.
    stat_error : ndarray, shape (n_components,)
        ``sqrt(sum_l Var(T_l))``.
    bias : ndarray, shape (n_groups,)
        Remaining bias per group (module docstring); 0 where it is not estimated.
    levels : ndarray of int, shape (n_levels,)
        Levels ``0..L``.
    n_samples : ndarray of int, shape (n_levels,)
        ``N_l``.
    term_means, term_variances : ndarray, shape (n_levels, n_components)
        ``T_l`` and ``Var(T_l)``.
    groups : ndarray of int, shape (n_components,)
        Tolerance group of each component.
    alpha, beta : ndarray, shape (n_groups,)
        Rates used for the bias and the allocation.
    gamma : float
        Cost rate used for the allocation.
    cost : float
        Total cost of the samples (sum of the sampler's costs).
    tol : ndarray, shape (n_groups,)
        Tolerance on the RMS error per group (NaN when none was given).
    theta : float
        Bias share of ``eps^2``.
    stop_reason : str
        ``"tol_met"``, ``"max_level"``, ``"max_cost"`` or ``"given"`` (from
        given samples, :func:`telescope`).
    is_bias_estimated : bool
        Whether ``bias`` is an estimate: the adaptive driver sampled levels
        ``0..min_finest_level`` (module docstring, "Adaptive driver"); given
        terms reach level 1 at least. Without it ``tol_met`` is False.
    is_variance_measured : bool
        False where the samples cannot measure a term's variance (a CDF
        whose thresholds miss a level's samples,
        :mod:`rough_uq.multilevel.distribution`): ``tol_met`` is False then.
    n_not_converged : int
        Samples with a solve that did not converge, kept with the QoIs of their last iterate
        (:func:`rough_uq.variance` counts them and warns, :func:`rough_uq.distribution` in its result's
        ``n_not_converged``; 0 from a level sampler).
    qoi_names : tuple of str or None
        Names of the components where each is a QoI column (:func:`rough_uq.variance`: the problem's
        columns), None otherwise (a CDF's components are thresholds; its :class:`CdfEstimate` names them).
    units : tuple of str or None
        Unit of each component of ``estimate`` where ``qoi_names`` names them (:func:`rough_uq.variance`: the
        square of its QoI's, e.g. ``"percent^2"``), None if not known.
    """

    estimate: np.ndarray
    stat_error: np.ndarray
    bias: np.ndarray
    levels: np.ndarray
    n_samples: np.ndarray
    term_means: np.ndarray
    term_variances: np.ndarray
    groups: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    gamma: float
    cost: float
    tol: np.ndarray
    theta: float
    stop_reason: str
    is_bias_estimated: bool
    is_variance_measured: bool = True
    n_not_converged: int = 0
    qoi_names: tuple[str, ...] | None = None
    units: tuple[str, ...] | None = None

    @property
    def rmse(self) -> np.ndarray:
        """Estimated RMS error per group, ``sqrt(max_c stat_error_c^2 + bias^2)``, shape (n_groups,).

        Without an estimated bias (``is_bias_estimated`` False) the statistical error alone. ``hypot``: the
        squares of errors near the float range's ends (a variance in units of 1e-100) under- or overflowed.
        """
        return np.hypot(_group_max(self.stat_error, self.groups), self.bias)

    @property
    def tol_met(self) -> bool:
        """``rmse <= tol`` in every group, with an estimated bias and measured variances (False otherwise)."""
        is_within = bool(np.all(self.rmse**2 <= self.tol**2 * (1 + 1e-12)))
        return self.is_bias_estimated and self.is_variance_measured and is_within

    @property
    def finest_level(self) -> int:
        """``L``."""
        return int(self.levels[-1])

    @property
    def noisy_bias_groups(self) -> tuple[int, ...]:
        """The groups whose bias exceeds ``sqrt(theta) tol`` while the finest level's terms are within their noise.

        Their bias estimate is then the noise of those terms, or a coarser detected level's term extrapolated
        with a rate the undetected levels could not help fit (the floor where fewer than two are detected): more
        samples per level may measure it smaller, as may a finer level.
        """
        if not self.is_bias_estimated or not self.is_variance_measured or len(self.levels) < 2:
            return ()
        detected = _is_detected(*_signal(self.term_means, self.term_variances, self.groups))[-1]
        # Terms that are exactly 0 with no spread (a CDF away from every sample) are measured, not noise.
        exact = (self.term_means[-1] == 0) & (self.term_variances[-1] == 0)
        is_exact = np.array([np.all(exact[self.groups == g]) for g in range(len(detected))])
        share = math.sqrt(self.theta) * self.tol
        return tuple(int(g) for g in np.flatnonzero((self.bias > share) & ~detected & ~is_exact))

    def __repr__(self) -> str:
        # One line for notebooks and print(): the per-level term arrays (a CDF's have a column per threshold)
        # stay in the attributes.
        names = "" if self.qoi_names is None else f"qoi_names={names_summary(self.qoi_names)}, "
        errors = errors_summary(self.rmse, self.stat_error, self.bias, self.is_bias_estimated)
        estimate = values_summary(self.estimate, ESTIMATE_DIGITS)
        return (
            f"TargetEstimate({names}{units_summary(self.units)}estimate={estimate}, {errors}, "
            f"tol={values_summary(self.tol)}, tol_met={self.tol_met}, stop_reason={self.stop_reason!r}, "
            f"levels={self.levels.tolist()}, n_samples={self.n_samples.tolist()})"
        )


# --------------------------------------------------------------------------
# Rates and bias of a hierarchy of terms
# --------------------------------------------------------------------------


def _fit_rate(levels: np.ndarray, values: np.ndarray, rel_se: np.ndarray, sign: float) -> float:
    """Rate of ``values ~ 2^(-sign rate l)`` on the positive values, floored; the floor when unfittable."""
    usable = values > 0
    line = rate_line(levels[usable], values[usable], rel_se[usable], sign)
    return RATE_FLOOR if line is None else max(line.rate, RATE_FLOOR)


def _signal(means: np.ndarray, variances: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-corrected mean square of ``E[T_l]`` over each group's components and its standard error.

    ``r2 = mean_c (T_c^2 - Var(T_c))`` is unbiased for ``mean_c E[T_c]^2``;
    its variance is taken as ``mean_c (4 T_c^2 Var_c + 2 Var_c^2) / m`` (the
    Gaussian value, components treated as independent: it only weights the
    fit and decides detectability). Shapes (n_levels, n_groups).
    """
    variances = np.maximum(variances, 0.0)
    n_groups = int(np.max(groups)) + 1
    r2, se = [], []
    for g in range(n_groups):
        t, v = means[:, groups == g], variances[:, groups == g]
        r2.append(np.mean(t**2 - v, axis=1))
        se.append(np.sqrt(np.mean(4.0 * t**2 * v + 2.0 * v**2, axis=1) / t.shape[1]))
    return np.stack(r2, axis=1), np.stack(se, axis=1)


def _is_detected(r2: np.ndarray, se: np.ndarray) -> np.ndarray:
    """The level terms differ from 0 by more than their noise: ``r2 > se(r2)`` (:func:`_signal`).

    For a single component that is ``|T| > 2.5 sd(T)`` or so; pooling many
    components (a CDF on a grid) detects much smaller terms than any one of
    them could.
    """
    return r2 > se


def _fit_alpha(means: np.ndarray, variances: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``alpha`` per group: weighted least squares of ``log2 sqrt(r2)`` on the detected levels ``>= 1``.

    The weights are the inverse variances of ``log2 sqrt(r2)``, so levels
    where the terms are mostly noise hardly count (the maximum of many noisy
    components, or the noise of a fine level, would flatten an unweighted
    fit). Floored at ``RATE_FLOOR``, and the floor where fewer than two
    levels are detected.
    """
    r2, se = _signal(means[1:], variances[1:], groups)
    levels = np.arange(1, len(means), dtype=float)
    alpha = []
    for g in range(r2.shape[1]):
        use = _is_detected(r2[:, g], se[:, g])
        if np.sum(use) < 2:
            alpha.append(RATE_FLOOR)
            continue
        x, y = levels[use], 0.5 * np.log2(r2[use, g])
        # sd(log2 sqrt(r2)) = sd(r2) / (2 r2 ln 2); an exact term (sd 0) gets a large finite weight.
        sd = np.maximum(se[use, g] / (2.0 * r2[use, g] * math.log(2.0)), 1e-6)
        weights = sd**-2
        x_mean = np.sum(weights * x) / np.sum(weights)
        slope = np.sum(weights * (x - x_mean) * y) / np.sum(weights * (x - x_mean) ** 2)
        alpha.append(max(-float(slope), RATE_FLOOR))
    return np.array(alpha)


def _term_rates(means: np.ndarray, variances: np.ndarray, n_samples: np.ndarray, groups: np.ndarray):
    """``alpha`` (:func:`_fit_alpha`) and ``beta`` per group from levels ``>= 1``, floored at ``RATE_FLOOR``."""
    levels = np.arange(len(means))[1:]
    n = n_samples[1:].astype(float)
    per_sample = _group_max(n[:, None] * np.maximum(variances[1:], 0.0), groups)
    # A variance from n samples has relative error about sqrt(2 / (n - 1)).
    rel_beta = np.sqrt(2.0 / np.maximum(n - 1.0, 1.0))
    beta = [_fit_rate(levels, per_sample[:, g], rel_beta, -1.0) for g in range(per_sample.shape[1])]
    return _fit_alpha(means, variances, groups), np.array(beta)


def _cost_rate(mean_cost: np.ndarray) -> float:
    levels = np.arange(len(mean_cost))[1:]
    costs = mean_cost[1:]
    return _fit_rate(levels, costs, np.zeros(len(levels)), 1.0)


def _bias_magnitudes(means: np.ndarray, variances: np.ndarray, groups: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``|E[T_l]|`` per group for the bias test, shape (n_levels, n_groups) (module docstring).

    The data ``max_c |T_l|`` up to the finest detected level ``k``
    (:func:`_is_detected`); above it, where the terms are noise, the smaller of
    the data and the ``alpha`` model anchored at ``k``. Without a detected
    level ``>= 1``, the data.
    """
    magnitude = _group_max(np.abs(means), groups)
    signal = _is_detected(*_signal(means, variances, groups))
    signal[0] = False  # the base level estimates theta_0, not a difference
    for g in range(magnitude.shape[1]):
        rows = np.flatnonzero(signal[:, g])
        if rows.size == 0:
            continue
        anchor = rows[-1]
        above = np.arange(anchor + 1, len(magnitude))
        model = magnitude[anchor, g] * 2.0 ** (-alpha[g] * (above - anchor))
        magnitude[above, g] = np.minimum(magnitude[above, g], model)
    return magnitude


def _tail_bias(magnitudes: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Geometric tail of the ``alpha`` model from the three finest levels ``>= 1`` (module docstring).

    ``magnitudes`` has shape (n_levels, n_groups), rows the levels ``0..L``;
    returns shape (n_groups,), zeros when only level 0 exists.
    """
    finest = len(magnitudes) - 1
    if finest < 1:
        return np.zeros(magnitudes.shape[1])
    # Each of the three finest levels predicts |E[T_L]|; the largest prediction is the safe one. The tail is
    # summed with alpha at most BIAS_RATE_CAP, as the mean's (rough_uq.multilevel.rates, "Remaining bias").
    alpha = tail_rate(alpha)
    return remaining_bias(giles_prediction(magnitudes[max(finest - 2, 1) :], alpha), alpha)


def _remaining_bias(means: np.ndarray, variances: np.ndarray, groups: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    return _tail_bias(_bias_magnitudes(means, variances, groups, alpha), alpha)


def telescope(
    terms: Sequence[LevelTerm],
    *,
    costs: np.ndarray | None = None,
    tol: float | np.ndarray | None = None,
    theta: float = 0.5,
    alpha: float | np.ndarray | None = None,
) -> TargetEstimate:
    """MLMC estimate from the terms of levels ``0..L`` (module docstring).

    Parameters
    ----------
    terms : sequence of LevelTerm
        ``T_0, ..., T_L`` with the same components and groups.
    costs : ndarray, shape (L+1,), optional
        Total cost spent per level (for the record; default 0).
    tol : float or ndarray, shape (n_groups,), optional
        Tolerance on the RMS error per group, for ``tol_met``.
    theta : float
        Bias share of ``eps^2`` (recorded).
    alpha : float or ndarray, shape (n_groups,), optional
        Bias rate; default: fitted on the levels ``>= 1`` (floored at 0.5).

    Returns
    -------
    TargetEstimate
        With ``stop_reason = "given"``; the bias is estimated from two
        levels on (level 0 alone has no difference to measure it from).
    """
    if len(terms) == 0:
        raise EstimationError("telescope needs the term of at least one level")
    groups = terms[0].groups
    for level, term in enumerate(terms):
        if term.mean.shape != terms[0].mean.shape or not np.array_equal(term.groups, groups):
            raise EstimationError(
                f"the level terms have different components: term {level} has means of shape {term.mean.shape} "
                f"and {term.groups.size} groups, term 0 {terms[0].mean.shape} and {groups.size}"
                + ("" if term.groups.shape != groups.shape else
                   f" (group {term.groups[term.groups != groups][0]} at component "
                   f"{int(np.flatnonzero(term.groups != groups)[0])} against {groups[term.groups != groups][0]})")
            )
    means, variances, n_samples = _stack(terms)
    fitted_alpha, beta = _term_rates(means, variances, n_samples, groups)
    n_groups = terms[0].n_groups
    alpha = fitted_alpha if alpha is None else np.broadcast_to(np.asarray(alpha, dtype=float), (n_groups,))
    tol_array = np.full(n_groups, np.nan) if tol is None else check_tol(tol, n_groups)
    return _estimate(
        means, variances, n_samples, groups, alpha, beta, 0.0,
        cost=0.0 if costs is None else float(np.sum(costs)), tol=tol_array, theta=check_fraction("theta", theta),
        stop_reason="given", is_bias_estimated=len(terms) > 1,
    )


def _estimate(
    means, variances, n_samples, groups, alpha, beta, gamma, *, cost, tol, theta, stop_reason, is_bias_estimated
):
    n_groups = int(np.max(groups)) + 1
    bias = _remaining_bias(means, variances, groups, alpha) if is_bias_estimated else np.zeros(n_groups)
    return TargetEstimate(
        estimate=readonly_array(np.sum(means, axis=0)),
        stat_error=readonly_array(np.sqrt(np.sum(np.maximum(variances, 0.0), axis=0))),
        bias=readonly_array(bias),
        levels=readonly_array(np.arange(len(means))),
        n_samples=readonly_array(n_samples),
        term_means=readonly_array(means),
        term_variances=readonly_array(variances),
        groups=readonly_array(groups),
        alpha=readonly_array(alpha),
        beta=readonly_array(beta),
        gamma=float(gamma),
        cost=float(cost),
        tol=readonly_array(tol),
        theta=theta,
        stop_reason=stop_reason,
        is_bias_estimated=bool(is_bias_estimated),
    )


# --------------------------------------------------------------------------
# Adaptive driver
# --------------------------------------------------------------------------


class _Level:
    """The samples of one level and its term, cached until the next batch."""

    def __init__(self, level: int) -> None:
        self.level = level
        self.fine: list[np.ndarray] = []
        self.coarse: list[np.ndarray] = []
        self.n = 0
        self._spent = ExactTotal()  # the same whatever the batches
        self._term: LevelTerm | None = None

    def add(self, fine: np.ndarray, coarse: np.ndarray, cost: np.ndarray) -> None:
        self.fine.append(fine)
        self.coarse.append(coarse)
        self.n += len(cost)
        self._spent.add(cost)
        self._term = None

    def term(self, function: TermFunction) -> LevelTerm:
        if self._term is None:
            fine = np.concatenate(self.fine)
            # The base level is sampled as Q_0 alone; its coarse values are not part of the sum.
            coarse = None if self.level == 0 else np.concatenate(self.coarse)
            self.fine, self.coarse = [fine], [] if coarse is None else [coarse]
            self._term = function(fine, coarse, self.level)
        return self._term

    @property
    def spent(self) -> float:
        return self._spent.value

    @property
    def mean_cost(self) -> float:
        return self.spent / self.n if self.n else 0.0


def _unit_cost(levels: list[_Level], level: int, gamma: float) -> float:
    """Predicted cost of one sample of ``level``, from the nearest level with samples (0 where none has any)."""
    known = [s for s in levels if s.n > 0 and s.mean_cost > 0]
    if not known:
        return 0.0
    nearest = min(known, key=lambda s: abs(s.level - level))
    return nearest.mean_cost * 2.0 ** (gamma * (level - nearest.level))


def _affordable(levels: list[_Level], level: int, wanted: int, max_cost: float | None, gamma: float) -> int:
    """Samples to draw now on ``level``: ``wanted`` unless ``max_cost`` forbids it (then possibly 0)."""
    unit = _unit_cost(levels, level, gamma)
    if max_cost is None or not unit > 0:
        return wanted
    return affordable_count(max_cost - sum(s.spent for s in levels), unit, wanted)


def _batch_count(levels: list[_Level], s: _Level, wanted: int, max_cost: float | None, gamma: float,
                 n_initial: int) -> int:
    """Samples to draw now on level ``s``, at most ``wanted``; 0 where ``max_cost`` ends the run.

    The ``n_initial`` samples of a level are one unit (module docstring):
    the level is started only if the budget pays for all of them, and once
    started it gets them all, whatever a batch cap splits them into.
    """
    if s.n == 0 and _affordable(levels, s.level, n_initial, max_cost, gamma) < n_initial:
        return 0
    return max(_affordable(levels, s.level, wanted, max_cost, gamma), min(wanted, n_initial - s.n))


def _draw(
    sampler: Sampler,
    levels: list[_Level],
    planned: list[int],
    batch_cap: float,
    max_cost: float | None,
    gamma: float,
    n_initial: int,
) -> bool:
    """Draw the missing samples; False if ``max_cost`` stopped it (module docstring, "Adaptive driver")."""
    while pending := [s for s in levels if s.n < planned[s.level]]:
        missing = [planned[s.level] - s.n for s in pending]
        share = None if max_cost is None else budget_share(
            missing, [_unit_cost(levels, s.level, gamma) for s in pending], max_cost - sum(s.spent for s in levels))
        # Level after level (whole levels, in batches of batch_cap), or each level its share of what the budget pays.
        for s, count in zip(pending, round_counts(missing, math.inf, share)):
            # A level's initial samples are one unit (module docstring): a pass completes them.
            goal = max(s.n + min(planned[s.level] - s.n, count), min(planned[s.level], n_initial))
            while s.n < goal:
                n = _batch_count(levels, s, int(min(goal - s.n, batch_cap)), max_cost, gamma, n_initial)
                if n == 0:
                    return False
                batch = call_sampler(sampler, s.level, s.n, n)
                s.add(batch.fine, batch.coarse, batch.cost)
    return True


def _targets(
    levels: list[_Level],
    terms: list[LevelTerm | None],
    n_initial: int,
    tol: np.ndarray,
    theta: float,
    beta: np.ndarray,
    gamma: float,
) -> list[int]:
    """Planned ``N_l`` (module docstring) for every level, sampled or not."""
    groups = terms[0].groups
    has_data = np.array([s.n > 0 for s in levels])
    width = len(groups)
    per_sample = np.zeros((len(levels), width))
    for s, term in zip(levels, terms):
        if term is not None:
            per_sample[s.level] = np.maximum(term.per_sample_variance, 0.0)
    variances = planning_variances(per_sample, has_data, beta[groups])
    costs = fill_costs(np.array([s.mean_cost for s in levels]), has_data, gamma)
    wanted = _allocate(variances, costs, groups, tol, theta)
    # A bound's W = N Var falls like 1 / N: planned as fixed, it asked for far more samples than the bound needs.
    wanted = [min(n, 2 * s.n) if term is not None and term.is_bound else n for s, term, n in zip(levels, terms, wanted)]
    return [max(s.n, int(n), n_initial) for s, n in zip(levels, wanted)]


def _allocate(per_sample: np.ndarray, costs: np.ndarray, groups: np.ndarray, tol: np.ndarray, theta: float):
    """``N_l`` of SPEC section 5 with ``W_l`` for ``V_l``, maximised over the components (real, rounded up)."""
    budget = (1.0 - theta) * tol[groups] ** 2
    return np.ceil(np.max(optimal_samples(per_sample, costs, budget), axis=1))


def sample_plan(
    terms: Sequence[LevelTerm], *, costs: np.ndarray, tol: float | np.ndarray, theta: float = 0.5
) -> np.ndarray:
    """Optimal ``N_l`` for a tolerance, from screened terms of levels ``0..L`` (module docstring).

    ``N_l = ceil((1-theta)^-1 eps^-2 sqrt(W_l/C_l) sum_k sqrt(W_k C_k))``,
    the mean's formula with ``W_l = N_l Var(T_l)`` in place of ``V_l``,
    maximised over the components (each against its group's ``eps``).

    Parameters
    ----------
    terms : sequence of LevelTerm
        ``T_0, ..., T_L`` (e.g. from a screening).
    costs : ndarray, shape (L+1,)
        ``C_l``, the cost of one level-``l`` sample (> 0).
    tol : float or ndarray, shape (n_groups,)
        Tolerance on the RMS error per group.
    theta : float
        Bias share of ``eps^2``.

    Returns
    -------
    ndarray of int, shape (L+1,)
        At least 1 per level.
    """
    _, variances, n_samples = _stack(terms)
    groups = terms[0].groups
    per_sample = n_samples[:, None] * np.maximum(variances, 0.0)
    costs = np.asarray(costs, dtype=float)
    if costs.shape != (len(terms),):
        raise EstimationError(f"costs need one value per level ({len(terms)}), got shape {costs.shape}")
    tol_groups = check_tol(tol, terms[0].n_groups)
    wanted = _allocate(per_sample, costs, groups, tol_groups, check_fraction("theta", theta))
    return np.maximum(wanted, 1).astype(np.int64)


def adaptive_mlmc(
    sampler: Sampler,
    *,
    term: TermFunction,
    tol: float | np.ndarray,
    theta: float = 0.5,
    n_initial: int = 32,
    min_finest_level: int = 2,
    max_level: int = 16,
    max_cost: float | None = None,
    batch_size: int | None = 10000,
    max_samples: int | None = None,
    label: str = "mlmc",
    qoi_names: Sequence[str] | None = None,
    checked_column: int | None = None,
    check: Callable[[TargetEstimate], TargetEstimate] | None = None,
) -> TargetEstimate:
    """Adaptive MLMC estimate of a target to an RMS tolerance per group (module docstring).

    Parameters
    ----------
    sampler : callable
        ``sampler(level, indices) -> (fine, coarse, cost)``
        (:mod:`rough_uq.multilevel.drivers`).
    term : callable
        ``term(fine, coarse, level) -> LevelTerm`` (``coarse`` None on level 0).
    tol : float or ndarray, shape (n_groups,)
        Tolerance ``eps`` on the RMS error, in the unit of the target.
    theta : float
        Bias share of ``eps^2``, in (0, 1).
    n_initial : int
        Samples every level gets before its term variance is trusted (>= 4:
        the unbiased variance of ``h2`` differences needs four).
    min_finest_level : int
        The run uses at least levels ``0..min_finest_level`` (>= 1).
    max_level : int
        Finest level allowed.
    max_cost : float, optional
        Stop before a batch would make the total cost exceed it; the
        initial samples of level 0 are always drawn (module docstring). A
        run stopped before levels ``0..min_finest_level`` have their samples
        estimates no bias and does not meet ``tol``.
    batch_size : int, optional
        Largest number of samples per sampler call.
    max_samples : int, optional
        A plan of more samples in all raises :class:`~rough_uq.errors.EstimationError`
        before they are drawn (the tolerance is out of reach).
    label, qoi_names, checked_column
        The checks of SPEC section 5 on the final samples (those of
        :func:`~rough_uq.multilevel.statistics.diagnose`: consistency, kurtosis of ``Q_l - Q_{l-1}``,
        coupling, differences that never varied, levels of fewer than two samples), of the QoI column
        ``checked_column`` (every column if None), named by ``qoi_names`` (one per column of the samples,
        checked against the first batch), each failed one an :class:`~rough_uq.errors.EstimationWarning`
        that starts with ``label``.
    check : callable, optional
        ``check(estimate) -> estimate``: the target's own checks of the final
        estimate (a CDF's bandwidth may withdraw its bias estimate), applied
        before the driver's warnings about it.

    Returns
    -------
    TargetEstimate
    """
    theta = check_fraction("theta", theta)
    n_initial = checked_integer("n_initial", n_initial, 4)
    min_finest_level, max_level = check_finest_levels(min_finest_level, max_level, least_max_level=1)
    batch_cap = checked_batch_cap(None if batch_size is None else checked_integer("batch_size", batch_size, 1))
    max_cost = check_optional_positive("max_cost", max_cost)
    max_samples = None if max_samples is None else checked_integer("max_samples", max_samples, 1)
    check_tol(tol, None)  # fails early; the number of groups is known after the first batch
    checked_names(qoi_names, None, argument="qoi_names")  # and their number against the first batch's columns
    refuse_large_start(n_initial, range(min_finest_level + 1), max_samples=max_samples)
    levels, stop_reason = _sample_to_tolerance(
        sampler, _checking_columns(term, qoi_names, checked_column), tol, theta=theta, n_initial=n_initial,
        n_start_levels=min_finest_level + 1, max_level=max_level, batch_cap=batch_cap, max_cost=max_cost,
        max_samples=max_samples,
    )
    estimate = _final_estimate(
        levels, term, tol, theta=theta, stop_reason=stop_reason, min_finest_level=min_finest_level
    )
    if check is not None:
        estimate = check(estimate)
    if stop_reason == "max_level" and not estimate.tol_met and estimate.noisy_bias_groups:
        _warn_noisy_bias(estimate)
    names = qoi_names if qoi_names is None or checked_column is None else [qoi_names[checked_column]]
    for message in diagnose(_statistics(levels, checked_column), kurtosis_limit=KURTOSIS_LIMIT, names=names):
        warn_at_caller(f"{label}: {message}", EstimationWarning)
    return estimate


def _checking_columns(term: TermFunction, qoi_names: Sequence[str] | None, column: int | None) -> TermFunction:
    """``term``, which first checks the number of ``qoi_names`` and ``column`` against the samples' columns."""

    def checked(fine: np.ndarray, coarse: np.ndarray | None, level: int) -> LevelTerm:
        result = term(fine, coarse, level)  # checks the samples (and a CDF's column, by its own name) first
        n_qoi = np.shape(fine)[1] if np.ndim(fine) == 2 else 1
        checked_names(qoi_names, n_qoi, argument="qoi_names")
        if column is not None and not 0 <= column < n_qoi:
            raise InvalidParameterError("checked_column", column, f"a column of the samples, 0..{n_qoi - 1}")
        return result

    return checked


def _statistics(levels: Sequence[_Level], column: int | None):
    """The mean driver's statistics of the sampled levels' pairs (``column``, every one if None), for the checks."""
    columns = slice(None) if column is None else [column]
    sampled = [s for s in levels if s.n]
    fine = [np.concatenate(s.fine)[:, columns] for s in sampled]
    coarse = [np.zeros_like(f) if s.level == 0 else np.concatenate(s.coarse)[:, columns] for s, f in zip(sampled, fine)]
    return level_statistics(fine=fine, coarse=coarse, cost=[np.full(s.n, s.mean_cost) for s in sampled],
                            levels=[s.level for s in sampled])


def _warn_noisy_bias(estimate: TargetEstimate) -> None:
    """Say that a run stopped at ``max_level`` on a bias estimate of terms within their noise.

    The groups are :attr:`TargetEstimate.noisy_bias_groups`.
    """
    noisy = list(estimate.noisy_bias_groups)
    share = math.sqrt(estimate.theta) * estimate.tol[noisy]
    biases = ", ".join(f"{b:.3g}" for b in estimate.bias[noisy])
    shares = ", ".join(f"{b:.3g}" for b in share)
    warn_at_caller(
        f"the bias estimate {biases} (the tolerance's share {shares}) rests on level terms within their noise "
        f"(the finest level's do not differ from 0 beyond it, with N_l {estimate.n_samples.tolist()}): it bounds "
        "the bias by that noise or by a coarser level's term extrapolated at the fitted or floor rate, and more "
        "initial samples per level may measure it smaller, as may a finer finest level",
        EstimationWarning,
    )


def _sample_to_tolerance(
    sampler: Sampler,
    term: TermFunction,
    tol: float | np.ndarray,
    *,
    theta: float,
    n_initial: int,
    n_start_levels: int,
    max_level: int,
    batch_cap: float,
    max_cost: float | None,
    max_samples: int | None,
) -> tuple[list[_Level], str]:
    """The sampling rounds of :func:`adaptive_mlmc`: its levels with their samples, and why it stopped."""
    levels = [_Level(level) for level in range(n_start_levels)]
    planned = [n_initial] * len(levels)
    gamma = RATE_FLOOR
    tol_groups: np.ndarray | None = None
    while True:
        if not _draw(sampler, levels, planned, batch_cap, max_cost, gamma, n_initial):
            return levels, "max_cost"
        terms = [s.term(term) if s.n else None for s in levels]
        sampled = [t for t in terms if t is not None]
        if tol_groups is None:
            tol_groups = check_tol(tol, sampled[0].n_groups)
        means, variances, n_samples = _stack(sampled)
        alpha, beta = _term_rates(means, variances, n_samples, sampled[0].groups)
        gamma = _cost_rate(np.array([s.mean_cost for s in levels if s.n]))
        planned = _targets(levels, terms, n_initial, tol_groups, theta, beta, gamma)
        refuse_large_plan(planned, max_samples=max_samples, tol=tol_groups, advice="loosen the tolerance")
        if any(planned[s.level] - s.n > 0.01 * s.n for s in levels):
            continue
        bias = _remaining_bias(means, variances, sampled[0].groups, alpha)
        if np.all(bias <= math.sqrt(theta) * tol_groups):
            return levels, "tol_met"
        if len(levels) - 1 >= max_level:
            return levels, "max_level"
        levels.append(_Level(len(levels)))
        planned = _targets(levels, terms + [None], n_initial, tol_groups, theta, beta, gamma)
        refuse_large_plan(planned, max_samples=max_samples, tol=tol_groups, advice="loosen the tolerance")


def _final_estimate(
    levels: Sequence[_Level],
    term: TermFunction,
    tol: float | np.ndarray,
    *,
    theta: float,
    stop_reason: str,
    min_finest_level: int,
) -> TargetEstimate:
    """The estimate of :func:`adaptive_mlmc` from the samples of its levels, with the rates refitted to them."""
    # Level 0 always has its samples, and levels are sampled in order (module docstring).
    sampled_levels = [s for s in levels if s.n]
    terms = [s.term(term) for s in sampled_levels]
    groups = terms[0].groups
    tol_groups = check_tol(tol, terms[0].n_groups)
    means, variances, n_samples = _stack(terms)
    # Rates of the final samples (a run stopped by max_cost may not have refitted them).
    alpha, beta = _term_rates(means, variances, n_samples, groups)
    gamma = _cost_rate(np.array([s.mean_cost for s in sampled_levels]))
    return _estimate(
        means, variances, n_samples, groups, alpha, beta, gamma,
        cost=sum(s.spent for s in levels), tol=tol_groups, theta=theta, stop_reason=stop_reason,
        is_bias_estimated=len(sampled_levels) > min_finest_level,
    )


def _stack(terms: Sequence[LevelTerm]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``T_l``, ``Var(T_l)`` (shape (n_levels, n_components)) and ``N_l`` of consecutive levels."""
    return (
        np.array([t.mean for t in terms]),
        np.array([t.variance for t in terms]),
        np.array([t.n_samples for t in terms], dtype=np.int64),
    )
