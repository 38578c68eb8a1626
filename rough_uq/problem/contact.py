"""The contact problem of a study, in Python: what one sample computes, and a level sampler of it.

A :class:`ContactProblem` says everything that makes a sample: the random
surface (:class:`~rough_uq.physics.surface.SurfaceSpectrum`), the load
(:mod:`rough_uq.problem.loads`), the quantities of interest and their units,
the grid hierarchy ``n_l = coarsest * 2**l``, the solver settings and the
seed. It needs no config file, no store and no pydantic; it builds the same
:class:`~rough_uq.problem.sampler.ContactModel` that the pipeline builds from
a study config. :class:`ContactSampler` serves its samples to the drivers of
:mod:`rough_uq.multilevel.drivers`, in this process or on an executor.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import KW_ONLY, dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from rough_uq.errors import (
    EstimationWarning,
    InvalidParameterError,
    checked_bool,
    checked_integer,
    is_integer,
    is_one_of,
    is_real_number,
    warn_at_caller,
)
from rough_uq.physics.qoi import AREA_ESTIMATORS, CLUSTER_COUNTS, QOI_NAMES, ordered_names
from rough_uq.physics.surface import PROJECTIONS, SurfaceSpectrum
from rough_uq.problem.batch import LevelBatch
from rough_uq.problem.kept import KeptSamples
from rough_uq.problem.loads import (
    QOI_UNITS,
    AbsoluteLoad,
    RelativeLoad,
    checked_mean_pressures,
    column_names,
    load_sequence,
    positive,
    qoi_scale,
    refuse_loads_beyond_rounding,
)
from rough_uq.problem.memory import memory_warning, physical_memory_bytes
from rough_uq.problem.sampler import ContactModel, compute_batch, is_coupled_stage, modelled_cost, warm_up

if TYPE_CHECKING:
    from collections.abc import Iterable

__all__ = [
    "ContactProblem",
    "ContactSampler",
    "BatchExecutor",
    "ProgressReporter",
    "MAX_GRID",
    "MAX_THREADS",
    "MIN_SOLVER_TOL",
    "MAX_SOLVER_TOL",
]


class BatchExecutor(Protocol):
    """Where samples are computed: ``run(model, items)`` yields one :class:`LevelBatch` per item.

    ``items`` are ``(stage, level, indices)``; batches may come in any order.
    The executors of :mod:`rough_uq.study.executors` have this interface.
    """

    def run(self, model: ContactModel, items: Sequence[tuple[int, int, np.ndarray]]) -> Iterable[LevelBatch]: ...


class ProgressReporter(Protocol):
    """What a run reports its progress to: samples planned and done per level.

    :class:`rough_uq.study.progress.PlainProgress` (lines, e.g. in a notebook
    or a log) and :class:`~rough_uq.study.progress.RichProgress` (bars on a
    terminal) have this interface; the core only calls it.
    """

    def start(self, title: str) -> None: ...

    def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None: ...

    def advance(self, level: int, n: int) -> None: ...

    def stop(self, *, is_complete: bool = True) -> None: ...


_PROGRESS_METHODS = ("start", "plan", "advance", "stop")


def _checked_progress(progress: object) -> ProgressReporter | None:
    """``progress`` if None or a :class:`ProgressReporter`, else :class:`InvalidParameterError` naming it.

    A class (``progress=PlainProgress``, its methods callable too) is refused: its methods would be called
    without an instance.
    """
    is_reporter = not isinstance(progress, type) and all(
        callable(getattr(progress, name, None)) for name in _PROGRESS_METHODS
    )
    allowed = "None or an object with start, plan, advance and stop, e.g. rough_uq.study.progress.PlainProgress()"
    if progress is None or (is_reporter and _takes_is_complete(progress.stop)):  # type: ignore[union-attr]
        return progress  # type: ignore[return-value]
    if is_reporter:  # a stop() without it turned a Ctrl-C into a TypeError from the run's clean-up
        allowed += "; its stop must take the keyword is_complete, with a default: stop(self, *, is_complete=True)"
    if isinstance(progress, type):
        allowed += f" (an instance: {progress.__name__}(), not the class)"
    raise InvalidParameterError("progress", progress, allowed)


def _takes_is_complete(stop: Callable[..., object]) -> bool:
    """Whether ``stop(is_complete=False)`` and ``stop()`` both bind, as the runs call it (True where the signature
    cannot be read, e.g. a builtin): ``stop(self, is_complete)`` without its default failed at the end of every
    run that finished."""
    try:
        signature = inspect.signature(stop)
    except (TypeError, ValueError):  # no signature to read
        return True
    try:
        signature.bind(is_complete=False)
        signature.bind()
    except TypeError:
        return False
    return True


#: The largest grid (nodes per side) of a hierarchy. One solve at 65536^2 needs
#: some 640 GiB (20 grid-sized arrays of 8 bytes) and far more time than a study
#: has; a larger ``max_level`` is a typo, and it would overflow the arithmetic of
#: grid sizes (2**1000) before any memory check could say so.
MAX_GRID = 65536


#: The smallest ``solver_tol`` a problem takes. Below it rounding stops the
#: solver before the tolerance: the error stalls at a floor and every solve runs
#: ``max_iter`` plus ``RETRY_FACTOR * max_iter`` iterations in vain (1e-17 took 13 s
#: for one coupled 16^2/8^2 sample; hours on real grids). Measured with
#: ``solve_contact`` (max_iter 500) on seeded surfaces (L = 2, k_l = k_r = 2,
#: k_s = 32, H = 0.8; seeds 1-3) at loads 0.01, 0.1 and 1 times the RMS slope,
#: converged solves of 9 per grid at tol 1e-12 / 1e-13 / 1e-14 / 1e-15:
#: 64^2 9/9/9/7, 128^2 9/9/9/3, 256^2 9/9/6/4, 512^2 9/9/3/2; at 1024^2 (2
#: solves) 2/1/0 at 1e-12 / 1e-13 / 1e-14; at 2048^2 one solve (load 0.1) stalled
#: after 69 iterations at all three. The floor rises with the grid, so a
#: tolerance above the bound may still end unconverged on a large grid; the
#: bound refuses only tolerances that no grid reaches reliably (1e-14 does on
#: 64^2 and 128^2).
MIN_SOLVER_TOL = 1e-14

#: The largest ``solver_tol`` a problem takes. Looser solves are not contact
#: solutions that a study could average: on three seeded 256^2 surfaces (L = 2,
#: k_l = k_r = 2, k_s = 64, H = 0.8, load 0.1 times the RMS slope) the contact
#: area at tol 0.1 / 0.03 / 0.01 / 1e-3 was off that at 1e-7 by up to 30 / 5.5 /
#: 3.0 / 0.4 % (0.9 gave 100 % after no iteration, "converged"); a QoI
#: tolerance written under ``solver`` by mistake was taken. At 1e-2 a solve
#: still says something on a quick look; studies keep the default 1e-7. A new
#: config refuses more; a problem warns (a study file's stored config from
#: before the bound is read as it was).
MAX_SOLVER_TOL = 1e-2


#: The most threads per solve: ``rough_uq.physics.solver.MAX_THREADS``, which says why (a copy: this module
#: loads no numba; tests/test_problem_arguments.py checks they agree).
MAX_THREADS = 1024


def _qoi_names(qoi: object) -> tuple[str, ...]:
    allowed = "a name or a list of distinct names from " + ", ".join(QOI_NAMES)
    if isinstance(qoi, Mapping):
        # The config file's qoi section maps names to settings; taken as its keys, the settings would be lost.
        raise InvalidParameterError("qoi", qoi, allowed + " (not a mapping of settings as in the config file: "
                                    "give units=, connectivity= and area_estimator= to ContactProblem and each "
                                    "QoI's tol to the run)")
    names = ordered_names("qoi", qoi, allowed)
    if not names or any(name not in QOI_NAMES for name in names) or len(set(names)) != len(names):
        raise InvalidParameterError("qoi", qoi, allowed)
    return names


def _units(units: object, names: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """The units given as ``(name, unit)`` pairs in the order of ``names``, those equal to the default left
    out: the same problem compares equal whether a default unit was given or not, and a problem made by
    ``dataclasses.replace`` with fewer QoIs does not carry the units of those it dropped."""
    if units is None:
        units = {}
    if not isinstance(units, Mapping):
        pairs = tuple(units) if isinstance(units, (tuple, list)) else None
        allowed = "a mapping from QoI name to unit, e.g. {'contact_area': 'fraction'}"
        if pairs is None or not all(isinstance(p, tuple) and len(p) == 2 and isinstance(p[0], str) for p in pairs):
            raise InvalidParameterError("units", units, allowed)
        repeated = sorted({name for name, _ in pairs if sum(other == name for other, _ in pairs) > 1}, key=str)
        if repeated:
            raise InvalidParameterError("units", units, allowed + f" (one unit per QoI; given twice: "
                                        f"{', '.join(map(str, repeated))})")
        units = dict(pairs)
    for name, unit in units.items():
        if not is_one_of(name, names):
            raise InvalidParameterError("units", name, "a QoI of this problem: " + ", ".join(names))
        qoi_scale(name, unit, system_size=1.0)  # refuses a unit the QoI does not have
    # str(): the plain text of a numpy string (np.str_('fraction') was kept and shown so in the results' units).
    return tuple((name, str(units[name])) for name in names
                 if units.get(name, QOI_UNITS[name][0]) != QOI_UNITS[name][0])


def _choice(name: str, value: object, allowed: tuple) -> object:
    # 8.0 == 8: a number must be an integer to stand for one of the allowed integers.
    if isinstance(value, bool) or (is_real_number(value) and not is_integer(value)) or not is_one_of(value, allowed):
        raise InvalidParameterError(name, value, " or ".join(repr(a) for a in allowed))
    return allowed[allowed.index(value)]  # the plain value: np.int64(8) is kept as 8, np.str_ as str


@dataclass(frozen=True)
class ContactProblem:
    """A random contact problem on a hierarchy of grids: what one sample computes.

    Parameters
    ----------
    spectrum : SurfaceSpectrum
        The random surface (carries the box side ``L``, lengths in its unit).
    load : RelativeLoad, AbsoluteLoad, or a sequence of them
        The imposed mean pressure (:mod:`rough_uq.problem.loads`), or a load
        curve: distinct loads of one kind, e.g.
        ``[RelativeLoad(0.01), RelativeLoad(0.05), RelativeLoad(0.1)]``
        (stored as a tuple). Each surface is then solved along the increasing
        loads with warm starts, and every QoI becomes one result column per
        load, named ``<qoi>@<load>`` (:attr:`columns`). Every load must give
        a mean pressure that a solve on the finest grid takes
        (:func:`checked_mean_pressures`: a dimensionless load
        ``p_mean L / (E* rms_height)`` in about ``[2e-298, 1e15]``), and at most
        ``max_convergent_load(solver_tol)`` (:func:`refuse_loads_beyond_rounding`).
    qoi : str or sequence of str
        Quantities of interest, in column order of every result (names of
        :data:`~rough_uq.physics.qoi.QOI_NAMES`). Stored as a tuple. A set
        is refused: its order, and so the columns', would change from one
        process to the next.
    coarsest : int
        Nodes per side ``n_0`` of level 0, even, ``> 2 k_r`` (the coarsest
        grid resolves the roll-off). Level ``l`` has ``n_0 2^l`` nodes per side.
    units : mapping of str to str, optional
        Unit per QoI where not the default (:data:`~rough_uq.problem.loads.QOI_UNITS`),
        e.g. ``{"contact_area": "fraction"}`` (or a sequence of ``(name, unit)`` pairs, each name once).
        Stored as a tuple of pairs in the order of ``qoi``, without those equal to the default
        (:attr:`qoi_units` has every QoI's).
    e_star : float
        Effective modulus ``E*``, > 0, in the pressure unit of the problem: absolute loads,
        ``critical_pressure`` and ``max_pressure`` are in the unit ``e_star`` is given in, not divided
        by it (:mod:`~rough_uq.problem.loads`). Default 1.
    max_level : int
        Finest level MLMC may add, >= 0, with ``coarsest * 2**max_level <=``
        :data:`MAX_GRID`. Default 4.
    projection : {"truncation", "injection"}
        How the coarse surface of a coupled sample is obtained
        (:func:`~rough_uq.physics.surface.sample_coupled`); injection needs
        ``k_s < coarsest / 2``.
    connectivity : {4, 8, "mean"}
        Neighbourhood of ``clusters``, or the mean of the 4- and 8-connected
        counts (:func:`~rough_uq.physics.qoi.cluster_count`).
    area_estimator : {"corrected", "nodes"}
        Estimator of ``contact_area`` (:func:`~rough_uq.physics.qoi.contact_area`):
        perimeter-corrected (default) or the node count.
    critical_pressure : float, optional
        Threshold of ``area_above`` (unit of ``E*``), > 0; required with it.
    seed : int
        Seed of all random streams, >= 0 (SPEC section 7). Default 0.
    solver_tol : float
        Relative stopping tolerance of the contact solver, in
        ``[MIN_SOLVER_TOL, 1)`` (:data:`MIN_SOLVER_TOL` = 1e-14, what rounding
        lets the solver reach; above :data:`MAX_SOLVER_TOL` = 1e-2 a solve is no
        contact solution: an :class:`~rough_uq.errors.EstimationWarning`; the
        config's ``solver.tol``, default 1e-7, refuses it).
    max_iter : int
        Iterations per solve before a retry (:mod:`rough_uq.problem.sampler`), >= 1.
    warm_start : bool
        Start the fine solve of a coupled sample from the coarse pressure.
    threads : int
        FFTW / numba threads per solve, 1 to :data:`MAX_THREADS`.

    Raises
    ------
    InvalidParameterError
        Naming the field that is out of range (a load as ``load.relative`` or
        ``load.absolute``, with its position in a load curve).
    """

    spectrum: SurfaceSpectrum
    _: KW_ONLY
    load: RelativeLoad | AbsoluteLoad
    qoi: tuple[str, ...]
    coarsest: int
    units: tuple[tuple[str, str], ...] = ()
    e_star: float = 1.0
    max_level: int = 4
    projection: str = "truncation"
    connectivity: int | str = 4
    area_estimator: str = "corrected"
    critical_pressure: float | None = None
    seed: int = 0
    solver_tol: float = 1e-7
    max_iter: int = 10_000
    warm_start: bool = True
    threads: int = 1
    _model: ContactModel = field(init=False, repr=False, compare=False)
    _kept: KeptSamples = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.spectrum, SurfaceSpectrum):
            raise InvalidParameterError("spectrum", self.spectrum, "a rough_uq.SurfaceSpectrum")
        set_ = object.__setattr__
        loads = load_sequence(self.load)
        if not isinstance(self.load, (RelativeLoad, AbsoluteLoad)):
            set_(self, "load", loads)
        names = _qoi_names(self.qoi)
        set_(self, "qoi", names)
        set_(self, "units", _units(self.units, names))
        set_(self, "e_star", positive("e_star", self.e_star))
        self._check_grids()
        pressures = checked_mean_pressures(
            loads, spectrum=self.spectrum, e_star=self.e_star, finest=self.grid(self.max_level)
        )
        set_(self, "connectivity", _choice("connectivity", self.connectivity, CLUSTER_COUNTS))
        set_(self, "area_estimator", _choice("area_estimator", self.area_estimator, AREA_ESTIMATORS))
        if self.critical_pressure is not None:
            set_(self, "critical_pressure", positive("critical_pressure", self.critical_pressure))
        elif "area_above" in names:
            raise InvalidParameterError("critical_pressure", None, "a number > 0 when 'area_above' is asked for")
        self._check_solver()
        refuse_loads_beyond_rounding(
            loads, pressures, spectrum=self.spectrum, e_star=self.e_star, solver_tol=self.solver_tol
        )
        set_(self, "_model", self._build_model())
        set_(self, "_kept", KeptSamples())

    def __getstate__(self) -> dict:
        # A pickled (or copied) problem leaves its kept samples behind: loaded by another version of rough_uq,
        # they would be another solver's numbers, and a pickle would grow with every run.
        return {name: value for name, value in self.__dict__.items() if name != "_kept"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        object.__setattr__(self, "_kept", KeptSamples())

    def _check_grids(self) -> None:
        set_ = object.__setattr__
        k_r, k_s = self.spectrum.k_r, self.spectrum.k_s
        n_0 = checked_integer("coarsest", self.coarsest, 4)
        if n_0 % 2 or not 2 * k_r < n_0 <= MAX_GRID:  # not n_0 / 2: an integer such as 10**400 has no float
            raise InvalidParameterError(
                "coarsest", self.coarsest,
                f"an even integer >= 4, > 2 k_r = {2 * k_r:g} (Nyquist) and <= {MAX_GRID} (MAX_GRID)",
            )
        set_(self, "coarsest", n_0)
        max_level = checked_integer("max_level", self.max_level, 0)
        # The level first: n_0 * 2**max_level of a max_level such as 2**63 would never finish.
        if max_level > MAX_GRID.bit_length() or n_0 * 2**max_level > MAX_GRID:
            raise InvalidParameterError(
                "max_level", self.max_level, f"a finest grid coarsest * 2**max_level <= {MAX_GRID} (MAX_GRID)"
            )
        set_(self, "max_level", max_level)
        set_(self, "projection", _choice("projection", self.projection, PROJECTIONS))
        if self.projection == "injection" and not k_s < n_0 / 2:
            raise InvalidParameterError(
                "projection", self.projection, f"'truncation', or injection with k_s < coarsest / 2 = {n_0 // 2}"
            )

    def _check_solver(self) -> None:
        set_ = object.__setattr__
        set_(self, "seed", checked_integer("seed", self.seed, 0))
        tol = self.solver_tol
        if not (is_real_number(tol) and MIN_SOLVER_TOL <= tol < 1):
            raise InvalidParameterError(
                "solver_tol", tol, f"a number in [{MIN_SOLVER_TOL:g}, 1) (MIN_SOLVER_TOL: below it rounding stops the "
                "solver before the tolerance, and every solve would run max_iter and its retry in vain)"
            )
        if tol > MAX_SOLVER_TOL:
            # A warning, not a refusal: a study file's config from before the config's bound (any tol < 1) must
            # still be read, reported and resumed.
            warn_at_caller(f"solver_tol {tol:g} is above MAX_SOLVER_TOL = {MAX_SOLVER_TOL:g}: a solve this loose "
                           "is no contact solution (at 0.1 contact areas were off by up to 30 %); use 1e-7, the "
                           "default", EstimationWarning)
        set_(self, "solver_tol", float(tol))
        set_(self, "max_iter", checked_integer("max_iter", self.max_iter, 1))
        set_(self, "warm_start", checked_bool("warm_start", self.warm_start))
        set_(self, "threads", checked_integer("threads", self.threads, 1, MAX_THREADS))

    def _build_model(self) -> ContactModel:
        scales = tuple(
            qoi_scale(name, unit, system_size=self.spectrum.system_size) for name, unit in zip(self.qoi, self.qoi_units)
        )
        return ContactModel(
            spectrum=self.spectrum,
            coarsest=self.coarsest,
            projection=self.projection,
            e_star=self.e_star,
            mean_pressure=self.mean_pressures[0],
            mean_pressures=self.mean_pressures if self.n_loads > 1 else (),
            qoi_names=self.qoi,
            qoi_scales=scales,
            seed=self.seed,
            tol=self.solver_tol,
            max_iter=self.max_iter,
            warm_start=self.warm_start,
            threads=self.threads,
            connectivity=self.connectivity,
            critical_pressure=self.critical_pressure,
            area_estimator=self.area_estimator,
        )

    @property
    def loads(self) -> tuple[RelativeLoad | AbsoluteLoad, ...]:
        """The loads, in column order (one for a single load)."""
        return load_sequence(self.load)

    @property
    def n_loads(self) -> int:
        """Number of loads per surface."""
        return len(self.loads)

    @property
    def mean_pressures(self) -> tuple[float, ...]:
        """The imposed mean pressure of every load (unit of ``E*``), in column order."""
        return tuple(load.mean_pressure(spectrum=self.spectrum, e_star=self.e_star) for load in self.loads)

    @property
    def mean_pressure(self) -> float:
        """The imposed mean pressure ``p_mean`` (unit of ``E*``); of the first load for a load curve."""
        return self.mean_pressures[0]

    @property
    def columns(self) -> tuple[str, ...]:
        """Names of the result columns: ``qoi``, or ``<qoi>@<load>`` per load for a load curve, QoI-major."""
        return column_names(self.qoi, tuple(load.value for load in self.loads))

    @property
    def qoi_units(self) -> tuple[str, ...]:
        """Unit of each QoI, in the order of ``qoi``."""
        given = dict(self.units)
        return tuple(given.get(name, QOI_UNITS[name][0]) for name in self.qoi)

    @property
    def column_units(self) -> tuple[str, ...]:
        """Unit of each result column (:attr:`columns`, QoI-major): its QoI's."""
        return tuple(unit for unit in self.qoi_units for _ in self.loads)

    @property
    def n_qoi(self) -> int:
        """Number of result columns (:attr:`columns`): quantities of interest times loads."""
        return len(self.columns)

    @property
    def model(self) -> ContactModel:
        """The :class:`~rough_uq.problem.sampler.ContactModel` that computes the samples."""
        return self._model

    def grid(self, level: int) -> int:
        """Nodes per side of ``level``, ``coarsest * 2**level``."""
        return self.coarsest * 2 ** checked_integer("level", level, 0)

    def sampler(
        self, stage: int, *, executor: BatchExecutor | None = None, progress: ProgressReporter | None = None,
        plans_asked: bool = False, least_level: int = 0,
    ) -> ContactSampler:
        """The level sampler (:mod:`rough_uq.multilevel.drivers` contract) of random stage ``stage``.

        Parameters
        ----------
        stage : int
            Stage of the random streams: :data:`~rough_uq.problem.batch.STAGE_SCREENING`
            (0) or a run's stage (:func:`~rough_uq.problem.sampler.run_stage`). Samples
            of screening and odd stages are coupled (fine and coarse solve of
            one surface), of even stages fine only (plain MC).
        executor : BatchExecutor, optional
            Where samples are computed (e.g. :mod:`rough_uq.study.executors`);
            default: in this process.
        progress : ProgressReporter, optional
            Told of every sample done (:attr:`ContactSampler.progress`).
        plans_asked : bool
            Also report the samples asked for so far as the plan (for runs
            whose estimator announces no plan).
        least_level : int
            The finest level the run samples at least (2 for a screening or an
            MLMC run): below it a memory warning advises a smaller coarsest
            grid, not a lower level.

        Every sample its samplers compute is kept with the problem (:mod:`rough_uq.problem.kept`): asked for
        again, it is given back, not solved again (a run interrupted by Ctrl-C and made again goes on from
        where it stopped). A problem made by ``dataclasses.replace`` starts with none.
        """
        if executor is not None and not callable(getattr(executor, "run", None)):
            raise InvalidParameterError(
                "executor", executor, "None (this process) or an executor with run(model, items), e.g. "
                "rough_uq.study.executors.PoolExecutor"
            )
        stage = checked_integer("stage", stage, 0)
        return ContactSampler(self.model, stage=stage, executor=executor, max_level=self.max_level,
                              progress=_checked_progress(progress), plans_asked=bool(plans_asked), kept=self._kept,
                              least_level=least_level)


def _checked_level(level: object, max_level: int | None) -> int:
    """``level`` as an int, or :class:`InvalidParameterError` naming ``level`` unless an integer in 0..max_level."""
    top = "" if max_level is None else f" and <= max_level = {max_level}"
    if not (is_integer(level) and 0 <= level and (max_level is None or level <= max_level)):
        raise InvalidParameterError("level", level, f"an integer >= 0{top} (the problem's levels)")
    return int(level)


def _checked_indices(indices: object) -> np.ndarray:
    """``indices`` as a flat int64 array, or :class:`InvalidParameterError` naming ``indices`` unless integers >= 0.

    Integers of any numpy integer dtype (or a list of ints) are taken; floats
    (even integral ones), booleans and negative numbers are refused, never converted.
    """
    allowed = "integers >= 0 (sample indices; an int, a sequence of ints or an integer array)"
    try:
        array = np.asarray(indices).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidParameterError("indices", indices, allowed) from None
    if array.size == 0:
        return np.zeros(0, dtype=np.int64)
    if array.dtype.kind not in "iu" or array.min() < 0 or array.max() > np.iinfo(np.int64).max:
        raise InvalidParameterError("indices", indices, allowed)
    return array.astype(np.int64)


def _ordered(batches: Sequence[LevelBatch], indices: np.ndarray) -> LevelBatch:
    """The rows of ``batches`` (in any order) for ``indices``, in the order of ``indices``."""
    names = ("indices", "fine", "coarse", "cost", "n_iter", "converged")
    joined = {name: np.concatenate([getattr(b, name) for b in batches]) for name in names}
    row_of = {int(index): row for row, index in enumerate(joined["indices"])}
    rows = np.array([row_of[int(index)] for index in indices], dtype=np.int64)
    return LevelBatch(level=batches[0].level, stage=batches[0].stage, **{n: v[rows] for n, v in joined.items()})


class ContactSampler:
    """Samples of a contact model on one stage, as the estimators ask for them.

    ``sampler(level, indices)`` returns ``(fine, coarse, cost)``: QoIs of
    shape ``(n, n_qoi)`` in the problem's units and the modelled cost of each
    sample, shape ``(n,)``, in reference seconds
    (:func:`~rough_uq.problem.sampler.modelled_cost`, as the pipeline plans with).

    Attributes
    ----------
    model : ContactModel
    stage : int
    max_level : int or None
        The finest level a batch may ask for (the problem's); None: no bound.
    n_samples : int
        Samples given so far (in whole batches), computed or kept from before (``kept``).
    n_computed : int
        Samples computed here so far (one by one, also those of a batch interrupted before its end).
    n_not_converged : int
        Samples among them with a solve that did not converge (kept, with
        the QoIs of the last iterate; :mod:`rough_uq.problem.sampler`).
    seconds : float
        Wall time of the samples computed so far (s; summed over workers).
        Before its first sample computed in this process a sampler runs
        :func:`~rough_uq.problem.sampler.warm_up`, uncounted, so that loading
        the kernels (about 0.3 s in a fresh process) is not timed as a sample.
    progress : ProgressReporter or None
        Told (``advance``) of each sample as it is done; with ``plans_asked``
        the samples asked for so far per level are its plan. In this process
        a batch is then computed one sample at a time (the same numbers).
    kept : KeptSamples or None
        Samples computed before (the problem's, :mod:`rough_uq.problem.kept`): those asked for again are
        given back (counted in ``n_samples`` and ``n_not_converged``, not in ``seconds``); every sample
        computed is added. None: none kept.
    """

    def __init__(
        self, model: ContactModel, *, stage: int, executor: BatchExecutor | None = None, max_level: int | None = None,
        progress: ProgressReporter | None = None, plans_asked: bool = False, kept: KeptSamples | None = None,
        least_level: int = 0,
    ) -> None:
        self.model = model
        self.least_level = least_level
        self.kept = kept
        self._kept_before = 0 if kept is None else len(kept)
        self.stage = stage
        self.executor = executor
        self.max_level = max_level
        self.progress = progress
        self.plans_asked = plans_asked
        self.n_samples = 0
        self.n_computed = 0
        self.n_not_converged = 0
        self.seconds = 0.0
        self._is_warm = False
        self._asked: dict[int, int] = {}
        self._memory_checked: set[int] = set()

    def batch(self, level: int, indices: np.ndarray) -> LevelBatch:
        """Samples ``(stage, level, i)`` for ``i`` in ``indices``, in that order, with their solver records.

        Raises
        ------
        InvalidParameterError
            Naming ``level`` unless an integer in ``0..max_level``, or
            ``indices`` unless integers >= 0.
        """
        level = _checked_level(level, self.max_level)
        indices = _checked_indices(indices)
        if self.progress is not None and self.plans_asked:
            done = dict(self._asked)  # every batch asked for before is done
            self._asked[level] = done.get(level, 0) + int(indices.size)
            levels = sorted(self._asked)
            self.progress.plan(levels, [self._asked[lv] for lv in levels], [done.get(lv, 0) for lv in levels])
        given, missing = (None, indices) if self.kept is None else self.kept.split(self.stage, level, indices)
        pieces = [] if given is None else [given]
        if given is not None and self.progress is not None:
            self.progress.advance(level, given.n_samples)
        if missing.size or given is None:  # an empty batch is computed as before (an empty LevelBatch)
            pieces.extend(self._computed(level, missing))
        batch = pieces[0] if len(pieces) == 1 else _ordered(pieces, indices)
        self.n_samples += batch.n_samples
        self.n_not_converged += batch.n_not_converged
        return batch

    @property
    def n_kept(self) -> int:
        """Samples this sampler computed and kept: what ``kept`` gained since the sampler was made (exact
        whatever an interrupt interrupts, where ``n_computed`` may lag by a piece); ``n_computed`` without ``kept``."""
        return self.n_computed if self.kept is None else len(self.kept) - self._kept_before

    def _computed(self, level: int, indices: np.ndarray) -> Iterator[LevelBatch]:
        """The pieces of :meth:`_pieces`, each counted, kept and reported as soon as it is done."""
        for piece in self._pieces(level, indices):
            if self.kept is not None:
                self.kept.add(piece)
            self.n_computed += piece.n_samples  # after add: an interrupt between them counts no unkept sample
            self.seconds += float(np.sum(piece.cost))
            if self.progress is not None:
                self.progress.advance(level, piece.n_samples)
            yield piece

    def _warn_memory(self, level: int) -> None:
        """An :class:`~rough_uq.errors.EstimationWarning` before the first solves of ``level`` if they need more
        than this machine's physical memory (:mod:`rough_uq.problem.memory`; the CLI prints the same line)."""
        if level in self._memory_checked or not getattr(self.executor, "runs_here", True):
            return
        self._memory_checked.add(level)
        grids = [self.model.grid(lv) for lv in range(level + 1)]
        n_workers = int(getattr(self.executor, "n_workers", 1)) if self.executor is not None else 1
        text = memory_warning(grids, level, n_workers, physical_memory_bytes(),
                              lower_with="a smaller max_level, or mc's level=",
                              workers="an executor with n_workers = {}", smaller_coarsest="a smaller coarsest",
                              least_level=self.least_level)
        if text:
            warn_at_caller(text, EstimationWarning)

    def _pieces(self, level: int, indices: np.ndarray) -> Iterator[LevelBatch]:
        """The samples of ``indices`` in batches as they are done: one (or, with progress, one per sample) here."""
        self._warn_memory(level)
        if self.executor is None or indices.size <= 1:
            if not self._is_warm:
                # Load the kernels before the first sample computed here is timed
                # (its `seconds`); a few ms once they are loaded in this process.
                warm_up(self.model)
                self._is_warm = True
            parts = [indices] if self.progress is None or indices.size <= 1 else np.split(indices, indices.size)
            for part in parts:
                yield compute_batch(self.model, stage=self.stage, level=level, indices=part)
        else:
            items = [(self.stage, level, indices[i : i + 1]) for i in range(indices.size)]
            yield from self.executor.run(self.model, items)

    def __call__(self, level: int, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        batch = self.batch(level, indices)
        cost = modelled_cost(self.model, level, batch.n_iter, is_coupled=is_coupled_stage(self.stage))
        return batch.fine, batch.coarse, cost
