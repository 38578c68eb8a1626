"""MLMC rates: the rate models of a level hierarchy, the remaining bias and the coarsest useful level.

This module fits the rate models of SPEC section 5 to a screening table
(:class:`~rough_uq.multilevel.statistics.LevelStatistics`), turns them into
the bias an estimator leaves (:func:`remaining_bias`, :func:`estimated_bias`)
and picks the level a hierarchy should start on (:func:`choose_coarsest_level`).
It needs only numpy and the standard library and has no state.

Conventions
-----------
Levels ``l = 0, 1, 2, ...`` (mesh size ``h_l = h_0 2^-l``), the quantity of
interest ``Q_l``, the level difference ``Y_l = Q_l - Q_{l-1}`` (``Y_0 =
Q_0``), ``V_l = Var(Y_l)`` and the cost ``C_l`` are those of
:mod:`~rough_uq.multilevel.statistics`.
All rate models are written against the *relative* mesh size
``h_l / h_0 = 2^-l``, i.e. they are fitted by least squares on ``log2`` values
against the level index ``l`` (``log2(h_l/h_0) = -l``); the constants are the
model values at ``l = 0``. With ``n_qoi`` quantities of interest, every QoI
has its own ``alpha`` and ``beta``; the cost is shared (``gamma``).

Symbols (SPEC section 5):

``alpha``
    Bias rate: ``|E[Y_l]| ~ C_alpha 2^(-alpha l)``.
``beta``
    Variance rate: ``V_l ~ C_beta 2^(-beta l)``.
``gamma``
    Cost rate: ``C_l ~ C_gamma 2^(gamma l)``, ``C_l`` the mean cost of one
    level-``l`` sample (both solves on ``l >= 1``).

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
A level mean that is zero to rounding while ``Y_l`` varies (integer
differences that cancel, e.g. cluster counts: with 20 samples on each of
levels 0..2 the level-2 mean of a cluster count came out exactly 0) is below
its noise: it is fitted at ``STALL_SIGNIFICANCE`` (2) standard errors
``2 sqrt(V_l / N_l)``, the largest mean its samples do not rule out, and
anchors no window. A mean of 0 with ``V_l = 0`` too is left out (a column 0
in every sample of every level is exact, :func:`fit_rates`).

Remaining bias
--------------
The bias of an estimator whose finest level is ``L`` is
``E[Q] - E[Q_L] = sum_{l > L} E[Y_l]``. Under the ``alpha`` model this is the
geometric tail ``|E[Y_L]| / (2^alpha - 1)`` (Giles 2015, section 3.1); this
module calls that the *remaining bias* (:func:`remaining_bias`).

Which ``|E[Y_L]|`` goes into it (:func:`estimated_bias`, used by
:func:`~rough_uq.multilevel.allocation.plan` and by the MLMC driver alike):
the largest of the fitted model ``c_alpha 2^(-alpha L)``, the measured
``|mean(Y_L)|`` where level ``L`` was sampled, and the measured means of the
two levels below it scaled to level ``L``, ``|mean(Y_{L-1})| 2^-alpha`` and
``|mean(Y_{L-2})| 2^(-2 alpha)`` (levels ``>= 1`` only; Giles' rule). The model, a least-squares line through the
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

Two limits keep the tail honest where the hierarchy is pre-asymptotic
(:func:`tail_rate`). The tail is summed with ``alpha`` at most
:data:`BIAS_RATE_CAP` (2): a coarsest grid that truncates the surface's
spectrum makes the first difference the surface's own change, and a rate
fitted on it is no rate of the discretisation (quickstart surface, coarsest
grid 16: means -5.5, -0.23 on levels 1, 2 fit ``alpha = 4.6`` and put the
bias of 64^2 at 0.01 where finer grids (means +0.115, +0.080, +0.045) show
0.29). And where ``alpha`` is a line through two level means (the fit's
window, above, has two levels: nothing confirms it) or the two finest means
differ in sign (no window is anchored, every level is fitted), the rate is
at most the decay those two means confirm,
``log2(|E[Y_{L-1}]| / (|E[Y_L]| + 2 se_L))``
(floored at :data:`RATE_FLOOR`): a finest mean that happens to lie near 0, or
one whose sign differs from the level below, no longer makes a fast decay
(coarsest 32: means -0.23 and +0.115 with 10 samples on level 2 fitted
``alpha`` 1.2-2.3 and gave biases of 0.01-0.08 on 128^2 against about 0.19;
4 of 10 runs at tol 0.2 stopped there with errors of 2-2.6 times their RMSE;
``scripts/bias_coverage.py``).

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
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from rough_uq.errors import EstimationError, InvalidParameterError, checked_integer, is_real_number
from rough_uq.multilevel.statistics import LevelStatistics, checked_names, readonly_array

__all__ = [
    "BIAS_RATE_CAP",
    "DROP_MARGIN",
    "EXACT_RATE",
    "RATE_FLOOR",
    "RATIO_LOG2_TOLERANCE",
    "CoarsestLevel",
    "DroppedLevel",
    "Rates",
    "choose_coarsest_level",
    "confirmed_tail",
    "estimated_bias",
    "fit_rates",
    "giles_prediction",
    "refuse_constant_columns",
    "remaining_bias",
    "stalled_bias",
    "tail_rate",
]
# Also imported by the drivers' planning and the targets, not part of the API: RateLine (a fitted rate),
# rate_line, alpha_line, beta_line, gamma_line.

#: Smallest predicted saving (fraction of the MLMC cost) for which coarse levels are dropped.
DROP_MARGIN = 0.1

#: Largest ``|log2 r_l - log2 r_{l-1}|`` of successive mean ratios, beyond two standard errors, still "stable".
RATIO_LOG2_TOLERANCE = 0.5

#: Lower bound of fitted rates and fallback when a rate cannot be fitted (Giles' ``mlmc``); the floor of the
#: decay two finest level means confirm (:func:`tail_rate`).
RATE_FLOOR = 0.5

#: Largest ``alpha`` the remaining bias is extrapolated with (module docstring, "Remaining bias"): a faster
#: fitted decay comes from pre-asymptotic levels, and the discretisation errors of these QoIs decay no
#: faster than second order.
BIAS_RATE_CAP = 2.0

#: The rates ``alpha`` and ``beta`` of a column that is exact on the screened levels (every level difference 0
#: in every sample: :func:`fit_rates`), with constants 0: its models are 0 on every grid. A finite stand-in for
#: an infinite rate (``inf * 0`` on level 0 would be NaN); no fitted rate comes near it.
EXACT_RATE = 64.0


def _as_qoi_array(value: object) -> np.ndarray:
    return readonly_array(np.atleast_1d(np.asarray(value, dtype=float)))


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
    gamma_beyond : float or None
        The least rate of the cost beyond the finest of ``levels_gamma``
        (:meth:`cost_model`), which the problem knows and the screened levels
        need not show (their costs still carry fixed parts that finer grids
        outgrow); None: the fitted ``gamma`` there too.
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
    gamma_beyond: float | None = None

    def __post_init__(self) -> None:
        n_qoi = max(np.size(self.alpha), np.size(self.beta), np.size(self.c_alpha), np.size(self.c_beta))
        for name in ("alpha", "beta", "c_alpha", "c_beta", "alpha_se", "beta_se"):
            value = _as_qoi_array(getattr(self, name))
            if value.shape == (1,) and n_qoi > 1:
                value = readonly_array(np.repeat(value, n_qoi))
            if value.shape != (n_qoi,):
                raise InvalidParameterError(f"Rates.{name}", getattr(self, name), f"a scalar or {n_qoi} values")
            object.__setattr__(self, name, value)
        for name in ("gamma", "c_gamma", "gamma_se"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "gamma_beyond", checked_gamma_beyond("Rates.gamma_beyond", self.gamma_beyond))

    @property
    def n_qoi(self) -> int:
        """Number of quantities of interest."""
        return len(self.alpha)

    @property
    def gamma_extrapolated(self) -> float:
        """The rate of the cost beyond the levels with a measured cost: the larger of ``gamma`` and
        ``gamma_beyond`` (``gamma`` without the latter)."""
        return self.gamma if self.gamma_beyond is None else max(self.gamma, self.gamma_beyond)

    def cost_rate_at(self, level: int) -> float:
        """The cost rate of the model at ``level``: ``gamma`` up to the finest level of the fit, beyond it
        :attr:`gamma_extrapolated` (:meth:`cost_model`; e.g. the share of a sample's cost its fine solve takes,
        :func:`~rough_uq.multilevel.allocation.fine_cost_share`)."""
        return self.gamma_extrapolated if _level(level) > max(self.levels_gamma, default=level) else self.gamma

    def bias_model(self, level: int) -> np.ndarray:
        """Model ``|E[Y_l]|``, shape (n_qoi,), at level ``level`` (an integer >= 0).

        Raises
        ------
        InvalidParameterError
            If ``level`` is not an integer >= 0 (a string, a float, a boolean or an array included).
        """
        return self.c_alpha * 2.0 ** (-self.alpha * _level(level))

    def variance_model(self, level: int) -> np.ndarray:
        """Model ``V_l``, shape (n_qoi,), at level ``level`` (an integer >= 0).

        Raises
        ------
        InvalidParameterError
            If ``level`` is not an integer >= 0 (a string, a float, a boolean or an array included).
        """
        return self.c_beta * 2.0 ** (-self.beta * _level(level))

    def cost_model(self, level: int) -> float:
        """Model cost ``C_l`` of one level-``level`` sample (``level`` an integer >= 0).

        ``c_gamma 2^(gamma l)``; beyond the finest level of the fit (``levels_gamma``) the model goes on from
        its value there at the larger of ``gamma`` and ``gamma_beyond``.

        Raises
        ------
        InvalidParameterError
            If ``level`` is not an integer >= 0 (a string, a float, a boolean or an array included).
        """
        level = _level(level)
        top = max(self.levels_gamma, default=level)
        if self.gamma_beyond is None or level <= top:
            return self.c_gamma * 2.0 ** (self.gamma * level)
        return self.c_gamma * 2.0 ** (self.gamma * top + self.gamma_extrapolated * (level - top))


def checked_gamma_beyond(name: str, value: object) -> float | None:
    """``value`` (None or a float), or :class:`InvalidParameterError` naming ``name`` unless None or a finite
    real number >= 0 (:attr:`Rates.gamma_beyond`)."""
    if value is None:
        return None
    if not is_real_number(value) or not 0.0 <= float(value) < math.inf:
        raise InvalidParameterError(name, value, "None or a finite real number >= 0")
    return float(value)


def _level(level: object) -> int:
    """``level`` as an int, or :class:`InvalidParameterError` naming ``level`` unless an integer ``>= 0``.

    Levels are numbered ``0, 1, 2, ...`` from the coarsest grid (module
    docstring): neither a fractional nor a negative level names a grid of the
    hierarchy. A string, a boolean or an array is refused, not converted
    (``True`` would pass for level 1, an array would give one model value per
    entry).
    """
    return checked_integer("level", level, 0)


@dataclass(frozen=True, eq=False)
class RateLine:
    rate: float
    constant: float
    se: float
    levels: tuple[int, ...]


def rate_line(levels: np.ndarray, values: np.ndarray, rel_se: np.ndarray, sign: float) -> RateLine | None:
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
    return RateLine(rate=sign * slope, constant=2.0**intercept, se=se, levels=tuple(int(level) for level in levels))


def _asymptotic_window(levels: np.ndarray, means: np.ndarray, rel_se: np.ndarray) -> np.ndarray:
    """Indices of the levels the bias rate is fitted on (module docstring, "Fitting alpha").

    ``levels`` increasing, ``means`` the signed ``mean(Y_l)`` (0 for a mean zero to rounding, which no
    decaying pair includes: ``abs(0) < abs(0)`` is false), ``rel_se`` their standard errors relative to the
    magnitudes fitted.
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


