"""The study pipeline: config + store + executor -> screening and estimation runs.

This is the only module that reads the config and meets the store. It

* builds the :class:`~rough_uq.problem.sampler.ContactModel` of a config
  (:func:`build_model`) with the load and unit conversions of
  :mod:`rough_uq.problem.loads` (a relative load is ``relative * E* *
  rms_slope``, SPEC section 6; ``percent`` scales fractions by 100,
  ``per_area`` divides cluster counts by ``L^2``);
* serves the estimators a sampler backed by the study file
  (:class:`StudySampler`): samples already stored are read back, missing ones
  are computed by the executor and appended as they arrive (at least every
  :data:`FLUSH_SECONDS`, and at the end of each batch the estimator asks for),
  so an interrupted run loses at most a few seconds of work and its rerun
  replays the same decisions from the stored samples;
* runs the screening (:func:`run_screening`), MLMC / MC estimation runs of
  the mean (:func:`run_estimation`) and MLMC runs of the variance and of a
  distribution function with quantiles (:func:`run_target`, the targets of
  :mod:`rough_uq.multilevel.targets`), and stores their records, the typed records of
  :mod:`rough_uq.study.records`; the warnings of the multilevel core
  (``EstimationWarning``) are collected here into the records' diagnostics,
  never passed on as warnings.

Cost used for planning is the modelled cost of :mod:`rough_uq.problem.sampler`
(reference seconds, independent of the process that computed a sample); the
records carry both it and the measured wall time.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shlex
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import yaml

from rough_uq import __version__
from rough_uq.study.config import (
    StudyConfig, SurfaceConfig, config_differences, config_from_stored_text, config_hash, load_config, resolved_yaml,
)
from rough_uq.errors import (
    PLANNED_COUNT_CAP,
    ConfigError,
    EstimationError,
    InvalidParameterError,
    PlanTooLargeError,
    RoughUQError,
    StudyFileError,
    checked_path,
    is_real_number,
)
from rough_uq.multilevel.drivers import (
    MAX_PLANNED_SAMPLES,
    BatchDone,
    Finished,
    PlanUpdated,
    RichardsonRefused,
    iter_mc,
    iter_mlmc,
    planning_rates,
    refuse_large_plan,
    starting_forecast,
    starting_plan,
)
from rough_uq.study.executors import Executor, SerialExecutor
from rough_uq.study.fft_wisdom import prepare_wisdom
from rough_uq.study.progress import PrefixedProgress, Progress, format_duration
from rough_uq.study.records import (
    Diagnostic,
    DistributionRecord,
    DroppedLevel,
    Forecast,
    LevelTable,
    PlanRecord,
    QuantileRecord,
    RatesRecord,
    RunOutcome,
    RunRecord,
    ScreeningRecord,
    count_not_converged,
    read_run_records,
    read_screening_record,
    utc_timestamp,
)
from rough_uq.problem.columns import column_of_load, tol_number, tol_text
from rough_uq.problem.contact import ContactProblem
from rough_uq.problem.loads import AbsoluteLoad, RelativeLoad
from rough_uq.multilevel.distribution import cdf_level_term, quantiles
from rough_uq.multilevel.moments import variance_level_term
from rough_uq.problem.distribution import DEFAULT_PROBABILITIES, TARGETS, estimate_target, initial_finest_level
from rough_uq.problem.runs import (
    MIN_SCREENED_LEVELS, ScreeningResult, exact_column_caveats, run_id, screening_of_batches, unreachable_text,
)
from rough_uq.problem.sampler import (
    STAGE_SCREENING,
    ContactModel,
    LevelBatch,
    is_coupled_stage,
    measured_seconds_per_cost,
    modelled_cost,
    run_stage,
)
from rough_uq.multilevel.allocation import MAX_TOL, MIN_TOL, TOL_RANGE_TEXT, Plan, plan
from rough_uq.multilevel.rates import (
    Rates, choose_coarsest_level, fit_rates, refuse_constant_columns, stalled_bias, stalled_text,
)
from rough_uq.multilevel.statistics import EstimationWarning, LevelStatistics, diagnose, level_statistics
from rough_uq.study.store import (
    StudyFile, StudyStore, checked_study_path, is_hdf5_file, open_study, open_study_readonly, remove_abandoned,
    shard_refusal,
)
from rough_uq.physics.surface import SurfaceSpectrum

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

#: Longest time computed samples wait in memory before they are written.
FLUSH_SECONDS = 2.0
#: Tolerances of the screening's cost predictions, as multiples of the base tolerance.
PREDICTION_FACTORS = (2.0, 1.0, 0.5, 0.25, 0.125)


# ---------------------------------------------------------------------------
# Study = config + store + model
# ---------------------------------------------------------------------------


#: The config field of each parameter of :class:`~rough_uq.physics.surface.SurfaceSpectrum`.
_SURFACE_FIELDS = {
    "system_size": "surface.system_size",
    "rms_height": "surface.rms_height",
    "hurst": "surface.hurst",
    **{k: f"surface.wavenumbers.{k}" for k in ("k_l", "k_r", "k_s")},
}


def _spectrum(surface: SurfaceConfig) -> SurfaceSpectrum:
    """The spectrum of a config's ``surface``; its refusals name the config's fields (``surface.rms_height``)."""
    try:
        return SurfaceSpectrum(
            system_size=surface.system_size,
            k_l=surface.k_l,
            k_r=surface.k_r,
            k_s=surface.k_s,
            hurst=surface.hurst,
            rms_height=surface.rms_height,
        )
    except InvalidParameterError as error:
        names = ", ".join(_SURFACE_FIELDS.get(name, name) for name in error.name.split(", "))
        raise InvalidParameterError(names, error.value, error.allowed) from None


def build_model(config: StudyConfig, *, source: str | None = None) -> ContactModel:
    """The contact model (surface, load, solver, QoIs) of a study config, checked before any solve.

    Every load is checked as a :class:`~rough_uq.problem.contact.ContactProblem`
    checks it (:func:`~rough_uq.problem.contact.checked_mean_pressures` on the
    finest grid, ``grid.max_level``): a mean pressure that overflows, or a
    dimensionless load outside the solver's range within a margin, is refused
    naming the config field (``load.relative``, ``load.absolute``, or
    ``load.relative.1`` in a load curve). Every path that opens a study builds
    its model here, so none of them can start a study no solve would take.

    ``source`` names where the config comes from (its file, or a sweep's
    ``--set KEY=VALUE``): a refusal then names it first, as
    :func:`~rough_uq.study.config.load_config` names the file in its errors
    (``bad.yaml: surface.rms_height, surface.system_size: got ...``), so that
    a loop over config files says which one is wrong.

    Raises
    ------
    InvalidParameterError
        Without ``source``: a load no solve takes, or a spectrum that cannot
        be built (e.g. a slope variance ``m2`` outside the float range),
        naming the config field.
    ConfigError
        With ``source``: the same refusal, ``<source>: <field>: got ...``
        (the :class:`InvalidParameterError` is its ``__cause__``).
    """
    with naming_source(source):
        return _model(config)


@contextmanager
def naming_source(source: str | None) -> Iterator[None]:
    """Refusals of a config's fields in the block name ``source``, where the config comes from, first.

    An :class:`InvalidParameterError` raised in the block becomes a
    :class:`ConfigError` ``<source>: <field>: got ...`` (the refusal is its
    ``__cause__``), as :func:`~rough_uq.study.config.load_config` names the
    file in its errors. The block must refuse only the config's fields (not
    command-line options). ``source`` None: refusals pass unchanged.
    """
    if source is None:
        yield
        return
    try:
        yield
    except InvalidParameterError as error:
        raise ConfigError(f"{source}: {error}") from error


def _model(config: StudyConfig) -> ContactModel:
    """:func:`build_model` without a source: its refusals name only the config field.

    The model of :func:`problem_of_config`'s problem: the CLI's samples and the Python API's are built by one
    mapping of the config.
    """
    return problem_of_config(config).model


def problem_of_config(config: StudyConfig) -> ContactProblem:
    """The :class:`~rough_uq.problem.contact.ContactProblem` of a study config: the same samples from Python.

    Every field that decides a sample is taken over (surface, load or load
    curve, grids up to ``grid.max_level``, QoIs with their units and
    settings, solver, seed), so that ``problem.model`` equals
    :func:`build_model`'s (FFT wisdom aside). The estimation settings
    (tolerances, ``theta``, the screening's size) are arguments of the run
    functions instead (``rough_uq.mlmc(problem, tol=...)``).
    """
    kind = RelativeLoad if config.load.kind == "relative" else AbsoluteLoad
    loads = tuple(kind(value) for value in config.load.values)
    settings = dict(config.qoi)
    clusters, above, area = settings.get("clusters"), settings.get("area_above"), settings.get("contact_area")
    return ContactProblem(
        _spectrum(config.surface),
        load=loads[0] if len(loads) == 1 else loads,
        qoi=list(settings),
        coarsest=config.grid.coarsest,
        units={name: qoi.unit for name, qoi in settings.items() if hasattr(qoi, "unit")},
        e_star=config.material.e_star,
        max_level=config.grid.max_level,
        projection=config.grid.projection,
        connectivity=4 if clusters is None else clusters.connectivity,
        area_estimator="corrected" if area is None else area.estimator,
        critical_pressure=None if above is None else above.critical_pressure,
        seed=config.seed,
        solver_tol=config.solver.tol,
        max_iter=config.solver.max_iter,
        warm_start=config.solver.warm_start,
        threads=config.solver.threads,
    )


def load_problem(path: str | os.PathLike[str]) -> ContactProblem:
    """The contact problem of a config file or of a study file (its stored config), for the Python API.

    ``path`` names a YAML config (as ``roughuq screen`` takes it) or a study
    file (HDF5, as ``roughuq screen`` writes it); :func:`problem_of_config`
    says what is taken over: the samples, not the estimation settings. A run
    on it draws the samples ``roughuq`` draws for that config (the same
    numbers where FFTs are planned alike, ``ROUGHUQ_FFTW_WISDOM=estimate``);
    it makes the same choices from the same screening (:func:`load_screening`)
    and settings (``n_initial=`` the config's ``estimation.initial_samples``,
    ``theta``, ...). ``dataclasses.replace(problem, max_level=5)`` changes a
    field.

    Raises
    ------
    ConfigError
        For a config file that cannot be read or is invalid, and a setting the problem refuses (e.g. a load no
        solve takes): one line per problem, ``<file>: <field>: ...``.
    StudyFileError
        For a study file that cannot be read (a path ending in ``.h5`` / ``.hdf5`` is read as a study file).
    InvalidParameterError
        For an empty path or one that does not exist.
    """
    name = checked_path("path", path)
    if not name or not Path(name).exists():
        raise InvalidParameterError("path", name, "an existing config file (YAML) or study file (HDF5)")
    if not (is_hdf5_file(name) or Path(name).suffix.lower() in (".h5", ".hdf5")):
        config = load_config(name)
        with naming_source(name):
            return problem_of_config(config)
    with open_study_readonly(name) as store:
        config = _stored_config(store)
    with naming_source(f"{name} (stored config)"):
        return problem_of_config(config)


def load_screening(path: str | os.PathLike[str]) -> ScreeningResult:
    """The screening a study file holds, as :func:`rough_uq.screen` returns it, for the Python API.

    Recomputed from the stored screening samples, as ``roughuq mlmc`` recomputes it, with the problem of
    :func:`load_problem`: ``rough_uq.mlmc(load_problem(path), tol=..., screening=load_screening(path))`` plans
    as ``roughuq mlmc --study path --tol ...`` does, without solving the screening again.

    Raises
    ------
    StudyFileError
        For an empty path and a file that is not a readable study file, or a study without a complete screening.
    EstimationError
        Where the rates cannot be fitted on the stored samples (``roughuq screen`` refused them), naming the file.
    """
    missing = ": load_screening reads the file `roughuq screen` wrote (its config's output.path)"
    with open_existing_study(path, writable=False, missing=missing) as study:
        with naming_source(f"{os.fspath(path)} (stored config)"):
            problem = problem_of_config(study.config)
        _, batches = screening_statistics(study)  # its table is computed again with the problem's model
    try:
        return screening_of_batches(problem, batches, n_not_converged=count_not_converged(batches))
    except EstimationError as error:
        raise EstimationError(f"{os.fspath(path)}: the stored screening gives no rates: {error}") from None


@dataclass
class Study:
    """An open study: its config, its store and the model of its samples (built from the config unless given).

    Building the model draws on the spectrum, whose set-up grows like ``k_s^2``
    (seconds at ``k_s`` in the thousands): a caller that has built it passes it.
    ``source`` is where ``config`` comes from when a command was given it (its
    file): the refusals of its fields then name it first (:func:`naming_source`).
    """

    config: StudyConfig
    store: StudyStore
    model: ContactModel | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        if self.model is None:
            try:
                self.model = build_model(self.config, source=self.source)
            except BaseException:
                self.store.close()  # a refused config leaves no open file behind
                raise
        self._planned: set[int] = set()

    def model_for(self, level: int, *, note: Callable[[str], None] | None = None) -> ContactModel:
        """The model, with FFTW wisdom that covers the grids of ``level`` (and its coarse grid).

        Plans are measured once per machine and grid (:mod:`rough_uq.study.fft_wisdom`)
        and travel with the model to every worker, so all use the same plans.
        ``note`` is told when plans are about to be measured.
        """
        grids = {self.model.grid(level)} | ({self.model.grid(level - 1)} if level > 0 else set())
        if not grids <= self._planned:
            self._planned |= grids
            wisdom = prepare_wisdom(sorted(self._planned), threads=self.model.threads, note=note)
            self.model = replace(self.model, fft_wisdom=wisdom)
        return self.model

    def close(self) -> None:
        self.store.close()

    def __enter__(self) -> Study:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


#: What to do about a study file of another config, in ``roughuq screen``'s terms (:func:`create_study`).
_SCREEN_REMEDY = "use another --out file or the config it was written with"


def create_study(
    config: StudyConfig, path: str | Path | None = None, *, remedy: str = _SCREEN_REMEDY,
    model: ContactModel | None = None, source: str | None = None,
) -> Study:
    """Open the study file of ``config`` for writing, creating it if missing.

    An existing file must have been created with the same config (hash of
    everything that changes numbers); otherwise :class:`StudyFileError`, whose
    message ends in ``remedy`` (what the command at hand lets the user do;
    the default names ``roughuq screen``'s ``--out``). A config whose model
    :func:`build_model` refuses is refused before the file is created: a file
    left behind would refuse the corrected config as another one. ``model``
    is the config's (:func:`build_model`, e.g. with the config file as its
    ``source``), built here if not given. ``source`` is where ``config``
    comes from (its file; :class:`Study`).
    """
    path = Path(path if path is not None else config.output.path)
    model = build_model(config, source=source) if model is None else model
    _refuse_other_config(path, config, remedy)
    store = open_study(
        path,
        config_text=resolved_yaml(config),
        config_hash=config_hash(config),
        qoi_names=config.qoi_names,
        create=True,
        code_version=__version__,
    )
    return Study(config, store, model, source)


@contextmanager
def removed_if_left_unused(path: str | Path) -> Iterator[None]:
    """Remove the study file at ``path`` if the block creates it and raises before storing anything in it.

    A command that creates its study file (``screen``, ``mlmc``/``mc
    --config``) and is then refused before its first sample (a config too
    shallow to screen, a bad ``--level`` or ``--tol``), or interrupted then,
    left an empty file behind, which refused the corrected config as "written
    by another config". A file that existed before the block, or that holds a
    sample, a screening or a run record, is kept.
    """
    path = Path(path)
    existed = path.exists()
    try:
        yield
    except BaseException:
        if not existed and path.is_file() and _is_unused(path):
            path.unlink()
        raise


def _is_unused(path: Path) -> bool:
    """Whether the study file at ``path`` holds no sample, no screening and no run record (False if unreadable)."""
    try:
        with open_study_readonly(path) as store:
            return not store.levels() and store.read_screening() is None and not store.read_runs()
    except (RoughUQError, OSError):
        return False


def _refuse_other_config(path: Path, config: StudyConfig, remedy: str) -> None:
    """Refuse an existing study file written by another config, before anything is written; ``remedy`` ends it."""
    if not path.is_file():
        return  # missing: created; anything else: open_study says what is wrong
    with open_study_readonly(path) as store:
        stored, stored_text = store.config_hash, store.config_text
    wanted = config_hash(config)
    if stored != wanted:
        stored_config = _readable_config(stored_text, source=f"{path} (stored config)")
        differences = _differences_text(stored_config, config, there="in the file", here="in this config")
        raise StudyFileError(
            f"{path} was written by another config (hash {stored[:12]}… ≠ {wanted[:12]}…{differences}); {remedy}",
            path,
        )


def _stored_config(store: StudyStore) -> StudyConfig:
    path = getattr(store, "path", "study")
    return config_from_stored_text(store.config_text, source=f"{path} (stored config)")


def _readable_config(text: str, *, source: str) -> StudyConfig | None:
    """The config stored as ``text``, or ``None`` if this version cannot read it (a refusal then names no settings)."""
    try:
        return config_from_stored_text(text, source=source)
    except RoughUQError:
        return None


#: The most differing settings a refusal of another config names (:func:`_differences_text`).
_SHOWN_DIFFERENCES = 4


def _differences_text(first: StudyConfig | None, second: StudyConfig, *, there: str, here: str) -> str:
    """``"; differs in seed: 2026 <there>, 1 <here>"`` for the settings that make the configs hash differently.

    Empty when ``first`` is ``None`` (unreadable) or no setting differs. At
    most :data:`_SHOWN_DIFFERENCES` settings are named, then how many more.
    """
    if first is None:
        return ""
    differences = config_differences(first, second)
    if not differences:
        return ""
    shown = [
        f"{key}: {_setting_text(ours)} {there}, {_setting_text(theirs)} {here}"
        for key, ours, theirs in differences[:_SHOWN_DIFFERENCES]
    ]
    more = len(differences) - _SHOWN_DIFFERENCES
    return "; differs in " + "; ".join(shown) + (f"; and {more} more setting(s)" if more > 0 else "")


def _setting_text(value: object) -> str:
    """A config value in a message: as in the YAML file, ``unset`` where the config does not have the key."""
    if value is None:
        return "unset"
    return yaml.safe_dump(value, default_flow_style=True, width=10**6).strip().removesuffix("...").strip()


def open_existing_study(
    path: str | Path, *, config: StudyConfig | None = None, writable: bool = True, source: str | None = None,
    missing: str | None = None, options: str = "--study or --config",
) -> Study:
    """Open an existing study file.

    The study's config is the one stored in the file unless ``config`` is
    given; a given config must hash like the stored one (it may differ in
    estimation settings and QoI tolerances, which do not change samples), and
    ``source`` is where it comes from (its file; :class:`Study`). A
    file whose stored ``qoi_names`` are not the result columns of its stored
    config is refused as damaged (:class:`StudyFileError`). ``missing`` follows ``study file '...' does not
    exist`` where the file is missing (default: the CLI's remedy, naming the command's ``options`` that take a
    study file: ``merge`` has ``--into``, ``sample`` no ``--config``).
    """
    path = checked_study_path(path)
    if not path.exists():
        if missing is None:
            missing = (f"; create it with `roughuq screen CONFIG --out {path}`, or name the study file screen wrote "
                       f"(its config's output.path) with {options}")
        raise StudyFileError(f"study file {str(path)!r} does not exist{missing}", path)
    with open_study_readonly(path) as header:
        config_text, stored_hash, qoi_names = header.config_text, header.config_hash, header.qoi_names
        stored = _stored_config(header)
    _check_columns(path, qoi_names, stored.qoi_names)
    if config is not None and config_hash(config) != stored_hash:
        differences = _differences_text(stored, config, there="in the file", here="in this config")
        raise StudyFileError(
            f"study file {str(path)!r} was created with another config (hash {stored_hash[:12]}, "
            f"this config {config_hash(config)[:12]}{differences}): use the config it was made with (or leave out "
            "--config: the stored one is used) or another --study file",
            path,
        )
    source = source if config is not None else None
    if not writable:
        return Study(config or stored, open_study_readonly(path), source=source)
    store = open_study(
        path,
        config_text=config_text,
        config_hash=stored_hash,
        qoi_names=qoi_names,
        create=False,
        code_version=__version__,
    )
    return Study(config or stored, store, source=source)


def _check_columns(path: Path, stored_names: Sequence[str], config_names: Sequence[str]) -> None:
    """Refuse a study whose stored ``qoi_names`` are not the result columns of its stored config.

    The columns follow from the config, so a difference means a damaged or
    altered file; reading on would label (or index) the columns wrongly.
    """
    if tuple(stored_names) != tuple(config_names):
        raise StudyFileError(
            f"{path} cannot be read: damaged study file (qoi_names {list(stored_names)} are not the result "
            f"columns of its stored config, {list(config_names)})",
            path,
        )


# ---------------------------------------------------------------------------
# The store-backed sampler
# ---------------------------------------------------------------------------


class StudySampler:
    """A level sampler (estimator contract) serving stored samples and computing missing ones.

    Parameters
    ----------
    study : Study
    stage : int
        Stage of the samples (:mod:`rough_uq.problem.sampler`).
    executor : Executor
    progress : Progress
    chunk : int
        Samples per work item sent to the executor.
    advance_served : bool
        Advance ``progress`` by the stored samples of a batch that also computes some (an estimation run's,
        whose progress counts a batch's stored samples only once the batch is done: a resumed run's progress
        started below what was stored, "411/827" of 416). Not where the plan counted them first (screening).
    """

    def __init__(
        self, study: Study, *, stage: int, executor: Executor, progress: Progress, chunk: int = 1,
        advance_served: bool = False,
    ) -> None:
        self.study = study
        self.stage = stage
        self.executor = executor
        self.progress = progress
        self.chunk = max(1, int(chunk))
        self.advance_served = advance_served
        self._cache: dict[int, dict[int, int]] = {}
        self._batches: dict[int, LevelBatch] = {}
        self.n_computed = 0

    def stored(self, level: int) -> LevelBatch:
        """All stored samples of ``(stage, level)``."""
        if level not in self._batches:
            self._batches[level] = self.study.store.read_samples(level=level, stage=self.stage)
            self._cache[level] = {int(i): row for row, i in enumerate(self._batches[level].indices)}
        return self._batches[level]

    def _forget(self, level: int) -> None:
        self._batches.pop(level, None)
        self._cache.pop(level, None)

    def missing(self, level: int, indices: np.ndarray) -> np.ndarray:
        """The ``indices`` of ``level`` not stored yet."""
        self.stored(level)
        rows = self._cache[level]
        return np.array([i for i in np.asarray(indices, dtype=np.int64) if int(i) not in rows], dtype=np.int64)

    def compute(self, level: int, indices: np.ndarray) -> None:
        """Compute and store the missing samples among ``indices`` of ``level``."""
        missing = self.missing(level, indices)
        if missing.size == 0:
            return
        if self.advance_served and missing.size < np.size(indices):
            self.progress.advance(level, np.size(indices) - missing.size)
        items = [(self.stage, level, missing[i : i + self.chunk]) for i in range(0, missing.size, self.chunk)]
        pending: list[LevelBatch] = []
        last_flush = time.monotonic()
        try:
            for batch in self.executor.run(self.study.model_for(level, note=self.progress.note), items):
                pending.append(batch)
                self.progress.advance(level, batch.n_samples)
                if time.monotonic() - last_flush >= FLUSH_SECONDS:
                    self._flush(level, pending)
                    last_flush = time.monotonic()
        finally:
            self._flush(level, pending)

    def _flush(self, level: int, pending: list[LevelBatch]) -> None:
        if not pending:
            return
        batch = _concatenate(pending)
        pending.clear()
        self.study.store.append_samples(batch)
        self.n_computed += batch.n_samples
        self._forget(level)

    def samples(self, level: int, indices: np.ndarray) -> LevelBatch:
        """Samples ``indices`` of ``level`` (computing the missing ones), in the order asked."""
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        self.compute(level, indices)
        stored = self.stored(level)
        rows = np.array([self._cache[level][int(i)] for i in indices], dtype=np.int64)
        return _take(stored, rows)

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        batch = self.samples(level, indices)
        cost = modelled_cost(self.study.model, level, batch.n_iter, is_coupled=is_coupled_stage(self.stage))
        return batch.fine, batch.coarse, cost


def _take(batch: LevelBatch, rows: np.ndarray) -> LevelBatch:
    return LevelBatch(
        level=batch.level,
        stage=batch.stage,
        indices=batch.indices[rows],
        fine=batch.fine[rows],
        coarse=batch.coarse[rows],
        cost=batch.cost[rows],
        n_iter=batch.n_iter[rows],
        converged=batch.converged[rows],
    )


def _concatenate(batches: Sequence[LevelBatch]) -> LevelBatch:
    first = batches[0]
    return LevelBatch(
        level=first.level,
        stage=first.stage,
        indices=np.concatenate([b.indices for b in batches]),
        fine=np.concatenate([b.fine for b in batches]),
        coarse=np.concatenate([b.coarse for b in batches]),
        cost=np.concatenate([b.cost for b in batches]),
        n_iter=np.concatenate([b.n_iter for b in batches]),
        converged=np.concatenate([b.converged for b in batches]),
    )


# ---------------------------------------------------------------------------
# Diagnostics: the core's warnings as typed entries of the records
# ---------------------------------------------------------------------------


@contextmanager
def _collecting_diagnostics() -> Iterator[list[Diagnostic]]:
    """Collect the warnings raised inside (the core's ``EstimationWarning``) as :class:`Diagnostic` entries.

    The multilevel core reports its checks as warnings; records carry them as
    fields, so they are caught here, at the pipeline boundary, and never
    reach the user's warning filters. The list fills when the block ends.
    """
    diagnostics: list[Diagnostic] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", EstimationWarning)
        yield diagnostics
    diagnostics.extend(Diagnostic(str(w.message)) for w in caught)


def _unique(diagnostics: Sequence[Diagnostic]) -> tuple[Diagnostic, ...]:
    """``diagnostics`` without repeats, in first-seen order."""
    return tuple(dict.fromkeys(diagnostics))


# ---------------------------------------------------------------------------
# Screening
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ScreeningOutcome:
    """What screening measured: per-level statistics, rates, and what accuracy will cost."""

    statistics: LevelStatistics
    rates: Rates
    record: ScreeningRecord


def screening_statistics(study: Study, sampler: StudySampler | None = None) -> tuple[LevelStatistics, list[LevelBatch]]:
    """Level statistics of the screening samples (computing missing ones if ``sampler`` is given).

    The statistics are recomputed from the stored samples, so every command
    sees the same numbers whatever process ran the screening. Without a
    sampler (estimation runs), the levels and sample count are those of the
    last completed screening (a study may be screened again with more levels
    or samples than its config first said).
    """
    config = study.config
    levels = list(range(config.screening.levels))
    indices = np.arange(config.screening.samples)
    if sampler is None:
        record = read_screening_record(study.store)
        if record is not None:
            levels = list(record.statistics.levels)
            indices = np.arange(record.n_screened)
        sampler = StudySampler(study, stage=STAGE_SCREENING, executor=SerialExecutor(), progress=Progress())
        for level in levels:
            if sampler.missing(level, indices).size:
                path = getattr(study.store, "path", None)
                if study.store.role == "shard":  # its screening is in its study: screening it would be refused
                    raise shard_refusal(path)
                out = "" if path is None else f" --out {path}"
                raise StudyFileError(f"the study has no complete screening yet: run `roughuq screen CONFIG{out}` first",
                                     path)
    batches = [sampler.samples(level, indices) for level in levels]
    statistics = level_statistics(
        fine=[b.fine for b in batches],
        coarse=[b.coarse for b in batches],
        cost=[modelled_cost(study.model, b.level, b.n_iter) for b in batches],
        levels=levels,
    )
    return statistics, batches


def _base_tolerance(config: StudyConfig, statistics: LevelStatistics) -> np.ndarray:
    """Per column: its QoI's configured tol, or 1% of the finest screened mean (its standard deviation if that is 0)."""
    base = []
    for q, (_, _, settings) in enumerate(config.qoi_columns):
        tol = getattr(settings, "tol", None)
        if tol is None:
            mean = abs(float(statistics.mean_fine[-1, q]))
            spread = math.sqrt(max(float(statistics.var_fine[-1, q]), 0.0))
            tol = 0.01 * mean if mean > 0 else spread
            tol = tol if tol > 0 else 1.0
        base.append(tol)
    return np.array(base)


def _marked_as_runs_refuse(prediction: Plan, config: StudyConfig, rates: Rates, statistics: LevelStatistics) -> Plan:
    """The table's optimal plan, unreachable (with the bias that decides it) where ``roughuq mlmc`` refuses it.

    The run starts from :func:`~rough_uq.multilevel.drivers.starting_plan` (its coarsest level may differ) and
    samples levels its bias test needs beyond a plan's finest (:func:`~rough_uq.multilevel.drivers.with_run_bias`).
    """
    start = starting_plan(tol=prediction.tol, rates=rates, statistics=statistics, theta=prediction.theta,
                          max_level=config.grid.max_level)
    if start.is_bias_met or not prediction.is_bias_met:
        return prediction
    return replace(prediction, bias=start.bias, is_bias_met=False)


def _no_prediction(names: Sequence[str], rates: Rates, statistics: LevelStatistics, exc: Exception | None) -> str:
    """Why the screening predicts no cost, in words (the QoIs whose bias does not decay, by name)."""
    stalled = stalled_bias(names, rates, statistics)
    if stalled:
        return (f"no cost prediction: {stalled_text(stalled)}, so no finest grid can be chosen; screen finer "
                "grids (screening.levels, grid.coarsest)")
    return f"no cost prediction: {exc}; screen more levels (screening.levels)"


def run_screening(study: Study, *, executor: Executor, progress: Progress) -> ScreeningOutcome:
    """Compute (or complete) the screening samples, fit the rates, predict costs, store the record.

    A study with ``grid.max_level < 2`` (a valid config for the runs that
    need no screening) is refused before any sample is computed
    (:class:`~rough_uq.errors.InvalidParameterError` naming ``grid.max_level``,
    or :class:`~rough_uq.errors.ConfigError` naming the study's ``source`` first):
    a screening needs levels ``0..2`` (:data:`~rough_uq.problem.runs.MIN_SCREENED_LEVELS`).
    """
    config = study.config
    with naming_source(study.source):
        _check_screenable(config)
    levels = list(range(config.screening.levels))
    n = config.screening.samples
    smaller = _smaller_screening_text(read_screening_record(study.store), levels, n)
    sampler = StudySampler(study, stage=STAGE_SCREENING, executor=executor, progress=progress)
    progress.start("screening")
    try:
        progress.plan(levels, [n] * len(levels), [n - sampler.missing(level, np.arange(n)).size for level in levels])
        with _collecting_diagnostics() as caught:
            statistics, batches = screening_statistics(study, sampler)
            rates = _screening_rates(statistics, config.qoi_names)
    except BaseException:
        progress.stop(is_complete=False)
        raise
    progress.stop()
    seconds_per_cost = measured_seconds_per_cost(batches, study.model)
    predictions, problems = _predictions(config, statistics, rates, seconds_per_cost)
    caveats = exact_column_caveats(study.model, config.qoi_names, rates, statistics)
    texts = (*diagnose(statistics, names=config.qoi_names), *problems, *caveats, *smaller)
    checks = [Diagnostic(text) for text in texts]
    coarsest = choose_coarsest_level(statistics)
    record = ScreeningRecord(
        created=utc_timestamp(),
        code_version=__version__,
        qoi_names=tuple(config.qoi_names),
        statistics=LevelTable.from_statistics(statistics, [float(np.mean(b.cost)) for b in batches]),
        rates=RatesRecord.from_rates(rates),
        predictions=predictions,
        seconds_per_cost=seconds_per_cost,
        n_not_converged=count_not_converged(batches),
        n_computed=sampler.n_computed,
        diagnostics=_unique(caught + checks),
        coarsest_level=int(coarsest.level),
        dropped_levels=tuple(DroppedLevel(int(d.level), d.reason) for d in coarsest.dropped),
    )
    study.store.write_screening(record.to_json())
    return ScreeningOutcome(statistics, rates, record)


def _smaller_screening_text(previous: ScreeningRecord | None, levels: Sequence[int], n: int) -> tuple[str, ...]:
    """A notice where this screening uses fewer levels or samples than the study's last one (its samples stay).

    A config with ``screening.samples: 10`` replaced a 20-sample screening and its rates without a word.
    """
    if previous is None:
        return ()
    n_before, levels_before = previous.n_screened, len(previous.statistics.levels)
    if n >= n_before and len(levels) >= levels_before:
        return ()
    return (f"this screening uses {n} samples on levels 0..{len(levels) - 1} (screening.samples, screening.levels) "
            f"where the study's last one used {n_before} on levels 0..{levels_before - 1}; its rates and plans "
            "replace that one's (the samples stay in the file: the config's earlier values screen with them again)",)


def _check_screenable(config: StudyConfig) -> None:
    """Refuse a config too shallow to screen (:func:`run_screening`), naming ``grid.max_level``."""
    if config.grid.max_level + 1 < MIN_SCREENED_LEVELS:
        raise InvalidParameterError(
            "grid.max_level", config.grid.max_level,
            f"an integer >= {MIN_SCREENED_LEVELS - 1} to screen: a screening needs levels 0..{MIN_SCREENED_LEVELS - 1} "
            "(the rates are fitted on levels >= 1, two of them at least); runs without a screening need none "
            "(mc --level; mlmc --tol-var / --tol-cdf from grid.max_level 1)",
        )


def _screening_rates(statistics: LevelStatistics, qoi_names: Sequence[str]) -> Rates:
    advice = "screen more levels (screening.levels) or more samples (screening.samples)"
    # Nothing to estimate at all (more levels or samples would not help), or no variance on the screened grids.
    refuse_constant_columns(statistics, qoi_names, advice=f"{advice}, or change the load")
    try:
        return fit_rates(statistics, names=qoi_names)
    except EstimationError as exc:
        raise EstimationError(f"screening cannot fit the rates: {exc}; {advice}") from None


def _predictions(
    config: StudyConfig, statistics: LevelStatistics, rates: Rates, seconds_per_cost: float
) -> tuple[tuple[PlanRecord, ...], list[str]]:
    """Plans for the multiples :data:`PREDICTION_FACTORS` of the base tolerance, and why any is missing."""
    base = _base_tolerance(config, statistics)
    predictions = []
    if stalled_bias(config.qoi_names, rates, statistics):
        return (), [_no_prediction(config.qoi_names, rates, statistics, None)]
    planned = planning_rates(statistics)  # floored, as the runs plan (the record keeps the fitted rates)
    for factor in PREDICTION_FACTORS:
        try:
            prediction = plan(
                tol=base * factor,
                rates=planned,
                statistics=statistics,
                theta=config.estimation.theta,
                max_level=config.grid.max_level,
                coarsest_level=None,
            )
        except RoughUQError as exc:
            # E.g. a bias that does not decay yet (alpha <= 0 on pre-asymptotic
            # levels): keep the table and rates, say why nothing can be predicted.
            return tuple(predictions), [_no_prediction(config.qoi_names, rates, statistics, exc)]
        predictions.append(PlanRecord.from_plan(_marked_as_runs_refuse(prediction, config, planned, statistics),
                                                seconds_per_cost))
    return tuple(predictions), []


# ---------------------------------------------------------------------------
# Estimation runs
# ---------------------------------------------------------------------------


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

    The planning rates are floored (:func:`~rough_uq.multilevel.drivers.planning_rates`) and would plan one all
    the same, on a bias model the screening contradicts.
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

    The plan uses the rates floored as the runs use them (:func:`~rough_uq.multilevel.drivers.planning_rates`).
    """
    statistics, _ = screening_statistics(study)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EstimationWarning)
        rates = fit_rates(statistics, names=study.config.qoi_names)
        planned = planning_rates(statistics)
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
                   max_level=config.grid.max_level)
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
        rates = planning_rates(statistics)  # floored, as the run plans
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
                                  tolerance=f"--tol {tol_text(names, tol, digits=3)}")
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
        if level is not None:
            fine_cost = rates.cost_model(finest) if finest > prediction.finest_level else prediction.costs[finest]
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


class _SamplesMissing(Exception):
    """Raised by the replay sampler of :func:`missing_samples` at the first sample not stored."""


@dataclass(frozen=True)
class WorkPlan:
    """Samples an estimation run still needs (:func:`missing_samples`).

    Attributes
    ----------
    run_id : str
        Name of the run.
    stage : int
        Its random stage (the ``--stage`` of ``roughuq sample``).
    missing : dict of int to ndarray of int64
        Per level, the sorted sample indices not stored yet.
    """

    run_id: str
    stage: int
    missing: dict[int, np.ndarray]

    @property
    def n_missing(self) -> int:
        """Total samples missing (0: the stored samples complete the run)."""
        return int(sum(indices.size for indices in self.missing.values()))


def missing_samples(
    study: Study, *, method: str, tol: np.ndarray, max_cost: float | None = None, level: int | None = None
) -> WorkPlan:
    """The sample indices the next round of a run needs that are not stored, per level.

    The run is replayed on the stored samples (exactly the decisions
    ``run_estimation`` would take) until it asks for a sample that is not
    stored; the missing indices of its current plan are returned. No missing
    index means the stored samples complete the run. An adaptive MLMC run may
    plan more samples once these are stored: ask again after merging them.
    Nothing is computed or written.
    """
    _check_run_arguments(study, method, level)
    estimation = study.config.estimation
    key = run_id(method, study.config.qoi_names, tol, estimation.theta, level, richardson=estimation.richardson)
    stage = run_stage(method, key)
    stored = StudySampler(study, stage=stage, executor=SerialExecutor(), progress=Progress())

    def replay(level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if stored.missing(level, indices).size:
            raise _SamplesMissing
        return stored(level, indices)

    max_cost = study.config.estimation.max_cost if max_cost is None else max_cost
    events, _ = _events(
        study, method=method, tol=np.asarray(tol, dtype=float), sampler=replay, max_cost=max_cost, level=level
    )
    planned: dict[int, int] = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", EstimationWarning)
            for event in events:
                if isinstance(event, PlanUpdated):
                    planned = {int(level): int(n) for level, n in zip(event.levels, event.n_planned)}
    except _SamplesMissing:
        missing = {level: stored.missing(level, np.arange(n)) for level, n in planned.items()}
        return WorkPlan(key, stage, {level: indices for level, indices in missing.items() if indices.size})
    return WorkPlan(key, stage, {})


def _events(
    study: Study,
    *,
    method: str,
    tol: np.ndarray,
    sampler: StudySampler,
    max_cost: float | None,
    level: int | None = None,
) -> tuple[Iterator[object], dict[str, Any]]:
    """The estimator's event stream and the run's context (``level``, ``screening_rates``, ``predicted``)."""
    config = study.config
    estimation = config.estimation
    options = dict(
        tol=tol,
        theta=estimation.theta,
        n_initial=estimation.initial_samples,
        max_cost=max_cost,
        batch_size=estimation.batch_size,
        qoi_names=config.qoi_names,
    )
    if method == "mc" and level is not None:
        # An explicit level needs no screening (and so no forecast); the bias of that level is then unknown.
        return _refusing_large_plans(iter_mc(sampler, level=level, **options), config.qoi_names, tol), {"level": level}
    events, context = _screened_events(study, method=method, sampler=sampler, options=options)
    return _refusing_large_plans(events, config.qoi_names, tol), context


def _screened_events(
    study: Study, *, method: str, sampler: StudySampler, options: dict[str, Any]
) -> tuple[Iterator[object], dict[str, Any]]:
    """The events of an ``mlmc`` or ``mc --tol`` run from the screening's plan, and the run's context."""
    config, estimation, tol = study.config, study.config.estimation, options["tol"]
    statistics, rates, prediction = _estimation_plan(study, tol, method=method)
    predicted = PlanRecord.from_plan(prediction, _screened_seconds_per_cost(read_screening_record(study.store)))
    context: dict[str, Any] = {"screening_rates": RatesRecord.from_rates(rates), "predicted": predicted}
    if method == "mlmc":
        events = iter_mlmc(
            sampler, max_level=config.grid.max_level, screening=statistics, richardson=estimation.richardson,
            coarsest_level=None, **options,
        )
    else:
        context["level"] = int(prediction.finest_level)
        events = iter_mc(
            sampler, level=prediction.finest_level, bias=prediction.bias, screening=statistics, **options
        )
    return events, context


def _earlier_run(study: Study, key: str) -> RunRecord | None:
    """The stored record of run ``key`` (read before this command rewrites it), or None."""
    return next((run for run in read_run_records(study.store) if run.run_id == key), None)


@dataclass(frozen=True)
class _RunClock:
    """When this command started a run, the wall seconds of the run's earlier finish, if any, and of its
    commands stopped before it finished (:attr:`~rough_uq.study.records.RunRecord.stopped_elapsed`)."""

    started: float
    earlier_elapsed: float | None
    stopped: float = 0.0

    @classmethod
    def start(cls, earlier: RunRecord | None) -> _RunClock:
        """Start now; ``earlier`` is the run's stored record (:func:`_earlier_run`), if any.

        Only a finished record's outcome counts: a dropped one keeps the outcome it had, which is not this
        run's. The stopped commands of a record that is not finished count too (not a dropped one's, for the
        same reason).
        """
        outcome = earlier.outcome if earlier is not None and earlier.is_finished else None
        elapsed = None if outcome is None or outcome.elapsed is None else float(outcome.elapsed)
        is_resumed = earlier is not None and not earlier.is_finished and earlier.status != "dropped"
        stopped = float(earlier.stopped_elapsed or 0.0) if is_resumed else 0.0
        return cls(started=time.monotonic(), earlier_elapsed=elapsed, stopped=stopped)

    def so_far(self) -> float:
        """Wall seconds of the run's stopped commands and of this one so far."""
        return self.stopped + time.monotonic() - self.started

    def elapsed(self, sampler: StudySampler) -> float:
        """Wall seconds of the run: its commands', the earlier finish's among them; the earlier finish's
        alone when this rerun computed nothing.

        A finished run that a rerun extends (e.g. one stopped by ``--max-cost``, run again without it) counted
        the rerun alone: 5.05 s against 21.6 CPU-seconds of samples on two workers, the first command's 8.68 s
        lost.
        """
        if sampler.n_computed == 0 and self.earlier_elapsed is not None:
            return self.earlier_elapsed
        return (self.earlier_elapsed or 0.0) + self.so_far()


def _screened_mc_cost(study: Study, tol: np.ndarray) -> float:
    """Modelled cost of plain MC to ``tol`` as the screening predicts it: ``roughuq mc --tol``'s forecast.

    On the level the screening's bias model needs for ``tol``, with its
    ``Var(Q)`` there. Not on the MLMC run's finest level: the levels a run
    starts with and its own bias test (two samples on its finest levels) can
    take it beyond, and plain MC priced there came out some 20 times dearer
    than the MC run at the same tolerance.
    """
    _, rates, prediction = _estimation_plan(study, np.asarray(tol, dtype=float), method="mc")
    _, counts, costs = _planned_samples("mc", None, prediction, rates,
                                        n_initial=study.config.estimation.initial_samples)
    return counts[0] * costs[0]


def run_estimation(
    study: Study,
    *,
    method: str,
    tol: np.ndarray,
    executor: Executor,
    progress: Progress,
    max_cost: float | None = None,
    level: int | None = None,
    forecast: Forecast | None = None,
) -> RunRecord:
    """Run MLMC (``method="mlmc"``) or plain MC (``"mc"``) to ``tol`` and store its record.

    ``forecast`` (:func:`forecast_run`, which the CLI calls first to refuse
    hopeless tolerances) is stored in the record as ``forecast``.

    MC runs on the finest level the screening's plan needs for ``tol``, or on
    ``level`` if given (no screening needed; its bias is then not estimated).

    ``max_cost`` (reference seconds of modelled cost; default the config's
    ``estimation.max_cost``) bounds the run. The record is written when the
    run starts (``status = "running"``) and when it ends (``"finished"``, or
    ``"refused"`` with the reason when the estimator raises
    :class:`~rough_uq.errors.EstimationError`, which is raised on); an
    interrupted run (Ctrl-C, SIGTERM) keeps its samples, its record says
    ``interrupted``, and the same command resumes it. A rerun of a finished
    run leaves the finished record in place until it finishes itself, so a
    rerun that is refused, interrupted or fails keeps the earlier result.

    Returns
    -------
    RunRecord
        The finished run (``roughuq report --json`` shows its ``to_json``).
    """
    _check_run_arguments(study, method, level)
    if level is not None:  # no screening's forecast checks its budget: at least its initial samples
        _check_initial_budget(study.config, [level], max_cost=max_cost, model=study.model,
                              without="the run has no variance estimate", source=study.source)
    tol = np.asarray(tol, dtype=float)
    max_cost = study.config.estimation.max_cost if max_cost is None else max_cost
    estimation = study.config.estimation
    key = run_id(method, study.config.qoi_names, tol, estimation.theta, level, richardson=estimation.richardson)
    earlier = _earlier_run(study, key)
    clock = _RunClock.start(earlier)
    sampler = StudySampler(study, stage=run_stage(method, key), executor=executor, progress=progress,
                           advance_served=True)
    events, context = _events(study, method=method, tol=tol, sampler=sampler, max_cost=max_cost, level=level)
    record = _started_record(study, key=key, method=method, tol=tol, stage=sampler.stage, max_cost=max_cost,
                             context=context, forecast=forecast)
    title = f"{method} {tol_text(study.config.qoi_names, tol)}"
    with _run_recorded(study, record, earlier, clock) as record:
        result, diagnostics = _follow(events, progress, title)
    outcome = _outcome(study, method=method, sampler=sampler, result=result, diagnostics=diagnostics, clock=clock)
    record = replace(record, status="finished", outcome=outcome)
    study.store.write_run(key, record.to_json())
    return record


@contextmanager
def _run_recorded(
    study: Study, record: RunRecord, earlier: RunRecord | None, clock: _RunClock
) -> Iterator[RunRecord]:
    """Store ``record`` as ``running`` for the block, then ``refused`` (EstimationError) or ``interrupted`` (else).

    Yields ``record`` with the wall time of the run's stopped commands (``clock``), which the stored records
    keep: the running one too, for a command killed outright.

    ``refused`` comes with the error's message; ``interrupted`` follows
    anything else that stops the block: Ctrl-C, SIGTERM (which raises
    KeyboardInterrupt too), a failing worker or disk.

    A refused run is not an interrupted one: rerunning it as it is would be
    refused again, so its record must not stay ``running`` (which the report
    shows as "interrupted; rerun the same command to resume"). The error is
    raised on. A rerun of a finished run (``earlier``) leaves its record
    as it is until the caller stores the new outcome: a rerun that is
    refused, interrupted or fails never downgrades a finished result.
    """
    record = replace(record, stopped_elapsed=clock.stopped or None)
    is_kept = earlier is not None and earlier.is_finished
    if not is_kept:
        study.store.write_run(record.run_id, record.to_json())
    try:
        yield record
    except EstimationError as exc:
        if not is_kept:
            refused = replace(record, status="refused", reason=str(exc), stopped_elapsed=clock.so_far())
            study.store.write_run(record.run_id, refused.to_json())
        raise
    except BaseException:
        # Ctrl-C, SIGTERM, a worker or the disk failing: the run stopped, and the same command resumes it. Recorded
        # so, that a report while another run holds the study does not show it as running (a process killed
        # outright leaves "running", which the report reads by the lock). Best effort: the record must not replace
        # the error or the interrupt that stopped the run.
        if not is_kept:
            with suppress(Exception):
                stopped = replace(record, status="interrupted", stopped_elapsed=clock.so_far())
                study.store.write_run(record.run_id, stopped.to_json())
        raise


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


def _started_record(
    study: Study, *, key: str, method: str, tol: np.ndarray, stage: int, max_cost: float | None,
    context: Mapping[str, Any], forecast: Forecast | None,
) -> RunRecord:
    """The record of a run that starts: its settings and context, no outcome."""
    config = study.config
    return RunRecord(
        run_id=key,
        method=method,
        status="running",
        tol=tuple(tol.tolist()),
        started=utc_timestamp(),
        code_version=__version__,
        qoi_names=tuple(config.qoi_names),
        theta=config.estimation.theta,
        max_cost=max_cost,
        stage=stage,
        initial_samples=config.estimation.initial_samples,
        forecast=forecast,
        **context,
    )


def _follow(events: Iterator[object], progress: Progress, title: str) -> tuple[Any, list[Diagnostic]]:
    """Drive the estimator's events with progress; its result and the diagnostics it raised."""
    progress.start(title)
    result = None
    try:
        with _collecting_diagnostics() as diagnostics:
            for event in events:
                if isinstance(event, (PlanUpdated, BatchDone)):
                    # A batch's counts include samples served from the store (an earlier run's, merged shards'),
                    # which no sample computed here advanced: a rerun's progress ended at "7/11 samples", "done".
                    progress.plan(event.levels, event.n_planned, event.n_done)
                elif isinstance(event, Finished):
                    result = event.result
                elif not isinstance(event, RichardsonRefused):  # pragma: no cover - the contract
                    raise RoughUQError(f"unexpected estimator event {event!r}")
    except BaseException:
        progress.stop(is_complete=False)
        raise
    # A run its budget stopped did not draw what it planned: "stopped after", not "done in".
    progress.stop(is_complete=getattr(result, "stop_reason", None) != "max_cost")
    if result is None:  # pragma: no cover - the event stream always ends with Finished
        raise RoughUQError("the estimator stopped without a result")
    return result, diagnostics


def _outcome(
    study: Study, *, method: str, sampler: StudySampler, result: Any, diagnostics: Sequence[Diagnostic],
    clock: _RunClock,
) -> RunOutcome:
    """What the finished run found, with the seconds and non-converged solves of the samples it used."""
    used = [sampler.samples(int(level), np.arange(int(n))) for level, n in zip(result.levels, result.n_samples)]
    seconds = 0.0
    for batch in used:  # summed level by level, as the records always have been
        seconds += float(np.sum(batch.cost))
    seconds_per_cost = seconds / result.cost if result.cost > 0 else 1.0
    screening = read_screening_record(study.store)
    if screening is not None and screening.seconds_per_cost:
        seconds_per_cost = float(screening.seconds_per_cost)  # robust to the pool's start-up
    mc_cost = _screened_mc_cost(study, result.tol) if method == "mlmc" else result.mc_cost
    return RunOutcome.from_result(
        result,
        mean_seconds=[float(np.mean(batch.cost)) for batch in used],
        seconds=seconds,
        elapsed=clock.elapsed(sampler),
        mc_cost=mc_cost,
        seconds_per_cost=seconds_per_cost,
        n_computed=sampler.n_computed,
        n_not_converged=count_not_converged(used),
        diagnostics=_unique(diagnostics),
    )


# ---------------------------------------------------------------------------
# Targets beyond the mean: variance and distribution function
# ---------------------------------------------------------------------------

#: Fewest initial samples per level of a target run: the variance of a level's variance term needs four.
MIN_TARGET_SAMPLES = 4


@dataclass(frozen=True)
class CdfRequest:
    """What a ``cdf`` run estimates: one column's distribution function on a grid, and which quantiles.

    Attributes
    ----------
    column : str
        A result column of the study (``config.qoi_names``).
    thresholds : ndarray, shape (m,)
        Strictly increasing ``s_j``, the column's unit.
    probabilities : tuple of float
        ``p`` of the quantiles reported: distinct, in (0, 1), in the order
        given (:func:`cdf_request`).
    """

    column: str
    thresholds: np.ndarray
    probabilities: tuple[float, ...]


def cdf_request(
    config: StudyConfig,
    *,
    column: str | None,
    thresholds: Sequence[float] | None = None,
    probabilities: Sequence[float] | None = None,
) -> CdfRequest:
    """The column, thresholds and probabilities of a ``cdf`` run: as given, else from ``estimation.distribution``.

    Raises :class:`~rough_uq.errors.InvalidParameterError` naming ``--qoi`` or
    ``--thresholds`` when the column is unknown or no thresholds are given
    (saying how to give them), and ``--probabilities`` unless they are
    distinct real numbers in (0, 1) (``0.5`` and ``5e-1`` are the same).

    Probabilities are kept in the order given, not sorted, as the CLI and the
    config keep them: each quantile is computed on its own, the record and
    the report list them in the user's order, and the run's name hashes them
    in that order (:func:`target_run_id`), so sorting would rename runs
    stored before. Two orders of the same probabilities are therefore two
    records of one run's samples (same stage), not one.
    """
    names = config.qoi_names
    if column is None and len(names) == 1:
        column = names[0]
    given, column = column, None if column is None else column_of_load(column, names)
    if column is None:  # it read "--qoi: got None"
        columns = ", ".join(names)
        raise InvalidParameterError("--qoi", None, f"one result column of this study: {columns}",
                                    text=f"--qoi: this study has several result columns; name one of {columns}")
    if column not in names:  # as typed: "contact_area@6", not the "contact_area@6.0" it was compared as
        raise InvalidParameterError("--qoi", given, f"one result column of this study: {', '.join(names)}")
    settings = config.estimation.distribution.get(_qoi_of(config, column))
    if thresholds is None and (settings is None or settings.thresholds is None):
        raise InvalidParameterError(
            "--thresholds", "none (neither the option nor the config gives them)",
            f"the values s where F(s) = P({column} <= s) is estimated: give --thresholds "
            f"START:STOP:COUNT (the QoI's unit) or set estimation.distribution.{_qoi_of(config, column)}.thresholds "
            "in the config",
        )
    values = np.asarray(settings.thresholds.values() if thresholds is None else thresholds, dtype=float)
    if values.ndim != 1 or values.size < 2 or not np.all(np.isfinite(values)) or np.any(np.diff(values) <= 0):
        raise InvalidParameterError("--thresholds", thresholds, "at least two finite, strictly increasing values")
    if probabilities is None:
        probabilities = DEFAULT_PROBABILITIES if settings is None else settings.probabilities
    return CdfRequest(column=column, thresholds=values, probabilities=_probabilities(probabilities))


def _probabilities(probabilities: object) -> tuple[float, ...]:
    """``probabilities`` as a tuple of floats, or InvalidParameterError naming ``--probabilities``."""
    allowed = "distinct numbers strictly between 0 and 1, at least one"
    items = (probabilities,) if isinstance(probabilities, (str, bytes)) else probabilities
    try:
        items = tuple(items)
    except TypeError:
        raise InvalidParameterError("--probabilities", probabilities, allowed) from None
    if not items or not all(is_real_number(x) and 0 < x < 1 for x in items):
        raise InvalidParameterError("--probabilities", probabilities, allowed)
    p = tuple(float(x) for x in items)
    if len(set(p)) != len(p):
        repeated = next(x for x in p if p.count(x) > 1)
        raise InvalidParameterError("--probabilities", probabilities, f"{allowed} ({repeated:g} is given twice)")
    return p


def _qoi_of(config: StudyConfig, column: str) -> str:
    """The QoI name of a result column (a load-curve column ``qoi@load`` belongs to ``qoi``)."""
    return next(name for col, name, _ in config.qoi_columns if col == column)


def target_run_id(study: Study, *, target: str, tol: np.ndarray, request: CdfRequest | None = None) -> str:
    """Name of a variance or cdf run (its record in the study).

    A variance run is named by its columns, ``tol`` and ``theta``
    (:func:`~rough_uq.problem.runs.run_id`). A ``cdf`` run's name adds
    ``_request-<8 hex digits>``, a hash of its thresholds and probabilities
    (:func:`_request_digest`): the same command gives the same name and
    resumes its run, while a run of the same column and tolerance with other
    thresholds or quantiles gets a record of its own instead of replacing the
    first one. Either way the run draws the samples of the name without that
    suffix (:func:`_target_stage`), the stage :func:`rough_uq.variance` /
    :func:`rough_uq.distribution` use: the CLI and the Python API draw the
    same samples, and cdf runs that differ only in thresholds share them.
    """
    base = _target_base_id(study, target=target, tol=tol, request=request)
    return base if target == "variance" else f"{base}_request-{_request_digest(request)}"


def _target_base_id(study: Study, *, target: str, tol: np.ndarray, request: CdfRequest | None) -> str:
    """The run id of a target without the cdf request's suffix: the name its random stage derives from."""
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
    columns = study.config.qoi_names if target == "variance" else [request.column]
    return run_id(target, columns, np.asarray(tol, dtype=float), study.config.estimation.theta)


def _target_stage(study: Study, *, target: str, tol: np.ndarray, request: CdfRequest | None) -> int:
    """Random stage of a variance or cdf run (the same for every thresholds and probabilities of a cdf run)."""
    return run_stage("mlmc", _target_base_id(study, target=target, tol=tol, request=request))


def _request_digest(request: CdfRequest) -> str:
    """8 hex digits of SHA-256 of the thresholds and probabilities (12 significant digits: stable to rounding)."""
    values = [[f"{float(s):.12g}" for s in request.thresholds], [f"{float(p):.12g}" for p in request.probabilities]]
    return hashlib.sha256(json.dumps(values, separators=(",", ":")).encode("ascii")).hexdigest()[:8]


class _PlannedSampler:
    """A sampler that announces every batch to the progress before the study sampler computes it.

    The targets' adaptive driver does not publish its plan, so the progress
    shows per level the samples asked for so far (bars that grow as the run
    adapts), which is also what the CLI's memory warning watches.
    """

    def __init__(self, sampler: StudySampler, progress: Progress) -> None:
        self.sampler = sampler
        self.progress = progress
        self.asked: dict[int, int] = {}

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        done = dict(self.asked)  # every earlier batch is complete
        # Samples of this batch already stored (a resumed run) count as done.
        done[level] = done.get(level, 0) + int(indices.size - self.sampler.missing(level, indices).size)
        self.asked[level] = self.asked.get(level, 0) + int(indices.size)
        levels = sorted(self.asked)
        self.progress.plan(levels, [self.asked[lv] for lv in levels], [done.get(lv, 0) for lv in levels])
        return self.sampler(level, indices)


def run_target(
    study: Study,
    *,
    target: str,
    tol: np.ndarray,
    executor: Executor,
    progress: Progress,
    max_cost: float | None = None,
    request: CdfRequest | None = None,
) -> RunRecord:
    """Run MLMC for the variance of every column (``target="variance"``) or one column's CDF (``"cdf"``).

    The adaptive driver of :mod:`rough_uq.multilevel.targets` runs on levels
    ``0..min(2, grid.max_level)`` first with ``estimation.initial_samples``
    samples each (at least :data:`MIN_TARGET_SAMPLES`), adding levels up to
    ``grid.max_level``; no screening is needed. Samples come through a
    :class:`StudySampler` of the run's stage, so an interrupted run resumes
    and the same config gives the same numbers with any number of workers.

    Parameters
    ----------
    target : {"variance", "cdf"}
    tol : ndarray
        ``variance``: RMS tolerance per column, the QoI's unit squared;
        ``cdf``: shape (1,), tolerance on the largest RMS error of ``F`` over
        the thresholds (dimensionless).
    max_cost : float, optional
        Modelled reference seconds; default ``estimation.max_cost``.
    request : CdfRequest
        ``cdf`` only (:func:`cdf_request`).

    Returns
    -------
    RunRecord
        Named by :func:`target_run_id` (a cdf run by its thresholds and
        probabilities too), method ``target``; stored as ``running`` when it
        starts and ``finished`` when it ends (``refused`` with the reason where the
        driver raises :class:`~rough_uq.errors.EstimationError`, e.g. for a
        plan of more than ``MAX_PLANNED_SAMPLES`` samples; the reason, raised
        on, names the options of ``roughuq mlmc``, ``--tol-var NAME=EPS`` or
        ``--tol-cdf EPS``, where the driver says ``tol``). A rerun of a
        finished run keeps the finished record until it finishes itself. A
        run that ``max_cost`` stops before its bias is estimated does not
        meet its tolerance (:mod:`rough_uq.multilevel.targets`).

    Raises
    ------
    InvalidParameterError, EstimationError
        Before any sample and any record, what :func:`check_target_run`
        refuses: a config without the levels or samples such a run needs, or
        a ``max_cost`` below the least cost of the run's initial samples,
        naming ``--max-cost X`` or ``estimation.max_cost X``.
    """
    tol = np.asarray(tol, dtype=float)
    if target == "cdf" and (request is None or tol.shape != (1,)):
        raise InvalidParameterError("--tol-cdf", tol.tolist(), "one number, with the column and thresholds")
    check_target_run(study.config, max_cost=max_cost, model=study.model, source=study.source)
    estimation = study.config.estimation
    max_cost = estimation.max_cost if max_cost is None else max_cost
    key = target_run_id(study, target=target, tol=tol, request=request)
    earlier = _earlier_run(study, key)
    clock = _RunClock.start(earlier)
    stage = _target_stage(study, target=target, tol=tol, request=request)
    sampler = StudySampler(study, stage=stage, executor=executor, progress=progress)
    names = study.config.qoi_names if target == "variance" else (request.column,)
    record = RunRecord(
        run_id=key, method=target, status="running", tol=tuple(tol.tolist()), started=utc_timestamp(),
        code_version=__version__, qoi_names=tuple(names), theta=estimation.theta, max_cost=max_cost,
        stage=sampler.stage, initial_samples=estimation.initial_samples,
    )
    title = f"{target} {tol_text(names, tol)}"
    option = _TARGET_OPTIONS[target]
    given = tol_text(names, tol) if target == "variance" else tol_number(tol[0])
    with _run_recorded(study, record, earlier, clock) as record, _naming_options(f"{option} {given}", option):
        result, diagnostics = _follow_target(study, target, tol, sampler, progress, title, max_cost, request)
    outcome = _target_outcome(study, target=target, sampler=sampler, result=result, request=request,
                              diagnostics=diagnostics, clock=clock)
    record = replace(record, status="finished", outcome=outcome)
    study.store.write_run(key, record.to_json())
    return record


#: The option of ``roughuq mlmc`` that asks for a target run, and gives its tolerance.
_TARGET_OPTIONS = {"variance": "--tol-var", "cdf": "--tol-cdf"}


def check_target_run(
    config: StudyConfig, *, max_cost: float | None = None, model: ContactModel | None = None,
    source: str | None = None,
) -> None:
    """Refuse, before any sample, a variance or cdf run that ``config`` cannot give.

    What :func:`run_target` checks before it opens a record, for callers that
    check before a study file exists (``roughuq mlmc --config``, which would
    otherwise leave an empty study file behind): ``grid.max_level`` at least
    1, ``estimation.initial_samples`` at least :data:`MIN_TARGET_SAMPLES` and
    within :func:`check_initial_samples`, and the budget
    (:func:`check_target_budget`; ``model`` and ``source`` as there).

    Raises
    ------
    InvalidParameterError
        Naming ``grid.max_level`` or ``estimation.initial_samples``.
    ConfigError
        The same, with ``source`` (the config's file) named first (:func:`naming_source`).
    EstimationError
        A budget below the least cost of the initial samples.
    """
    with naming_source(source):
        _check_target_fields(config)
    check_target_budget(config, max_cost=max_cost, model=model, source=source)


def _check_target_fields(config: StudyConfig) -> None:
    """The levels and initial samples a variance or cdf run needs (:func:`check_target_run`)."""
    if config.grid.max_level < 1:
        raise InvalidParameterError("grid.max_level", config.grid.max_level,
                                    "an integer >= 1 for variance and cdf runs (they estimate level differences)")
    if config.estimation.initial_samples < MIN_TARGET_SAMPLES:
        raise InvalidParameterError(
            "estimation.initial_samples", config.estimation.initial_samples,
            f"an integer >= {MIN_TARGET_SAMPLES} for variance and cdf runs (the variance of a level's "
            "variance term needs four samples)",
        )
    check_initial_samples(config, n_levels=initial_finest_level(config.grid.max_level) + 1,
                          run="variance and cdf runs")


def check_target_budget(
    config: StudyConfig, *, max_cost: float | None = None, model: ContactModel | None = None,
    source: str | None = None,
) -> None:
    """Refuse, before any sample, a variance or cdf run whose budget cannot pay for its initial samples.

    The run estimates its bias only once it has ``estimation.initial_samples``
    samples on each of levels ``0..min(2, grid.max_level)``
    (:mod:`rough_uq.multilevel.targets`); their modelled cost is at least that
    of solves that need no iteration at all. A budget below that bound could
    only stop the run before its bias is estimated, a result that cannot meet
    its tolerance (the mean's forecast refuses a predicted overrun alike,
    :func:`forecast_run`). ``max_cost`` is ``--max-cost`` (reference seconds);
    None takes ``estimation.max_cost``, named so in the message; no budget at
    all passes. ``model`` is the config's (:func:`build_model`), built here if
    not given. ``source`` (the config's file) is named first in a refusal of
    ``estimation.max_cost``.

    Raises
    ------
    EstimationError
        ``--max-cost X is too small for the initial samples of levels 0..2
        (N each), which cost at least ...: raise --max-cost (or lower
        estimation.initial_samples)`` (``estimation.max_cost X`` where that is
        the budget).
    """
    finest = initial_finest_level(config.grid.max_level)
    _check_initial_budget(config, list(range(finest + 1)), max_cost=max_cost, model=model,
                          without="no bias is estimated", source=source)


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


@contextmanager
def _naming_options(tolerance: str, option: str) -> Iterator[None]:
    """Re-raise the driver's refusal of a tolerance naming what the user gave instead of the driver's ``tol``.

    The multilevel core (and the Python API, :func:`rough_uq.variance` and
    :func:`rough_uq.distribution`, which keep its words) says ``tol 1e-06
    needs about ...: loosen the tolerance``; a run of ``roughuq mlmc`` says
    ``--tol-var contact_area=1e-06 needs about ...: loosen --tol-var``
    (``tolerance`` is the option with its value, ``option`` the bare option),
    the same :class:`~rough_uq.errors.PlanTooLargeError` with the same numbers.
    Other errors pass as they are.
    """
    try:
        yield
    except PlanTooLargeError as exc:
        raise exc.named(tolerance=tolerance, advice=f"loosen {option}") from None


def _follow_target(
    study: Study, target: str, tol: np.ndarray, sampler: StudySampler, progress: Progress, title: str,
    max_cost: float | None, request: CdfRequest | None,
) -> tuple[Any, list[Diagnostic]]:
    """Run the targets' adaptive driver with progress; its estimate and the diagnostics it raised."""
    config = study.config
    per_target = dict(qoi_names=config.qoi_names) if target == "variance" else dict(
        thresholds=request.thresholds, qoi=config.qoi_names.index(request.column), qoi_names=config.qoi_names
    )
    planned = _PlannedSampler(sampler, progress)
    progress.start(title)
    try:
        with _collecting_diagnostics() as diagnostics:
            result = estimate_target(
                planned, target=target, tol=tol, max_level=config.grid.max_level, theta=config.estimation.theta,
                n_initial=config.estimation.initial_samples, max_cost=max_cost,
                batch_size=config.estimation.batch_size, **per_target,
            )
    except BaseException:
        progress.stop(is_complete=False)
        raise
    progress.stop(is_complete=getattr(result, "stop_reason", None) != "max_cost")  # as _follow
    return result, diagnostics


def _target_outcome(
    study: Study, *, target: str, sampler: StudySampler, result: Any, request: CdfRequest | None,
    diagnostics: Sequence[Diagnostic], clock: _RunClock,
) -> RunOutcome:
    """The outcome of a variance run (a :class:`TargetEstimate`) or a cdf run (a :class:`CdfEstimate`)."""
    estimate = result if target == "variance" else result.target
    used = [sampler.samples(int(level), np.arange(int(n))) for level, n in zip(estimate.levels, estimate.n_samples)]
    seconds = float(sum(float(np.sum(batch.cost)) for batch in used))
    seconds_per_cost = seconds / estimate.cost if estimate.cost > 0 else 1.0
    screening = read_screening_record(study.store)
    if screening is not None and screening.seconds_per_cost:
        seconds_per_cost = float(screening.seconds_per_cost)
    mc_cost = _target_mc_cost(study, estimate, used[-1], result if target == "cdf" else None, request)
    extra: list[Diagnostic] = []
    distribution = None if target == "variance" else _distribution_record(result, request, extra)
    return RunOutcome(
        finished=utc_timestamp(),
        estimate=_floats(estimate.estimate), stat_error=_floats(estimate.stat_error),
        bias_estimate=_floats(estimate.bias), is_bias_estimated=estimate.is_bias_estimated,
        rmse=_floats(estimate.rmse), levels=tuple(int(level) for level in estimate.levels),
        n_samples=tuple(int(n) for n in estimate.n_samples), cost=float(estimate.cost), seconds=seconds,
        mc_cost=mc_cost, mc_seconds_predicted=mc_cost * seconds_per_cost, n_computed=sampler.n_computed,
        n_not_converged=count_not_converged(used), tol_met=bool(estimate.tol_met), stop_reason=estimate.stop_reason,
        elapsed=clock.elapsed(sampler),
        diagnostics=_unique([*diagnostics, *extra]), distribution=distribution,
    )


def _floats(values: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in np.atleast_1d(values))


def _target_mc_cost(
    study: Study, estimate: Any, finest: LevelBatch, cdf: Any, request: CdfRequest | None
) -> float:
    """Modelled cost of plain MC on the run's finest level to the run's tolerance.

    ``N = max (per-sample variance of the single-level term) / ((1 - theta) tol^2)``,
    the per-sample variance from the run's own ``Q_L`` values (the level-0
    term of the target computed on level ``L``'s values, with ``L``'s
    bandwidth for a CDF), times the mean modelled cost of one uncoupled
    level-``L`` solve.
    """
    level = int(estimate.levels[-1])
    if cdf is None:
        term = variance_level_term(finest.fine, None)
    else:
        index = study.config.qoi_names.index(request.column)
        term = cdf_level_term(finest.fine, None, level, thresholds=request.thresholds,
                              bandwidth=float(cdf.bandwidths[0]), qoi=index)
    budget = (1.0 - estimate.theta) * np.asarray(estimate.tol, dtype=float)[term.groups] ** 2
    n_mc = max(float(np.max(np.ceil(term.per_sample_variance / budget))), 1.0)
    per_sample = float(np.mean(modelled_cost(study.model, level, finest.n_iter, is_coupled=False)))
    return n_mc * per_sample


def _bound(value: float) -> float | None:
    """A quantile's error-bar end, None where it is beyond the thresholds (infinite)."""
    return float(value) if math.isfinite(value) else None


def _distribution_record(cdf: Any, request: CdfRequest, diagnostics: list[Diagnostic]) -> DistributionRecord:
    """Thresholds, monotone CDF with its band and the quantiles.

    A quantile the grid of thresholds does not bracket is a diagnostic.
    """
    rows = []
    for p in request.probabilities:
        try:
            q = quantiles(cdf, probabilities=[p])
        except EstimationError as exc:
            diagnostics.append(Diagnostic(f"quantile p = {p:g} of {request.column}: {exc}"))
            rows.append(QuantileRecord(probability=p, value=None, lower=None, upper=None))
            continue
        rows.append(QuantileRecord(probability=p, value=float(q.values[0]), lower=_bound(q.lower[0]),
                                   upper=_bound(q.upper[0])))
    return DistributionRecord(
        column=request.column,
        thresholds=_floats(cdf.thresholds),
        cdf=_floats(cdf.cdf),
        cdf_lower=_floats(np.clip(cdf.cdf - cdf.rmse, 0.0, 1.0)),
        cdf_upper=_floats(np.clip(cdf.cdf + cdf.rmse, 0.0, 1.0)),
        bandwidths=_floats(cdf.bandwidths),
        quantiles=tuple(rows),
    )


# ---------------------------------------------------------------------------
# Shards: samples computed elsewhere (cluster jobs) and merged into the study
# ---------------------------------------------------------------------------


def _refuse_existing_shard(out: Path) -> None:
    """The refusal of an ``--out`` that exists: a shard to merge or remove, a study to keep, or another file.

    "merge or remove it first" of a study with a screening or runs advised deleting its results.
    """
    try:
        with open_study_readonly(out) as stored:
            role = stored.role
            has_results = read_screening_record(stored) is not None or bool(read_run_records(stored))
    except (RoughUQError, OSError):
        raise StudyFileError(f"--out {str(out)!r} exists and is not a shard (not a study file); choose another "
                             "--out", out) from None
    if role == "shard":
        raise StudyFileError(f"shard {str(out)!r} already exists; merge it (roughuq merge {shlex.quote(str(out))} "
                             "--into STUDY) or remove it first", out)
    what = " with results (a screening or runs)" if has_results else ""
    raise StudyFileError(f"--out {str(out)!r} is a study file{what}, not a shard; choose another --out", out)


def compute_shard(
    study: Study,
    *,
    stage: int,
    level: int,
    indices: np.ndarray,
    out: str | Path,
    executor: Executor,
    progress: Progress,
) -> Path:
    """Compute samples ``(stage, level, indices)`` of a study into the shard file ``out``.

    The shard is a study file with the study's config and hash holding just
    these samples. It is written under a temporary name and renamed to
    ``out`` only when complete, so a killed job never leaves a partial shard
    under the final name; what a job killed outright left under the
    temporary name (``out.partial-PID`` and its lock) is removed by the next
    run of the shard. The study itself is only read.
    """
    _refuse_writing_the_study(study, out)
    out = Path(out)
    if out.exists():
        _refuse_existing_shard(out)
    if not 0 <= level <= study.config.grid.max_level:
        allowed = f"an integer in 0..{study.config.grid.max_level} (grid.max_level)"
        raise InvalidParameterError("--level", level, allowed)
    abandoned = remove_abandoned(out, ".partial-")  # of this shard, by a run killed outright
    partial = out.with_name(f"{out.name}.partial-{os.getpid()}")
    indices = np.unique(np.asarray(indices, dtype=np.int64))
    shard_store = open_study(
        partial,
        config_text=study.store.config_text,
        config_hash=study.store.config_hash,
        qoi_names=study.store.qoi_names,
        create=True,
        code_version=__version__,
        role="shard",
    )
    shard = Study(study.config, shard_store)
    progress.start(f"shard stage {stage} level {level}")
    for path in abandoned:
        progress.note(f"removed {path.name}, left by a run of this shard that was killed")
    try:
        with shard:
            progress.plan([level], [indices.size], [0])
            StudySampler(shard, stage=stage, executor=executor, progress=progress).compute(level, indices)
    except BaseException:
        partial.unlink(missing_ok=True)
        progress.stop(is_complete=False)
        raise
    try:
        _publish_shard(partial, out)  # a shard that cannot take its name is kept under another, never removed
    except BaseException:
        progress.stop(is_complete=False)
        raise
    progress.stop()
    return out


def _publish_shard(partial: Path, out: Path) -> None:
    """Rename the complete shard ``partial`` to ``out``, never over a file that appeared there meanwhile.

    Two jobs given the same ``--out`` both passed the check at their start, and the second rename replaced the
    first one's shard: both said "130 samples written", one shard's samples were gone. A hard link fails where
    ``out`` exists; the shard is then kept under a name of its own, which the error names (status 2). Where the
    file system has no hard links, a last check and a rename (a window of microseconds instead of the job's run).
    """
    if not _rename_new(partial, out):
        _keep_clashing_shard(partial, out)


def _rename_new(partial: Path, target: Path) -> bool:
    """Rename ``partial`` to ``target`` unless a file has that name (False, ``partial`` left as it is): a hard
    link, which fails where ``target`` exists, then the old name removed; on a file system without hard links
    a check and a rename."""
    try:
        os.link(partial, target)
    except FileExistsError:
        return False
    except OSError as exc:
        if exc.errno not in _NO_HARD_LINKS:
            raise
        if target.exists():
            return False
        os.replace(partial, target)
        return True
    partial.unlink()
    return True


#: What ``os.link`` raises on a file system without hard links (and across devices).
_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS}


