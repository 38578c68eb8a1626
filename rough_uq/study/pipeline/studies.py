"""Study = config + store + model: build the contact model of a config, create and open study files.

:func:`build_model` makes the :class:`~rough_uq.problem.sampler.ContactModel` of a config with the load and unit
conversions of :mod:`rough_uq.problem.loads` (a relative load is ``relative * E* * rms_slope``, SPEC section 6;
``percent`` scales fractions by 100, ``per_area`` divides cluster counts by ``L^2``); :func:`create_study` and
:func:`open_existing_study` give a :class:`Study` (config, store and model) and refuse a file of another config;
:func:`problem_of_config` and :func:`load_problem` are the Python API's way in to a config or a study file.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import yaml

from rough_uq import __version__
from rough_uq.study.config import (
    StudyConfig, SurfaceConfig, config_differences, config_from_stored_text, config_hash, load_config, resolved_yaml,
)
from rough_uq.errors import ConfigError, InvalidParameterError, RoughUQError, StudyFileError, checked_path
from rough_uq.study.fft_wisdom import prepare_wisdom
from rough_uq.problem.contact import ContactProblem
from rough_uq.problem.loads import AbsoluteLoad, RelativeLoad
from rough_uq.problem.sampler import ContactModel
from rough_uq.study.store import (
    StudyStore,
    checked_study_path,
    is_hdf5_file,
    lock_if_free,
    open_study,
    open_study_readonly,
)
from rough_uq.physics.surface import SurfaceSpectrum


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
    checks it (:func:`~rough_uq.problem.loads.checked_mean_pressures` on the
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
    it makes the same choices from the same screening (:func:`~rough_uq.study.pipeline.screening.load_screening`)
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
        if not existed:
            # Under the file's lock: a file another process has just created and holds is its own, however empty
            # (two `screen`s on one new study: the one refused as "locked" removed the other's file).
            with lock_if_free(path) as is_free:
                if is_free and path.is_file() and _is_unused(path):
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
