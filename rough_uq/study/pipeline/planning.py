"""Before an estimation run: tolerances, plans, forecasts, budgets and the choice between MC and MLMC.

:func:`parse_tolerances` reads ``--tol`` values, :func:`forecast_run` predicts a run's samples, cost and time from
the screening, :func:`choose_method` picks the cheaper of MC and MLMC, :func:`check_initial_samples` and the budget
checks refuse what cannot run. Nothing here computes a sample.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np

from rough_uq.study.config import StudyConfig
from rough_uq.errors import PLANNED_COUNT_CAP, EstimationError, InvalidParameterError
from rough_uq.multilevel.drivers import (
    MAX_PLANNED_SAMPLES, PlanUpdated, refuse_large_plan, starting_forecast, starting_plan,
)
from rough_uq.study.progress import format_duration
from rough_uq.study.records import Forecast, ScreeningRecord, read_screening_record
from rough_uq.problem.columns import column_of_load, tol_text
from rough_uq.problem.runs import run_id, unreachable_text
from rough_uq.problem.sampler import ContactModel, modelled_cost, run_stage
from rough_uq.multilevel.allocation import MAX_TOL, MIN_TOL, TOL_RANGE_TEXT, Plan, fine_cost_share, plan
from rough_uq.multilevel.rates import Rates, fit_rates, stalled_bias, stalled_text
from rough_uq.multilevel.statistics import EstimationWarning, LevelStatistics
from rough_uq.study.pipeline.screening import screening_statistics, study_planning_rates
from rough_uq.study.pipeline.studies import Study, build_model, naming_source


#: What a ``--tol`` / ``--tol-var`` value may be (the CLI's pre-check says the same).
_TOLERANCE_FORM = ("EPS or NAME=EPS, comma-separated, e.g. 0.2 or contact_area=0.2 (no empty item, no '=' without "
                   "a name)")


def parse_tolerances(
    values: Sequence[str] | None, config: StudyConfig, *, option: str = "--tol", use_config: bool = True
) -> np.ndarray:
    """Tolerances per column from ``--tol`` values (``EPS`` or ``NAME=EPS``), falling back to the config's.

    A bare number is allowed only for a single QoI (with a load curve: for
    each of its load columns). With a load curve, ``NAME`` may be a QoI (its
    tolerance for every load) or one column ``QOI@LOAD``, which takes
    precedence. Raises :class:`~rough_uq.errors.InvalidParameterError` naming
    ``option`` and what is wrong, also for an empty value or list item (``""``,
    ``"0.2,"``, ``" , "``: never read as "not given") and for ``=EPS`` without
    a name. ``use_config=False`` (``--tol-var``, whose unit is the QoI's
    squared) ignores the config's ``qoi.<name>.tol``. ``values`` None or
    empty: no tolerance given, every one from the config.
    """
    given = _given_tolerances(values, config, option=option)
    tol, missing = [], []
    for column, name, settings in config.qoi_columns:
        configured = getattr(settings, "tol", None) if use_config else None
        eps = given.get(column, given.get(name, configured))
        if eps is None and name not in missing:
            missing.append(name)
        tol.append(eps)
    if missing:  # every one at once: a study of three QoIs named one per attempt
        where = " (or set qoi.NAME.tol in the config)" if use_config else ""
        wanted = " ".join(f"{option} {name}=EPS" for name in missing)
        raise InvalidParameterError(option, None, f"a tolerance for every QoI: give {wanted}{where}",
                                    text=f"{option}: no tolerance for {', '.join(missing)}; give {wanted}{where}")
    return np.array(tol, dtype=float)


def _given_tolerances(values: Sequence[str] | None, config: StudyConfig, *, option: str) -> dict[str, float]:
    """The tolerances ``values`` give (:func:`parse_tolerances`), by QoI or column name (a bare EPS: the one QoI's)."""
    columns = config.qoi_columns
    names = tuple(config.qoi) + tuple(column for column, _, _ in columns if column not in config.qoi)
    given: dict[str, float] = {}
    for text in values or ():
        for part in str(text).split(","):
            part = part.strip()
            name, sep, number = part.rpartition("=")
            if not part or (sep and not name):
                raise InvalidParameterError(option, text, _TOLERANCE_FORM)
            if not name:
                if len(config.qoi) != 1:
                    raise InvalidParameterError(
                        option, part, f"NAME=EPS pairs, one per QoI ({', '.join(config.qoi)}), with several QoIs"
                    )
                name = next(iter(config.qoi))
            name = column_of_load(name, names)
            if name not in names:
                raise InvalidParameterError(option, part, f"a QoI of this study: {', '.join(names)}")
            try:
                eps = float(number)
            except ValueError:
                raise InvalidParameterError(option, part, "a positive number, e.g. 0.2 or contact_area=0.2") from None
            if not (math.isfinite(eps) and eps > 0):
                raise InvalidParameterError(option, part, "a positive, finite number")
            if not MIN_TOL <= eps <= MAX_TOL:
                raise InvalidParameterError(option, part, f"a tolerance {TOL_RANGE_TEXT}")
            if name in given:
                raise InvalidParameterError(option, part, f"one tolerance per QoI; {name} was already given "
                                            f"{given[name]:g}")
            given[name] = eps
    return given


def _refuse_stalled_bias(config: StudyConfig, statistics: LevelStatistics, rates: Rates) -> None:
    """Refuse a run planned from a screening whose fitted bias of a QoI does not decay (``alpha <= 0``).

    The planning rates are floored (:func:`~rough_uq.multilevel.drivers.planning.planning_rates`) and would plan
    one all the same, on a bias model the screening contradicts.
    """
    stalled = stalled_bias(config.qoi_names, rates, statistics)
    if stalled:
        finer = _finer_screening(config, len(statistics.levels))
        raise EstimationError(
            f"{stalled_text(stalled)}, so no finest grid can be chosen for a tolerance: screen finer grids ({finer}), "
            "or use `roughuq mc --level L` (bias not estimated)"
        )


def _estimation_plan(study: Study, tol: np.ndarray, *, method: str) -> tuple[LevelStatistics, Rates, Plan]:
    """The screening's statistics and fitted rates, and the plan the run of ``method`` starts from.

    The plan uses the rates floored as the runs use them
    (:func:`~rough_uq.multilevel.drivers.planning.planning_rates`).
    """
    statistics, _ = screening_statistics(study)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EstimationWarning)
        rates = fit_rates(statistics, names=study.config.qoi_names)
        planned = study_planning_rates(study, statistics)
    _refuse_stalled_bias(study.config, statistics, rates)
    return statistics, rates, _run_plan(study.config, tol, planned, statistics, method=method)