def _keep_clashing_shard(partial: Path, out: Path) -> NoReturn:
    """Keep ``partial`` as ``<stem>.<pid><suffix>`` beside ``out``, which another process wrote (or
    ``<stem>.<pid>-<k><suffix>`` where that name is taken too: never over a file), and say so."""
    names = (out.with_name(f"{out.stem}.{os.getpid()}{'' if k == 0 else f'-{k}'}{out.suffix}") for k in range(100))
    kept = next((name for name in names if _rename_new(partial, name)), partial)
    raise StudyFileError(
        f"shard {str(out)!r} was written by another process while this one computed its samples (two jobs with "
        f"the same --out?); this job's shard is kept as {str(kept)!r}: merge both (roughuq merge "
        f"{shlex.quote(str(out))} {shlex.quote(str(kept))} --into STUDY)", out)


def merge_shards(study: Study, shards: Sequence[str | Path]) -> dict[str, int]:
    """Add the samples of shard files to the study.

    Every shard is checked first: the study file itself (also through
    another path or a link), a shard of another config (hash) or with other
    QoI columns is refused before anything is written. Samples already in
    the study are skipped, never counted twice.

    Returns
    -------
    dict
        ``{"added": n, "duplicates": n, "studies": [paths]}``, ``studies`` the inputs that are study files, not
        shards (their samples are added; their screening and run records are not).
    """
    from rough_uq.study.store import DuplicateSampleWarning

    try:
        batches, studies = _read_shards(study, shards)
    except StudyFileError as exc:
        # Damaged rows read "... or start a new study file" (a study's remedy) and not what became of the others.
        text = str(exc).replace("or start a new study file", _SHARD_REMEDY)
        text = text if text.endswith("; nothing was merged") else f"{text}; nothing was merged"
        raise StudyFileError(text, exc.path) from None
    added = duplicates = 0
    for batch in batches:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DuplicateSampleWarning)
            n = study.store.append_samples(batch)
        added += n
        duplicates += batch.n_samples - n
    return {"added": added, "duplicates": duplicates, "studies": studies}


