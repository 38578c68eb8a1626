"""MLMC estimation of a distribution function and its quantiles (SPEC section 5, "Beyond the mean").

Smoothed indicators
-------------------
``F(s) = P(Q <= s) = E[1{Q <= s}]`` is a mean, but the indicator's level
differences ``1{Q_l <= s} - 1{Q_{l-1} <= s}`` are rare, large jumps. As in
Giles, Nagapetyan & Ritter (SIAM/ASA JUQ 2015) the indicator is replaced by a
smooth step of width ``delta``, ``g((s - Q) / delta)``, with

    g(x) = 0 (x <= -1),   1/2 + 15/16 (x - 2x^3/3 + x^5/5) (|x| < 1),   1 (x >= 1),

the integral of the biweight kernel ``K(t) = 15/16 (1 - t^2)^2`` on
``[-1, 1]``: non-decreasing, twice continuously differentiable, exact (0 or
1) farther than ``delta`` from ``s``. ``K`` is symmetric, so the smoothing
bias is of second order, ``E[g((s - Q)/delta)] - F(s) = delta^2 f'(s) / 14 +
O(delta^4)`` (``1/7`` the second moment of ``K``, ``f`` the density of
``Q``).

A value equal to a threshold (within :data:`TIE_TOLERANCE` bandwidths, or
of the thresholds' scale where that is smaller, which absorbs the rounding of
thresholds typed in decimal) counts whole,
``1`` instead of ``g(0) = 1/2``:
for a ``Q`` with atoms (a count of clusters, a rounded value) the smoothed
indicator otherwise tends to ``F(s-) + P(Q = s) / 2`` on every level, a bias
no level term shows (integer thresholds under an integer ``Q`` with an atom
of 0.2 at 0: an RMS error of 0.106 against tol 0.02, the tolerance claimed in
20 of 20 runs). For a continuous ``Q`` the rule changes nothing (ties have
probability 0). Atoms within a bandwidth of a threshold but off it are
smoothed like any value and resolved only once ``delta_l`` is below their
distance: put the thresholds of a discrete ``Q`` on or between its values.

Levels whose pairs change no indicator
--------------------------------------
On a level ``l >= 1`` whose ``N`` pairs all lie on the same side of every
threshold, farther than a bandwidth (``Q_l`` and ``Q_{l-1}`` alike), every
difference is 0 and so is the sample variance, although the values may lie
on both sides of the grid (the check of missed thresholds below then passes).
Such a level's change of ``F`` was not measured: ``N`` unchanged pairs bound
the probability of a change by about ``3/N`` (95 %, the rule of three), and a
difference lies in ``[-1, 1]``, so its variance is taken as
``UNSEEN_CHANGE / N^2`` at every threshold (``LevelTerm.is_bound``), unless
the thresholds miss the level's values altogether (below: the run then says
so and claims no tolerance) (a tail grid's level of 32 pairs
had reported a variance of 0, was never sampled again, and its run claimed
tol 0.01 at an error of 0.058). The allocation then at most doubles the
pairs of such a level per round, until they show a change or the bound,
which falls like ``1 / N^2``, fits the tolerance
(:mod:`rough_uq.multilevel.targets`).

Bandwidth per level
-------------------
Level ``l`` uses ``delta_l = bandwidth 2^(-bandwidth_rate l)`` (the unit of
``Q``); the level-``l`` term at threshold ``s_j`` is the sample mean of
``g((s_j - Q_l)/delta_l) - g((s_j - Q_{l-1})/delta_{l-1})`` (on level 0:
``g((s_j - Q_0)/delta_0)``), so the sum telescopes to the smoothed CDF of
``Q_L`` with bandwidth ``delta_L``. Its bias ``F_L(s) - F(s)`` then has a
discretisation part (the decay of ``Q_l``) and a smoothing part
``~ delta_L^2``, decaying by ``4^(-bandwidth_rate)`` per level; both show in
the level terms and are estimated together from their decay
(:mod:`rough_uq.multilevel.targets`). Changing the bandwidth between levels
costs variance: a sample within ``delta_l`` of ``s`` contributes ``O(1)`` to
the term, so ``W_l ~ delta_l`` and ``beta <= bandwidth_rate`` (the default
1 gives ``beta = 1``). With ``bandwidth_rate = 0`` the bandwidth is fixed,
the estimate converges to the smoothed CDF, and its smoothing bias
``delta^2 f'/14`` is *not* part of the reported bias.

Error measure
-------------
``stat_error`` and ``rmse`` are per threshold; the tolerance is on their
maximum over the grid, ``max_j sqrt(E[(Fhat(s_j) - F(s_j))^2])``. The mean
of the squared supremum, ``E[max_j |Fhat(s_j) - F(s_j)|^2]``, is larger
(by a factor that grows slowly with the number of effectively independent
thresholds): for a simultaneous band, widen accordingly.

Thresholds that miss the samples
--------------------------------
The variance of a level term is estimated from the spread of its samples at
the thresholds. Where every value of level ``l`` (``Q_l``, and ``Q_{l-1}``
on ``l >= 1``) lies at least its bandwidth away on one side of each
threshold (e.g. every threshold below the smallest value, or above the
largest), the smoothed indicators are 0 on all samples or 1 on all, and the
term's sample variance is 0 at every threshold whatever ``F`` is: the
samples do not measure it. (``N`` values on one side of ``s`` only bound the
probability of the other side by about ``3/N`` (95 %), so the term's true
standard error can be up to about ``sqrt(3)/N``.) The thresholds then *miss
the samples* of that level, and the estimate lists the level in
``missed_levels``, warns (:class:`~rough_uq.errors.EstimationWarning`,
naming the thresholds and, per missed level, the range of its values),
reports ``stop_reason = "thresholds_miss_samples"`` and does not meet its
tolerance, whatever its error estimate (0 where every level is missed)
says. A grid over part of the distribution misses no level as long as each
level has a value within a bandwidth of some threshold, or values on both
sides of one; a grid over a thin tail alone can miss a level of few
samples: extend the grid, or draw more initial samples.

A bandwidth wider than the distribution
---------------------------------------
The smoothing bias is estimated from the decay of the level terms, which
follows ``delta_l^2`` only while the bandwidth is narrow against the spread
of ``Q``. Far wider, every value lies in the linear part of ``g``: the
smoothed CDF is about 1/2 everywhere, it changes little from level to level,
and the decay estimate misses most of the bias (with ``bandwidth = 1e4`` on a
contact area in percent a run reported an RMSE of 0.004 for a CDF that was
0.5 at every threshold, 0.5 off). For a normal ``Q`` of standard deviation
``sigma``, the estimate from the last term at the decay ``4^-1`` per level
is 0.94 / 0.83 / 0.57 / 0.33 / 0.20 of the largest smoothing bias over the
thresholds at ``delta_L = 0.5 / 1 / 2 / 4 / 8 sigma``, and misses 0.0003 /
0.003 / 0.025 / 0.10 / 0.21 of it (numerical integration). An estimate whose
finest bandwidth ``delta_L`` exceeds :data:`BANDWIDTH_SPREAD_LIMIT` (2) times
the standard deviation of ``Q_L`` (its variance telescoped over the levels,
``sum_l [Var(Q_l) - Var(Q_{l-1})]`` from each level's own pairs, as the
estimate telescopes, or the finest level's own sample variance where that is
larger; :class:`_Spread`) therefore warns (:class:`~rough_uq.errors.EstimationWarning`), reports
``stop_reason = "bandwidth_too_wide"`` with its bias not estimated, and does
not meet its tolerance: give a narrower ``bandwidth`` (the default is twice
the spacing of the thresholds: give finer thresholds). Below the limit, a
run whose bias share ``sqrt(theta) tol`` is below the estimate at ``2
sigma`` (0.03 for a normal ``Q``) refines further anyway, towards bandwidths
whose bias the estimate measures. Left as they are:
a run stopped before it estimated its bias (``max_cost``) claims none; with
``bandwidth_rate = 0`` the target is the smoothed CDF itself; and where
every value of the finest level lies a bandwidth or more from every
threshold (e.g. a discrete ``Q`` with thresholds between its values) the
smoothed indicators are exact there.

Monotone output
---------------
The raw sum ``cdf_raw`` need not be monotone or lie in ``[0, 1]``. The
reported ``cdf`` is its least-squares isotonic regression (pool-adjacent
violators), clipped to ``[0, 1]``. Both steps are monotone maps that commute
with adding a constant (clipping: up to the bounds), and the true ``F`` is a
fixed point of both, so ``max_j |cdf_j - F(s_j)| <= max_j |cdf_raw_j -
F(s_j)|``: the projection never increases the sup-norm error (pointwise it
can move the error from one threshold to a neighbour, never beyond the
sup).

Quantiles
---------
``q_p = inf {s : F(s) >= p}`` of the monotone ``cdf``, linearly
interpolated between thresholds. Its error bar comes from the band ``cdf
+- rmse`` (the sup-norm RMS error): ``lower`` is where the upper band
reaches ``p``, ``upper`` where the lower band does (``-inf``/``+inf`` where
the band leaves the grid). To first order ``(upper - lower) / 2 = rmse /
f(q_p)``, the delta-method error. The linear interpolation between
thresholds is not part of the error bar: choose a grid whose spacing is well
below it (a distribution with atoms, e.g. a deterministic ``Q``, shows the
interpolation alone). An estimate without an error band
(:data:`NO_ERROR_BAND`: the thresholds miss a level's samples, or the
bandwidth is too wide, whose smoothing bias is known to be large and not
estimated) has open error bars, ``-inf`` to ``+inf``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from rough_uq.errors import (
    EstimationError,
    EstimationWarning,
    InvalidParameterError,
    checked_real_array,
    is_real_number,
    warn_at_caller,
)
from rough_uq.multilevel.allocation import MIN_TOL
from rough_uq.multilevel.drivers import Sampler
from rough_uq.multilevel.statistics import readonly_array
from rough_uq.multilevel.targets import LevelTerm, TargetEstimate, adaptive_mlmc, telescope

__all__ = [
    "CdfEstimate",
    "check_cdf_tol",
    "Quantiles",
    "THRESHOLDS_MISS_SAMPLES",
    "BANDWIDTH_TOO_WIDE",
    "BANDWIDTH_SPREAD_LIMIT",
    "DEFAULT_PROBABILITIES",
    "NO_ERROR_BAND",
    "cdf_from_samples",
    "cdf_level_term",
    "isotonic",
    "level_bandwidth",
    "mlmc_cdf",
    "quantiles",
    "smoothed_step",
    "UNSEEN_CHANGE",
    "TIE_TOLERANCE",
]
# Also imported by rough_uq.problem.distribution, not part of the API: checked_thresholds.

#: ``stop_reason`` of an estimate whose thresholds miss the samples of a level (module docstring).
THRESHOLDS_MISS_SAMPLES = "thresholds_miss_samples"

#: ``stop_reason`` of a CDF estimate whose finest bandwidth exceeds the spread of the values there (module
#: docstring, "A bandwidth wider than the distribution"): its smoothing bias is not estimated.
BANDWIDTH_TOO_WIDE = "bandwidth_too_wide"

#: The ``stop_reason`` of estimates without an error band (:attr:`CdfEstimate.has_error_band`).
NO_ERROR_BAND = (THRESHOLDS_MISS_SAMPLES, BANDWIDTH_TOO_WIDE)

#: Quantiles reported by default: the 5 %, 50 % and 95 % points.
DEFAULT_PROBABILITIES = (0.05, 0.5, 0.95)

#: A level ``>= 1`` of ``n`` pairs none of which changes a smoothed indicator has ``Var(T_c) = UNSEEN_CHANGE / n^2``
#: (module docstring: the rule of three).
UNSEEN_CHANGE = 3.0

#: A value within this many bandwidths of a threshold is on it (module docstring): the rounding of a threshold
#: typed in decimal (300 against 3 clusters in a box of 0.1, 3 / 0.1**2 = 299.99999999999994) must not halve an atom.
#: Of the thresholds' scale (their span or size, the larger) where the bandwidth is wider: with ``bandwidth=1e12``
#: every value was on every threshold (F = 1 at all of them, values of 17-22 at 10 too).
TIE_TOLERANCE = 1e-9

#: Largest finest bandwidth, in standard deviations of the values, whose smoothing bias the decay of the level
#: terms is taken to measure (module docstring, "A bandwidth wider than the distribution").
BANDWIDTH_SPREAD_LIMIT = 2.0

#: Rows of samples per block when evaluating the smoothed indicators (bounds memory to block x thresholds).
_BLOCK = 4096


def smoothed_step(x: np.ndarray) -> np.ndarray:
    """The smooth step ``g(x)`` of the module docstring (dimensionless, same shape as ``x``)."""
    x = np.clip(np.asarray(x, dtype=float), -1.0, 1.0)
    step = 0.5 + 15.0 / 16.0 * x * (1.0 - x**2 * (2.0 / 3.0 - x**2 / 5.0))
    # The polynomial rounds to +-1e-16 beyond 0 and 1 near x = -+1; the step is exactly 0 or 1 there.
    return np.clip(step, 0.0, 1.0)


def level_bandwidth(level: int, *, bandwidth: float, bandwidth_rate: float = 1.0) -> float:
    """``delta_l = bandwidth 2^(-bandwidth_rate level)``, in the unit of ``Q``."""
    return float(bandwidth * 2.0 ** (-bandwidth_rate * level))


def check_cdf_tol(tol: object, name: str = "tol") -> float:
    """The tolerance of a CDF estimate, one number in [MIN_TOL, 1), or :class:`InvalidParameterError` naming
    ``name`` (errors are compared in squares, :data:`~rough_uq.multilevel.allocation.MIN_TOL`)."""
    if np.ndim(tol) != 0 or not (is_real_number(tol) and MIN_TOL <= tol < 1):
        # F is a probability: an RMS error of 1 or more is met by any estimate.
        raise InvalidParameterError(name, tol, f"one number in [{MIN_TOL:g}, 1): the RMS error of F = P(Q <= s) "
                                    "on the sup norm")
    return float(tol)


def checked_thresholds(thresholds: object) -> np.ndarray:
    allowed = "a 1-d array of at least two finite, strictly increasing values"
    array = checked_real_array("thresholds", thresholds, allowed)  # numbers only: strings ("10") were converted
    if array.ndim != 1 or array.size < 2 or not np.all(np.isfinite(array)) or np.any(np.diff(array) <= 0):
        raise InvalidParameterError("thresholds", thresholds, allowed)
    return array


def _check_bandwidth(bandwidth: float, bandwidth_rate: float) -> None:
    """Refuse by name a bandwidth or rate that is not a finite number (strings and booleans are not converted)."""
    if not (is_real_number(bandwidth) and np.isfinite(bandwidth) and bandwidth > 0):
        raise InvalidParameterError("bandwidth", bandwidth, "a positive number (the unit of Q)")
    if not (is_real_number(bandwidth_rate) and np.isfinite(bandwidth_rate) and bandwidth_rate >= 0):
        raise InvalidParameterError("bandwidth_rate", bandwidth_rate, "a non-negative number")


def _column(values: np.ndarray, qoi: int, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    array = array[:, None] if array.ndim == 1 else array
    if array.ndim != 2 or not 0 <= qoi < array.shape[1]:
        raise InvalidParameterError("qoi", qoi, f"a column index of {name}, shape {np.shape(values)}")
    if array.shape[0] < 2:
        raise InvalidParameterError(name, f"{array.shape[0]} samples", "at least 2 samples")
    if not np.all(np.isfinite(array[:, qoi])):
        raise InvalidParameterError(name, "non-finite values", "finite values")
    return array[:, qoi]


def _indicator(s: np.ndarray, values: np.ndarray, delta: float) -> np.ndarray:
    """The smoothed indicators ``g((s - Q) / delta)``, 1 where ``Q`` equals ``s`` to :data:`TIE_TOLERANCE` (module
    docstring), shape ``(n_values, n_thresholds)`` for ``values`` of shape ``(n_values, 1)`` and all the
    thresholds ``s`` (increasing)."""
    # The thresholds' scale caps the bandwidth's: their span, or their size where that is larger (two thresholds
    # 1e-5 apart near 300 would otherwise make the width less than the rounding of 300).
    tie = TIE_TOLERANCE * min(delta, max(float(s[-1] - s[0]), float(np.max(np.abs(s)))))
    return np.where(np.abs(s - values) <= tie, 1.0, smoothed_step((s - values) / delta))


def _indicator_differences(x: np.ndarray, y: np.ndarray | None, s: np.ndarray, delta_x: float, delta_y: float):
    """Yield blocks of ``g((s - x)/delta_x) - g((s - y)/delta_y)``, shape (block, n_thresholds)."""
    for start in range(0, len(x), _BLOCK):
        block = _indicator(s, x[start : start + _BLOCK, None], delta_x)
        if y is not None:
            block = block - _indicator(s, y[start : start + _BLOCK, None], delta_y)
        yield block


def cdf_level_term(
    fine: np.ndarray,
    coarse: np.ndarray | None,
    level: int,
    *,
    thresholds: np.ndarray,
    bandwidth: float,
    bandwidth_rate: float = 1.0,
    qoi: int = 0,
) -> LevelTerm:
    """Level term of the smoothed CDF at every threshold (module docstring).

    Parameters
    ----------
    fine, coarse : ndarray, shape (n,) or (n, n_qoi)
        The level's pairs ``(Q_l, Q_{l-1})``, ``n >= 2``; ``coarse`` None on
        level 0.
    level : int
        ``l``, which sets the bandwidths ``delta_l`` and ``delta_{l-1}``.
    thresholds : ndarray, shape (n_thresholds,)
        Strictly increasing ``s_j``, the unit of ``Q``.
    bandwidth : float
        ``delta_0``, the unit of ``Q``.
    bandwidth_rate : float
        ``delta_l = delta_0 2^(-bandwidth_rate l)``.
    qoi : int
        Column of the QoI whose distribution is estimated.

    Returns
    -------
    LevelTerm
        One component per threshold, all in one tolerance group; the
        variance is the sample variance of the differences over ``n``.
    """
    s = checked_thresholds(thresholds)
    _check_bandwidth(bandwidth, bandwidth_rate)
    x = _column(fine, qoi, "fine")
    y = None if coarse is None else _column(coarse, qoi, "coarse")
    if y is not None and (y.shape != x.shape or level < 1):
        raise InvalidParameterError(
            "coarse", f"{y.shape[0]} samples on level {level}", "one per fine sample, on a level >= 1"
        )
    n = len(x)
    delta_x = level_bandwidth(level, bandwidth=bandwidth, bandwidth_rate=bandwidth_rate)
    delta_y = level_bandwidth(level - 1, bandwidth=bandwidth, bandwidth_rate=bandwidth_rate)
    # Block means and squared deviations merged pairwise (Chan et al.): one evaluation of g per
    # sample, and no cancellation where F is near 0 or 1.
    count, mean, square = 0, np.zeros(len(s)), np.zeros(len(s))
    for block in _indicator_differences(x, y, s, delta_x, delta_y):
        size = block.shape[0]
        block_mean = np.mean(block, axis=0)
        shift = block_mean - mean
        square += np.sum((block - block_mean) ** 2, axis=0) + shift**2 * count * size / (count + size)
        mean += shift * size / (count + size)
        count += size
    variance = square / (n - 1) / n
    is_bound = y is not None and not np.any(square) and not np.any(mean) and not _is_missed(x, y, s, delta_x, delta_y)
    if is_bound:
        # No pair changed any indicator: the level's variance is unmeasured, not 0 (module docstring).
        variance = np.full(len(s), UNSEEN_CHANGE / n**2)
    return LevelTerm(
        mean=readonly_array(mean),
        variance=readonly_array(variance),
        n_samples=n,
        groups=readonly_array(np.zeros(len(s), dtype=np.int64)),
        is_bound=is_bound,
    )


def _is_missed(x: np.ndarray, y: np.ndarray | None, s: np.ndarray, delta_x: float, delta_y: float) -> bool:
    """Whether the thresholds miss a level's fine values ``x`` and coarse values ``y`` (None on level 0) alike
    (module docstring)."""
    return _is_one_sided(x, s, delta_x) and (y is None or _is_one_sided(y, s, delta_y))


def _is_one_sided(values: np.ndarray, s: np.ndarray, delta: float) -> bool:
    """Whether every value's indicator is 0 at a threshold, or every value's 1 (``delta`` or more on one side of it,
    or on it: a tie counts 1), at each threshold."""
    all_zero, all_one = np.ones(len(s), dtype=bool), np.ones(len(s), dtype=bool)
    for start in range(0, len(values), _BLOCK):
        block = _indicator(s, values[start : start + _BLOCK, None], delta)
        all_zero &= np.all(block == 0.0, axis=0)
        all_one &= np.all(block == 1.0, axis=0)
    return bool(np.all(all_zero | all_one))


def _missed_range(
    fine: np.ndarray,
    coarse: np.ndarray | None,
    level: int,
    *,
    thresholds: np.ndarray,
    bandwidth: float,
    bandwidth_rate: float,
    qoi: int,
) -> tuple[float, float] | None:
    """The range of the level's values (unit of ``Q``) if the thresholds miss them (module docstring), else None.

    Arguments as in :func:`cdf_level_term`, ``thresholds`` already checked.
    """
    x = _column(fine, qoi, "fine")
    y = None if coarse is None else _column(coarse, qoi, "coarse")
    delta_x, delta_y = (
        level_bandwidth(at, bandwidth=bandwidth, bandwidth_rate=bandwidth_rate) for at in (level, level - 1)
    )
    if not _is_missed(x, y, thresholds, delta_x, delta_y):
        return None
    values = x if y is None else np.concatenate([x, y])
    return float(np.min(values)), float(np.max(values))


def isotonic(values: np.ndarray) -> np.ndarray:
    """Least-squares non-decreasing fit of a sequence (pool-adjacent violators, equal weights).

    Parameters
    ----------
    values : ndarray, shape (m,)

    Returns
    -------
    ndarray, shape (m,)
        The non-decreasing sequence closest to ``values`` in the Euclidean norm.
    """
    values = np.asarray(values, dtype=float)
    sums: list[float] = []
    counts: list[int] = []
    for value in values:
        sums.append(float(value))
        counts.append(1)
        # Merge backwards while the last block's mean is below its predecessor's.
        while len(sums) > 1 and sums[-2] * counts[-1] > sums[-1] * counts[-2]:
            total, count = sums.pop(), counts.pop()
            sums[-1] += total
            counts[-1] += count
    return np.repeat(np.array(sums) / np.array(counts), counts)


@dataclass(frozen=True, eq=False)
class CdfEstimate:
    """MLMC estimate of ``F(s) = P(Q <= s)`` on a grid of thresholds.

    Attributes
    ----------
    thresholds : ndarray, shape (m,)
        ``s_j``, the unit of ``Q``.
    cdf : ndarray, shape (m,)
        Monotone estimate in ``[0, 1]`` (module docstring, "Monotone output").
    cdf_raw : ndarray, shape (m,)
        The telescoped sum before the projection.
    stat_error : ndarray, shape (m,)
        Statistical error of ``cdf_raw`` per threshold.
    bias : float
        Remaining bias (maximum over the thresholds) from the decay of the level terms; 0 where it is not
        estimated (``is_bias_estimated``). At most 1, as ``rmse``: ``cdf`` lies in ``[0, 1]``, and no error of it
        exceeds 1 (level terms of thresholds that miss a level's samples extrapolated a bias of 1.96).
    rmse : float
        ``sqrt(max_j stat_error_j^2 + bias^2)``, the sup-norm RMS error estimate, at most 1.
    bandwidths : ndarray, shape (n_levels,)
        ``delta_l`` per level.
    target : TargetEstimate
        The underlying telescoping estimate (levels, ``n_samples``, terms,
        rates, cost, ``stop_reason``, ``tol``).
    missed_levels : ndarray of int, shape (k,)
        Levels whose samples the thresholds miss (module docstring): their
        variance estimate is 0 whatever ``F`` is, and ``tol_met`` is False.
        Empty where every level's samples meet a threshold.
    """

    thresholds: np.ndarray
    cdf: np.ndarray
    cdf_raw: np.ndarray
    stat_error: np.ndarray
    bias: float
    rmse: float
    bandwidths: np.ndarray
    target: TargetEstimate
    missed_levels: np.ndarray

    @property
    def levels(self) -> np.ndarray:
        """Levels ``0..L``."""
        return self.target.levels

    @property
    def n_samples(self) -> np.ndarray:
        """``N_l`` per level."""
        return self.target.n_samples

    @property
    def stop_reason(self) -> str:
        """Why the run stopped (see :class:`~rough_uq.multilevel.targets.TargetEstimate`).

        ``"thresholds_miss_samples"`` (:data:`THRESHOLDS_MISS_SAMPLES`) where the thresholds miss the samples of
        a level (``missed_levels``), and ``"bandwidth_too_wide"`` (:data:`BANDWIDTH_TOO_WIDE`) where the finest
        bandwidth exceeds twice the spread of the values (module docstring), whatever the driver's reason: the
        tolerance is not met.
        """
        return self.target.stop_reason

    @property
    def noisy_bias_groups(self) -> tuple[int, ...]:
        """``(0,)`` where the bias exceeds its share while the finest level's terms are within their noise
        (:attr:`~rough_uq.multilevel.targets.TargetEstimate.noisy_bias_groups`), else ``()``."""
        return self.target.noisy_bias_groups

    @property
    def is_bias_estimated(self) -> bool:
        """Whether ``bias`` is an estimate (:class:`~rough_uq.multilevel.targets.TargetEstimate`)."""
        return self.target.is_bias_estimated

    @property
    def has_error_band(self) -> bool:
        """Whether the band ``cdf +- rmse`` measures the error: False where the thresholds miss a level's samples
        (its variance unmeasured) or the bandwidth is too wide (the smoothing bias, known to be large, not
        estimated). A run stopped before its bias, or one level of given samples, has the band of its
        statistical error, as a mean estimate without a bias has its statistical error."""
        return self.stop_reason not in NO_ERROR_BAND

    @property
    def tol_met(self) -> bool:
        """``rmse <= tol`` with an estimated bias; False without a tolerance or that estimate, or with missed levels."""
        return self.target.tol_met

    @property
    def tol(self) -> float:
        """The tolerance on the sup-norm RMS error (every threshold is in the one group of ``target.tol``)."""
        return float(self.target.tol[0])

    def __repr__(self) -> str:
        # One line: the arrays over the thresholds (some 25 000 characters for 121 of them) stay in the attributes.
        s = self.thresholds
        return (
            f"CdfEstimate(thresholds=<{s.size} from {s[0]:g} to {s[-1]:g}>, rmse={self.rmse:.3g}, "
            f"tol={self.tol:g}, tol_met={self.tol_met}, stop_reason={self.stop_reason!r}, "
            f"levels={self.levels.tolist()}, n_samples={self.n_samples.tolist()})"
        )


def _warn_thresholds_miss(thresholds: np.ndarray, missed: dict[int, tuple[float, float]]) -> None:
    """The :class:`~rough_uq.errors.EstimationWarning` of an estimate whose thresholds miss some level's samples."""
    ranges = ", ".join(
        f"level {level} (values {low:.4g} .. {high:.4g})" for level, (low, high) in sorted(missed.items())
    )
    warn_at_caller(
        EstimationWarning(
            f"cdf: the thresholds [{thresholds[0]:.6g}, {thresholds[-1]:.6g}] miss the samples of {ranges}: every "
            "value lies beyond the smoothing bandwidth on one side of each threshold (or on it), so the variance "
            "estimate there is 0 whatever F is, and the tolerance is not met; put thresholds among the values (extend "
            "the grid) or draw more initial samples"
        ),
    )


def _warn_bandwidth_too_wide(finest: float, spread: float, level: int) -> None:
    """The :class:`~rough_uq.errors.EstimationWarning` of an estimate whose finest bandwidth exceeds the spread."""
    if not spread > 0:  # a constant Q within a bandwidth of a threshold: its step is smoothed away
        warn_at_caller(EstimationWarning(
            f"cdf: the values of the finest level {level} do not vary, and lie within its smoothing bandwidth, "
            f"{finest:.4g}, of a threshold: the smoothed CDF spreads their step there, which the bias estimate does "
            "not measure; the tolerance is not met; give a bandwidth below the distance from the values to the "
            "nearest threshold (by default twice the thresholds' spacing: give finer thresholds)"))
        return
    warn_at_caller(
        EstimationWarning(
            f"cdf: the smoothing bandwidth on the finest level {level}, {finest:.4g}, exceeds "
            f"{BANDWIDTH_SPREAD_LIMIT:g} standard deviations of the values (standard deviation {spread:.4g}): "
            "the smoothing bias is then beyond what the decay of the level terms measures (the smoothed CDF "
            "flattens towards 1/2), so the bias is not estimated and the tolerance is not met; give a bandwidth "
            "below twice the spread of the values (by default twice the thresholds' spacing: give finer thresholds)"
        ),
    )


class _Spread:
    """The standard deviation of the finest level's ``Q_L``, telescoped over the levels' latest samples.

    ``Var(Q_L) = sum_l [Var(Q_l) - Var(Q_{l-1})]``, each difference from the level's own sample pairs (sample
    variances, ``Var(Q_{-1}) = 0``), uses every level's samples, as the estimate does: the finest level's own
    few samples gave a noisy spread, and pooling the levels' spreads measured mostly the coarsest one, whose
    spread can differ from the finest level's by a factor of 2-6 (contact areas, clusters). Each level is
    centred on its own means. Telescoping raw moments, ``E[Q_L^2] - E[Q_L]^2`` from ``sum_l E[Q_l^2 -
    Q_{l-1}^2]``, added a term ``2 sum_l E[Y_l] (mean of level l - mean of level 0)`` of noise: on the
    quickstart with 10 samples per level it gave a standard deviation of 0.16 where the values' is about 1.0,
    and a correct run ended NOT MET (``bandwidth_too_wide``); centred, 0.55, and the same run at other thresholds
    still ended so (a finest bandwidth of 1.5 against twice 0.55, where the finest level's own values had a
    standard deviation of 1.08). The larger of the telescoped and the finest level's own sample variance is
    taken: each alone is noisy with few samples, and the check is to catch a bandwidth that is clearly too wide,
    not to fail a correct run on noise.
    """

    def __init__(self) -> None:
        self.levels: dict[int, tuple[float, float]] = {}

    def add(self, level: int, fine: np.ndarray, coarse: np.ndarray | None, qoi: int) -> None:
        x = _column(fine, qoi, "fine")
        fine_variance = _sample_variance(x)
        below = 0.0 if coarse is None or level == 0 else _sample_variance(_column(coarse, qoi, "coarse"))
        self.levels[level] = (fine_variance - below, fine_variance)

    def value(self, levels: np.ndarray) -> float:
        telescoped = sum(self.levels[int(level)][0] for level in levels)
        return float(np.sqrt(max(telescoped, self.levels[int(levels[-1])][1])))


def _sample_variance(values: np.ndarray) -> float:
    """The unbiased sample variance; 0 for a single value (no spread measured)."""
    return float(np.var(values, ddof=1)) if values.size > 1 else 0.0


def _is_exact(fine: np.ndarray, qoi: int, thresholds: np.ndarray, delta: float) -> bool:
    """Whether every value lies ``delta`` or more from every threshold (``g`` is then 0 or 1 on each)."""
    values = _column(fine, qoi, "fine")
    right = np.clip(np.searchsorted(thresholds, values), 0, thresholds.size - 1)
    left = np.clip(right - 1, 0, thresholds.size - 1)
    nearest = np.minimum(np.abs(values - thresholds[left]), np.abs(values - thresholds[right]))
    return bool(np.all(nearest >= delta))


def _checked_target(
    target: TargetEstimate,
    thresholds: np.ndarray,
    bandwidth: float,
    bandwidth_rate: float,
    missed: dict[int, tuple[float, float]],
    spread: float,
    is_exact: bool,
) -> TargetEstimate:
    """``target`` with the CDF's own checks applied, each failed one warned: ``missed``, the value range per level
    whose samples the thresholds miss; ``spread``, the standard deviation of ``Q_L`` (:class:`_Spread`);
    ``is_exact``: every finest value lies a finest bandwidth or more from every threshold."""
    finest_level = int(target.levels[-1])
    finest = level_bandwidth(finest_level, bandwidth=bandwidth, bandwidth_rate=bandwidth_rate)
    # A run stopped before it estimated its bias claims none; with bandwidth_rate 0 the target is the smoothed CDF.
    is_checked = target.is_bias_estimated and bandwidth_rate > 0 and not is_exact
    if missed:
        _warn_thresholds_miss(thresholds, missed)
        return replace(target, stop_reason=THRESHOLDS_MISS_SAMPLES, is_variance_measured=False)
    if is_checked and not finest <= BANDWIDTH_SPREAD_LIMIT * spread:
        _warn_bandwidth_too_wide(finest, spread, finest_level)
        return replace(target, stop_reason=BANDWIDTH_TOO_WIDE, is_bias_estimated=False,
                       bias=np.zeros_like(target.bias))
    return target


def _cdf_estimate(
    target: TargetEstimate,
    thresholds: np.ndarray,
    bandwidth: float,
    bandwidth_rate: float,
    missed: dict[int, tuple[float, float]],
) -> CdfEstimate:
    """The CDF estimate of a checked ``target`` (:func:`_checked_target`)."""
    raw = target.estimate
    return CdfEstimate(
        thresholds=readonly_array(thresholds),
        cdf=readonly_array(np.clip(isotonic(raw), 0.0, 1.0)),
        cdf_raw=raw,
        stat_error=target.stat_error,
        bias=min(float(target.bias[0]), 1.0),
        rmse=min(float(target.rmse[0]), 1.0),
        bandwidths=readonly_array(
            [level_bandwidth(int(level), bandwidth=bandwidth, bandwidth_rate=bandwidth_rate) for level in target.levels]
        ),
        target=target,
        missed_levels=readonly_array(np.array(sorted(missed), dtype=np.int64)),
    )


def cdf_from_samples(
    *,
    fine: Sequence[np.ndarray],
    coarse: Sequence[np.ndarray],
    thresholds: np.ndarray,
    bandwidth: float,
    bandwidth_rate: float = 1.0,
    qoi: int = 0,
    tol: float | None = None,
) -> CdfEstimate:
    """MLMC estimate of the CDF from given level samples (levels ``0, 1, ..., L``).

    Parameters
    ----------
    fine, coarse : sequence of ndarray, each shape (n_l,) or (n_l, n_qoi)
        Per level, ``Q_l`` and ``Q_{l-1}`` (``coarse`` of level 0 ignored).
    thresholds, bandwidth, bandwidth_rate, qoi
        As in :func:`cdf_level_term`.
    tol : float, optional
        Tolerance on the sup-norm RMS error (sets ``tol_met``).

    Returns
    -------
    CdfEstimate

    Warns
    -----
    EstimationWarning
        Where the thresholds miss the samples of a level (module docstring):
        ``tol_met`` is then False, ``stop_reason`` ``"thresholds_miss_samples"``;
        where the finest bandwidth exceeds twice the spread of the values:
        ``stop_reason`` ``"bandwidth_too_wide"``, the bias not estimated.
    """
    s = checked_thresholds(thresholds)
    if len(fine) != len(coarse) or len(fine) == 0:
        raise EstimationError(f"fine and coarse need one entry per level, got {len(fine)} and {len(coarse)}")
    options = {"thresholds": s, "bandwidth": bandwidth, "bandwidth_rate": bandwidth_rate, "qoi": qoi}
    pairs = [(f, None if level == 0 else c) for level, (f, c) in enumerate(zip(fine, coarse))]
    terms = [cdf_level_term(f, c, level, **options) for level, (f, c) in enumerate(pairs)]
    ranges = {level: _missed_range(f, c, level, **options) for level, (f, c) in enumerate(pairs)}
    missed = {level: values for level, values in ranges.items() if values is not None}
    spread = _Spread()
    for level, (values, below) in enumerate(zip(fine, coarse)):
        spread.add(level, values, below, qoi)
    finest = level_bandwidth(len(fine) - 1, bandwidth=bandwidth, bandwidth_rate=bandwidth_rate)
    target = _checked_target(telescope(terms, tol=tol), s, bandwidth, bandwidth_rate, missed,
                             spread.value(np.arange(len(fine))), _is_exact(fine[-1], qoi, s, finest))
    return _cdf_estimate(target, s, bandwidth, bandwidth_rate, missed)


def mlmc_cdf(
    sampler: Sampler,
    *,
    thresholds: np.ndarray,
    tol: float,
    bandwidth: float,
    bandwidth_rate: float = 1.0,
    qoi: int = 0,
    **options: object,
) -> CdfEstimate:
    """Adaptive MLMC estimate of the CDF to a sup-norm RMS tolerance.

    Parameters
    ----------
    sampler : callable
        ``sampler(level, indices) -> (fine, coarse, cost)``.
    thresholds : ndarray, shape (m,)
        Strictly increasing ``s_j`` (the unit of ``Q``); cover the quantiles
        of interest with a spacing well below their error bars.
    tol : float
        Tolerance on ``max_j`` RMS error of ``F(s_j)`` (dimensionless, in (0, 1)).
    bandwidth, bandwidth_rate, qoi
        As in :func:`cdf_level_term`.
    **options
        Keyword arguments of :func:`~rough_uq.multilevel.targets.adaptive_mlmc`.

    Returns
    -------
    CdfEstimate

    Warns
    -----
    EstimationWarning
        Where the thresholds miss the samples of a level (module docstring):
        the run does not meet ``tol``, its ``stop_reason`` is
        ``"thresholds_miss_samples"``, whatever the driver stopped for; and
        where the finest bandwidth exceeds twice the spread of the values
        (module docstring): ``"bandwidth_too_wide"``, the bias not estimated.
    """
    s = checked_thresholds(thresholds)
    _check_bandwidth(bandwidth, bandwidth_rate)
    check_cdf_tol(tol)

    settings = {"thresholds": s, "bandwidth": bandwidth, "bandwidth_rate": bandwidth_rate, "qoi": qoi}
    # Per level, from the samples of its latest term: the driver's final estimate uses that term.
    ranges: dict[int, tuple[float, float] | None] = {}
    spread, exact = _Spread(), {}

    def term(fine: np.ndarray, coarse: np.ndarray | None, level: int) -> LevelTerm:
        ranges[level] = _missed_range(fine, coarse, level, **settings)
        spread.add(level, fine, coarse, qoi)
        exact[level] = _is_exact(fine, qoi, s, level_bandwidth(level, bandwidth=bandwidth,
                                                               bandwidth_rate=bandwidth_rate))
        return cdf_level_term(fine, coarse, level, **settings)

    def missed_ranges(target: TargetEstimate) -> dict[int, tuple[float, float]]:
        return {int(level): ranges[int(level)] for level in target.levels if ranges[int(level)] is not None}

    def check(target: TargetEstimate) -> TargetEstimate:
        # Before the driver's own warnings: a bias this check withdraws is not then called one of noisy terms.
        return _checked_target(target, s, bandwidth, bandwidth_rate, missed_ranges(target),
                               spread.value(target.levels), exact[int(target.levels[-1])])

    options = {"label": "cdf"} | options | {"checked_column": qoi, "check": check}
    target = adaptive_mlmc(sampler, term=term, tol=tol, **options)
    return _cdf_estimate(target, s, bandwidth, bandwidth_rate, missed_ranges(target))


@dataclass(frozen=True, eq=False)
class Quantiles:
    """Quantiles from a CDF estimate, with error bars.

    Attributes
    ----------
    probabilities : ndarray, shape (k,)
        ``p``, in (0, 1).
    values : ndarray, shape (k,)
        ``q_p``, the unit of ``Q``.
    lower, upper : ndarray, shape (k,)
        Where the band ``cdf +- rmse`` reaches ``p`` (module docstring);
        ``-inf``/``+inf`` where that is beyond the grid, and everywhere when
        the estimate has no error band (:attr:`CdfEstimate.has_error_band`:
        the thresholds miss a level's samples, or the bandwidth is too wide).
    """

    probabilities: np.ndarray
    values: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @property
    def half_width(self) -> np.ndarray:
        """``(upper - lower) / 2``: the error bar of ``values``, shape (k,)."""
        return (self.upper - self.lower) / 2.0


def _invert(cdf: np.ndarray, thresholds: np.ndarray, p: float) -> float:
    """``inf {s : cdf(s) >= p}`` of the piecewise-linear ``cdf``; +-inf when the grid does not reach ``p``."""
    j = int(np.searchsorted(cdf, p, side="left"))
    if j == len(cdf):
        return np.inf
    if j == 0:
        return thresholds[0] if cdf[0] == p else -np.inf
    weight = (p - cdf[j - 1]) / (cdf[j] - cdf[j - 1])
    return float(thresholds[j - 1] + weight * (thresholds[j] - thresholds[j - 1]))


def quantiles(estimate: CdfEstimate, *, probabilities: Sequence[float] | np.ndarray) -> Quantiles:
    """Quantiles ``q_p`` by inverting the monotone CDF estimate, with error bars.

    Parameters
    ----------
    estimate : CdfEstimate
    probabilities : float or sequence of float, shape (k,)
        ``p`` in (0, 1).

    Returns
    -------
    Quantiles

    Raises
    ------
    InvalidParameterError
        If ``probabilities`` is not a number or a non-empty 1-d sequence of
        distinct numbers strictly between 0 and 1 (strings such as ``"0.5"`` and booleans are
        refused, not converted).
    EstimationError
        If the estimated CDF does not cross some ``p`` inside the grid
        (extend the thresholds).
    """
    # Distinct and at least one, as --probabilities: [] gave empty quantiles, [0.5, 0.5] one quantile twice.
    allowed = "a number or a non-empty 1-d sequence of distinct numbers strictly between 0 and 1"
    p = np.atleast_1d(checked_real_array("probabilities", probabilities, allowed))
    if p.ndim != 1 or p.size == 0 or np.unique(p).size != p.size or not np.all((p > 0) & (p < 1)):
        raise InvalidParameterError("probabilities", probabilities, allowed)
    cdf, s = estimate.cdf, estimate.thresholds
    values = np.array([_invert(cdf, s, float(pk)) for pk in p])
    outside = ~np.isfinite(values)
    if np.any(outside):
        raise EstimationError(
            f"the thresholds [{s[0]:.6g}, {s[-1]:.6g}] do not bracket the quantiles of p = {p[outside].tolist()} "
            f"(F = {cdf[0]:.3g} .. {cdf[-1]:.3g} on the grid); extend the grid"
        )
    if estimate.has_error_band:
        band_high = np.clip(cdf + estimate.rmse, 0.0, 1.0)
        band_low = np.clip(cdf - estimate.rmse, 0.0, 1.0)
        lower = [_invert(band_high, s, float(pk)) for pk in p]
        upper = [_invert(band_low, s, float(pk)) for pk in p]
    else:  # no band: a variance not measured, or a bias known to be large and not estimated
        lower, upper = np.full(p.size, -np.inf), np.full(p.size, np.inf)
    return Quantiles(
        probabilities=readonly_array(p), values=readonly_array(values), lower=readonly_array(lower),
        upper=readonly_array(upper),
    )
