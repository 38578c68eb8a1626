"""Sweeps: one study per value of a config field, plain MC on one level in each (:func:`run_sweep`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rough_uq.study.config import StudyConfig, resolved_yaml
from rough_uq.errors import InvalidParameterError, StudyFileError
from rough_uq.study.executors import Executor
from rough_uq.study.progress import PrefixedProgress, Progress
from rough_uq.study.records import RunRecord
from rough_uq.study.pipeline.estimation import run_estimation
from rough_uq.study.pipeline.planning import (
    _check_initial_budget, _given_tolerances, check_initial_samples, parse_tolerances,
)
from rough_uq.study.pipeline.studies import _refuse_other_config, create_study


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
    may draw (:func:`check_initial_samples`; :class:`~rough_uq.errors.ConfigError` naming
    ``source``, the swept config's file, or ``--set KEY=VALUE`` where ``key``
    is that field); an ``estimation.max_cost`` below the least cost of those
    samples (:class:`~rough_uq.errors.EstimationError`, named alike); a study
    file in ``directory`` written by another config (:class:`StudyFileError`).
    """
    directory = Path(directory)
    remedy = f"use another --dir than {str(directory)!r}, or the config and --set of that sweep"
    paths = [directory / Path(config.output.path).name for _, config in configs]
    tolerances = [parse_tolerances(tol, config) for _, config in configs]
    if configs:  # every value has the same QoIs
        _refuse_overridden_tolerance(key, configs[0][1], tol)
    _refuse_mixed_units(key, configs)
    for value, config in configs:
        # A budget below a later value's initial samples was refused after the first studies ran, naming the file.
        swept = f"--set {key}={value}"
        check_initial_samples(config, n_levels=1, run=f"a sweep (mc on level {level})",
                              source=swept if key == "estimation.initial_samples" else source)
        _check_initial_budget(config, [level], max_cost=None, model=None, without="the run has no variance estimate",
                              source=swept if key == "estimation.max_cost" else source)
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