def _read_shards(study: Study, shards: Sequence[str | Path]) -> tuple[list[LevelBatch], list[str]]:
    """Every sample of ``shards``, each checked (:func:`merge_shards`), and the inputs that are study files."""
    batches: list[LevelBatch] = []
    studies = []
    for path in shards:
        _refuse_the_study_itself(study, path)
        with _open_shard(path) as shard:
            _check_shard(study, path, shard)
            if shard.role != "shard":
                studies.append(str(path))
            for level in shard.levels():
                for stage in shard.stages(level=level):
                    batches.append(shard.read_samples(level=level, stage=stage))
    return batches, studies


def _open_shard(path: str | Path) -> StudyFile:
    """A shard for reading; a missing one refused as a shard (it was called a study file)."""
    if not Path(checked_path("shard", path)).exists():
        raise StudyFileError(f"{path}: no such shard file (`roughuq sample --out` writes one)", Path(path))
    return open_study_readonly(path)  # a damaged shard's remedy: merge_shards


#: What to do with a damaged shard, where a study's remedy says "start a new study file".
_SHARD_REMEDY = "or compute the shard again (`roughuq sample`)"


def _is_the_study_file(study: Study, path: str | Path) -> bool:
    """Whether ``path`` is the study's file (same device and inode: another path or a link too)."""
    target = getattr(study.store, "path", None)
    try:
        return target is not None and os.path.samefile(path, target)
    except OSError:  # a missing file
        return False