def _screened_seconds_per_cost(screening: ScreeningRecord | None) -> float:
    """CPU-seconds per reference second of modelled cost measured by the screening (1 without one)."""
    return float((screening.seconds_per_cost if screening is not None else None) or 1.0)


def _run_plan(
    config: StudyConfig, tol: np.ndarray, rates: Rates, statistics: LevelStatistics, *, method: str,
    richardson: bool | None = None,
) -> Plan:
    """The screening plan of a run: MLMC's starting plan (its coarsest level included), MC's finest level."""
    options = dict(tol=tol, rates=rates, statistics=statistics, theta=config.estimation.theta,
                   max_level=config.grid.max_level, qoi_names=config.qoi_names)
    if method != "mlmc":
        return plan(**options, coarsest_level=None)
    richardson = bool(config.estimation.richardson) if richardson is None else richardson
    return starting_plan(**options, richardson=richardson)


#: Without ``--max-cost``, plans predicted to take longer than this (CPU-seconds of samples) are refused.
DEFAULT_COST_CEILING = 7 * 24 * 3600.0


def _finer_screening(config: StudyConfig, n_screened: int) -> str:
    """How to screen finer grids: more levels extend this study while the grids allow them, else a new study.

    ``n_screened`` is the number of levels screened (the screening record's: a study screened again with more
    levels keeps the screening section of the config it was created with).
    """
    max_level = config.grid.max_level
    if n_screened <= max_level:
        return (f"raise screening.levels, up to grid.max_level + 1 = {max_level + 1}, and run `roughuq screen` again "
                "on this study, which extends its screening; or start a new study with a larger grid.coarsest")
    return ("every level up to grid.max_level is screened: start a new study with a larger grid.coarsest or "
            "grid.max_level")


