"""Adaptive MLMC (:func:`iter_mlmc`, :func:`mlmc`): Giles' algorithm and its start from a screening.

Also the refusals of a plan or a start too large (:func:`refuse_large_plan`, :func:`refuse_large_start`,
:data:`MAX_PLANNED_SAMPLES`), which every run uses. "The module docstring" below is the package's,
:mod:`rough_uq.multilevel.drivers`, which describes the algorithm step by step.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import (
    EstimationError,
    InvalidParameterError,
    PlanTooLargeError,
    checked_bool,
    checked_integer,
    is_integer,
    warn_at_caller,
)
from rough_uq.multilevel.allocation import (
    Plan,
    check_fraction,
    check_tol,
    fine_cost_share,
    mc_run_cost,
    optimal_samples,
    plan,
)
from rough_uq.multilevel.drivers.events import EstimationResult, Event, Finished, RichardsonRefused
from rough_uq.multilevel.drivers.hierarchy import _Hierarchy
from rough_uq.multilevel.drivers.loop import (
    _MAX_COUNT,
    _Options,
    _Run,
    _check_qoi_names,
    _drive,
    _per_qoi,
    _warn_zero_cost,
    checked_batch_cap,
)
from rough_uq.multilevel.drivers.planning import (
    _floor_rates,
    _lenient_rates,
    fill_costs,
    planning_rates,
    planning_variances,
)
from rough_uq.multilevel.drivers.samples import (
    Sampler, _shape_out, check_initial_count, check_kurtosis_limit, check_optional_positive,
)
from rough_uq.multilevel.rates import (
    STALL_SIGNIFICANCE, DroppedLevel, Rates, checked_gamma_beyond, confirmed_tail, estimated_bias, tail_rate,
)
from rough_uq.multilevel.richardson import RICHARDSON_MIN_LEVELS, ratio_instability, richardson_bias, richardson_weight
from rough_uq.multilevel.statistics import (
    KURTOSIS_LIMIT, EstimationWarning, LevelStatistics, diagnose, readonly_array, scaled_by_largest,
)

#: Plans with more samples than this are refused, by the Python runs (:mod:`rough_uq.problem.runs`, unless
#: ``max_samples=`` moves the limit) and by ``roughuq`` (whatever ``--max-cost``).
MAX_PLANNED_SAMPLES = 10**7
MIN_LEVEL_SAMPLES = 2
"""Fewest samples on a level of an MLMC run started from a screening (one variance needs two)."""


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
    gamma_beyond: float | None = None,
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
        ``2^gamma`` per level (the rates' ``gamma_extrapolated``: with
        ``gamma_beyond``, the larger of both); before any cost is known the run draws two
        samples first (:data:`~rough_uq.multilevel.drivers.loop._PROBE`) and then what the rest of the budget
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
    gamma_beyond : float or None
        The problem's least cost rate beyond the screened levels, with which
        the screening's plan predicts the cost of finer levels
        (:attr:`~rough_uq.multilevel.rates.Rates.gamma_beyond`; None: the
        fitted ``gamma``). Ignored without a screening or with ``rates``.

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
    theta = check_fraction("theta", theta)
    n_initial = check_initial_count(n_initial)
    # Two levels above the base (>= 0) to fit the rates from: levels 0..2 at least.
    min_finest_level, max_level = check_finest_levels(min_finest_level, max_level, least_max_level=2)
    batch_size = None if batch_size is None else checked_integer("batch_size", batch_size, 1)
    max_cost = check_optional_positive("max_cost", max_cost)
    if rates is not None and not isinstance(rates, Rates):
        raise InvalidParameterError("rates", rates, "a Rates (e.g. the rates of rough_uq.screen's result) or None")
    n_qoi = screening.n_qoi if screening is not None else (rates.n_qoi if rates is not None else None)
    tol = check_tol(tol, n_qoi)
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
        kurtosis_limit=check_kurtosis_limit(kurtosis_limit),
        richardson=checked_bool("richardson", richardson),
        coarsest_level=None if coarsest_level is None else checked_integer("coarsest_level", coarsest_level, 0),
        gamma_beyond=checked_gamma_beyond("gamma_beyond", gamma_beyond),
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
    gamma_beyond: float | None


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
    """Fixed rates whose ``alpha`` is not positive meet no tolerance; a screening's raw fits can have such one.

    Rates that are not finite numbers (a hand-built ``Rates`` with a NaN) are refused first, naming the field.
    """
    for name in ("alpha", "beta", "gamma", "c_alpha", "c_beta", "c_gamma"):
        values = np.asarray(getattr(rates, name), dtype=float)
        if not np.all(np.isfinite(values)):
            raise InvalidParameterError(f"rates.{name}", getattr(rates, name), "finite numbers")
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
    screening_rates = rates if rates is not None else planning_rates(screening, gamma_beyond=options.gamma_beyond)
    initial = starting_plan(
        tol=options.tol, rates=screening_rates, statistics=screening, theta=options.theta,
        max_level=options.max_level, richardson=options.richardson, coarsest_level=options.coarsest_level,
        min_finest_level=options.min_finest_level, qoi_names=options.qoi_names,
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
    qoi_names: Sequence[str] | None = None,
) -> Plan:
    """The plan an MLMC run started from a screening begins with (:func:`iter_mlmc`).

    :func:`~rough_uq.multilevel.allocation.plan` with the run's options; the
    coarsest level is chosen from the screening unless given, and is level 0
    when ``max_level`` leaves no two levels above the chosen one (the rates
    need them). Forecasts use it to predict what the run will plan. Its bias is the one the run's levels
    predict (:func:`with_run_bias`). ``qoi_names`` name the QoIs in the plan's reasons (a forecast said
    ``(QoI 0)`` where the run named ``contact_area@0.05``).
    """
    options = dict(tol=tol, rates=rates, statistics=statistics, theta=theta, max_level=max_level, richardson=richardson,
                   qoi_names=qoi_names)
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
        return self.driver.gamma_extrapolated

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
        variances = planning_variances(var_diff, has_data, self.driver.beta, base)
        if self.extrapolation == "active":
            variances[-1] = variances[-1] * richardson_weight(self.driver.alpha) ** 2
        costs = fill_costs(mean_cost, np.array([s.n > 0 for s in hierarchy.samples]), self.cost_rate)
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
        variance_error=_shape_out(_root_sum_squares(statistics.var_delta_se), is_scalar),
        n_samples=statistics.n_samples,
        levels=statistics.levels,
        cost=hierarchy.spent,
        mc_cost=_predicted_mc_cost(statistics, driver, tol, run.options),
        statistics=statistics,
        rates=driver,
        tol=readonly_array(tol),
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
    costs = fill_costs(statistics.mean_cost, np.ones(statistics.n_levels, dtype=bool), gamma)
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
    n_planned, *, max_samples: int | None, tol: np.ndarray, advice: str, tolerance: str | None = None,
    limit: str | None = None,
) -> None:
    """Raise :class:`~rough_uq.errors.PlanTooLargeError` for a plan of more than ``max_samples`` samples in all.

    ``n_planned`` are the samples per level; ``advice`` ends the message (what
    to change); ``tolerance`` and ``limit`` name the tolerance and the limit in it (default ``tol`` and its values,
    ``max_samples = N``). ``max_samples`` None: no limit.
    """
    total = float(np.sum(n_planned))
    if max_samples is not None and total > max_samples:
        raise PlanTooLargeError(
            n_planned=n_planned, total=total, max_samples=max_samples, tol=np.ravel(tol), advice=advice,
            tolerance=tolerance, limit=limit,
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


def _root_sum_squares(values: np.ndarray) -> np.ndarray:
    """``sqrt(sum(values^2, axis=0))`` in units of the largest: no squares that overflow (errors of 1e200); an
    infinite value gives ``inf``."""
    scaled, scale = scaled_by_largest(values)
    finite = np.isfinite(scale)
    return np.where(finite, np.sqrt(np.sum(scaled**2, axis=0)) * np.where(finite, scale, 0.0), scale)