def _refuse_writing_the_study(study: Study, out: str | Path) -> None:
    """Refuse a shard ``out`` that is the study file (its refusal would otherwise say "remove it first")."""
    if _is_the_study_file(study, out):
        raise InvalidParameterError("--out", str(out), "a new shard file, not the study file (--study) itself")


def _refuse_the_study_itself(study: Study, path: str | Path) -> None:
    """Refuse a shard that is the study file (same file by device and inode: another path or a link too)."""
    target = getattr(study.store, "path", None)
    if _is_the_study_file(study, path):
        raise StudyFileError(
            f"shard {str(path)!r} is the study file {str(target)!r} itself (a file cannot be merged into "
            "itself); nothing was merged",
            path,
        )


def _check_shard(study: Study, path: str | Path, shard: StudyStore) -> None:
    """Refuse a shard of another config, or with other QoI columns than the study's (one of them is damaged)."""
    here = study.store
    if shard.config_hash != here.config_hash:
        shard_config = _readable_config(shard.config_text, source=f"{path} (stored config)")
        differences = _differences_text(shard_config, study.config, there="in the shard", here="in this study")
        raise StudyFileError(
            f"shard {str(path)!r} belongs to another study (config hash {shard.config_hash[:12]}, "
            f"this study {here.config_hash[:12]}{differences}); nothing was merged",
            path,
        )
    if tuple(shard.qoi_names) != tuple(here.qoi_names):
        raise StudyFileError(
            f"shard {str(path)!r} has the study's config hash but other QoI columns ({', '.join(shard.qoi_names)}; "
            f"this study: {', '.join(here.qoi_names)}), so it is damaged; nothing was merged",
            path,
        )