def forecast_run(
    study: Study, *, method: str, tol: np.ndarray, max_cost: float | None = None, level: int | None = None,
    n_workers: int = 1, richardson: bool | None = None,
) -> Forecast | None:
    """Predict a run from the screening, or refuse it before its first sample.

    Refused (:class:`~rough_uq.errors.EstimationError`, naming what to
    change): a tolerance whose bias ``grid.max_level`` cannot reach (the
    message gives the smallest reachable tolerance), a predicted modelled cost
    above ``max_cost``, without ``max_cost`` a plan beyond
    :data:`DEFAULT_COST_CEILING` CPU-seconds, and any plan of more than
    :data:`MAX_PLANNED_SAMPLES` samples. ``mc --level`` without a screening
    (or with one whose bias does not decay) predicts nothing (None).
    ``richardson`` (default: the config's ``estimation.richardson``) plans
    the Richardson-extrapolated MLMC estimate where the screening allows it.
    """
    _check_run_arguments(study, method, level)
    config = study.config
    tol = np.asarray(tol, dtype=float)
    screening = read_screening_record(study.store)
    is_given_level = method == "mc" and level is not None
    if is_given_level and screening is None:
        return None
    with np.errstate(all="ignore"):
        statistics, _ = screening_statistics(study)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", EstimationWarning)
            rates = fit_rates(statistics, names=config.qoi_names)
        if is_given_level and stalled_bias(config.qoi_names, rates, statistics):
            return None  # MC on a given level needs no bias model, and there is none to predict from
        _refuse_stalled_bias(config, statistics, rates)
        rates = study_planning_rates(study, statistics)  # floored, as the run plans
        prediction = _run_plan(config, tol, rates, statistics, method=method, richardson=richardson)
        if not prediction.is_bias_met and not is_given_level:
            raise _unreachable(config, tol, prediction, n_screened=int(np.min(statistics.n_samples)))
        finest, counts, costs = _planned_samples(method, level, prediction, rates,
                                                 n_initial=config.estimation.initial_samples)
    seconds_per_cost = _screened_seconds_per_cost(screening)
    forecast = _forecast(config, finest=finest, counts=counts, modelled=float(np.dot(counts, costs)),
                         seconds_per_cost=seconds_per_cost, n_workers=n_workers,
                         is_richardson=bool(prediction.is_richardson), richardson_note=prediction.richardson_note)
    _check_budget(config.qoi_names, tol, forecast, max_cost)
    levels = [finest] if method == "mc" else range(len(counts))
    stored = _stored_counts(study, method, tol, level, richardson, dict(zip(levels, counts)))
    if not any(stored):
        return forecast
    return replace(forecast, n_stored=stored, stored_cost=float(np.dot(stored, costs)))


#: How a command-line run's refusals name the limit of its plans (:class:`~rough_uq.errors.PlanTooLargeError`'s
#: ``limit``): ``max_samples`` is an argument of the Python API, which no roughuq command takes.
RUN_PLAN_LIMIT = f"the {MAX_PLANNED_SAMPLES:.0e} samples a roughuq run may plan"


