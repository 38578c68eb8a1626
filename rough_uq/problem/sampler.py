"""Level samples: how one contact sample is computed, and what a batch of them carries.

A *level* ``l`` is the grid ``n_l = n_0 * 2**l``. A sample on level ``l``
gives the quantities of interest on that grid (``fine``) and, from the same
surface realisation projected on grid ``n_{l-1}``, on the next coarser one
(``coarse``; zero on level 0). Samples are identified by ``(stage, level,
index)``, which is also the key of their random stream (SPEC section 7)::

    rng = Generator(PCG64(SeedSequence(seed, spawn_key=(stage, level, index))))

so any sample can be recomputed alone, in any process, in any order.

Stages
------
``STAGE_SCREENING`` (0) holds the screening samples; every estimation run has
a stage of its own (SPEC section 7: two runs never share a random stream),
derived from the run's name by :func:`run_stage`, so that rerunning the same
command (or computing its samples as shards on a cluster) finds the same
stage without any bookkeeping. The stage also says whether samples are
coupled: screening and MLMC stages are (odd run stages), plain MC stages are
not (even run stages: only the fine grid is solved, ``coarse`` is zero).

Cost
----
Planning needs each sample's cost, and the plan must not depend on how fast a
particular process happened to run, or the same study would draw different
``N_l`` serially and on a cluster. The cost handed to the estimators is
therefore *modelled* (:func:`modelled_cost`): reference seconds computed from
the grid sizes and solver iteration counts, with constants fitted once on the
reference machine. The measured wall time is kept beside it (``LevelBatch.cost``)
and reported.

Load curves
-----------
A model with several loads (``mean_pressures``) solves each surface along the
increasing loads (:func:`~rough_uq.physics.load_curve.solve_load_curve`).
The coarse grid follows the sequence, each load warm-started from the
previous one. With ``warm_start`` every fine load starts from the coarse
pressure at the same load, as a single load does (a better guess than the
previous fine load's: module docstring there); without it the fine grid
follows the sequence too. The QoI vector
of a sample then has ``n_qoi_names * n_loads`` columns, QoI-major, in the
order of ``mean_pressures`` (names in :mod:`rough_uq.problem.loads`). A
sample's ``n_iter`` and ``converged`` cover all loads of its grid (summed,
and all converged).

Non-convergence
---------------
A solve that does not reach ``tol`` within ``max_iter`` is continued from
where it stopped for ``RETRY_FACTOR * max_iter`` more iterations. If it still
fails, the sample keeps the QoIs of its last iterate and is flagged
(``converged`` False); the pipeline counts and reports flagged samples and
never drops them silently.
"""

from __future__ import annotations

import hashlib
import math
import signal
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np

from rough_uq.problem.batch import STAGE_SCREENING, LevelBatch
from rough_uq.physics.fft import use_wisdom
from rough_uq.physics.load_curve import LoadCurveSolution, solve_load_curve
from rough_uq.physics.qoi import evaluate_qoi
from rough_uq.physics.solver import ContactSolution
from rough_uq.physics.surface import SurfaceSpectrum, sample_coupled, sample_surface

__all__ = [
    "LevelBatch",
    "ContactModel",
    "STAGE_SCREENING",
    "is_coupled_stage",
    "run_stage",
    "RETRY_FACTOR",
    "sample_rng",
    "modelled_cost",
    "measured_seconds_per_cost",
    "cost_rate_beyond",
    "compute_batch",
    "warm_up",
    "SampleSolution",
    "solve_sample",
]

#: A non-converged solve is continued for this many times ``max_iter`` more iterations.
RETRY_FACTOR = 10

#: Cost model of one solve, ``(n_iter + COST_EXTRA_ITERATIONS) * (COST_PER_POINT
#: * n^2 log2(n^2) + COST_PER_ITERATION)`` reference seconds. Fitted on the
#: reference machine (2 cores, 1 thread per solve, 2026-11-23, refitted for the
#: preconditioned solver; within 15% from 32^2 to 512^2 there,
#: ``scripts/calibrate_cost.py``); the extra iterations stand for the surface
#: synthesis and the QoIs.
COST_PER_POINT = 1.9e-9
COST_PER_ITERATION = 6.8e-5
COST_EXTRA_ITERATIONS = 2