# ---------------------------------------------------------------------------
# Sweeps: one study per value of a config field
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SweepRow:
    """One value of a sweep (:func:`run_sweep`): where its study lives and its MC run.

    Attributes
    ----------
    value : str
        The value of the swept field, as given.
    config, study : str
        Paths of its resolved config and its study file.
    grid : int
        Nodes per side of the sampled level.
    run : RunRecord
    """

    value: str
    config: str
    study: str
    grid: int
    run: RunRecord

    def to_json(self) -> dict[str, Any]:
        """The row as ``roughuq sweep --json`` prints it: the location keys, then the run record's."""
        return {"value": self.value, "config": self.config, "study": self.study, "grid": self.grid,
                **self.run.to_json()}


def run_sweep(
    configs: Sequence[tuple[str, StudyConfig]],
    *,
    key: str,
    directory: str | Path,
    tol: Sequence[str] | None,
    level: int,
    executor: Executor,
    progress: Progress,
    source: str | None = None,
) -> list[SweepRow]:
    """Plain MC on ``level`` for every config of a sweep (:func:`~rough_uq.study.config.sweep_configs`).

    ``configs`` are the sweep of the dotted ``key``. Each value gets its
    config (``<output stem>.yaml``) and its study file in ``directory``; a
    rerun resumes every study. ``tol`` are ``--tol`` strings
    (:func:`parse_tolerances`, per config), each in the unit of its QoI in
    each study. Refused before any file is written, so that a config file
    never disagrees with its study (:class:`InvalidParameterError` unless
    said otherwise): tolerances :func:`parse_tolerances` refuses; a ``tol``
    for the QoI whose ``qoi.<name>.tol`` is ``key`` (it would override every
    swept value: the studies would run the same tolerance); studies that give
    a QoI in different units (one tolerance would ask each for another
    accuracy); ``estimation.initial_samples`` beyond what MC on ``level``
    may draw (:func:`check_initial_samples`; :class:`ConfigError` naming
    ``source``, the swept config's file, or ``--set KEY=VALUE`` where ``key``
    is that field); a study file in ``directory`` written by another config
    (:class:`StudyFileError`).
    """
    directory = Path(directory)
    remedy = f"use another --dir than {str(directory)!r}, or the config and --set of that sweep"
    paths = [directory / Path(config.output.path).name for _, config in configs]
    tolerances = [parse_tolerances(tol, config) for _, config in configs]
    if configs:  # every value has the same QoIs
        _refuse_overridden_tolerance(key, configs[0][1], tol)
    _refuse_mixed_units(key, configs)
    for value, config in configs:
        where = f"--set {key}={value}" if key == "estimation.initial_samples" else source
        check_initial_samples(config, n_levels=1, run=f"a sweep (mc on level {level})", source=where)
    for study_path, (_, config) in zip(paths, configs):
        _refuse_other_config(study_path, config, remedy)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # below a file, no permission: one line, not a traceback
        reason = exc.strerror or str(exc)
        raise StudyFileError(f"cannot write {directory}: {reason}; choose another --dir", directory) from None
    rows = []
    for study_path, tolerance, (value, config) in zip(paths, tolerances, configs):
        config_path = study_path.with_suffix(".yaml")
        with create_study(config, study_path, remedy=remedy, source=source) as study:
            config_path.write_text(resolved_yaml(config))
            record = run_estimation(
                study,
                method="mc",
                tol=tolerance,
                executor=executor,
                progress=PrefixedProgress(progress, f"{key}={value}"),
                level=level,
            )
        rows.append(SweepRow(value=value, config=str(config_path), study=str(study_path),
                             grid=config.grid.n_at(level), run=record))
    return rows