def _refusing_large_plans(events: Iterator[object], names: Sequence[str], tol: np.ndarray) -> Iterator[object]:
    """``events``, refused (:class:`~rough_uq.errors.PlanTooLargeError`) at a plan of more than MAX_PLANNED_SAMPLES.

    The forecast checks a run's first plan only. The plans that follow come
    from the run's own samples: after the initial samples of ``mc --level``
    a tight ``--tol`` asked for some 1e10 samples (an ETA of years), and on a
    study in full contact, whose mean gap is rounding noise, ``mc --tol`` at a
    tolerance the screening called cheap re-planned some 2.7e7 samples; both
    runs began to draw them.
    """
    try:
        for event in events:
            if isinstance(event, PlanUpdated):
                refuse_large_plan(event.n_planned, max_samples=MAX_PLANNED_SAMPLES, tol=tol, advice="loosen --tol",
                                  tolerance=f"--tol {tol_text(names, tol, digits=3)}", limit=RUN_PLAN_LIMIT)
            yield event
    finally:
        events.close()


def check_initial_samples(config: StudyConfig, *, n_levels: int, run: str, source: str | None = None) -> None:
    """Refuse ``estimation.initial_samples`` whose samples on ``n_levels`` levels alone exceed MAX_PLANNED_SAMPLES.

    A run without a screening (``run``: ``mc --level``, or a variance or cdf
    run) starts with that many samples on each of its first levels, whatever
    the tolerance; before this check ``initial_samples: 100000000`` began a
    run of some 80 hours on the quickstart's level 1. ``source`` (the
    config's file) is named first in the refusal (:func:`naming_source`).
    """
    n_initial = config.estimation.initial_samples
    if n_initial * n_levels > MAX_PLANNED_SAMPLES:
        where = "its level" if n_levels == 1 else f"each of its first {n_levels} levels"
        with naming_source(source):
            raise InvalidParameterError(
                "estimation.initial_samples", n_initial,
                f"an integer <= {MAX_PLANNED_SAMPLES // n_levels} for {run} (it starts with that many samples on "
                f"{where}; at most {MAX_PLANNED_SAMPLES} samples in all)",
            )


def _unreachable(config: StudyConfig, tol: np.ndarray, prediction: Plan, *, n_screened: int) -> EstimationError:
    """The refusal of a tolerance whose bias the finest allowed grid cannot reach, with the smallest reachable one.

    That tolerance comes from the screening's ``n_screened`` samples per level: a run estimates the bias from its
    own samples and may find it larger, which the message says (on the quickstart study, 20 samples per level,
    runs at tol 0.03 and 0.04 found 0.06 and 0.08 where the screening predicted 0.012).
    """
    max_level = config.grid.max_level
    return EstimationError(unreachable_text(
        config.qoi_names, tol, prediction, tol_name="--tol", level_name="grid.max_level", max_level=max_level,
        grid=config.grid.n_at(max_level), n_screened=n_screened,
        advice=" (a run estimates the bias from its own samples and may find it larger: then it stops at "
        "grid.max_level, tolerance not met); or screen a study with a larger grid.max_level",
    ))


def _planned_samples(
    method: str, level: int | None, prediction: Plan, rates: Rates, *, n_initial: int
) -> tuple[int, tuple[int, ...], tuple[float, ...]]:
    """Finest level, samples per level (at least 2 each) and the modelled cost of one sample of each.

    ``mc --level`` starts with ``n_initial`` samples (``estimation.initial_samples``) whatever the screening
    predicts: its forecast counts them at least (it said N 3 for a run that drew 10, and a ``--max-cost`` set on
    it stopped the run before its initial samples were drawn).
    """
    if method == "mc":
        finest = prediction.finest_level if level is None else int(level)
        least = 2 if level is None else max(n_initial, 2)
        counts = (max(int(prediction.mc_n_samples), least),)
        fine_cost = prediction.mc_cost / max(prediction.mc_n_samples, 1)
        if level is not None:  # the fine solve's share of a coupled sample, as for the level MC plans (allocation)
            coupled = rates.cost_model(finest) if finest > prediction.finest_level else prediction.costs[finest]
            fine_cost = coupled * fine_cost_share(rates.cost_rate_at(finest), finest)
        return finest, counts, (float(fine_cost),)
    # What the run asks for first: nothing below the plan's coarsest level, two levels above it at least.
    counts, costs = starting_forecast(prediction, rates)
    return len(counts) - 1, counts, costs