@dataclass(frozen=True)
class ContactModel:
    """Everything needed to compute a sample: the random surface, the contact problem and the QoIs.

    Built by the pipeline from a study config; picklable, so worker processes
    receive it once.

    Attributes
    ----------
    spectrum : SurfaceSpectrum
        The surface's power spectrum (carries the box side ``L``).
    coarsest : int
        Nodes per side of level 0, ``n_0``.
    projection : {"truncation", "injection"}
        How the coarse surface of a coupled sample is obtained.
    e_star : float
        Effective modulus (pressure unit).
    mean_pressure : float
        Imposed mean pressure (unit of ``e_star``); with a load curve the
        first of ``mean_pressures``.
    qoi_names : tuple of str
        Quantities of interest, in column order (:data:`rough_uq.physics.qoi.QOI_NAMES`);
        with a load curve each one is a block of ``n_loads`` columns.
    qoi_scales : tuple of float
        Factor from the raw QoI (area fraction, cluster count, ...) to its
        reported unit (e.g. 100 for percent), one per QoI.
    seed : int
        Study seed.
    tol, max_iter, warm_start, threads
        Solver settings (:func:`~rough_uq.physics.solver.solve_contact`); with
        ``warm_start`` the fine solve starts from the coarse pressure.
    connectivity : {4, 8, "mean"}
        Cluster connectivity, or the mean of both counts
        (:func:`~rough_uq.physics.qoi.cluster_count`).
    critical_pressure : float or None
        Threshold of ``area_above``.
    area_estimator : {"corrected", "nodes"}
        Estimator of ``contact_area`` (:func:`~rough_uq.physics.qoi.contact_area`).
    fft_wisdom : tuple of bytes or None
        FFTW wisdom that every process computing samples plans from
        (:func:`rough_uq.physics.fft.use_wisdom`), so that all use the same plans;
        ``None``: ``FFTW_ESTIMATE`` plans. Not part of the model's identity.
    mean_pressures : tuple of float
        The loads of a load curve (unit of ``e_star``), distinct, in column
        order (module docstring); empty for the single load ``mean_pressure``.
    """

    spectrum: SurfaceSpectrum
    coarsest: int
    projection: str
    e_star: float
    mean_pressure: float
    qoi_names: tuple[str, ...]
    qoi_scales: tuple[float, ...]
    seed: int
    tol: float = 1e-7  # these defaults are the config's (tests/test_config.py checks)
    max_iter: int = 10_000
    warm_start: bool = True
    threads: int = 1
    connectivity: int | str = 4
    critical_pressure: float | None = None
    area_estimator: str = "corrected"
    fft_wisdom: tuple[bytes, ...] | None = field(default=None, repr=False, compare=False)
    mean_pressures: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.mean_pressures and self.mean_pressures[0] != self.mean_pressure:
            raise ValueError("ContactModel.mean_pressure must be the first of mean_pressures")

    def grid(self, level: int) -> int:
        """Nodes per side of ``level``."""
        return self.coarsest * 2**level

    @property
    def loads(self) -> tuple[float, ...]:
        """The mean pressures solved per surface, in column order (one for a single load)."""
        return self.mean_pressures or (self.mean_pressure,)

    @property
    def n_loads(self) -> int:
        """Number of loads per surface."""
        return len(self.loads)

    @property
    def n_qoi(self) -> int:
        """Number of result columns: quantities of interest times loads."""
        return len(self.qoi_names) * self.n_loads


def run_stage(method: str, run_id: str) -> int:
    """Stage of the estimation run ``run_id``: odd for ``"mlmc"`` (coupled), even for ``"mc"``.

    A 56-bit hash of the name, so distinct runs have distinct streams (a
    collision has probability about ``n_runs^2 / 2^57``).
    """
    if method not in ("mlmc", "mc"):
        raise ValueError(f"method must be 'mlmc' or 'mc', got {method!r}")
    digest = int.from_bytes(hashlib.sha256(run_id.encode()).digest()[:7], "big")
    return 2 * digest + (1 if method == "mlmc" else 2)