def _refuse_overridden_tolerance(key: str, config: StudyConfig, tol: Sequence[str] | None) -> None:
    """Refuse a ``--tol`` for the QoI whose tolerance ``qoi.<name>.tol`` the sweep of ``key`` varies.

    ``--tol`` takes precedence over the config's tolerance, so every study of
    such a sweep would run the same tolerance: one study computed under
    several names, the swept values ignored.
    """
    section, _, rest = key.partition(".")
    name, _, field = rest.partition(".")
    if section != "qoi" or field != "tol" or not tol:
        return
    given = _given_tolerances(tol, config, option="--tol")
    columns = {column for column, qoi, _ in config.qoi_columns if qoi == name}
    overriding = ", ".join(f"{given_name}={eps:g}" for given_name, eps in given.items()
                           if given_name == name or given_name in columns)
    if overriding:
        raise InvalidParameterError(
            "--tol", ",".join(tol), f"no tolerance for {name} in a sweep of {key}: --tol overrides the swept "
            f"value, so every study would run {overriding} (leave out --tol to run each study at its swept "
            f"tolerance, or give --tol for the other QoIs only)"
        )


def _refuse_mixed_units(key: str, configs: Sequence[tuple[str, StudyConfig]]) -> None:
    """Refuse a sweep whose studies give a QoI in different units (a sweep of ``qoi.<name>.unit``).

    A tolerance, ``--tol`` or ``qoi.<name>.tol``, is a number in each study's
    own unit of the QoI: one number would ask each study for another accuracy
    (0.5 percentage points, or a fraction of 0.5). And a unit only rescales
    the same samples, so such a sweep has nothing to compare.
    """
    if not configs:
        return
    first_value, first = configs[0]
    for value, config in configs[1:]:
        for name, settings in config.qoi.items():
            unit, first_unit = settings.unit_label, first.qoi[name].unit_label
            if unit != first_unit:
                values = ",".join(swept for swept, _ in configs)
                raise InvalidParameterError(
                    "--set", f"{key}={values}", f"values that keep each QoI's unit: {name} would be in {first_unit} "
                    f"(value {first_value}) and in {unit} (value {value}), and a tolerance (--tol or qoi.{name}.tol) "
                    f"is a number in each study's own unit, so one number would ask each study for another accuracy "
                    f"(a unit only rescales the same samples: sweep another field)"
                )