def _stored_counts(study: Study, method: str, tol: np.ndarray, level: int | None, richardson: bool | None,
                   counts: dict[int, int]) -> tuple[int, ...]:
    """How many of the first ``counts[l]`` samples of each level the run would find stored (merged shards).

    Counted from the stored indices (unique per stage and level), not from the planned ones: a plan may ask for
    millions.
    """
    estimation = study.config.estimation
    richardson = bool(estimation.richardson) if richardson is None else richardson
    key = run_id(method, study.config.qoi_names, tol, estimation.theta, level, richardson=richardson)
    stage = run_stage(method, key)
    return tuple(int(np.count_nonzero(study.store.read_samples(level=lv, stage=stage).indices < n))
                 for lv, n in counts.items())


def _forecast(
    config: StudyConfig, *, finest: int, counts: tuple[int, ...], modelled: float, seconds_per_cost: float,
    n_workers: int, is_richardson: bool, richardson_note: str = "",
) -> Forecast:
    from rough_uq.study.config import solver_memory_bytes

    cpu_seconds = modelled * seconds_per_cost
    n_workers = max(1, int(n_workers))
    return Forecast(
        finest_level=int(finest),
        grid=config.grid.n_at(int(finest)),
        n_samples=counts,
        modelled_cost=modelled,
        cpu_seconds=cpu_seconds,
        wall_seconds=cpu_seconds / min(n_workers, max(sum(counts), 1)),
        memory_bytes=solver_memory_bytes(config.grid.n_at(int(finest))) * n_workers,
        is_richardson=is_richardson,
        richardson_note=richardson_note,
    )


def _check_budget(names: Sequence[str], tol: np.ndarray, forecast: Forecast, max_cost: float | None) -> None:
    """Refuse a forecast of more than :data:`MAX_PLANNED_SAMPLES` samples, over ``max_cost``, or (without it) over
    :data:`DEFAULT_COST_CEILING`."""
    total, modelled, cpu_seconds = sum(forecast.n_samples), forecast.modelled_cost, forecast.cpu_seconds
    asked = tol_text(names, tol, digits=3)
    if total > MAX_PLANNED_SAMPLES or not math.isfinite(modelled):
        # A level planned at the planners' cap needs more than the count says (as PlanTooLargeError words it).
        amount = "more than" if max(forecast.n_samples) >= PLANNED_COUNT_CAP else "about"
        raise EstimationError(
            f"--tol {asked} needs {amount} {total:.3g} samples ({format_duration(cpu_seconds)} "
            f"CPU), more than the {MAX_PLANNED_SAMPLES:.0e} a roughuq run may plan (whatever --max-cost): loosen --tol"
        )
    if max_cost is not None and modelled > max_cost:
        raise EstimationError(
            f"--tol {asked} is predicted to cost {modelled:.3g} reference seconds of modelled cost, "
            f"more than --max-cost {max_cost:g}: loosen --tol or raise --max-cost"
        )
    if max_cost is None and cpu_seconds > DEFAULT_COST_CEILING:
        raise EstimationError(
            f"--tol {asked} is predicted to take {format_duration(cpu_seconds)} of CPU time "
            f"({total} samples), more than the default ceiling of {format_duration(DEFAULT_COST_CEILING)}: "
            "loosen --tol, or allow it with --max-cost SECONDS"
        )


@dataclass(frozen=True)
class MethodChoice:
    """What ``roughuq mlmc --method auto`` runs, and why.

    Attributes
    ----------
    method : {"mlmc", "mc"}
        The estimator.
    richardson : bool
        Richardson-extrapolated MLMC.
    reason : str
        The predicted modelled cost of each candidate, or why it was left out.
    """

    method: str
    richardson: bool
    reason: str