def is_coupled_stage(stage: int) -> bool:
    """Whether samples of ``stage`` pair the fine with the coarse solve (screening, MLMC)."""
    return stage == STAGE_SCREENING or stage % 2 == 1


def sample_rng(seed: int, stage: int, level: int, index: int) -> np.random.Generator:
    """The random generator of sample ``(stage, level, index)`` of a study (SPEC section 7)."""
    sequence = np.random.SeedSequence(seed, spawn_key=(int(stage), int(level), int(index)))
    return np.random.Generator(np.random.PCG64(sequence))


def _iteration_cost(n: int) -> float:
    """Modelled cost of one solver iteration on an ``n x n`` grid (reference seconds)."""
    return COST_PER_POINT * n * n * math.log2(n * n) + COST_PER_ITERATION


def _solve_cost(n: int, n_iter: np.ndarray) -> np.ndarray:
    return (n_iter + COST_EXTRA_ITERATIONS) * _iteration_cost(n)


#: Least growth per level (``log2``) of a coupled sample's iterations that :func:`cost_rate_beyond` assumes. The
#: screened grids show less than finer grids do: on the quickstart's surface (levels 32^2..2048^2, MLMC samples of
#: 2026-11-29) the iterations per unit of work grew by 2^0.12 from level 1 to 2 and by 2^0.21 per level from 128^2
#: to 2048^2; a cold solve on the benchmark surface by 2^0.27 per level from 256^2 to 4096^2.
ITERATION_RATE_FLOOR = 0.2


def cost_rate_beyond(model: ContactModel, levels: np.ndarray, mean_cost: np.ndarray, max_level: int) -> float | None:
    """The rate ``gamma`` at which a coupled sample's modelled cost grows beyond the finest screened level.

    A screening's ``gamma`` is fitted where the fixed cost of an iteration (``COST_PER_ITERATION``) still
    weighs, so that it underrates finer grids (the quickstart's 1.54 against 2.1-2.6 per level from 128^2 to
    2048^2). This rate is that of the modelled work of an iteration on the fine and the coarse grid from the
    finest screened level ``L`` to ``max_level``, plus the growth of the iterations (the mean cost over that
    work) between the two finest screened levels >= 1, at least :data:`ITERATION_RATE_FLOOR` and at most 1.
    None where nothing lies beyond ``L`` or fewer than two levels >= 1 have a positive cost.

    Parameters
    ----------
    model : ContactModel
    levels, mean_cost : ndarray, shape (n_levels,)
        The screened levels and the mean modelled cost of a sample on each.
    max_level : int
        The finest level a run may reach.
    """
    levels, mean_cost = np.asarray(levels), np.asarray(mean_cost, dtype=float)
    usable = np.flatnonzero((levels >= 1) & (mean_cost > 0))
    if usable.size < 2 or max_level <= levels[usable[-1]]:
        return None
    top, below = (int(levels[row]) for row in usable[-1:-3:-1])

    def work(level: int) -> float:
        return _iteration_cost(model.grid(level)) + _iteration_cost(model.grid(level - 1))

    iterations = [mean_cost[row] / work(int(levels[row])) for row in usable[-2:]]
    iteration_rate = math.log2(iterations[1] / iterations[0]) / (top - below)
    work_rate = math.log2(work(max_level) / work(top)) / (max_level - top)
    return work_rate + min(max(iteration_rate, ITERATION_RATE_FLOOR), 1.0)


