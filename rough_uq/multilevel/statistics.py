"""MLMC level statistics: the screening table of a level hierarchy and its checks.

This module turns samples of a level hierarchy into the per-level numbers SPEC
section 5 works with (:func:`level_statistics`, Giles' ``mlmc_test`` table) and
checks them (:func:`diagnose`). It needs only numpy and the standard library
and has no state. What is built on the table lives next to it:
:mod:`~rough_uq.multilevel.rates` (rate fits, the remaining bias, the coarsest
useful level), :mod:`~rough_uq.multilevel.richardson` (Richardson
extrapolation) and :mod:`~rough_uq.multilevel.allocation` (the sample plan).

Conventions
-----------
Levels are numbered ``l = 0, 1, 2, ...`` with mesh size ``h_l = h_0 2^-l``.
With ``n_qoi`` quantities of interest, every per-QoI array has a last axis of
length ``n_qoi``; the cost of a sample is shared by its QoIs.

Symbols (SPEC section 5):

``Q_l``
    The quantity of interest on level ``l`` (``fine`` samples of level ``l``;
    ``coarse`` samples of level ``l`` are ``Q_{l-1}`` of the same random input,
    zero on level 0).
``Y_l = Q_l - Q_{l-1}``
    The level difference (``Y_0 = Q_0``); ``V_l = Var(Y_l)``.
``C_l``
    The mean cost of one level-``l`` sample (both solves on ``l >= 1``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import EstimationError, EstimationWarning, InvalidParameterError, warn_at_caller

__all__ = [
    "CONSISTENCY_CHECK_SAMPLES",
    "KURTOSIS_LIMIT",
    "FEWEST_VARIANCE_SAMPLES",
    "SAMPLE_KURTOSIS_CHECK_SAMPLES",
    "kurtosis_text",
    "kurtosis_threshold",
    "EstimationWarning",
    "LevelStatistics",
    "diagnose",
    "level_statistics",
]
# Also imported by the other modules of rough_uq.multilevel (and the problem's results), not part of the API:
# checked_names, readonly_array, scaled_by_largest, ExactTotal, qoi_text, the repr helpers values_summary /
# names_summary / units_summary / errors_summary, and level_moments / assemble_statistics (the drivers' level
# table, kept as LevelMoments per level).

#: Kurtosis of ``Y_l`` above which ``V_l`` is considered unreliable (Giles' ``mlmc_test`` value).
KURTOSIS_LIMIT = 100.0

#: From this many samples a level's kurtosis is also checked against what its samples can show
#: (:func:`kurtosis_threshold`). The sample kurtosis ``k`` of ``n`` values is at most ``n - 2 + 1 / (n - 1)``
#: (one value apart, the others equal), so :data:`KURTOSIS_LIMIT` can flag nothing below 102 samples: not
#: the 20 of a default screening. ``n / k = (sum d^2)^2 / sum d^4`` (``d`` the deviations) counts the samples
#: the sample variance rests on, about 1.1 of 20 where one value stands apart; a level is flagged where it is
#: below :data:`FEWEST_VARIANCE_SAMPLES`. Simulated (400 000 levels each): Gaussian values were flagged 1.0 %
#: of the time at 10 samples, 0.05 % at 15, 2e-5 at 20 and never at 40; exponential ones (kurtosis 9, a
#: variance of 20 samples with a relative error of 0.63) 4 % at 20 samples; lognormal ones (kurtosis 114) 18 %.
SAMPLE_KURTOSIS_CHECK_SAMPLES = 20

#: Fewest samples (``n / kurtosis``, :data:`SAMPLE_KURTOSIS_CHECK_SAMPLES`) a level's variance may rest on.
FEWEST_VARIANCE_SAMPLES = 2.0


def kurtosis_threshold(n_samples: int, limit: float = KURTOSIS_LIMIT) -> float:
    """The kurtosis above which the variance of ``n_samples`` values is flagged as unreliable.

    ``limit``, and from :data:`SAMPLE_KURTOSIS_CHECK_SAMPLES` samples on at most
    ``n_samples / FEWEST_VARIANCE_SAMPLES`` (the variance then rests on fewer than that many of the samples);
    ``limit = inf`` turns the check off altogether.
    """
    if n_samples < SAMPLE_KURTOSIS_CHECK_SAMPLES or not math.isfinite(limit):
        return limit
    return min(limit, n_samples / FEWEST_VARIANCE_SAMPLES)


def kurtosis_text(kurtosis: float, n_samples: int, limit: float) -> str:
    """What a kurtosis above :func:`kurtosis_threshold` exceeds, e.g. ``exceeds 100`` or ``exceeds 10 (...)``."""
    threshold = kurtosis_threshold(n_samples, limit)
    if threshold == limit:
        return f"exceeds {limit:g}"
    return (f"exceeds {threshold:.3g} = {n_samples} samples / {FEWEST_VARIANCE_SAMPLES:g}: the variance rests on "
            f"{n_samples} / {kurtosis:.3g} = {n_samples / kurtosis:.3g} of them, fewer than "
            f"{FEWEST_VARIANCE_SAMPLES:g}")


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


#: Arrays of up to this many values are shown whole in a summary (:func:`values_summary`); longer ones by their
#: first and last :data:`_EDGE_VALUES` and their size (a load curve of 121 loads, a CDF of 121 thresholds).
_SHOWN_VALUES = 12
_EDGE_VALUES = 3


def _elided(items: list[str], noun: str) -> str:
    """``a, b, c`` for a few items; ``a, b, c, ..., x, y, z (121 values)`` for many."""
    if len(items) <= _SHOWN_VALUES:
        return ", ".join(items)
    return f"{', '.join(items[:_EDGE_VALUES])}, ..., {', '.join(items[-_EDGE_VALUES:])} ({len(items)} {noun})"


def values_summary(values: object, digits: int = 3) -> str:
    """``[1.23, 4.56]`` (``digits`` significant digits), for a long array ``[1.23, 4.56, 7.89, ..., 2.34, 5.67,
    8.9 (121 values)]`` (the results' reprs; they showed ``<8 values>`` and no number). Estimates take
    :data:`ESTIMATE_DIGITS`."""
    values = np.atleast_1d(np.asarray(values, dtype=float))
    return "[" + _elided([f"{value:.{digits}g}" for value in values], "values") + "]"


#: Significant digits of an estimate in a result's repr: 20.148 ± 0.30 printed ``estimate=[20.1]``, a digit
#: short of what its error supports; errors and tolerances keep three.
ESTIMATE_DIGITS = 4


def names_summary(names: tuple[str, ...] | None) -> str:
    """The names of a result's columns for its repr, the first and last few of many (a load curve's)."""
    if names is None or len(names) <= _SHOWN_VALUES:
        return repr(names)
    return "(" + _elided([repr(name) for name in names], "columns") + ")"


def units_summary(units: tuple[str, ...] | None) -> str:
    """``units=(...), `` for a result's repr (for many columns, a load curve's: ``units=<percent, length>``, each
    distinct unit once, in column order); ``""`` where not known."""
    if units is None:
        return ""
    return f"units={units!r}, " if len(units) <= _SHOWN_VALUES else f"units=<{', '.join(dict.fromkeys(units))}>, "


def errors_summary(
    rmse: object, stat_error: object, bias: object, is_bias_estimated: bool, *, bias_name: str = "bias"
) -> str:
    """``rmse=[..], stat_error=[..], bias=[..]``; without an estimated bias the RMSE is unknown:
    ``stat_error=[..], bias='not estimated'``. ``bias_name``: the result's attribute that holds the bias."""
    if not is_bias_estimated:
        return f"stat_error={values_summary(stat_error)}, {bias_name}='not estimated'"
    return f"rmse={values_summary(rmse)}, stat_error={values_summary(stat_error)}, {bias_name}={values_summary(bias)}"