#: A level mean at most this times its standard error is zero to rounding (:func:`_is_rounding_zero`).
ROUNDING_ZERO_MEAN = 1e-12


def _is_rounding_zero(mean: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Where a level mean is zero to rounding: at most :data:`ROUNDING_ZERO_MEAN` times its standard error.

    Integer differences (cluster counts) whose pooled mean is exactly 0 came out as 1.9e-17, whose logarithm
    fitted alpha = 57 and certified a bias of 1.8e-34; no sample resolves a mean that small. Such a mean has no
    sign: the fit takes it at its bound and anchors no window on it (:func:`alpha_line`), and the tail is held
    to the decay the two finest means confirm (:func:`confirmed_tail`). A mean of 0 with a standard error of 0
    (every difference 0) is zero too.
    """
    return np.abs(mean) <= ROUNDING_ZERO_MEAN * np.asarray(error)


def alpha_line(statistics: LevelStatistics, q: int, min_level: int) -> tuple[RateLine | None, str]:
    use = (statistics.levels >= min_level) & (statistics.n_samples >= 2)
    mean = np.abs(statistics.mean_diff[:, q])
    se = statistics.mean_diff_error[:, q]
    # A mean zero to rounding with a positive variance is fitted at its bound (module docstring, "Fitting
    # alpha"); left out, it left a screening of levels 0..2 one level to fit, and the screening was refused
    # after all its samples.
    is_zero = _is_rounding_zero(mean, se)
    magnitude = np.where(is_zero, STALL_SIGNIFICANCE * se, mean)  # the largest mean not ruled out
    usable = use & (magnitude > 0)
    rel_se = se[usable] / magnitude[usable]
    # A bounded mean has no sign: no asymptotic window is anchored on it.
    signed = np.where(is_zero, 0.0, statistics.mean_diff[:, q])[usable]
    window = _asymptotic_window(statistics.levels[usable], signed, rel_se)
    line = rate_line(statistics.levels[usable][window], magnitude[usable][window], rel_se[window], -1.0)
    zero = statistics.levels[use & ~(magnitude > 0)].tolist()
    return line, f"levels with E[Q_l - Q_l-1] = 0 and no variance (unusable): {zero}" if zero else ""


def beta_line(statistics: LevelStatistics, q: int, min_level: int) -> tuple[RateLine | None, str]:
    use = (statistics.levels >= min_level) & (statistics.n_samples >= 2)
    var = statistics.var_diff[:, q]
    usable = use & (var > 0)
    n = statistics.n_samples[usable]
    # Var(s^2)/sigma^4 = (kurtosis - (n-3)/(n-1))/n; the kurtosis is >= 1, the bracket > 0.
    rel_var = np.maximum(statistics.kurtosis[usable, q] - (n - 3) / (n - 1), 0.0) / n
    line = rate_line(statistics.levels[usable], var[usable], np.sqrt(rel_var), -1.0)
    zero = statistics.levels[use & (var == 0)].tolist()
    return line, f"levels with Var(Q_l - Q_l-1) = 0 (unusable): {zero}" if zero else ""


def refuse_constant_columns(
    statistics: LevelStatistics, names: Sequence[str] | None,
    advice: str = "sample finer levels or more samples, or change the load",
) -> None:
    """Raise :class:`~rough_uq.errors.EstimationError` where every column took one value in every sample.

    Far past full contact (or before any) the area is 100 % (0 %) in every sample: there is nothing to
    estimate, and more levels or samples would not change that. A constant column beside others that vary (a
    load curve through full contact) is fitted as exact (:func:`_exact_line`).

    A load so small that only the highest node touches on the sampled grids gives each level one value (one
    node's area, one cluster), but another on each grid: no variance to fit beta with. Finer grids or more
    samples may find a second node in contact (at a relative load of 3e-5 the grids of 64^2 and 128^2 did,
    where those up to 32^2 did not), a larger load does: ``advice`` says so, in the caller's terms.
    """
    columns, sampled = range(statistics.n_qoi), statistics.n_samples >= 2
    if not np.any(sampled) or np.any(statistics.var_fine[sampled] != 0):
        return
    constant = [q for q in columns if _is_constant(statistics, q)]
    which = ", ".join(names[q] if names is not None else f"QoI {q}" for q in columns)
    if len(constant) == statistics.n_qoi:
        raise EstimationError(
            f"{which} took one value in every sample of every level (at this load, e.g. full contact or none): "
            "there is nothing to estimate; change the load or the QoIs"
        )
    raise EstimationError(
        f"{which} took one value in every sample of each level, which only the grid changes (at this load, e.g. "
        f"a single node in contact on every grid sampled): no variance to fit; {advice}"
    )


def _is_constant(statistics: LevelStatistics, q: int) -> bool:
    """Whether column ``q`` had the same value in every sample (no variance, no level differences)."""
    values = np.concatenate([statistics.mean_fine[:, q], statistics.mean_coarse[statistics.levels > 0, q]])
    return bool(np.all(statistics.var_fine[:, q] == 0) and np.all(values == values[0]))


def _exact_line(statistics: LevelStatistics, q: int, min_level: int) -> RateLine | None:
    """Rate :data:`EXACT_RATE` with constant 0 for a column whose differences are 0 in every sample of every
    fitted level.

    Such a column (a contact area of 100 % at full contact, one cluster, a mean gap of 0) has no bias and no
    variance to fit: its models are 0 on every grid, so it asks for no level and no sample of its own. Two
    levels at least, each of two samples or more, must show it. None for any other column.
    """
    use = (statistics.levels >= min_level) & (statistics.n_samples >= 2)
    if np.count_nonzero(use) < 2:
        return None
    if np.any(statistics.mean_diff[use, q] != 0) or np.any(statistics.var_diff[use, q] != 0):
        return None
    return RateLine(rate=EXACT_RATE, constant=0.0, se=0.0, levels=tuple(statistics.levels[use].tolist()))


def gamma_line(statistics: LevelStatistics, min_level: int) -> tuple[RateLine | None, str]:
    use = statistics.levels >= min_level
    cost = statistics.mean_cost
    usable = use & (cost > 0)
    rel_se = np.sqrt(statistics.var_cost[usable] / statistics.n_samples[usable]) / cost[usable]
    line = rate_line(statistics.levels[usable], cost[usable], rel_se, 1.0)
    zero = statistics.levels[use & (cost <= 0)].tolist()
    return line, f"levels with zero cost (unusable): {zero}" if zero else ""


#: A level mean ``|E[Y_L]|`` counts as measured (not noise) beyond this many standard errors (:func:`stalled_bias`).
STALL_SIGNIFICANCE = 2.0


def stalled_bias(names: Sequence[str], rates: Rates, statistics: LevelStatistics | None = None) -> list[str]:
    """The QoIs whose fitted bias does not decay (``alpha`` not above 0), in words: ``clusters (alpha = -0.3)``.

    No finest level can be chosen for them from these rates. With the ``statistics`` the rates were fitted
    on, only those whose means ``Y_l`` on the two finest levels (both ``>= 1``) are measured, beyond
    :data:`STALL_SIGNIFICANCE` standard errors from 0: a level mean within its noise gives a fitted
    ``alpha`` of either sign, which says nothing of the decay, and the runs plan such a QoI at the floor
    rate and estimate its bias from their own samples. (A fitted -0.0 reads ``alpha = 0``.)
    """
    alpha = np.atleast_1d(rates.alpha)
    measured = np.ones(alpha.size, dtype=bool)
    if statistics is not None:
        for row in np.flatnonzero(statistics.levels >= 1)[-2:]:
            measured &= np.abs(statistics.mean_diff[row]) > STALL_SIGNIFICANCE * statistics.mean_diff_error[row]
    return [f"{name} (alpha = {a + 0.0:.2g})" for name, a, m in zip(names, alpha, measured) if not a > 0 and m]


def stalled_text(stalled: Sequence[str]) -> str:
    """The words every layer uses for :func:`stalled_bias`'s QoIs: ``the bias of clusters (alpha = -2.7) does
    not decrease from level to level on the screened grids``."""
    return f"the bias of {', '.join(stalled)} does not decrease from level to level on the screened grids"


def fit_rates(statistics: LevelStatistics, *, min_level: int = 1, names: Sequence[str] | None = None) -> Rates:
    """Fit ``alpha``, ``beta``, ``gamma`` and their constants by least squares.

    Ordinary least squares of ``log2 |E[Y_l]|``, ``log2 V_l`` and
    ``log2 C_l`` against the level index ``l`` (equivalently against
    ``log2(h_l/h_0) = -l``), over the levels ``l >= min_level``; for
    ``alpha``, over those of them whose means look asymptotic (module
    docstring, "Fitting alpha").

    Parameters
    ----------
    statistics : LevelStatistics
        Screening table (:func:`~rough_uq.multilevel.statistics.level_statistics`).
    min_level : int
        Coarsest level used (default 1). Level 0 is excluded by default
        because ``Y_0 = Q_0`` follows none of the models, and because a
        level-0 sample has no coarse solve, so its cost is off the ``gamma``
        model too.
    names : sequence of str, optional
        Names of the QoI columns, length ``n_qoi``: an error names the QoI
        (``for contact_area``); without them it gives its column index
        (``for QoI 0``).

    Returns
    -------
    Rates
        Rates, constants, standard errors and the levels used.

    Raises
    ------
    EstimationError
        If any rate has fewer than two usable levels. A level is unusable
        for ``alpha`` if ``E[Y_l] = 0`` and ``V_l = 0`` (a zero mean of a
        varying ``Y_l`` is fitted at its bound, module docstring, "Fitting
        alpha"), for ``beta`` if ``V_l = 0``, for
        both if it has fewer than two samples, and for ``gamma`` if its mean
        cost is 0 (a logarithm of 0 is never taken). A column with
        ``Y_l = 0`` in every sample of every fitted level (two at least) is
        no such failure: it is exact there, and gets ``alpha = beta =``
        :data:`EXACT_RATE` with constants 0. Also raised where every column
        took one value in every sample (nothing to estimate), or one value
        in every sample of each level (no variance on the levels sampled;
        :func:`refuse_constant_columns`).

    Notes
    -----
    The standard error of each rate is the larger of the residual-based OLS
    error (needs three or more levels) and the sampling error of the
    ``log2`` values propagated through the fit: ``se(E[Y_l]) = sqrt(V_l /
    N_l)``, ``Var(s^2)/sigma^4 = (kurtosis - (N-3)/(N-1))/N`` for ``V_l``
    and ``se(C_l) = sd(cost)/sqrt(N_l)``.
    """
    names = checked_names(names, statistics.n_qoi)
    refuse_constant_columns(statistics, names)
    alpha, beta = [], []
    for q in range(statistics.n_qoi):
        qoi = names[q] if names is not None else f"QoI {q}"
        exact = _exact_line(statistics, q, min_level)
        if exact is not None:
            alpha.append(exact)
            beta.append(exact)
            continue
        for name, fit, out in (("alpha", alpha_line, alpha), ("beta", beta_line, beta)):
            line, note = fit(statistics, q, min_level)
            if line is None:
                raise EstimationError(
                    f"cannot fit {name} for {qoi}: needs at least two usable levels >= {min_level} "
                    f"with two or more samples each; screened levels {statistics.levels.tolist()}"
                    + (f"; {note}" if note else "")
                )
            out.append(line)
    gamma, note = gamma_line(statistics, min_level)
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
    *, rates: Rates, level: int, mean_diff: np.ndarray | None = None, coarser: np.ndarray | None = None,
    mean_error: np.ndarray | None = None,
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
    mean_error : ndarray, shape (n_qoi,), optional
        Standard error of ``mean_diff``: where ``alpha`` was fitted on two
        levels only (``rates.levels_alpha``) or the two finest means differ
        in sign, the tail rate is then at most the decay those means confirm
        (:func:`tail_rate`).

    Returns
    -------
    ndarray, shape (n_qoi,)
        ``max(c_alpha 2^(-alpha L), |mean(Y_L)|, |mean(Y_{L-1})| 2^-a,
        |mean(Y_{L-2})| 2^(-2 a)) / (2^a - 1)`` over the terms given, with
        ``a`` the tail rate (:func:`tail_rate`), in the QoI's unit.

    Raises
    ------
    InvalidParameterError
        If ``level`` is not an integer >= 0.
    EstimationError
        If some ``alpha <= 0`` (:func:`remaining_bias`).
    """
    expected = rates.bias_model(level)
    alpha = tail_rate(rates.alpha)
    if mean_diff is not None or coarser is not None:
        unknown = np.full(rates.n_qoi, np.nan)
        finest = unknown if mean_diff is None else np.asarray(mean_diff, dtype=float)
        below = np.empty((0, rates.n_qoi)) if coarser is None else np.asarray(coarser, dtype=float)[-2:]
        if mean_error is not None and len(below):
            alpha, binding = confirmed_tail(rates, below[-1], finest, mean_error)
            # Where the bound binds, from those two means only: a level further down may be far from any decay
            # (a mean of -5.5 two levels below, scaled at the floor rate, put the bias at 6.6 where it is 0.2).
            below = np.where(binding, np.vstack([np.full((len(below) - 1, rates.n_qoi), np.nan), below[-1:]]), below)
        expected = np.fmax(expected, giles_prediction(np.vstack([below, finest]), alpha))
    return remaining_bias(expected, alpha)


def confirmed_tail(
    rates: Rates, coarser_mean: np.ndarray, finest_mean: np.ndarray, finest_error: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The rate the remaining bias sums its tail with, from the two finest level means ``E[Y_{L-1}]``,
    ``E[Y_L]`` (levels ``>= 1``) and the standard error of the finest, and where the bound on it binds.

    A line through two level means (``rates.levels_alpha``) is confirmed by nothing, nor a fit whose finest
    means change sign or have none (a mean zero to rounding, :func:`_is_rounding_zero`; no window is anchored
    there): their rate is held to the decay the two means confirm (:func:`tail_rate`). A finest mean of
    exactly 0 gave a bias of 0.235 where one of 1e-9 gave 0.389 (means 4, 1 and 0 on levels 1-3, standard
    error 0.23). Both arrays have shape (n_qoi,).
    """
    alpha = tail_rate(rates.alpha)
    levels = rates.levels_alpha
    two_point = np.array([len(fitted) == 2 for fitted in levels]) if len(levels) == rates.n_qoi else False
    no_sign = (np.sign(coarser_mean) * np.sign(finest_mean) <= 0) | _is_rounding_zero(finest_mean, finest_error)
    unconfirmed = two_point | no_sign
    bounded = tail_rate(rates.alpha, coarser_mean, finest_mean, finest_error)
    binding = unconfirmed & (bounded < alpha)
    return np.where(binding, bounded, alpha), binding


def tail_rate(
    alpha: np.ndarray, coarser_mean: np.ndarray | None = None, finest_mean: np.ndarray | None = None,
    finest_error: np.ndarray | None = None,
) -> np.ndarray:
    """The rate the remaining bias sums its tail with (module docstring, "Remaining bias").

    ``alpha`` at most :data:`BIAS_RATE_CAP`; given the two finest level means ``E[Y_{L-1}]``, ``E[Y_L]`` and the
    standard error of the finest, also at most the decay they confirm, ``log2(|E[Y_{L-1}]| / (|E[Y_L]| +
    STALL_SIGNIFICANCE se_L))``, and not below :data:`RATE_FLOOR`. A level mean not measured (NaN) leaves ``alpha``
    as it is; an infinite standard error (a level of one sample) confirms no decay: the floor.
    """
    rate = np.minimum(np.asarray(alpha, dtype=float), BIAS_RATE_CAP)
    if coarser_mean is None:
        return rate
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.abs(np.asarray(finest_mean, dtype=float)) + STALL_SIGNIFICANCE * np.asarray(finest_error, float)
        confirmed = np.log2(np.abs(np.asarray(coarser_mean, dtype=float)) / bound)
    confirmed = np.where(np.isnan(confirmed), np.inf, np.maximum(confirmed, RATE_FLOOR))
    return np.minimum(rate, confirmed)


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