def modelled_cost(model: ContactModel, level: int, n_iter: np.ndarray, *, is_coupled: bool = True) -> np.ndarray:
    """Modelled cost of samples in reference seconds (module docstring).

    Parameters
    ----------
    model : ContactModel
    level : int
    n_iter : ndarray of int, shape (n, 2)
        Iterations of the fine and coarse solves.
    is_coupled : bool
        Whether the samples include the coarse solve (level >= 1, not MC).

    Returns
    -------
    ndarray of float64, shape (n,)
    """
    n_iter = np.asarray(n_iter, dtype=float).reshape(-1, 2)
    cost = _solve_cost(model.grid(level), n_iter[:, 0])
    if is_coupled and level > 0:
        cost = cost + _solve_cost(model.grid(level - 1), n_iter[:, 1])
    return cost


def measured_seconds_per_cost(batches: Sequence[LevelBatch], model: ContactModel) -> float:
    """Measured CPU-seconds per modelled reference second over coupled (screening) batches (1 without any).

    The median of the per-sample ratios: the first samples of every worker
    also pay its start-up (loading the compiled kernels, FFT plans), which
    would otherwise inflate every prediction of a cheap study many times.
    """
    seconds = np.concatenate([np.asarray(b.cost, dtype=float) for b in batches])
    modelled = np.concatenate([np.asarray(modelled_cost(model, b.level, b.n_iter), dtype=float) for b in batches])
    usable = modelled > 0
    return float(np.median(seconds[usable] / modelled[usable])) if np.any(usable) else 1.0


def _solve(model: ContactModel, heights: np.ndarray, initial: LoadCurveSolution | None) -> LoadCurveSolution:
    """Solve at every load (from ``initial``'s pressure at the same load, if given), continuing a solve once
    with ``RETRY_FACTOR * max_iter`` iterations if needed."""
    return solve_load_curve(
        heights,
        system_size=model.spectrum.system_size,
        mean_pressures=model.loads,
        e_star=model.e_star,
        tol=model.tol,
        max_iter=model.max_iter,
        threads=model.threads,
        initial_pressures=None if initial is None else [solution.pressure for solution in initial.solutions],
        retry_iter=RETRY_FACTOR * model.max_iter,
    )


def _qoi(model: ContactModel, curve: LoadCurveSolution) -> np.ndarray:
    """QoIs of every load, shape (n_qoi_names * n_loads,), QoI-major."""
    values = np.array(
        [
            evaluate_qoi(
                model.qoi_names,
                pressure=solution.pressure,
                gap=solution.gap,
                connectivity=model.connectivity,
                critical_pressure=model.critical_pressure,
                area_estimator=model.area_estimator,
            )
            for solution in curve.solutions
        ]
    )  # (n_loads, n_qoi_names)
    return (values * np.asarray(model.qoi_scales)).T.reshape(-1)


@dataclass(frozen=True, eq=False)  # arrays: no field-wise == (as ContactSolution)
class SampleSolution:
    """The fields behind one sample (:func:`solve_sample`).

    Attributes
    ----------
    heights : ndarray, shape (n_l, n_l)
        The surface on the sample's grid.
    fine_curve : LoadCurveSolution
        Its contact solutions, one per load (in the model's load order).
    coarse_curve : LoadCurveSolution or None
        The solutions on the coarser grid of the same surface (coupled samples).
    """

    heights: np.ndarray
    fine_curve: LoadCurveSolution
    coarse_curve: LoadCurveSolution | None = None

    @property
    def fine(self) -> ContactSolution:
        """The fine solution at the first load."""
        return self.fine_curve.solutions[0]

    @property
    def n_iter(self) -> int:
        """Iterations of the fine solves, retries included."""
        return self.fine_curve.total_iter

    @property
    def coarse(self) -> ContactSolution | None:
        """The coarse solution at the first load (coupled samples)."""
        return None if self.coarse_curve is None else self.coarse_curve.solutions[0]

    @property
    def coarse_n_iter(self) -> int:
        """Iterations of the coarse solves (0 without them)."""
        return 0 if self.coarse_curve is None else self.coarse_curve.total_iter