def readonly_array(array: np.ndarray) -> np.ndarray:
    array = np.array(array)
    array.setflags(write=False)
    return array


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
        level 0 by definition. At least 1 on a level ``l >= 1``: the levels
        are at best weakly coupled for that QoI (MLMC gains nothing over MC
        there); about 2 or more: fine and coarse values look uncorrelated.
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
    def mean_diff_error(self) -> np.ndarray:
        """Standard error of ``mean_diff``, ``sqrt(var_diff / n_samples)``, shape (n_levels, n_qoi)."""
        return np.sqrt(np.maximum(self.var_diff, 0.0) / np.maximum(self.n_samples, 1)[:, None])

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
class LevelMoments:
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
        row, column = np.argwhere(~np.isfinite(array))[0]
        raise EstimationError(
            f"{name} of level {level} contains non-finite values (the first: {array[row, column]} in sample {row}, "
            f"QoI {column}); every sample value must be finite"
        )
    return array


def _sample_variance(centred: np.ndarray, n: int) -> np.ndarray:
    if n < 2:
        return np.zeros(centred.shape[1:])
    return np.sum(centred**2, axis=0) / (n - 1)


class ExactTotal:
    """A sum of floats kept exactly (Shewchuk's non-overlapping partials), read correctly rounded.

    A run's spent cost was added batch by batch, so its last bit depended on the batch size (0.8075319616 and
    0.8075319616000001 for one run at ``batch_size`` 10 and 3): the exact sum is the same in every order.
    """

    def __init__(self) -> None:
        self._partials: list[float] = []
        self._non_finite = 0.0  # inf and NaN, added as floats add them

    def add(self, values: np.ndarray) -> None:
        """Add every value of ``values``."""
        values = np.ravel(np.asarray(values, dtype=float))
        finite = np.isfinite(values)
        if not np.all(finite):
            self._non_finite += float(np.sum(values[~finite]))
            values = values[finite]
        for value in values.tolist():
            kept = 0
            for partial in self._partials:
                if abs(value) < abs(partial):
                    value, partial = partial, value
                high = value + partial
                low = partial - (high - value)
                if low:
                    self._partials[kept] = low
                    kept += 1
                value = high
            self._partials[kept:] = [value]

    @property
    def value(self) -> float:
        """The exact sum, rounded once (inf where it overflows; inf or NaN where such values were added)."""
        try:
            total = math.fsum(self._partials)
        except (OverflowError, ValueError):  # beyond the float range (partials that overflowed give -inf + inf)
            total = math.copysign(math.inf, self._partials[-1])
        return total + self._non_finite


