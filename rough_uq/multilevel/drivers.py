"""Monte Carlo and adaptive Multilevel Monte Carlo drivers (SPEC section 5).

Symbols follow SPEC section 5 and :mod:`rough_uq.multilevel.statistics`,
:mod:`~rough_uq.multilevel.rates` and :mod:`~rough_uq.multilevel.allocation`: ``Q_l`` the
quantity of interest on level ``l`` (mesh ``h_l = h_0 2^-l``),
``Y_l = Q_l - Q_{l-1}`` (``Y_0 = Q_0``), ``V_l = Var(Y_l)``, ``C_l`` the mean
cost of a level-``l`` sample, ``|E[Y_l]| ~ 2^(-alpha l)``,
``V_l ~ 2^(-beta l)``, ``C_l ~ 2^(gamma l)``; ``eps`` (``tol``) bounds the
root-mean-square error, ``MSE = sum_l V_l / N_l + bias^2 <= eps^2``, and
``theta`` is the share of ``eps^2`` given to the squared bias.

The sampler contract
--------------------
A level sampler is any callable ``sampler(level, sample_indices) ->
(fine, coarse, cost)``:

* ``sample_indices``: int64 array of shape ``(n,)``;
* ``fine``, ``coarse``: shape ``(n,)`` (one QoI) or ``(n, n_qoi)``, the
  QoIs ``Q_l`` and ``Q_{l-1}`` of the *same* random input (``coarse`` is 0
  on level 0);
* ``cost``: shape ``(n,)`` (a scalar is broadcast), the cost of each sample,
  seconds or model units, ``>= 0``.

The sampler derives all randomness from ``(level, index)`` (the pipeline uses
``SeedSequence(seed, spawn_key=(stage, level, index))``), so the engine never
touches a random generator and every sample can be recomputed. **The engine
asks for contiguous new indices per level**: the samples of level ``l`` are
indices ``0, 1, 2, ...`` in that order, each requested exactly once, batch
after batch. A sampler backed by a cache (the pipeline's study file) can
therefore serve the indices it already holds and compute only the rest; a
resumed run that gets the stored values and costs back makes the same
decisions and so replays the same sequence of requests.

Drivers are generators
----------------------
:func:`iter_mlmc` and :func:`iter_mc` yield small frozen events:
:class:`PlanUpdated` (levels and samples planned/done per level),
:class:`BatchDone` (one batch: its indices, values and costs, plus progress)
and finally :class:`Finished` (the :class:`EstimationResult`). The CLI
consumes them for progress bars and store writes; :func:`mlmc` and
:func:`mc` simply run them to the end.

One loop serves both (``_drive``): a run holds a hierarchy of levels (its
samples, planned ``N_l`` and spent cost) and, round after round, draws the
missing samples of every level in batches, re-plans ``N_l`` and, once the
samples are (nearly) complete, decides whether to stop. What differs is the
run's state object: the MLMC run (``_MlmcRun``) refits the rates, allocates
over the levels, checks the Richardson ratios and the bias and may add a
level; plain MC (``_McRun``) is the one-level hierarchy at its level, sampled
as ``Q_level`` alone, whose ``N`` follows ``Var(Q_level)`` and which stops once
its samples are drawn.

Adaptive MLMC
-------------
Giles (2015), algorithm 1, with the refinements of his ``mlmc`` code:

1. Start on levels ``0..min_finest_level`` with ``n_initial`` samples each
   (Giles' ``N0``: nothing is known about the levels yet), or from a
   screening table: the finest level and ``N_l`` of
   :func:`~rough_uq.multilevel.allocation.plan`, at least 2 per level (so that every level
   has a sample variance). With a screening, the screening's and the run's
   ``Y_l`` of a level both sampled are independent samples of the same
   level: ``V_l`` is their pooled variance, for the allocation and for the
   statistical error, and ``E[Y_l]`` their count-weighted mean, for the bias
   estimate and the fit of ``alpha`` (step 3; its standard error
   ``sqrt(V_l / (N_run + N_screening))`` for the Richardson ratio check). The
   estimate itself uses the run's samples only. Without a screening, every
   level keeps at least ``n_initial`` samples.
2. Draw the missing samples level by level, each level all it misses, in
   batches of at most ``batch_size``, so that the plans and the result do not
   depend on the batch size (where ``max_cost`` cannot pay what the current plan
   still misses, at the costs per sample measured so far, a round draws on
   each level the share of its missing samples that the budget left pays,
   so that a run the budget stops has its samples in about the planned
   ratio: with equal batches, one stopped by ``max_cost = 2`` had 351 / 350
   / 342 samples where its plan asked for 15008 / 2237 / 616, and a
   statistical error of 0.19 where the same cost in the plan's ratio gives
   about 0.11. A budget that pays every plan of the run changes nothing; one
   that an early plan overshoots draws that round differently, and so may
   end with other counts than the run without a budget); after each round
   re-estimate ``V_l``, ``C_l`` and refit the
   rates (unless given), and update ``N_l = ceil((1-theta)^-1 eps^-2
   sqrt(V_l/C_l) sum_k sqrt(V_k C_k))`` (maximum over QoIs; never below the
   samples already drawn). For ``l >= 2``, ``V_l`` is floored at
   ``V_{l-1} 2^-beta / 2`` so that a few lucky samples cannot starve a level,
   and a sampled ``V_l`` (``l >= 1``) at half the sampled ``V_{l+1}``, so
   that a level whose samples all missed a rare difference is not starved
   either (:data:`_FLOOR_FROM_ABOVE`).
3. Once every level has (nearly, within 1%) its planned samples, estimate
   the remaining bias ``max(c_alpha 2^(-alpha L), |E[Y_L]|, |E[Y_{L-1}]|
   2^-alpha, |E[Y_{L-2}]| 2^(-2 alpha)) / (2^alpha - 1)``
   (:func:`~rough_uq.multilevel.rates.estimated_bias`: the tail sum of
   the ``alpha`` model, whose least-squares line through all levels above the
   base is robust against a finest mean that happens to be near 0, and never
   below what the three finest difference levels predict; the tail is summed
   at ``alpha`` at most 2, and where ``alpha`` is a line through two means or
   the two finest means differ in sign, at most at the decay they confirm,
   from those two means only: module docstring of
   :mod:`~rough_uq.multilevel.rates`; the rule :func:`plan` uses too, beyond
   the screened levels at the rate of the finest screened pair, so a run and
   the screening's prediction agree). If it exceeds ``sqrt(theta) eps`` for
   some QoI, add level ``L+1`` with ``V_{L+1} = V_L 2^-beta``, ``C_{L+1} =
   C_L 2^gamma`` and go to 2. Each time the plan changes, a run whose bias so
   far, carried to ``max_level`` at that rate, is above twice its share warns
   before drawing the plan's samples (:meth:`_MlmcRun.check_reach`).
4. Stop when all planned samples are drawn and the bias test passes
   (``stop_reason = "tol_met"``), when the bias test fails on ``max_level``
   (``"max_level"``), or before a batch would exceed ``max_cost``
   (``"max_cost"``). ``tol_met`` is then ``sum_l V_l/N_l + bias^2 <= eps^2``
   for every QoI, with the sample variances and the remaining bias of the
   estimate, whose finest level is the finest one sampled (``max_cost`` may
   stop a run before it samples a level it added). The bias is estimated
   only once the run has sampled its levels ``base..max(min_finest_level,
   base + 2)``, the fewest its bias test ever uses (``is_bias_estimated``);
   a run that ``max_cost`` stops earlier reports the bias as 0, not
   estimated, and does not meet its tolerance, however small its
   statistical error (it plainly telescopes its sampled levels, without
   Richardson extrapolation).

Richardson extrapolation (``richardson=True``)
-----------------------------------------------
The estimate becomes ``sum_{l<L} mean(Y_l) + w mean(Y_L)``,
``w = 2^alpha / (2^alpha - 1)`` with the driver's ``alpha`` (see
:mod:`rough_uq.multilevel.richardson` for the formulas and the remaining-bias estimate).
While it is *active*, the allocation gives the finest level the variance
``w^2 V_L`` and step 3 tests the extrapolated estimate's remaining bias
(:func:`~rough_uq.multilevel.richardson.richardson_bias`) instead of the plain one. It is
active from the start if the screening's plan is extrapolated
(:func:`~rough_uq.multilevel.allocation.plan` with ``richardson``), else *pending* (plain
MLMC) until the run has ``RICHARDSON_MIN_LEVELS`` levels above its base
level. Each time the samples
are complete the run's own level means (standard errors from the pooled
``V_l``) are checked with :func:`~rough_uq.multilevel.richardson.ratio_instability`; a
failed check *refuses* the extrapolation for the rest of the run (a
:class:`RichardsonRefused` event, ``EstimationResult.richardson =
"refused"`` with the reason, an :class:`EstimationWarning`) and the run goes
on as plain MLMC, adding levels if the plain bias test asks for them. So
does a screening whose means fail the check (two levels ``>= 1`` suffice
there), and a run that ends while still pending.

Fitted rates are floored at 0.5 (as in Giles' code) so that extrapolation
stays sane, and when a rate cannot be fitted (fewer than two usable levels,
e.g. all ``E[Y_l] = 0``) the screening rates or 0.5 are used instead.

Beyond the mean
---------------
The same samples give the MLMC estimate of ``Var(Q)``:
``sum_l [s^2(Q_l) - s^2(Q_{l-1})]`` over the level-``l`` samples (both with
the ``n - 1`` normalisation, so each term is unbiased for
``Var(Q_l) - Var(Q_{l-1})``), with standard error
``sqrt(sum_l se_l^2)``, ``se_l`` the plug-in fourth-moment standard error of
:func:`~rough_uq.multilevel.statistics.level_statistics`. Its bias
``Var(Q) - Var(Q_L)`` is not controlled.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from rough_uq.errors import (
    PLANNED_COUNT_CAP,
    EstimationError,
    InvalidParameterError,
    PlanTooLargeError,
    checked_bool,
    checked_integer,
    checked_real_array,
    is_integer,
    is_real_number,
    warn_at_caller,
)
from rough_uq.multilevel.allocation import (
    Plan,
    _check_fraction,
    _check_tol,
    fine_cost_share,
    mc_run_cost,
    optimal_samples,
    plan,
)
from rough_uq.multilevel.rates import (
    RATE_FLOOR,
    STALL_SIGNIFICANCE,
    DroppedLevel,
    Rates,
    _fit_alpha,
    _fit_beta,
    _fit_gamma,
    _Line,
    confirmed_tail,
    estimated_bias,
    fit_rates,
    tail_rate,
)
from rough_uq.multilevel.richardson import RICHARDSON_MIN_LEVELS, ratio_instability, richardson_bias, richardson_weight
from rough_uq.multilevel.statistics import (
    KURTOSIS_LIMIT,
    EstimationWarning,
    LevelStatistics,
    _assemble,
    _checked_names,
    _level_moments,
    _Moments,
    _qoi_text,
    _readonly,
    _errors_summary,
    _names_summary,
    _summary,
    _units_summary,
    diagnose,
    kurtosis_text,
    kurtosis_threshold,
    level_statistics,
)

__all__ = [
    "BatchDone",
    "EstimationResult",
    "EstimationWarning",
    "Event",
    "Finished",
    "LevelStatistics",
    "Plan",
    "PlanUpdated",
    "Rates",
    "RichardsonRefused",
    "Sampler",
    "affordable_count",
    "check_finest_levels",
    "diagnose",
    "fit_rates",
    "iter_mc",
    "iter_mlmc",
    "level_statistics",
    "mc",
    "mlmc",
    "plan",
    "planning_rates",
    "refuse_large_plan",
    "refuse_large_start",
    "starting_forecast",
    "starting_plan",
    "starting_samples",
]

Sampler = Callable[[int, np.ndarray], tuple[object, object, object]]

_MAX_COUNT = float(PLANNED_COUNT_CAP)
#: Plans with more samples than this are refused, by the Python runs (:mod:`rough_uq.problem.runs`, unless
#: ``max_samples=`` moves the limit) and by ``roughuq`` (whatever ``--max-cost``).
MAX_PLANNED_SAMPLES = 10**7
MIN_LEVEL_SAMPLES = 2
"""Fewest samples on a level of an MLMC run started from a screening (one variance needs two)."""


# --------------------------------------------------------------------------
# Events and result
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PlanUpdated:
    """The plan changed: a new level, new ``N_l``, or the initial plan.

    Attributes
    ----------
    levels : ndarray of int, shape (n_levels,)
        Levels of the hierarchy.
    n_planned, n_done : ndarray of int, shape (n_levels,)
        Samples planned and drawn so far, per level.
    reason : str
        ``"initial"``, ``"variance"`` (re-estimated ``V_l``/``C_l``) or
        ``"new level"``.
    """

    levels: np.ndarray
    n_planned: np.ndarray
    n_done: np.ndarray
    reason: str


@dataclass(frozen=True, eq=False)
class RichardsonRefused:
    """Richardson extrapolation was refused; the run continues as plain MLMC.

    Attributes
    ----------
    levels : ndarray of int, shape (n_levels,)
        Levels of the hierarchy when it was refused.
    reason : str
        Which check failed (:func:`~rough_uq.multilevel.richardson.ratio_instability`).
    """

    levels: np.ndarray
    reason: str


@dataclass(frozen=True, eq=False)
class BatchDone:
    """One batch of samples was drawn.

    Attributes
    ----------
    level : int
        Level of the batch.
    indices : ndarray of int64, shape (n,)
        Sample indices (contiguous, continuing the previous batch of the level).
    fine, coarse : ndarray, shape (n, n_qoi)
        QoIs returned by the sampler (always 2-d here).
    cost : ndarray, shape (n,)
        Per-sample cost returned by the sampler.
    levels : ndarray of int, shape (n_levels,)
        Levels of the hierarchy.
    n_done, n_planned : ndarray of int, shape (n_levels,)
        Progress per level after this batch.
    """

    level: int
    indices: np.ndarray
    fine: np.ndarray
    coarse: np.ndarray
    cost: np.ndarray
    levels: np.ndarray
    n_done: np.ndarray
    n_planned: np.ndarray


@dataclass(frozen=True, eq=False)
class EstimationResult:
    """Outcome of an MC or MLMC run.

    Per-QoI fields are floats when the sampler returned 1-d arrays (one QoI)
    and arrays of shape (n_qoi,) otherwise (``rough_uq.mlmc`` / ``rough_uq.mc``
    on a contact problem always give arrays).

    Attributes
    ----------
    method : str
        ``"mlmc"`` or ``"mc"``.
    estimate : float or ndarray
        Estimate of ``E[Q]``.
    stat_error : float or ndarray
        Statistical (standard) error, ``sqrt(sum_l V_l / N_l)``, with ``V_l`` pooled from the run's samples and
        the screening's where the screening sampled level ``l`` (so for MC not always ``sqrt(variance / N)``).
    bias_estimate : float or ndarray
        Estimated bias: the remaining bias of the finest level (MLMC), the
        ``bias`` given to :func:`mc`, or 0 if unknown (``is_bias_estimated``).
    variance : float or ndarray
        Estimate of ``Var(Q)`` from the run's own samples: for MLMC the telescoped sum of the levels' terms
        (unbiased, but not bounded below: with few samples per level it can be negative), for MC the sample
        variance. :func:`rough_uq.variance` estimates ``Var(Q)`` to a tolerance.
    variance_error : float or ndarray
        Standard error of ``variance``.
    n_samples : ndarray of int, shape (n_levels,)
        ``N_l`` drawn.
    levels : ndarray of int, shape (n_levels,)
        Levels used (``[level]`` for MC).
    cost : float
        Total cost of the samples (sum of the sampler's costs).
    mc_cost : float
        Predicted cost of plain MC for the same tolerance (fine solves only),
        on the level the bias model needs for ``tol``
        (:func:`~rough_uq.multilevel.allocation.mc_run_cost`): for MLMC the
        run's own statistics and rates (:func:`rough_uq.mlmc` with a screening:
        the screening's, as ``roughuq mlmc`` reports it); for :func:`mc`, the
        cost its own estimates predict.
    statistics : LevelStatistics
        Per-level statistics (for MC: of ``Q`` alone, coarse values ignored).
    rates : Rates or None
        Rates the MLMC driver used last (None for MC): the given ``rates``, or
        fitted on the run's levels ``>= 1`` and floored at 0.5; a rate that could
        not be fitted keeps the screening value or the floor (empty ``levels_*``).
    tol : ndarray, shape (n_qoi,)
        Tolerance per QoI.
    theta : float
        Bias share of ``eps^2``.
    tol_met : bool
        ``stat_error^2 + bias_estimate^2 <= tol^2`` for every QoI, with an
        estimated bias (MC without a ``bias``: the statistical error alone,
        ``stat_error <= sqrt(1 - theta) tol``, the share it plans for);
        False for MC stopped by ``max_cost`` before it drew the samples it
        starts with (``n_initial``, 2 from a screening).
    stop_reason : str
        ``"tol_met"``, ``"max_cost"``, ``"max_level"`` (MLMC: the bias needs a
        level beyond ``max_level``) or ``"bias"`` (MC: the statistical target is
        met but the given bias is too large).
    is_bias_estimated : bool
        False for MC without a ``bias`` (``bias_estimate`` is then 0 and
        ``tol_met`` concerns the statistical error only, within its share), and for MLMC
        stopped by ``max_cost`` before the levels its bias test needs were
        sampled (module docstring, step 4: ``bias_estimate`` 0, ``tol_met``
        False).
    richardson : str
        ``"off"`` (not asked for), ``"applied"`` (``estimate``, ``stat_error``
        and ``bias_estimate`` are those of the extrapolated estimate) or
        ``"refused"`` (plain MLMC; ``richardson_reason`` says why).
    richardson_reason : str
        Why the extrapolation was refused ("" otherwise).
    dropped_levels : tuple of DroppedLevel
        MLMC: coarse levels left out (``levels`` then starts above 0) and why.
    qoi_names : tuple of str or None
        Names of the QoI columns of the per-QoI fields, in order (the run's
        ``qoi_names``; a contact problem's columns), None if not given.
    n_not_converged : int
        Samples of the run with a solve that did not converge, kept with the
        QoIs of their last iterate (:func:`rough_uq.mlmc` and :func:`rough_uq.mc`
        count them and warn; 0 from a level sampler, which has no solves).
    units : tuple of str or None
        Unit of each QoI column (:func:`rough_uq.mlmc` and :func:`rough_uq.mc`: the problem's
        ``column_units``, e.g. ``"percent"``), None if not known (a level sampler's run).
    """

    method: str
    estimate: float | np.ndarray
    stat_error: float | np.ndarray
    bias_estimate: float | np.ndarray
    variance: float | np.ndarray
    variance_error: float | np.ndarray
    n_samples: np.ndarray
    levels: np.ndarray
    cost: float
    mc_cost: float
    statistics: LevelStatistics = field(repr=False)  # long arrays: printing a result shows the estimate
    rates: Rates | None = field(repr=False)
    tol: np.ndarray
    theta: float
    tol_met: bool
    stop_reason: str
    is_bias_estimated: bool
    richardson: str = "off"
    richardson_reason: str = ""
    dropped_levels: tuple[DroppedLevel, ...] = ()
    qoi_names: tuple[str, ...] | None = None
    n_not_converged: int = 0
    units: tuple[str, ...] | None = None

    def __repr__(self) -> str:
        # One line for notebooks and print(), with the RMSE (a property the dataclass repr left out); the
        # per-QoI arrays of a load curve's columns (944 characters for 6) summarised as TargetEstimate's are.
        # Without an estimated bias the RMSE is unknown: the repr says so rather than show the statistical error
        # as the RMSE next to tol_met=True (mc on a given level).
        errors = _errors_summary(self.rmse, self.stat_error, self.bias_estimate, self.is_bias_estimated,
                                 bias_name="bias_estimate")
        return (
            f"EstimationResult(method={self.method!r}, qoi_names={_names_summary(self.qoi_names)}, "
            f"{_units_summary(self.units)}estimate={_summary(self.estimate)}, {errors}, "
            f"tol={_summary(self.tol)}, tol_met={self.tol_met}, "
            f"stop_reason={self.stop_reason!r}, levels={np.asarray(self.levels).tolist()}, "
            f"n_samples={np.asarray(self.n_samples).tolist()}, n_not_converged={self.n_not_converged})"
        )

    @property
    def rmse(self) -> float | np.ndarray:
        """Estimated root-mean-square error ``sqrt(stat_error^2 + bias_estimate^2)``."""
        return np.sqrt(np.square(self.stat_error) + np.square(self.bias_estimate))

    @property
    def finest_level(self) -> int:
        """Finest level used."""
        return int(self.levels[-1])


@dataclass(frozen=True, eq=False)
class Finished:
    """The run ended; ``result`` is its :class:`EstimationResult`."""

    result: EstimationResult


Event = PlanUpdated | BatchDone | RichardsonRefused | Finished


# --------------------------------------------------------------------------
# Sample storage and sampler calls
# --------------------------------------------------------------------------


class _LevelSamples:
    """All samples of one level, with their statistics cached until the next batch."""

    def __init__(self, level: int) -> None:
        self.level = level
        self.n = 0
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._moments: _Moments | None = None

    def add(self, fine: np.ndarray, coarse: np.ndarray, cost: np.ndarray) -> None:
        self._chunks.append((fine, coarse, cost))
        self.n += len(cost)
        self._moments = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if len(self._chunks) > 1:
            # Merge once so that later concatenations do not redo the work.
            self._chunks = [tuple(np.concatenate(part) for part in zip(*self._chunks))]
        return self._chunks[0]

    def moments(self) -> _Moments:
        if self._moments is None:
            self._moments = _level_moments(*self.arrays())
        return self._moments


def _qoi_array(values: object, *, name: str, level: int, n: int) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2 or array.shape[0] != n:
        raise EstimationError(
            f"sampler returned {name} of shape {np.shape(values)} for {n} samples on level {level}; "
            "expected (n,) or (n, n_qoi)"
        )
    bad = ~np.all(np.isfinite(array), axis=1)
    if np.any(bad):
        rows = np.flatnonzero(bad)[:10].tolist()
        raise EstimationError(f"sampler returned non-finite {name} values on level {level} (batch rows {rows})")
    return array


@dataclass(frozen=True, eq=False)
class _Batch:
    """One validated sampler answer; ``is_scalar`` records a 1-d (single QoI) return."""

    indices: np.ndarray
    fine: np.ndarray
    coarse: np.ndarray
    cost: np.ndarray
    is_scalar: bool


def _call_sampler(sampler: Sampler, level: int, start: int, n: int) -> _Batch:
    indices = np.arange(start, start + n, dtype=np.int64)
    returned = sampler(level, indices.copy())
    try:
        fine, coarse, cost = returned
    except (TypeError, ValueError) as error:
        raise EstimationError("a sampler must return a tuple (fine, coarse, cost)") from error
    is_scalar = np.ndim(fine) == 1
    fine = _qoi_array(fine, name="fine", level=level, n=n)
    coarse = _qoi_array(coarse, name="coarse", level=level, n=n)
    if coarse.shape != fine.shape:
        raise EstimationError(f"sampler returned fine {fine.shape} and coarse {coarse.shape} on level {level}")
    if level == 0 and np.any(coarse != 0):
        raise EstimationError("sampler returned nonzero coarse values on level 0 (there is no coarser level)")
    try:
        cost = np.array(np.broadcast_to(np.asarray(cost, dtype=float), (n,)))
    except ValueError as error:
        raise EstimationError(f"sampler returned cost of shape {np.shape(cost)} for {n} samples") from error
    if not np.all(np.isfinite(cost)) or np.any(cost < 0):
        raise EstimationError(f"sampler returned a negative or non-finite cost on level {level}")
    return _Batch(indices=indices, fine=fine, coarse=coarse, cost=cost, is_scalar=is_scalar)


def _check_optional_positive(name: str, value: object) -> float | None:
    """A limit: a number > 0, or None for none (``math.inf`` means none too)."""
    if value is None:
        return None
    if not (is_real_number(value) and value > 0):
        raise InvalidParameterError(name, value, "a number > 0, or None for no limit")
    return None if value == math.inf else float(value)


def _check_positive(name: str, value: object) -> float:
    if not (is_real_number(value) and value > 0):
        raise InvalidParameterError(name, value, "a number > 0")
    return float(value)


def _shape_out(values: np.ndarray, is_scalar: bool) -> float | np.ndarray:
    return float(values[0]) if is_scalar else _readonly(values)


# --------------------------------------------------------------------------
# Rates and allocation of a run
# --------------------------------------------------------------------------


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


def planning_rates(screening: LevelStatistics) -> Rates:
    """The rates an MLMC run started from ``screening`` plans with: fitted on levels >= 1, floored at RATE_FLOOR.

    The fits of :func:`~rough_uq.multilevel.rates.fit_rates` with every rate
    raised to :data:`RATE_FLOOR` (0.5, as in Giles' code; the constants stay
    those of the fits), and the floor where a rate cannot be fitted. A
    fitted ``alpha`` near 0 (level means at the noise of the screening)
    would make the tail sum ``|E[Y_L]| / (2^alpha - 1)`` of the bias many
    times the level means themselves. Forecasts and the plain MC level
    chosen from a screening plan with these rates, so that they predict
    what the run does.
    """
    return _lenient_rates(screening, None)


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
        [_fit_alpha(means, q, min_level)[0] for q in qois], base.alpha, base.c_alpha, base.alpha_se, base.levels_alpha
    )
    beta = _lenient_fit(
        [_fit_beta(statistics, q, min_level)[0] for q in qois], base.beta, base.c_beta, base.beta_se, base.levels_beta
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
    )


@dataclass(frozen=True, eq=False)
class _QoiRates:
    """A per-QoI rate model: rates, constants and standard errors of shape (n_qoi,), and the levels fitted."""

    rate: np.ndarray
    constant: np.ndarray
    se: np.ndarray
    levels: tuple[tuple[int, ...], ...]


def _lenient_fit(
    lines: list[_Line | None],
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


def _lenient_gamma(statistics: LevelStatistics, base: Rates, min_level: int, *, is_anchored: bool) -> _Line:
    """``gamma`` fitted (floored), else the fallback's; ``is_anchored``: put a fallback's ``c_gamma`` on the data."""
    line, _ = _fit_gamma(statistics, min_level)
    if line is not None:
        return _Line(rate=max(line.rate, RATE_FLOOR), constant=line.constant, se=line.se, levels=line.levels)
    c_gamma = base.c_gamma
    known = np.flatnonzero(statistics.mean_cost > 0)
    if is_anchored and known.size:
        # Anchor the cost model at the finest level with a measured cost, so that
        # extrapolated costs stay on the scale of the measured ones.
        top = known[-1]
        c_gamma = statistics.mean_cost[top] * 2.0 ** (-base.gamma * statistics.levels[top])
    return _Line(rate=base.gamma, constant=c_gamma, se=base.gamma_se, levels=base.levels_gamma)


def _fill_costs(mean_cost: np.ndarray, has_data: np.ndarray, gamma: float) -> np.ndarray:
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


def _planning_variances(var_diff: np.ndarray, has_data: np.ndarray, beta: np.ndarray, base: int = 0) -> np.ndarray:
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


# --------------------------------------------------------------------------
# The hierarchy: samples, plan and spent cost of a run
# --------------------------------------------------------------------------


class _Hierarchy:
    """Mutable state of one run: the samples of levels ``0..L``, the plan, the spent cost.

    ``base`` is the level the telescoping sum starts on (sampled as ``Q_base``;
    levels below it get no samples); ``floor`` is the fewest samples any level
    from ``base`` on gets; ``prior_var``, ``prior_mean`` and ``prior_n``
    (keyed by level) are the screening's ``V_l``, ``E[Y_l]`` and sample
    counts, pooled with the run's samples in :meth:`variances` (allocation and
    statistical error) and :meth:`bias_means` (bias estimate and rate
    ``alpha``; module docstring). Events report the levels from
    ``reported_from`` on (MC: its one level; MLMC: all, from 0).
    """

    def __init__(
        self, n_levels: int, floor: int, prior: LevelStatistics | None = None, base: int = 0, reported_from: int = 0
    ) -> None:
        self.samples = [_LevelSamples(level) for level in range(n_levels)]
        self.base = base
        self.targets = [floor if level >= base else 0 for level in range(n_levels)]
        self.floor = floor
        self.spent = 0.0
        self.reported_from = reported_from
        self.prior_var: dict[int, np.ndarray] = {}
        self.prior_mean: dict[int, np.ndarray] = {}
        self.prior_n: dict[int, int] = {}
        if prior is not None:
            for row, level in enumerate(prior.levels):
                if prior.n_samples[row] >= 2 and level >= base:
                    # The base level is sampled as Q_base: its prior is the screening's Q, not Y.
                    is_base = level == base
                    self.prior_var[int(level)] = prior.var_fine[row] if is_base else prior.var_diff[row]
                    self.prior_mean[int(level)] = prior.mean_fine[row] if is_base else prior.mean_diff[row]
                    self.prior_n[int(level)] = int(prior.n_samples[row])

    def add_level(self) -> None:
        self.samples.append(_LevelSamples(self.n_levels))
        self.targets.append(0)

    def variances(self, level: int, run_var: np.ndarray, n_run: int) -> np.ndarray:
        """``V_level``: the run's sample variance, pooled with the screening's where it has the level."""
        if level not in self.prior_var:
            return run_var
        return _pooled_variance(run_var, n_run, self.prior_var[level], self.prior_n[level])

    def bias_means(self, n_qoi: int) -> tuple[np.ndarray, np.ndarray]:
        """Pooled ``E[Y_l]`` of levels ``0..L`` and their standard errors, shapes (n_levels, n_qoi).

        Where the screening sampled a level, its samples and the run's are
        independent draws of the same ``Y_l``: the mean is their
        count-weighted mean, its error ``sqrt(V_l / (N_run + N_screening))``
        with the pooled ``V_l``. Elsewhere the run's own (zeros, error inf,
        on a level without samples).
        """
        means = np.zeros((self.n_levels, n_qoi))
        errors = np.full((self.n_levels, n_qoi), np.inf)
        for s in self.samples:
            n_prior = self.prior_n.get(s.level, 0)
            n_total = s.n + n_prior
            if n_total == 0:
                continue
            run_mean = s.moments().mean_diff if s.n else np.zeros(n_qoi)
            means[s.level] = (s.n * run_mean + n_prior * self.prior_mean.get(s.level, 0.0)) / n_total
            if s.n >= 2 or n_prior:
                run_var = s.moments().var_diff if s.n else np.zeros(n_qoi)
                errors[s.level] = np.sqrt(self.variances(s.level, run_var, s.n) / n_total)
        return means, errors

    def bias_statistics(self, statistics: LevelStatistics) -> LevelStatistics:
        """``statistics`` (the run's) with ``mean_diff``, ``var_diff`` and ``n_samples`` pooled, for ``alpha``."""
        if not self.prior_n:
            return statistics
        n_qoi = statistics.n_qoi
        means, _ = self.bias_means(n_qoi)
        var_diff = np.array(statistics.var_diff)
        n_samples = np.array(statistics.n_samples)
        for row, level in enumerate(statistics.levels):
            level = int(level)
            var_diff[row] = self.variances(level, statistics.var_diff[row], int(statistics.n_samples[row]))
            n_samples[row] += self.prior_n.get(level, 0)
        return dataclasses.replace(
            statistics,
            mean_diff=_readonly(means[statistics.levels]),
            var_diff=_readonly(var_diff),
            n_samples=_readonly(n_samples),
        )

    def planning_inputs(self, n_qoi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pooled ``V_l`` (shape (n_levels, n_qoi)), which levels have one, and mean costs ``C_l`` (0 if unsampled)."""
        has_data = np.array([self.has_variance(s.level) for s in self.samples])
        var_diff = np.zeros((self.n_levels, n_qoi))
        mean_cost = np.zeros(self.n_levels)
        for s in self.samples:
            run_var = s.moments().var_diff if s.n > 0 else np.zeros(n_qoi)
            if has_data[s.level]:
                var_diff[s.level] = self.variances(s.level, run_var, s.n)
            if s.n > 0:
                mean_cost[s.level] = s.moments().mean_cost
        return var_diff, has_data, mean_cost

    def has_variance(self, level: int) -> bool:
        return level >= self.base and (self.samples[level].n >= 2 or level in self.prior_var)

    @property
    def n_levels(self) -> int:
        return len(self.samples)

    def levels(self) -> np.ndarray:
        return _readonly(np.arange(self.reported_from, self.n_levels))

    def n_done(self) -> np.ndarray:
        return _readonly(np.array([s.n for s in self.samples[self.reported_from :]], dtype=np.int64))

    def n_planned(self) -> np.ndarray:
        return _readonly(np.array(self.targets[self.reported_from :], dtype=np.int64))

    def plan_event(self, reason: str) -> PlanUpdated:
        return PlanUpdated(levels=self.levels(), n_planned=self.n_planned(), n_done=self.n_done(), reason=reason)

    def pending(self) -> list[_LevelSamples]:
        """Levels with fewer samples than planned, coarsest first."""
        return [s for s in self.samples if s.n < self.targets[s.level]]

    def is_nearly_complete(self) -> bool:
        """Every level within 1 % of its planned samples (Giles' test before the bias check)."""
        return not any(self.targets[s.level] - s.n > 0.01 * s.n for s in self.samples)

    def is_complete(self) -> bool:
        return all(s.n >= self.targets[s.level] for s in self.samples)

    def sampled(self) -> list[_LevelSamples]:
        return [s for s in self.samples if s.n > 0]

    def statistics(self) -> LevelStatistics:
        sampled = self.sampled()
        return _assemble([s.level for s in sampled], [s.moments() for s in sampled], base_level=self.base)


def _per_sample_cost(hierarchy: _Hierarchy, level: int, gamma: float) -> float:
    """Predicted cost of one sample on ``level`` (0 when nothing is known yet)."""
    known = [s for s in hierarchy.samples if s.n > 0 and s.moments().mean_cost > 0]
    if not known:
        return 0.0
    nearest = min(known, key=lambda s: abs(s.level - level))
    return nearest.moments().mean_cost * 2.0 ** (gamma * (level - nearest.level))


def affordable_count(budget_left: float, unit: float, wanted: int) -> int:
    """``min(wanted, floor(budget_left / unit))``, at least 0, for any finite budget.

    A budget as large as ``1e308`` over a small ``unit`` is an infinite
    count in floating point, which ``math.floor`` cannot make an integer;
    such a budget affords ``wanted``.
    """
    count = budget_left / unit
    return wanted if count >= wanted else max(math.floor(count), 0)


def _batch_size(hierarchy: _Hierarchy, level: int, wanted: int, max_cost: float | None, gamma: float) -> int:
    """Samples to draw now on ``level``: ``wanted`` unless ``max_cost`` forbids (then maybe 0)."""
    if max_cost is None:
        return wanted
    unit = _per_sample_cost(hierarchy, level, gamma)
    if unit <= 0:
        return wanted
    n = affordable_count(max_cost - hierarchy.spent, unit, wanted)
    # A level with a single sample has no variance; do not start one that cannot get two.
    return n if hierarchy.samples[level].n + n >= 2 else 0


# --------------------------------------------------------------------------
# The driver loop, shared by MC and MLMC
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Options:
    """The checked arguments every run takes (:func:`iter_mlmc`, :func:`iter_mc`).

    ``tol`` has shape (n_qoi,), or (1,) while the number of QoIs is unknown;
    ``qoi_names`` is checked against the number of QoIs once it is known.
    """

    tol: np.ndarray
    theta: float
    n_initial: int
    screening: LevelStatistics | None
    kurtosis_limit: float
    qoi_names: tuple[str, ...] | None


class _Run:
    """What MC and MLMC runs share: the hierarchy, the tolerance, the QoI count, the stop reason.

    :func:`_drive` runs the loop; a subclass decides the plan (:meth:`replan`),
    what happens once a round of samples is (nearly) complete
    (:meth:`after_round`) and the result (:meth:`finish`). MC is the
    one-level hierarchy at its level.
    """

    def __init__(self, hierarchy: _Hierarchy, options: _Options) -> None:
        self.hierarchy = hierarchy
        self.options = options
        self.tol = options.tol
        self.n_qoi: int | None = None
        self.is_scalar = False
        self.stop_reason = ""

    @property
    def cost_rate(self) -> float:
        """``gamma`` for predicting the cost of a level from the nearest sampled one.

        Any value serves a run that samples one level only (``2^(gamma 0) = 1``).
        """
        return RATE_FLOOR

    def accept(self, batch: _Batch, level: int) -> None:
        """Check a batch's number of QoIs; the first batch fixes it."""
        if self.n_qoi is None:
            self.n_qoi, self.is_scalar = batch.fine.shape[1], batch.is_scalar
            self.tol = _check_tol(self.tol, self.n_qoi)
            _check_qoi_names(self.options.qoi_names, self.n_qoi)
            self.on_qoi_count(self.n_qoi)
        elif batch.fine.shape[1] != self.n_qoi:
            raise EstimationError(f"sampler returned {batch.fine.shape[1]} QoIs on level {level}, earlier {self.n_qoi}")

    def on_qoi_count(self, n_qoi: int) -> None:
        """Check what depends on the number of QoIs, once it is known."""

    def start(self) -> Iterator[Event]:
        """Events right after the initial plan."""
        return iter(())

    def check_reach(self) -> None:
        """Warn of a tolerance the run cannot meet, before the new plan's samples are drawn (MLMC only)."""

    def replan(self) -> None:
        raise NotImplementedError

    def after_round(self) -> Iterator[Event]:
        raise NotImplementedError

    def finish(self) -> Iterator[Event]:
        raise NotImplementedError


def checked_batch_cap(batch_size: int | None) -> float:
    """The most samples one sampler call draws: ``batch_size`` (checked by the caller), ``inf`` for None or for a
    size beyond any plan (``10**400`` has no float, and no plan asks for more than :data:`PLANNED_COUNT_CAP`)."""
    return math.inf if batch_size is None or batch_size > _MAX_COUNT else float(batch_size)


def round_counts(missing: Sequence[int], batch_cap: float, share: float | None) -> list[float]:
    """Per level, the most samples one pass draws, for levels still ``missing`` that many samples.

    ``share`` None (no budget, or one that pays what the plan misses): ``batch_cap`` each. Otherwise ``share``
    is the fraction of the missing samples' predicted cost that the budget left pays, and every level draws that
    fraction of its missing samples (at least one), scaled down together where the level missing most would
    draw more than ``batch_cap``: a run the budget stops has then drawn its levels in about the ratio of its
    plan, not in equal batches (or level after level) that leave the finer levels short.
    """
    largest = max(missing, default=0)
    if share is None or largest <= 0:
        return [batch_cap] * len(missing)
    scale = min(share, batch_cap / largest)
    return [max(1, math.ceil(scale * count)) for count in missing]


def budget_share(missing: Sequence[int], unit_costs: Sequence[float], budget_left: float) -> float | None:
    """The fraction of the missing samples' predicted cost that ``budget_left`` pays, or None where it pays all
    of it, or where some level's cost is not known yet (then a run draws as without a budget)."""
    if any(not unit > 0 for unit in unit_costs):
        return None
    needed = sum(count * unit for count, unit in zip(missing, unit_costs))
    return None if needed <= budget_left else max(budget_left, 0.0) / needed


def _round_share(run: _Run, pending: Sequence[_LevelSamples], missing: Sequence[int],
                 max_cost: float | None) -> float | None:
    """:func:`budget_share` of a round of the mean driver (None without ``max_cost``)."""
    if max_cost is None:
        return None
    hierarchy = run.hierarchy
    units = [_per_sample_cost(hierarchy, s.level, run.cost_rate) for s in pending]
    return budget_share(missing, units, max_cost - hierarchy.spent)


def _draw(
    run: _Run, sampler: Sampler, samples: _LevelSamples, batch_cap: float, max_cost: float | None
) -> tuple[list[_Batch], bool]:
    """Draw and store the next samples of one level; the batches, and whether ``max_cost`` stops the run.

    The run stops when the budget affords no sample, or when it cannot pay
    the rest of a batch whose cost a probe had to tell first (:data:`_PROBE`).
    """
    hierarchy = run.hierarchy
    level = samples.level
    wanted = int(min(hierarchy.targets[level] - samples.n, batch_cap))
    batches = []
    is_probed = max_cost is not None and wanted > _PROBE and _per_sample_cost(hierarchy, level, run.cost_rate) <= 0
    if is_probed:
        batches.append(_draw_batch(run, sampler, samples, _PROBE))
        wanted -= _PROBE
    n = _batch_size(hierarchy, level, wanted, max_cost, run.cost_rate)
    if n:
        batches.append(_draw_batch(run, sampler, samples, n))
    is_over_budget = n < wanted if is_probed else n == 0
    return batches, is_over_budget


#: Samples drawn first, alone, where a run with a budget knows no cost yet (its first batch): a budget below
#: the cost of the first batch (``n_initial`` samples) paid all of it before, e.g. 1300 times
#: ``--max-cost 1e-5`` for an MC run on one level; now the run stops once the probe shows the rest unaffordable.
_PROBE = 2


def _draw_batch(run: _Run, sampler: Sampler, samples: _LevelSamples, n: int) -> _Batch:
    """Draw ``n`` samples of ``samples``' level and store them."""
    hierarchy = run.hierarchy
    batch = _call_sampler(sampler, samples.level, samples.n, n)
    run.accept(batch, samples.level)
    # The base level is sampled as Q_base: its coarse values are not part of the sum.
    coarse = np.zeros_like(batch.fine) if samples.level == hierarchy.base else batch.coarse
    samples.add(batch.fine, coarse, batch.cost)
    hierarchy.spent += float(np.sum(batch.cost))
    return batch


def _batch_event(hierarchy: _Hierarchy, level: int, batch: _Batch) -> BatchDone:
    return BatchDone(
        level=level,
        indices=_readonly(batch.indices),
        fine=_readonly(batch.fine),
        coarse=_readonly(batch.coarse),
        cost=_readonly(batch.cost),
        levels=hierarchy.levels(),
        n_done=hierarchy.n_done(),
        n_planned=hierarchy.n_planned(),
    )


def _drive(
    make_run: Callable[[], _Run], sampler: Sampler, *, batch_cap: float, max_cost: float | None
) -> Iterator[Event]:
    """The run's events: rounds of batches, each followed by a new plan, until a stop reason is set.

    ``make_run`` is called on the first event, so that errors in the run's
    set-up surface where the events are consumed. Warnings of
    :meth:`_Run.finish` name the consumer's line (:func:`~rough_uq.errors.warn_at_caller`).
    """
    run = make_run()
    hierarchy = run.hierarchy
    yield hierarchy.plan_event("initial")
    yield from run.start()
    while not run.stop_reason:
        pending = hierarchy.pending()
        missing = [hierarchy.targets[samples.level] - samples.n for samples in pending]
        share = _round_share(run, pending, missing, max_cost)
        counts = round_counts(missing, batch_cap, share)
        for samples, count in zip(pending, counts):
            is_over_budget = False
            while not is_over_budget:
                # A level needs two samples for a variance (_batch_size refuses to start it with fewer).
                batches, is_over_budget = _draw(run, sampler, samples, max(count, 2 - samples.n), max_cost)
                for batch in batches:
                    yield _batch_event(hierarchy, samples.level, batch)
                # Without a budget that cuts the round, a level gets all it misses before the next plan, in
                # batches of batch_size: the plans, and so the result, do not depend on the batch size.
                if share is not None or samples.n >= hierarchy.targets[samples.level]:
                    break
            if is_over_budget:
                run.stop_reason = "max_cost"
                break
        if run.stop_reason:
            break
        if pending:
            before = list(hierarchy.targets)
            run.replan()
            if hierarchy.targets != before:
                yield hierarchy.plan_event("variance")
                run.check_reach()  # after the plan's event: a consumer that refuses the plan never draws it
            if not hierarchy.is_nearly_complete():
                continue
        yield from run.after_round()
    yield from run.finish()


def _per_qoi(names: Sequence[str], values: np.ndarray, columns: np.ndarray) -> str:
    """``values`` of ``columns`` in a message, ``name=value`` with three significant digits."""
    return ", ".join(f"{names[column]}={float(values[column]):.3g}" for column in columns)


def _check_qoi_names(qoi_names: object, n_qoi: int | None) -> tuple[str, ...] | None:
    """``qoi_names`` as a tuple of ``n_qoi`` strings (any number while ``n_qoi`` is None), or None."""
    names = _checked_names(qoi_names, n_qoi, argument="qoi_names")
    return None if names is None else tuple(names)


def _warn_zero_cost(statistics: LevelStatistics) -> None:
    if np.any(statistics.mean_cost <= 0):
        warn_at_caller(
            f"the sampler reported zero cost on levels {statistics.levels[statistics.mean_cost <= 0].tolist()}; "
            "the sample allocation uses costs extrapolated with the cost rate instead",
            EstimationWarning,
        )


# --------------------------------------------------------------------------
# Adaptive MLMC
# --------------------------------------------------------------------------


def iter_mlmc(
    sampler: Sampler,
    *,
    tol: float | np.ndarray,
    theta: float = 0.5,
    n_initial: int = 10,
    min_finest_level: int = 2,
    max_level: int = 16,
    max_cost: float | None = None,
    batch_size: int | None = 1000,
    screening: LevelStatistics | None = None,
    rates: Rates | None = None,
    kurtosis_limit: float = KURTOSIS_LIMIT,
    richardson: bool = False,
    coarsest_level: int | None = 0,
    qoi_names: Sequence[str] | None = None,
) -> Iterator[Event]:
    """Adaptive MLMC to a tolerance, as a generator of events.

    Parameters
    ----------
    sampler : callable
        ``sampler(level, sample_indices) -> (fine, coarse, cost)`` (module
        docstring). Indices are requested contiguously from 0 per level.
    tol : float or ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error, one for all QoIs or one each.
    theta : float
        Bias share of ``eps^2`` (default 1/2).
    n_initial : int
        Without a screening: samples drawn on every level before its variance
        is trusted (>= 2; Giles' ``N0``). With a screening, levels need only
        ``MIN_LEVEL_SAMPLES`` (2): their variances are pooled with the
        screening's or floored by extrapolation.
    min_finest_level : int
        The run uses at least levels ``0..min_finest_level`` (>= 1; the default
        2 gives two levels ``>= 1`` to fit the rates from).
    max_level : int
        Finest level allowed, at least 2 (two levels ``>= 1`` to fit the rates
        from); if the bias needs more, the run stops with
        ``stop_reason = "max_level"``.
    max_cost : float, optional
        Budget in the sampler's cost unit. A batch is drawn (possibly
        shortened) only if its predicted cost fits in what is left, otherwise
        the run stops with ``stop_reason = "max_cost"``. The prediction is the
        level's mean cost so far, or the nearest sampled level's scaled by
        ``2^gamma`` per level; before any cost is known the run draws two
        samples first (:data:`_PROBE`) and then what the rest of the budget
        pays, stopping if that is not the whole first batch. The total can
        exceed ``max_cost`` only by those two samples or a misprediction of a
        level's first batch. A run stopped before its bias is estimated
        does not meet ``tol`` (module docstring, step 4). None (or
        ``math.inf``): no budget.
    batch_size : int or None
        Largest batch per sampler call (None: no cap). Smaller batches give
        more frequent events and store writes; the plans do not change (a
        round draws all a level misses before the next plan, step 2), so
        neither does the result, except where ``max_cost`` cuts a round.
    screening : LevelStatistics, optional
        Screening table (from independent samples); sets the initial finest
        level and ``N_l`` via :func:`~rough_uq.multilevel.allocation.plan`, and its ``V_l``
        are pooled with the run's (module docstring). Its samples are not part
        of the estimate.
    rates : Rates, optional
        Fixed ``alpha``, ``beta``, ``gamma``; by default they are refitted from
        the run's samples after every round (falling back to the screening
        rates, then to 0.5). The bias tail is still summed at ``alpha`` at most
        2, and at most the decay of two finest means that differ in sign (step 3).
    kurtosis_limit : float
        Kurtosis of ``Y_l`` above which a warning is issued (> 0; ``math.inf``: never); from 20 samples a
        level is also flagged above half its samples
        (:func:`~rough_uq.multilevel.statistics.kurtosis_threshold`).
    richardson : bool
        Richardson-extrapolate the finest level where the ratios of successive
        level means are stable, else fall back to plain MLMC (module docstring).
    coarsest_level : int or None
        Level ``b`` the hierarchy starts on (default 0): its samples give
        ``Q_b`` alone (the sampler's coarse values are ignored) and the levels
        below are never sampled. None lets the screening's plan choose it
        (:func:`~rough_uq.multilevel.rates.choose_coarsest_level`; 0 without a
        screening; 0 if ``max_level`` leaves fewer than two levels above the
        chosen one); ``EstimationResult.dropped_levels`` says why.
    qoi_names : sequence of str, optional
        Names of the QoI columns, one per QoI: warnings and the Richardson
        refusal name the QoIs (``for contact_area``); without them they give
        column indices (``for QoI [0]``).

    Yields
    ------
    PlanUpdated, BatchDone, RichardsonRefused, Finished
        ``Finished`` is last and carries the :class:`EstimationResult`.

    Warns
    -----
    EstimationWarning
        At the end, for every failed check of
        :func:`~rough_uq.multilevel.statistics.diagnose`, for zero reported costs and for a
        refused Richardson extrapolation.
    """
    theta = _check_fraction("theta", theta)
    n_initial = checked_integer("n_initial", n_initial, 2)
    # Two levels above the base (>= 0) to fit the rates from: levels 0..2 at least.
    min_finest_level, max_level = check_finest_levels(min_finest_level, max_level, least_max_level=2)
    batch_size = None if batch_size is None else checked_integer("batch_size", batch_size, 1)
    max_cost = _check_optional_positive("max_cost", max_cost)
    if rates is not None and not isinstance(rates, Rates):
        raise InvalidParameterError("rates", rates, "a Rates (e.g. the rates of rough_uq.screen's result) or None")
    n_qoi = screening.n_qoi if screening is not None else (rates.n_qoi if rates is not None else None)
    tol = _check_tol(tol, n_qoi)
    if rates is not None:
        _refuse_growing_bias(rates)
        if screening is not None and rates.n_qoi != screening.n_qoi:
            raise EstimationError(f"rates have {rates.n_qoi} QoIs, the screening {screening.n_qoi}")
    options = _MlmcOptions(
        tol=tol,
        qoi_names=_check_qoi_names(qoi_names, n_qoi),
        theta=theta,
        n_initial=n_initial,
        min_finest_level=min_finest_level,
        max_level=max_level,
        screening=screening,
        rates=rates,
        kurtosis_limit=_check_positive("kurtosis_limit", kurtosis_limit),
        richardson=checked_bool("richardson", richardson),
        coarsest_level=None if coarsest_level is None else checked_integer("coarsest_level", coarsest_level, 0),
    )
    batch_cap = checked_batch_cap(batch_size)
    return _drive(functools.partial(_MlmcRun, options), sampler, batch_cap=batch_cap, max_cost=max_cost)


def check_finest_levels(min_finest_level: object, max_level: object, *, least_max_level: int) -> tuple[int, int]:
    """``min_finest_level`` (an integer >= 1) and ``max_level`` (>= ``least_max_level``, the fewest a run needs).

    A ``min_finest_level`` above ``max_level`` is refused naming
    ``min_finest_level``: ``max_level`` is often the problem's, which the
    caller of a run did not give as an argument.
    """
    min_finest_level = checked_integer("min_finest_level", min_finest_level, 1)
    if least_max_level >= 2 and is_integer(max_level) and 0 <= max_level < least_max_level:
        raise InvalidParameterError(
            "max_level", max_level, f"an integer >= {least_max_level}: an MLMC run fits its rates on levels >= 1, "
            "two of them at least; on fewer levels use mc(level=...) (bias not estimated), variance or distribution",
        )
    max_level = checked_integer("max_level", max_level, least_max_level)
    if min_finest_level > max_level:
        raise InvalidParameterError("min_finest_level", min_finest_level, f"an integer in 1..max_level = {max_level}")
    return min_finest_level, max_level


@dataclass(frozen=True, eq=False)
class _MlmcOptions(_Options):
    """The checked arguments of :func:`iter_mlmc` that shape the run (see there)."""

    min_finest_level: int
    max_level: int
    rates: Rates | None
    richardson: bool
    coarsest_level: int | None


@dataclass(frozen=True, eq=False)
class _MlmcStart:
    """How an MLMC run begins (:func:`_mlmc_start`).

    ``targets`` are the initial ``N_l`` of levels ``0, 1, ...`` (empty: every
    level gets ``floor``); ``fallback`` the rates used where the run's cannot
    be fitted; ``extrapolation`` the Richardson state (:class:`_MlmcRun`).
    """

    base: int
    dropped: tuple[DroppedLevel, ...]
    targets: tuple[int, ...]
    floor: int
    fallback: Rates | None
    extrapolation: str
    refusal: str = ""


def _refuse_growing_bias(rates: Rates) -> None:
    """Fixed rates whose ``alpha`` is not positive meet no tolerance; a screening's raw fits can have such one."""
    alpha = np.asarray(rates.alpha, dtype=float)
    if np.all(alpha > 0):
        return
    values = ", ".join(f"{value:.3g}" for value in alpha.ravel())
    raise EstimationError(
        f"rates: alpha = {values}: the bias does not decay with the level, so no finest level meets a tolerance; "
        "a screening's rates are its raw fits: pass screening=... instead, which plans with them raised to at "
        "least 0.5"
    )


def _mlmc_start(options: _MlmcOptions) -> _MlmcStart:
    """Giles' ``N0`` on every level without a screening; else the screening's plan (module docstring, step 1)."""
    screening, rates, richardson = options.screening, options.rates, options.richardson
    if screening is None:
        return _MlmcStart(
            base=options.coarsest_level or 0, dropped=(), targets=(), floor=options.n_initial, fallback=rates,
            extrapolation="pending" if richardson else "off",
        )
    screening_rates = rates if rates is not None else planning_rates(screening)
    initial = starting_plan(
        tol=options.tol, rates=screening_rates, statistics=screening, theta=options.theta,
        max_level=options.max_level, richardson=options.richardson, coarsest_level=options.coarsest_level,
        min_finest_level=options.min_finest_level,
    )
    base = initial.coarsest_level
    targets = starting_samples(initial, min_finest_level=options.min_finest_level)
    extrapolation, refusal = "off", ""
    if richardson:
        refusal = _screening_instability(screening, base, options.qoi_names)
        extrapolation = "refused" if refusal else ("active" if initial.is_richardson else "pending")
    return _MlmcStart(
        base=base, dropped=initial.dropped_levels, targets=targets, floor=MIN_LEVEL_SAMPLES,
        fallback=screening_rates, extrapolation=extrapolation, refusal=refusal,
    )


def starting_samples(initial: Plan, *, min_finest_level: int = 2) -> tuple[int, ...]:
    """Samples per level that an MLMC run started from the screening plan ``initial`` asks for first.

    The plan's ``N_l`` (at least :data:`MIN_LEVEL_SAMPLES`) from its coarsest
    level on, none below it, and :data:`MIN_LEVEL_SAMPLES` on the levels the
    run adds: it spans at least levels ``0..min_finest_level`` and two levels
    above its coarsest one, from which it fits the rates.
    """
    base = initial.coarsest_level
    targets = [max(int(n), MIN_LEVEL_SAMPLES) if level >= base else 0 for level, n in enumerate(initial.n_samples)]
    n_levels = max(min_finest_level + 1, base + 3, len(targets))
    return tuple(targets + [MIN_LEVEL_SAMPLES] * (n_levels - len(targets)))


def starting_forecast(
    initial: Plan, rates: Rates, *, min_finest_level: int = 2
) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """What an MLMC run started from the screening plan ``initial`` asks for first, and what one sample costs.

    The samples per level (:func:`starting_samples`) and the modelled cost of one sample of each level: the
    plan's where it has the level, else ``rates``' cost model (the levels the run adds for its rates).
    """
    counts = starting_samples(initial, min_finest_level=min_finest_level)
    costs = tuple(float(initial.costs[level]) if level < len(initial.costs) else float(rates.cost_model(level))
                  for level in range(len(counts)))
    return counts, costs


def starting_plan(
    *, tol: np.ndarray, rates: Rates, statistics: LevelStatistics, theta: float, max_level: int,
    richardson: bool = False, coarsest_level: int | None = None, min_finest_level: int = 2,
) -> Plan:
    """The plan an MLMC run started from a screening begins with (:func:`iter_mlmc`).

    :func:`~rough_uq.multilevel.allocation.plan` with the run's options; the
    coarsest level is chosen from the screening unless given, and is level 0
    when ``max_level`` leaves no two levels above the chosen one (the rates
    need them). Forecasts use it to predict what the run will plan. Its bias is the one the run's levels
    predict (:func:`with_run_bias`).
    """
    options = dict(tol=tol, rates=rates, statistics=statistics, theta=theta, max_level=max_level, richardson=richardson)
    initial = plan(**options, coarsest_level=coarsest_level)
    if coarsest_level is None and initial.coarsest_level + 2 > max_level:
        initial = plan(**options, coarsest_level=0)
    return with_run_bias(initial, rates=rates, statistics=statistics, max_level=max_level,
                         min_finest_level=min_finest_level)


def with_run_bias(initial: Plan, *, rates: Rates, statistics: LevelStatistics, max_level: int,
                  min_finest_level: int = 2) -> Plan:
    """``initial``, or where the levels a run samples cannot meet the bias it plans for, the plan marked so.

    A run samples at least levels ``0..max(min_finest_level, coarsest + 2)`` and tests the bias on its finest
    sampled level. Where the screening's level means do not decay monotonically a plan can stop below those
    levels with its bias met while the run's own levels predict more: the run then adds levels up to
    ``max_level`` and ends NOT MET (on the quickstart with ``grid.max_level: 2``: a plan for tol 0.5 stopped on
    level 1, bias 0.20, and the run on levels 0..2 found 0.42-0.45, where the screening predicted 0.37). Where
    no level from the run's finest to ``max_level`` meets the bias, the plan returned has ``is_bias_met`` False
    and the bias ``max_level`` predicts (the refusals then name the smallest tolerance that level reaches).
    """
    bias_level = min(max(min_finest_level, initial.coarsest_level + 2), max_level)
    if not initial.is_bias_met or initial.is_richardson or initial.finest_level >= bias_level:
        return initial
    for level in range(bias_level, max_level + 1):
        deeper = plan(tol=initial.tol, rates=rates, statistics=statistics, theta=initial.theta, max_level=max_level,
                      coarsest_level=initial.coarsest_level, finest_level=level)
        if deeper.is_bias_met:
            return initial
    return dataclasses.replace(initial, bias=deeper.bias, is_bias_met=False)


class _MlmcRun(_Run):
    """An adaptive MLMC run (module docstring): its rates, Richardson state and bias test.

    ``extrapolation`` is ``"off"``, ``"pending"`` (too few levels to check the
    ratios), ``"active"`` or ``"refused"`` (``refusal`` says why).
    """

    def __init__(self, options: _MlmcOptions) -> None:
        start = _mlmc_start(options)
        # Two levels above the base to fit the rates from.
        n_levels = max(options.min_finest_level + 1, start.base + 3, len(start.targets))
        if n_levels - 1 > options.max_level:
            raise InvalidParameterError(
                "coarsest_level", options.coarsest_level, f"at most max_level - 2 = {options.max_level - 2}"
            )
        hierarchy = _Hierarchy(n_levels, start.floor, options.screening, start.base)
        hierarchy.targets[: len(start.targets)] = start.targets
        super().__init__(hierarchy, options)
        self.fallback, self.dropped = start.fallback, start.dropped
        self.driver = start.fallback if start.fallback is not None else _floor_rates(options.tol.size)
        self.extrapolation, self.refusal = start.extrapolation, start.refusal
        # The fewest levels the bias test uses: min_finest_level, and two levels above the base for the rates.
        self.bias_levels = max(options.min_finest_level, start.base + 2)
        self.is_reach_warned = False

    @property
    def cost_rate(self) -> float:
        return self.driver.gamma

    def on_qoi_count(self, n_qoi: int) -> None:
        if self.fallback is not None and self.fallback.n_qoi != n_qoi:
            raise EstimationError(f"the rates/screening have {self.fallback.n_qoi} QoIs, the sampler {n_qoi}")
        if self.driver.n_qoi != n_qoi:
            self.driver = _floor_rates(n_qoi)

    def start(self) -> Iterator[Event]:
        if self.extrapolation == "refused":
            yield RichardsonRefused(levels=self.hierarchy.levels(), reason=self.refusal)

    def check_reach(self) -> None:
        """Warn once where the samples so far put the bias on ``max_level`` above twice its share ``sqrt(theta) tol``.

        Giles' algorithm tests the bias only once a round's samples are drawn: a run without a screening at a
        tolerance out of reach planned some 8 million samples for its statistical error, silently, and would
        then stop at ``max_level`` with the tolerance not met. Only QoIs whose finest level mean is measured
        (beyond :data:`~rough_uq.multilevel.rates.STALL_SIGNIFICANCE` standard errors from 0) count, and the
        bias on ``max_level`` is the estimate's, decaying by ``2^-a`` per level at the rate ``a`` its tail is
        summed with (:func:`~rough_uq.multilevel.rates.confirmed_tail`); not for an extrapolated estimate.
        """
        if self.is_reach_warned or self.extrapolation not in ("off", "refused") or not self.is_bias_estimated():
            return
        finest, max_level = self.finest_sampled(), self.options.max_level
        means, errors = self.hierarchy.bias_means(self.n_qoi)
        alpha = tail_rate(self.driver.alpha)
        if finest - 2 >= self.hierarchy.base:  # as bias() sums the tail
            alpha, _ = confirmed_tail(self.driver, means[finest - 1], means[finest], errors[finest])
        reach = self.bias() * 2.0 ** (-alpha * (max_level - finest))
        share = math.sqrt(self.options.theta) * self.tol
        # Twice the share: a bias near it may still meet it once more samples firm up the means.
        out = np.flatnonzero((reach > 2 * share) & (np.abs(means[finest]) > STALL_SIGNIFICANCE * errors[finest]))
        if not out.size:
            return
        self.is_reach_warned = True
        names = self.options.qoi_names or [f"QoI {column}" for column in range(self.n_qoi)]
        planned = sum(self.hierarchy.targets) - sum(s.n for s in self.hierarchy.samples)
        warn_at_caller(
            f"mlmc: from the samples so far the bias on max_level = {max_level} is about "
            f"{_per_qoi(names, reach, out)}, above its share sqrt(theta) tol = {_per_qoi(names, share, out)}: "
            "the run will likely stop at max_level with its "
            f"tolerance not met, after the {planned} samples it now plans for its statistical error; loosen tol or "
            "raise max_level (a screening first forecasts this), or set max_cost",
            EstimationWarning,
        )

    def replan(self) -> None:
        """Refit the rates (unless given) and set ``N_l`` from the pooled ``V_l`` (module docstring, step 2)."""
        hierarchy = self.hierarchy
        base = hierarchy.base
        statistics = hierarchy.statistics()
        if self.options.rates is None:
            self.driver = _lenient_rates(statistics, self.fallback, base + 1, hierarchy.bias_statistics(statistics))
        var_diff, has_data, mean_cost = hierarchy.planning_inputs(self.n_qoi)
        variances = _planning_variances(var_diff, has_data, self.driver.beta, base)
        if self.extrapolation == "active":
            variances[-1] = variances[-1] * richardson_weight(self.driver.alpha) ** 2
        costs = _fill_costs(mean_cost, np.array([s.n > 0 for s in hierarchy.samples]), self.driver.gamma)
        budget = (1.0 - self.options.theta) * self.tol**2
        wanted = np.zeros(hierarchy.n_levels)
        wanted[base:] = np.ceil(np.max(optimal_samples(variances[base:], costs[base:], budget), axis=1))
        hierarchy.targets = [
            max(s.n, int(n), hierarchy.floor) if s.level >= base else 0 for s, n in zip(hierarchy.samples, wanted)
        ]

    def finest_sampled(self) -> int:
        """The finest level with samples, where the estimate ends (levels are sampled in order)."""
        return self.hierarchy.sampled()[-1].level

    def is_bias_estimated(self) -> bool:
        """Levels ``base..bias_levels`` have samples (module docstring, step 4)."""
        return self.finest_sampled() >= self.bias_levels

    def bias(self) -> np.ndarray:
        """Remaining bias of the run's estimate (plain or extrapolated) from the pooled level means; 0 unestimated.

        The estimate ends on the finest sampled level: a level the run added
        but ``max_cost`` left unsampled is not part of it.
        """
        if not self.is_bias_estimated():
            return np.zeros(self.n_qoi)
        finest = self.finest_sampled()
        all_means, errors = self.hierarchy.bias_means(self.n_qoi)
        means = all_means[self.hierarchy.base : finest + 1]  # row 0 is the base level, whose Y is Q
        if self.extrapolation == "active":
            return richardson_bias(means[1:], self.driver.alpha, errors[self.hierarchy.base + 1 : finest + 1])
        # The two levels below the finest, as far as they are differences (above the base level).
        coarser = means[1:-1][-2:]
        return estimated_bias(rates=self.driver, level=finest, mean_diff=means[-1], coarser=coarser,
                              mean_error=errors[finest])

    def after_round(self) -> Iterator[Event]:
        """Check the extrapolation, then the bias: stop, or add a level (module docstring, steps 3 and 4)."""
        hierarchy = self.hierarchy
        is_complete = hierarchy.is_complete()
        if self.extrapolation in ("pending", "active") and is_complete:
            is_replanned = yield from self._check_richardson()
            if is_replanned:
                return
        if np.all(self.bias() <= math.sqrt(self.options.theta) * self.tol):
            if is_complete:
                self.stop_reason = "tol_met"
            return
        if hierarchy.n_levels - 1 >= self.options.max_level:
            if is_complete:
                self.stop_reason = "max_level"
            return
        hierarchy.add_level()
        self.replan()
        yield hierarchy.plan_event("new level")

    def _check_richardson(self) -> Iterator[Event]:
        """Activate or refuse the extrapolation on the run's means; returns whether the plan changed."""
        hierarchy = self.hierarchy
        reason = _run_instability(hierarchy, self.options.qoi_names)
        enough = hierarchy.n_levels - 1 - hierarchy.base >= RICHARDSON_MIN_LEVELS
        before = self.extrapolation
        if reason and enough:
            self.extrapolation, self.refusal = "refused", reason
            yield RichardsonRefused(levels=hierarchy.levels(), reason=reason)
        else:
            # Too few levels above the base to check the ratios: plain MLMC until there are.
            self.extrapolation = "pending" if reason else "active"
        if self.extrapolation == before:
            return False
        targets = list(hierarchy.targets)
        self.replan()
        if hierarchy.targets == targets:
            return False
        yield hierarchy.plan_event("richardson")
        return True

    def finish(self) -> Iterator[Event]:
        hierarchy = self.hierarchy
        if self.extrapolation == "pending":
            self.refusal = _run_instability(hierarchy, self.options.qoi_names) or "the ratios were never checked"
        elif self.extrapolation == "active" and not self.is_bias_estimated():
            self.refusal = (f"max_cost stopped the run before levels {hierarchy.base}..{self.bias_levels} had "
                            "samples")
        if self.refusal and self.extrapolation != "refused":
            self.extrapolation = "refused"
            yield RichardsonRefused(levels=hierarchy.levels(), reason=self.refusal)
        statistics = hierarchy.statistics()
        result = _mlmc_result(self, statistics)
        for message in diagnose(statistics, kurtosis_limit=self.options.kurtosis_limit, names=self.options.qoi_names):
            warn_at_caller(f"mlmc: {message}", EstimationWarning)
        if self.extrapolation == "refused":
            warn_at_caller(
                f"mlmc: Richardson extrapolation refused, the estimate is plain MLMC: {self.refusal}",
                EstimationWarning,
            )
        _warn_zero_cost(statistics)
        yield Finished(result=result)


def _mlmc_result(run: _MlmcRun, statistics: LevelStatistics) -> EstimationResult:
    hierarchy, driver, tol, is_scalar = run.hierarchy, run.driver, run.tol, run.is_scalar
    n = statistics.n_samples[:, None]
    var_diff = np.array(
        [hierarchy.variances(int(level), statistics.var_diff[row], int(statistics.n_samples[row]))
         for row, level in enumerate(statistics.levels)]
    )
    # Levels are sampled in order, so the sampled ones are 0..L without gaps.
    weights = np.ones_like(statistics.mean_diff)
    if run.extrapolation == "active":
        weights[-1] = richardson_weight(driver.alpha)
    bias = run.bias()
    estimate = np.sum(weights * statistics.mean_diff, axis=0)
    stat_variance = np.sum(weights**2 * var_diff / n, axis=0)
    return EstimationResult(
        method="mlmc",
        estimate=_shape_out(estimate, is_scalar),
        stat_error=_shape_out(np.sqrt(stat_variance), is_scalar),
        bias_estimate=_shape_out(bias, is_scalar),
        variance=_shape_out(np.sum(statistics.var_delta, axis=0), is_scalar),
        variance_error=_shape_out(np.sqrt(np.sum(statistics.var_delta_se**2, axis=0)), is_scalar),
        n_samples=statistics.n_samples,
        levels=statistics.levels,
        cost=hierarchy.spent,
        mc_cost=_predicted_mc_cost(statistics, driver, tol, run.options),
        statistics=statistics,
        rates=driver,
        tol=_readonly(tol),
        theta=run.options.theta,
        tol_met=run.is_bias_estimated() and bool(np.all(stat_variance + bias**2 <= tol**2 * (1 + 1e-12))),
        stop_reason=run.stop_reason,
        is_bias_estimated=run.is_bias_estimated(),
        richardson={"active": "applied", "refused": "refused"}.get(run.extrapolation, "off"),
        richardson_reason=run.refusal,
        dropped_levels=run.dropped,
        qoi_names=run.options.qoi_names,
    )


def _predicted_mc_cost(statistics: LevelStatistics, rates: Rates, tol: np.ndarray, options: _MlmcOptions) -> float:
    """Cost of plain MC for the same tolerance (fine solves only) on the level the run's bias model needs.

    That level, not the run's finest: the levels a run starts with and its bias test can take it beyond what
    the tolerance needs, and plain MC priced there came out up to some 20 times dearer. On the finest level
    where the bias model cannot choose one.
    """
    try:
        prediction = plan(tol=tol, rates=rates, statistics=statistics, theta=options.theta,
                          max_level=options.max_level, coarsest_level=None)
    except EstimationError:
        return _finest_mc_cost(statistics, rates.gamma, tol, options.theta)
    return mc_run_cost(prediction)


def _finest_mc_cost(statistics: LevelStatistics, gamma: float, tol: np.ndarray, theta: float) -> float:
    """Cost of plain MC on the finest level for the same tolerance (fine solves only)."""
    finest = statistics.n_levels - 1
    costs = _fill_costs(statistics.mean_cost, np.ones(statistics.n_levels, dtype=bool), gamma)
    budget = (1.0 - theta) * tol**2
    mc_n = float(np.max(np.minimum(np.ceil(statistics.var_fine[finest] / budget), _MAX_COUNT)))
    return float(mc_n * costs[finest] * fine_cost_share(gamma, finest))


def _screening_instability(screening: LevelStatistics, base: int, names: Sequence[str] | None) -> str:
    """Why the screening's means of levels above ``base`` forbid extrapolation ("" if they do not, or cannot tell).

    ``names``: of the QoIs, for the reason (:func:`~rough_uq.multilevel.richardson.ratio_instability`).
    """
    rows = [r for r in range(screening.n_levels) if screening.levels[r] > base and screening.n_samples[r] >= 2]
    if len(rows) < 2:
        return ""
    errors = np.sqrt(screening.var_diff[rows] / screening.n_samples[rows][:, None])
    reason = ratio_instability(
        screening.mean_diff[rows], errors, [int(screening.levels[r]) for r in rows], min_levels=2, names=names
    )
    return f"screening: {reason}" if reason else ""


def _run_instability(hierarchy: _Hierarchy, names: Sequence[str] | None) -> str:
    """Why the pooled means of the run's levels above its base are not stable ("" if they are).

    ``names``: of the QoIs, for the reason (:func:`~rough_uq.multilevel.richardson.ratio_instability`).
    """
    levels = [s.level for s in hierarchy.samples[hierarchy.base + 1 :] if s.n >= 2]
    if not levels:
        return ratio_instability(np.zeros((0, 1)), np.zeros((0, 1)), [])
    means, errors = hierarchy.bias_means(hierarchy.samples[levels[0]].moments().mean_diff.size)
    return ratio_instability(means[levels], errors[levels], levels, names=names)


def mlmc(
    sampler: Sampler, *, tol: float | np.ndarray, qoi_names: Sequence[str] | None = None, **options: object
) -> EstimationResult:
    """Adaptive MLMC estimate of ``E[Q]`` to RMS tolerance ``tol``.

    Runs :func:`iter_mlmc` to the end; ``qoi_names`` (names of the QoI
    columns, for the warnings) and ``options`` are its keyword arguments
    (``theta``, ``n_initial``, ``min_finest_level``, ``max_level``,
    ``max_cost``, ``batch_size``, ``screening``, ``rates``,
    ``kurtosis_limit``, ``richardson``, ``coarsest_level``).

    Returns
    -------
    EstimationResult
    """
    return _final(iter_mlmc(sampler, tol=tol, qoi_names=qoi_names, **options))


def refuse_large_plan(
    n_planned, *, max_samples: int | None, tol: np.ndarray, advice: str, tolerance: str | None = None
) -> None:
    """Raise :class:`~rough_uq.errors.PlanTooLargeError` for a plan of more than ``max_samples`` samples in all.

    ``n_planned`` are the samples per level; ``advice`` ends the message (what
    to change); ``tolerance`` names the tolerance in it (default ``tol`` and
    its values). ``max_samples`` None: no limit.
    """
    total = float(np.sum(n_planned))
    if max_samples is not None and total > max_samples:
        raise PlanTooLargeError(
            n_planned=n_planned, total=total, max_samples=max_samples, tol=np.ravel(tol), advice=advice,
            tolerance=tolerance,
        )


def refuse_large_start(n_initial: int, levels: Sequence[int], *, max_samples: int | None) -> None:
    """Raise :class:`~rough_uq.errors.InvalidParameterError` naming ``n_initial`` if it alone exceeds ``max_samples``.

    A run that starts with ``n_initial`` samples on each of ``levels`` plans
    them whatever the tolerance: when they exceed ``max_samples`` the
    tolerance is not to blame (:func:`refuse_large_plan` would say so), and
    the refusal comes before any sample. ``max_samples`` None: no limit.
    """
    n_levels = len(levels)
    if max_samples is None or n_initial * n_levels <= max_samples:
        return
    where = f"level {levels[0]}" if n_levels == 1 else f"levels {levels[0]}..{levels[-1]}"
    raise InvalidParameterError(
        "n_initial", n_initial, f"at most max_samples / levels = {max_samples // n_levels}: the initial samples of "
        f"{where} alone exceed max_samples = {max_samples}",
    )


def _final(events: Iterator[Event]) -> EstimationResult:
    for event in events:
        if isinstance(event, Finished):
            return event.result
    raise EstimationError("the estimator stopped without a result")  # pragma: no cover - generator bug


# --------------------------------------------------------------------------
# Plain Monte Carlo: the one-level hierarchy at its level
# --------------------------------------------------------------------------


def iter_mc(
    sampler: Sampler,
    *,
    tol: float | np.ndarray,
    level: int,
    theta: float = 0.5,
    bias: float | np.ndarray | None = None,
    n_initial: int = 10,
    max_cost: float | None = None,
    batch_size: int | None = 1000,
    screening: LevelStatistics | None = None,
    kurtosis_limit: float = KURTOSIS_LIMIT,
    qoi_names: Sequence[str] | None = None,
) -> Iterator[Event]:
    """Plain MC on one level to a tolerance, as a generator of events.

    Draws ``N = ceil((1-theta)^-1 eps^-2 Var(Q_level))`` samples (at least
    ``n_initial``; maximum over QoIs), re-estimating ``Var(Q_level)`` after
    every batch. Only the ``fine`` values are used; a sampler for MC may
    return zeros as ``coarse``.

    With a ``screening`` the run is treated as MLMC's (:func:`iter_mlmc`):
    it starts from the ``N`` the screening's ``Var(Q)`` implies, needs at
    least 2 samples, and ``Var(Q_level)`` is pooled with the screening's if
    the screening sampled ``level``; otherwise the variance used to plan is
    floored at half the screening's ``Var(Q)`` on its finest level.

    Parameters
    ----------
    sampler : callable
        ``sampler(level, sample_indices) -> (fine, coarse, cost)``.
    tol : float or ndarray, shape (n_qoi,)
        Tolerance ``eps`` on the RMS error.
    level : int
        The level (grid) to sample.
    theta : float
        Bias share of ``eps^2``; the statistical target is ``(1-theta) eps^2``,
        as in :func:`~rough_uq.multilevel.allocation.plan`'s MC prediction.
    bias : float or ndarray, optional
        Estimated bias of level ``level`` (e.g. ``Plan.bias`` from the
        screening). MC cannot estimate it from one level; without it the
        result has ``bias_estimate = 0`` and ``is_bias_estimated = False``.
    n_initial : int
        Samples before the variance is trusted (>= 2), without a screening.
    max_cost : float, optional
        Budget in the sampler's cost unit (as in :func:`iter_mlmc`); a run it
        stops before its first ``n_initial`` samples (2 from a screening) does
        not meet ``tol``.
    batch_size : int or None
        Largest batch per sampler call; the result does not depend on it (as for :func:`iter_mlmc`).
    screening : LevelStatistics, optional
        Screening table (independent samples) of the same hierarchy.
    kurtosis_limit : float
        Kurtosis of ``Q`` above which a warning is issued, as for :func:`iter_mlmc`.
    qoi_names : sequence of str, optional
        Names of the QoI columns, one per QoI: the kurtosis warning names the
        QoIs it concerns (``for clusters``); without them it names none.

    Yields
    ------
    PlanUpdated, BatchDone, Finished
    """
    theta = _check_fraction("theta", theta)
    level = checked_integer("level", level, 0)
    n_initial = checked_integer("n_initial", n_initial, 2)
    batch_size = None if batch_size is None else checked_integer("batch_size", batch_size, 1)
    max_cost = _check_optional_positive("max_cost", max_cost)
    n_qoi = screening.n_qoi if screening is not None else None
    tol = _check_tol(tol, n_qoi)
    options = _McOptions(
        tol=tol,
        qoi_names=_check_qoi_names(qoi_names, n_qoi),
        level=level,
        theta=theta,
        bias=None if bias is None else _checked_bias(bias),
        n_initial=n_initial,
        screening=screening,
        kurtosis_limit=_check_positive("kurtosis_limit", kurtosis_limit),
    )
    batch_cap = checked_batch_cap(batch_size)
    return _drive(functools.partial(_McRun, options), sampler, batch_cap=batch_cap, max_cost=max_cost)


def _checked_bias(bias: object) -> np.ndarray:
    """``|bias|`` as a 1-d float array; strings, booleans and non-finite values are refused naming ``bias``."""
    allowed = "a finite number or a 1-d array of them (one per QoI)"
    values = checked_real_array("bias", bias, allowed)
    if values.ndim > 1 or not np.all(np.isfinite(values)):
        raise InvalidParameterError("bias", bias, allowed)
    return np.atleast_1d(np.abs(values))


def _mc_screened_variance(screening: LevelStatistics, level: int) -> tuple[np.ndarray, float | np.ndarray]:
    """``Var(Q_level)`` the screening predicts, and the floor of the run's planning variance.

    The level's own screened variance (no floor: the run pools it instead);
    else that of the finest screened level, half of which floors the run's;
    zeros without a level screened with two or more samples.
    """
    usable = np.flatnonzero(screening.n_samples >= 2)
    same = usable[screening.levels[usable] == level]
    if same.size:
        return screening.var_fine[same[0]], 0.0
    if usable.size:
        return screening.var_fine[usable[-1]], 0.5 * screening.var_fine[usable[-1]]
    return np.zeros(screening.n_qoi), 0.0


@dataclass(frozen=True, eq=False)
class _McOptions(_Options):
    """The checked arguments of :func:`iter_mc` that shape the run (see there)."""

    level: int
    bias: np.ndarray | None


class _McRun(_Run):
    """Plain MC on ``level``: a hierarchy whose base is ``level``, so its samples are ``Q_level`` alone.

    ``bias`` is the bias given to :func:`iter_mc` (None if unknown), one per
    QoI once their number is known.
    """

    def __init__(self, options: _McOptions) -> None:
        screening, level, tol = options.screening, options.level, options.tol
        floor = options.n_initial if screening is None else MIN_LEVEL_SAMPLES
        # The hierarchy pools the screening's Var(Q_level), if it sampled the level, as MLMC's base level.
        hierarchy = _Hierarchy(level + 1, floor, screening, base=level, reported_from=level)
        super().__init__(hierarchy, options)
        self.level, self.bias = level, options.bias
        self.var_floor: float | np.ndarray = 0.0
        if screening is not None:
            first_var, self.var_floor = _mc_screened_variance(screening, level)
            first = np.max(np.ceil(first_var / ((1.0 - options.theta) * tol**2)))
            hierarchy.targets[level] = max(int(min(first, _MAX_COUNT)), floor)

    @property
    def samples(self) -> _LevelSamples:
        return self.hierarchy.samples[self.level]

    def on_qoi_count(self, n_qoi: int) -> None:
        if self.bias is not None:
            self.bias = _check_bias(self.bias, n_qoi)

    def variance(self) -> np.ndarray:
        """``Var(Q_level)``: the run's, pooled with the screening's where it sampled the level."""
        return self.hierarchy.variances(self.level, self.samples.moments().var_fine, self.samples.n)

    def replan(self) -> None:
        """``N = ceil((1-theta)^-1 eps^-2 Var(Q_level))``, maximum over QoIs, never below the drawn or the floor."""
        budget = (1.0 - self.options.theta) * self.tol**2
        wanted = np.max(np.ceil(np.maximum(self.variance(), self.var_floor) / budget))
        n = max(self.samples.n, int(min(wanted, _MAX_COUNT)), self.hierarchy.floor)
        self.hierarchy.targets[self.level] = n

    def bias_values(self) -> np.ndarray:
        return self.bias if self.bias is not None else np.zeros(self.n_qoi)

    def is_tol_met(self) -> bool:
        """``Var / N + bias^2 <= eps^2`` with a given bias, ``Var / N <= (1 - theta) eps^2`` without one (the
        statistical error's share, which the plan aims at), once the run has the samples it starts with.

        Fewer than the first plan's samples (``n_initial``, or 2 from a
        screening) give no variance estimate to trust: a budget that stopped
        the run after a probe of two (:data:`_PROBE`) claimed the tolerance met.
        Without a bias, ``max_cost`` stopped runs between the two errors and
        called them met, while the same run without the budget drew on.
        """
        if self.samples.n < self.hierarchy.floor:
            return False
        stat_variance = self.variance() / self.samples.n
        if self.bias is None:
            return bool(np.all(stat_variance <= (1.0 - self.options.theta) * self.tol**2 * (1 + 1e-12)))
        return bool(np.all(stat_variance + self.bias_values() ** 2 <= self.tol**2 * (1 + 1e-12)))

    def after_round(self) -> Iterator[Event]:
        # MC has no level to add: once the samples are drawn, only the given bias can fail.
        if self.hierarchy.is_complete():
            self.stop_reason = "tol_met" if self.is_tol_met() else "bias"
        yield from ()

    def finish(self) -> Iterator[Event]:
        moments = self.samples.moments()
        result = _mc_result(self)
        limit, names = self.options.kurtosis_limit, self.options.qoi_names
        heavy = np.flatnonzero(moments.kurtosis > kurtosis_threshold(moments.n, limit))
        if heavy.size:
            which = "" if names is None else f" for {_qoi_text(heavy, names)}"
            worst = float(np.max(moments.kurtosis))
            warn_at_caller(
                f"mc: kurtosis {worst:.3g} of Q on level {self.level}{which} {kurtosis_text(worst, moments.n, limit)}; "
                "the variance and error estimates are unreliable",
                EstimationWarning,
            )
        yield Finished(result=result)


def _mc_result(run: _McRun) -> EstimationResult:
    moments = run.samples.moments()
    # A table of Q alone (coarse values stored as zeros), with base level 0 as MC tables always had.
    statistics = _assemble([run.level], [moments])
    is_scalar = run.is_scalar
    budget = (1.0 - run.options.theta) * run.tol**2
    mc_n = float(np.max(np.minimum(np.ceil(run.variance() / budget), _MAX_COUNT)))
    return EstimationResult(
        method="mc",
        estimate=_shape_out(moments.mean_fine, is_scalar),
        stat_error=_shape_out(np.sqrt(run.variance() / run.samples.n), is_scalar),
        bias_estimate=_shape_out(run.bias_values(), is_scalar),
        variance=_shape_out(moments.var_fine, is_scalar),
        variance_error=_shape_out(moments.var_delta_se, is_scalar),
        n_samples=statistics.n_samples,
        levels=statistics.levels,
        cost=run.hierarchy.spent,
        mc_cost=float(mc_n * moments.mean_cost),
        statistics=statistics,
        rates=None,
        tol=_readonly(run.tol),
        theta=run.options.theta,
        tol_met=run.is_tol_met(),
        stop_reason=run.stop_reason,
        is_bias_estimated=run.bias is not None,
        qoi_names=run.options.qoi_names,
    )


def _check_bias(bias: np.ndarray, n_qoi: int) -> np.ndarray:
    """Bias as an array of shape (n_qoi,) (a single value is broadcast)."""
    if bias.size == 1:
        return np.repeat(bias, n_qoi)
    if bias.size != n_qoi:
        raise InvalidParameterError("bias", bias, f"a scalar or {n_qoi} values (one per QoI)")
    return bias


def mc(
    sampler: Sampler, *, tol: float | np.ndarray, level: int, qoi_names: Sequence[str] | None = None,
    **options: object,
) -> EstimationResult:
    """Plain Monte Carlo estimate of ``E[Q_level]`` to RMS tolerance ``tol``.

    Runs :func:`iter_mc` to the end; ``qoi_names`` (names of the QoI
    columns, for the warnings) and ``options`` are its keyword arguments
    (``theta``, ``bias``, ``n_initial``, ``max_cost``, ``batch_size``,
    ``screening``, ``kurtosis_limit``).

    Returns
    -------
    EstimationResult
    """
    return _final(iter_mc(sampler, tol=tol, level=level, qoi_names=qoi_names, **options))