def solve_sample(model: ContactModel, *, stage: int, level: int, index: int) -> SampleSolution:
    """Surface and contact solution(s) of sample ``(stage, level, index)``.

    Samples of coupled stages (:func:`is_coupled_stage`) pair the level-``l``
    solve with the coarse solve of the same surface
    (:func:`~rough_uq.physics.surface.sample_coupled`), and with ``warm_start`` the
    fine solve (of each load) starts from the coarse pressure; samples
    of MC stages and of level 0 solve the fine grid only. The result depends
    only on ``model`` and ``(stage, level, index)`` (and, at the level of
    rounding, on the FFT plans: every process plans from ``model.fft_wisdom``).
    """
    use_wisdom(model.fft_wisdom)
    rng = sample_rng(model.seed, stage, level, index)
    n_fine = model.grid(level)
    if not (is_coupled_stage(stage) and level > 0):
        heights = sample_surface(model.spectrum, n_fine, rng)
        return SampleSolution(heights=heights, fine_curve=_solve(model, heights, None))
    heights, coarse_heights = sample_coupled(model.spectrum, n_fine, rng, projection=model.projection)
    coarse = _solve(model, coarse_heights, None)
    fine = _solve(model, heights, coarse if model.warm_start else None)
    return SampleSolution(heights=heights, fine_curve=fine, coarse_curve=coarse)


def warm_up(model: ContactModel) -> None:
    """Run every kernel a sample of ``model`` uses once, before any sample is timed.

    One coupled sample on a tiny copy of the model's grids (coarsest 8, level
    1): numba compiles its kernels, or loads them from its disk cache, which
    would otherwise fall into the measured cost of the first sample of a
    process (about 0.3 s in the quickstart's pool workers, against 1.5 ms for
    its 32^2 samples). Its result is discarded; it changes no other sample.

    A Ctrl-C meanwhile takes effect once it is done (:func:`_sigint_deferred`): one that landed while numba
    registered its implementations left them half-registered, and every later solve of the process raised
    ``RuntimeError: generator raised StopIteration`` (6 of about 290 processes interrupted in their first run).
    """
    with _sigint_deferred():
        compute_batch(replace(model, coarsest=8), stage=1, level=1, indices=np.zeros(1, dtype=np.int64))


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """On the main thread with a SIGINT handler: record a Ctrl-C in the body and hand it to that handler when it
    ends (Python's raises :class:`KeyboardInterrupt`); elsewhere (a pool worker ignores SIGINT) nothing changes."""
    if threading.current_thread() is not threading.main_thread() or not callable(signal.getsignal(signal.SIGINT)):
        yield
        return
    received: list[object] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        previous(signal.SIGINT, received[0])


def compute_batch(model: ContactModel, *, stage: int, level: int, indices: np.ndarray) -> LevelBatch:
    """Compute samples ``(stage, level, i)`` for ``i`` in ``indices`` (:func:`solve_sample`).

    Returns
    -------
    LevelBatch
        QoIs of the fine and coarse solutions (``coarse`` zero without a coarse
        solve), with the measured wall time per sample as ``cost``.
    """
    indices = np.asarray(indices, dtype=np.int64).reshape(-1)
    n = len(indices)
    fine = np.zeros((n, model.n_qoi))
    coarse = np.zeros((n, model.n_qoi))
    cost = np.zeros(n)
    n_iter = np.zeros((n, 2), dtype=np.int64)
    converged = np.ones((n, 2), dtype=bool)
    for row, index in enumerate(indices):
        start = time.perf_counter()
        sample = solve_sample(model, stage=stage, level=level, index=int(index))
        fine[row] = _qoi(model, sample.fine_curve)
        n_iter[row] = (sample.n_iter, sample.coarse_n_iter)
        converged[row, 0] = sample.fine_curve.is_converged
        if sample.coarse_curve is not None:
            coarse[row] = _qoi(model, sample.coarse_curve)
            converged[row, 1] = sample.coarse_curve.is_converged
        cost[row] = time.perf_counter() - start
    return LevelBatch(
        level=level,
        stage=stage,
        indices=indices,
        fine=fine,
        coarse=coarse,
        cost=cost,
        n_iter=n_iter,
        converged=converged,
    )