def scaled_by_largest(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``values`` in units of each column's largest magnitude (along axis 0), and those units.

    The scaled values lie in ``[-1, 1]``: their fourth powers neither overflow nor underflow (QoIs of 1e100 or
    1e-100). A column whose largest magnitude is 0 or not finite comes out as zeros.
    """
    scale = np.max(np.abs(values), axis=0)
    usable = np.isfinite(scale) & (scale > 0)
    return np.divide(values, scale, out=np.zeros_like(values), where=usable), scale


def _kurtosis(centred: np.ndarray) -> np.ndarray:
    # Scaling by the largest deviation keeps z in [-1, 1]: no overflow in z^4, no
    # underflow of m2^2, and m2 >= 1/n whenever the scale is positive.
    z, _ = scaled_by_largest(centred)
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
    # In units of each column's largest deviation (as _kurtosis): the fourth powers of values of 1e100 overflowed
    # (a NaN error), those of 1e-100 underflowed (an error of 0).
    (x, sx), (y, sy) = scaled_by_largest(dx), scaled_by_largest(dy)
    c = np.divide(np.divide(cov, sx, out=np.zeros_like(sx), where=sx > 0), sy, out=np.zeros_like(sy), where=sy > 0)
    mu22 = np.mean(x**2 * y**2, axis=0)
    var_x = np.sum(x**2, axis=0) / (n - 1)
    var_y = np.sum(y**2, axis=0) / (n - 1)
    variance = (mu22 - (n - 2) / (n - 1) * c**2 + var_x * var_y / (n - 1)) / n
    # Deviations or a covariance beyond the float range (values near 1e308): an infinite error, not 0.
    finite = np.isfinite(sx) & np.isfinite(sy) & np.isfinite(cov)
    return np.where(finite, np.sqrt(np.maximum(variance, 0.0)) * sx * sy, np.inf)


def _centre(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and deviations; shifting by the first sample makes both exact for constant data."""
    shifted = values - values[:1]
    mean_shift = np.mean(shifted, axis=0)
    return values[0] + mean_shift, shifted - mean_shift


def level_moments(fine: np.ndarray, coarse: np.ndarray, cost: np.ndarray) -> LevelMoments:
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
    return LevelMoments(
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


#: The per-level moments :func:`assemble_statistics` stacks into :class:`LevelStatistics` (fields of
#: :class:`LevelMoments`).
_MOMENT_FIELDS = (
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


def assemble_statistics(levels: Sequence[int], moments: Sequence[LevelMoments], base_level: int = 0) -> LevelStatistics:
    """Stack per-level moments and add the cross-level checks (``base_level``: see :class:`LevelStatistics`)."""
    levels_array = np.asarray(levels, dtype=np.int64)
    table = {name: np.array([getattr(m, name) for m in moments], dtype=float) for name in _MOMENT_FIELDS}
    n_samples = np.array([m.n for m in moments], dtype=np.int64)
    return LevelStatistics(
        base_level=int(base_level),
        levels=readonly_array(levels_array),
        n_samples=readonly_array(n_samples),
        consistency=readonly_array(_consistency(table, n_samples, levels_array)),
        coupling_ratio=readonly_array(_coupling_ratio(table, levels_array, base_level)),
        **{name: readonly_array(value) for name, value in table.items()},
    )


def _consistency(table: dict[str, np.ndarray], n_samples: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The telescoping check per level and QoI (:attr:`LevelStatistics.consistency`)."""
    consistency = np.zeros_like(table["mean_fine"])
    for row in range(1, len(levels)):
        below = row - 1
        fewest = min(n_samples[row], n_samples[below])
        if levels[below] != levels[row] - 1 or fewest < 2:
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
    return consistency


def _coupling_ratio(table: dict[str, np.ndarray], levels: np.ndarray, base_level: int) -> np.ndarray:
    """``V_l / Var(Q_l)`` per level and QoI (:attr:`LevelStatistics.coupling_ratio`)."""
    # Where Q_l never varies, V_l > 0 means the coarse value adds all the variance
    # (ratio inf, not coupled); V_l = 0 as well means there is nothing to reduce (0).
    coupling = np.divide(
        table["var_diff"],
        table["var_fine"],
        out=np.where(table["var_diff"] > 0, np.inf, 0.0),
        where=table["var_fine"] > 0,
    )
    coupling[levels <= base_level] = 1.0
    return coupling


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
            (bad,) = np.flatnonzero(~(np.isfinite(k) & (k >= 0)))[:1]
            raise EstimationError(
                f"cost of level {level} must be finite and non-negative, got {k[bad]} for sample {bad}"
            )
        if level == 0 and np.any(c != 0):
            raise EstimationError("coarse values on level 0 must be zero (there is no coarser level)")
        if f.shape[0] < 2:
            warn_at_caller(
                f"level {level} has a single sample: its variances are unknown and reported as 0",
                EstimationWarning,
            )
        moments.append(level_moments(f, c, k))
    return assemble_statistics(levels, moments)


COUPLING_CHECK_SAMPLES = 10
"""Fewest samples on a level for the coupling check of :func:`diagnose`."""


def checked_names(names: object, n_qoi: int | None, *, argument: str = "names") -> list[str] | None:
    """``names`` as a list of ``n_qoi`` strings (None stays None), else an error naming ``argument``.

    ``n_qoi`` None (the number of QoIs is not known yet) accepts any number of names.
    """
    if names is None:
        return None
    count = "" if n_qoi is None else f"{n_qoi} "
    allowed = f"a sequence of {count}QoI names (strings), one per column"
    if isinstance(names, (str, bytes)) or not isinstance(names, Sequence):
        raise InvalidParameterError(argument, names, allowed)
    if n_qoi not in (None, len(names)) or not all(isinstance(name, str) for name in names):
        raise InvalidParameterError(argument, names, allowed)
    return list(names)


def qoi_text(columns: np.ndarray, names: Sequence[str] | None) -> str:
    """The QoIs of ``columns`` in a message: by name (``clusters, area_above``), else by index (``QoI [1, 4]``)."""
    if names is None:
        return f"QoI {columns.tolist()}"
    return ", ".join(names[column] for column in columns)


def _coupling_message(level: int, ratios: np.ndarray, names: Sequence[str] | None) -> str | None:
    """The coupling check of one level (:func:`diagnose`), or None where ``V_l < Var(Q_l)`` for every QoI."""
    loose = np.flatnonzero(ratios >= 1.0)
    if not loose.size:
        return None
    if names is None:
        found = f"for QoI {loose.tolist()} (ratio {float(np.max(ratios)):.3g})"
    else:
        found = "for " + ", ".join(f"{names[q]} (ratio {float(ratios[q]):.3g})" for q in loose)
    # A ratio of variances from ten or twenty samples is noisy, and a noisy QoI (a count, a maximum) on a
    # coarse grid is weakly coupled without anything being wrong: say what was seen, not a defect.
    which, it = ("this QoI", "it") if loose.size == 1 else ("these QoIs", "them")
    return (
        f"level {level}: Var(Q_l - Q_l-1) >= Var(Q_l) {found}: the levels are weakly coupled for {which}, "
        f"so MLMC gains little for {it}; on coarse grids this can be noise (a ratio near 2 or above means the "
        "coarse values look unrelated to the fine ones)"
    )


def _level_messages(
    statistics: LevelStatistics, row: int, kurtosis_limit: float, names: Sequence[str] | None
) -> list[str]:
    """The failed checks of row ``row`` of ``statistics`` (:func:`diagnose`)."""
    level, n = statistics.levels[row], statistics.n_samples[row]
    if n < 2:
        return [f"level {level}: {n} sample(s), variance unknown"]
    messages = []
    bad = np.flatnonzero(statistics.consistency[row] > 1.0)
    if bad.size:
        worst = float(np.max(statistics.consistency[row]))
        messages.append(
            f"level {level}: consistency check failed for {qoi_text(bad, names)} "
            f"(|E[Q_l - Q_l-1] - (E[Q_l] - E[Q_l-1])| = {worst:.3g} x 3 standard deviations); "
            "the coarse sample of level l does not match the fine sample of level l-1"
        )
    heavy = np.flatnonzero(statistics.kurtosis[row] > kurtosis_threshold(n, kurtosis_limit))
    if heavy.size:
        worst = float(np.max(statistics.kurtosis[row]))
        of = "Q_l" if level <= statistics.base_level else "Q_l - Q_l-1"  # the base level's samples are Q_l alone
        messages.append(
            f"level {level}: kurtosis {worst:.3g} of {of} for {qoi_text(heavy, names)} "
            f"{kurtosis_text(worst, n, kurtosis_limit)}; its variance estimate is unreliable"
        )
    if level <= statistics.base_level:
        return messages
    frozen = np.flatnonzero((statistics.var_diff[row] == 0) & (statistics.var_fine[row] > 0))
    if frozen.size:
        messages.append(
            f"level {level}: Q_l - Q_l-1 is the same in all {n} samples for {qoi_text(frozen, names)} "
            "although Q_l varies; if the differences are rare events (integer QoIs), this level's "
            "mean and variance are underestimated -- use more samples per level"
        )
    coupling = _coupling_message(level, statistics.coupling_ratio[row], names)
    if coupling is not None and n >= COUPLING_CHECK_SAMPLES:
        messages.append(coupling)
    return messages


def diagnose(
    statistics: LevelStatistics, *, kurtosis_limit: float = KURTOSIS_LIMIT, names: Sequence[str] | None = None
) -> tuple[str, ...]:
    """The failed MLMC checks of a screening table, as one message each.

    Checks (SPEC section 5): the consistency check (ratio above 1; below
    ``CONSISTENCY_CHECK_SAMPLES`` samples on a level only a gap with no spread), the
    kurtosis of ``Y_l`` (above ``kurtosis_limit``, or above half the level's samples from
    ``SAMPLE_KURTOSIS_CHECK_SAMPLES`` on, :func:`kurtosis_threshold`: ``V_l`` unreliable), the
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
        Largest acceptable kurtosis (default 100, as in ``mlmc_test``; ``math.inf``: no kurtosis check), and
        from 20 samples on at most half the level's samples (:func:`kurtosis_threshold`).
    names : sequence of str, optional
        Names of the QoI columns, length ``n_qoi``: messages name the QoIs
        (``for area_above``); without them they give column indices
        (``for QoI [4]``).

    Returns
    -------
    tuple of str
        Empty when every check passes.
    """
    names = checked_names(names, statistics.mean_fine.shape[1])
    messages = []
    for row in range(len(statistics.levels)):
        messages += _level_messages(statistics, row, kurtosis_limit, names)
    return tuple(messages)