def choose_method(study: Study, *, tol: np.ndarray, max_cost: float | None = None) -> MethodChoice:
    """The cheapest of MLMC, Richardson-extrapolated MLMC and plain MC as predicted by the screening.

    Each candidate is forecast with :func:`forecast_run`; one it refuses (a
    tolerance out of reach, a cost over ``max_cost``) or, for Richardson, one
    whose screened level means do not allow extrapolation is left out, and the
    reason says so. Raises :class:`~rough_uq.errors.EstimationError` when no
    candidate remains (with the refusal of plain MLMC).
    """
    candidates = (("MLMC", "mlmc", False), ("Richardson-extrapolated MLMC", "mlmc", True), ("MC", "mc", False))
    costs, notes, first_refusal = [], [], None
    for name, method, richardson in candidates:
        try:
            forecast = forecast_run(study, method=method, tol=tol, max_cost=max_cost, richardson=richardson)
        except EstimationError as exc:
            first_refusal = first_refusal or exc
            notes.append(f"{name} left out ({exc})")
            continue
        if forecast is None or (richardson and not forecast.is_richardson):
            notes.append(f"{name} left out (the screened level means do not allow extrapolation)")
            continue
        costs.append((forecast.modelled_cost, name, method, richardson))
    if not costs:
        raise first_refusal or EstimationError("no estimator can be predicted from the screening")
    cost, name, method, richardson = min(costs)
    others = [f"{other} {other_cost:.3g} ref-s" for other_cost, other, _, _ in costs if other != name]
    reason = f"{name}, predicted {cost:.3g} ref-s (modelled cost)"
    if others:
        reason += "; " + ", ".join(others)
    if notes:
        reason += "; " + "; ".join(notes)
    return MethodChoice(method=method, richardson=richardson, reason=reason)


def _check_run_arguments(study: Study, method: str, level: int | None) -> None:
    if method not in ("mlmc", "mc"):
        raise ValueError(f"method must be 'mlmc' or 'mc', got {method!r}")
    max_level = study.config.grid.max_level
    if level is not None and method != "mc":
        raise InvalidParameterError("--level", level, "nothing: a level is given to mc only")
    if level is not None and not 0 <= level <= max_level:
        raise InvalidParameterError("--level", level, f"an integer in 0..{max_level} (grid.max_level)")
    if level is not None:
        check_initial_samples(study.config, n_levels=1, run="mc --level", source=study.source)


def _check_initial_budget(
    config: StudyConfig, levels: Sequence[int], *, max_cost: float | None, model: ContactModel | None, without: str,
    source: str | None = None,
) -> None:
    """Refuse a budget below the least modelled cost of ``estimation.initial_samples`` on each of ``levels``.

    The least cost is that of solves that need no iteration at all.
    ``max_cost`` None takes ``estimation.max_cost`` (so named in the
    message); no budget at all passes. ``without`` says what the run lacks
    without those samples. ``source`` (the config's file) is named first
    where the budget is ``estimation.max_cost``.
    """
    option = "estimation.max_cost" if max_cost is None else "--max-cost"
    where_given = f"{source}: " if source is not None and max_cost is None else ""
    max_cost = config.estimation.max_cost if max_cost is None else max_cost
    if max_cost is None:
        return
    model = build_model(config, source=source) if model is None else model
    n_initial = config.estimation.initial_samples
    no_iterations = np.zeros((1, 2))
    least = n_initial * sum(float(modelled_cost(model, level, no_iterations)[0]) for level in levels)
    if max_cost < least:
        where = f"level {levels[0]}" if len(levels) == 1 else f"levels {levels[0]}..{levels[-1]}"
        raise EstimationError(
            f"{where_given}{option} {max_cost:g} is too small for the initial samples of {where} "
            f"({n_initial}{' each' if len(levels) > 1 else ''}), "
            f"which cost at least {least:.3g} reference seconds of modelled cost (even if every solve converged at "
            f"once); without them {without}: raise {option} (or lower estimation.initial_samples)"
        )
