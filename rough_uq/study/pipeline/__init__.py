"""The study pipeline: config + store + executor -> screening and estimation runs.

This is the only part of roughuq that reads the config and meets the store. Its modules, in the order in which
they build on each other (each imports only those before it):

* :mod:`~rough_uq.study.pipeline.studies`: the :class:`~rough_uq.problem.sampler.ContactModel` of a config
  (:func:`build_model`, with the load and unit conversions of :mod:`rough_uq.problem.loads`) and the study files
  (:func:`create_study`, :func:`open_existing_study`, the :class:`Study` they give);
* :mod:`~rough_uq.study.pipeline.sampling`: the sampler backed by the study file (:class:`StudySampler`): samples
  already stored are read back, missing ones are computed by the executor and appended as they arrive, so an
  interrupted run loses at most a few seconds of work and its rerun replays the same decisions;
* :mod:`~rough_uq.study.pipeline.diagnostics`: the warnings of the multilevel core (``EstimationWarning``)
  collected into the records' diagnostics, never passed on as warnings;
* :mod:`~rough_uq.study.pipeline.screening`: the screening (:func:`run_screening`);
* :mod:`~rough_uq.study.pipeline.planning`: tolerances, forecasts, budgets and the choice of method before a run;
* :mod:`~rough_uq.study.pipeline.estimation`: MLMC / MC runs of the mean (:func:`run_estimation`) and the samples
  a run still needs (:func:`missing_samples`);
* :mod:`~rough_uq.study.pipeline.target_runs`: MLMC runs of the variance and of a distribution function with
  quantiles (:func:`run_target`, the targets of :mod:`rough_uq.multilevel.targets`);
* :mod:`~rough_uq.study.pipeline.shards`: samples computed elsewhere and merged (:func:`compute_shard`,
  :func:`merge_shards`);
* :mod:`~rough_uq.study.pipeline.sweep`: one study per value of a config field (:func:`run_sweep`).

Runs store their records, the typed records of :mod:`rough_uq.study.records`. Cost used for planning is the
modelled cost of :mod:`rough_uq.problem.sampler` (reference seconds, independent of the process that computed a
sample); the records carry both it and the measured wall time. The names below are the pipeline's interface to
the CLI and the Python API; names with a leading underscore are private to the package. A name is looked up in
the submodule that defines it: a test that replaces one (``monkeypatch.setattr``) patches that submodule (or each
submodule that imports it), since setting it on the package changes no caller inside.
"""

from __future__ import annotations

from rough_uq.problem.distribution import TARGETS
from rough_uq.problem.runs import run_id
from rough_uq.study.records import Forecast
from rough_uq.study.pipeline.studies import (
    Study, build_model, create_study, load_problem, naming_source, open_existing_study, problem_of_config,
    removed_if_left_unused,
)
from rough_uq.study.pipeline.sampling import FLUSH_SECONDS, StudySampler
from rough_uq.study.pipeline.screening import (
    PREDICTION_FACTORS, ScreeningOutcome, load_screening, run_screening, screening_statistics,
)
from rough_uq.study.pipeline.planning import (
    MethodChoice, check_initial_samples, choose_method, forecast_run, parse_tolerances,
)
from rough_uq.study.pipeline.estimation import WorkPlan, index_ranges, missing_samples, run_estimation
from rough_uq.study.pipeline.target_runs import (
    CdfRequest, cdf_request, check_target_budget, check_target_run, run_target, target_run_id,
)
from rough_uq.study.pipeline.shards import compute_shard, merge_shards
from rough_uq.study.pipeline.sweep import SweepRow, run_sweep

__all__ = [
    "FLUSH_SECONDS",
    "PREDICTION_FACTORS",
    "Study",
    "StudySampler",
    "build_model",
    "problem_of_config",
    "load_problem",
    "load_screening",
    "create_study",
    "removed_if_left_unused",
    "open_existing_study",
    "parse_tolerances",
    "run_screening",
    "run_estimation",
    "run_target",
    "check_initial_samples",
    "check_target_budget",
    "check_target_run",
    "target_run_id",
    "cdf_request",
    "CdfRequest",
    "TARGETS",
    "screening_statistics",
    "missing_samples",
    "WorkPlan",
    "index_ranges",
    "run_id",
    "compute_shard",
    "merge_shards",
    "naming_source",
    "run_sweep",
    "ScreeningOutcome",
    "SweepRow",
    "Forecast",
    "MethodChoice",
    "choose_method",
    "forecast_run",
]
