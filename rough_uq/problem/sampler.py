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
import time
from dataclasses import dataclass, field

import numpy as np

from rough_uq.problem.batch import STAGE_SCREENING, LevelBatch
from rough_uq.physics.fft import use_wisdom
from rough_uq.physics.qoi import evaluate_qoi
from rough_uq.physics.solver import ContactSolution, solve_contact
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
    "compute_batch",
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
        Imposed mean pressure (unit of ``e_star``).
    qoi_names : tuple of str
        Quantities of interest, in column order (:data:`rough_uq.physics.qoi.QOI_NAMES`).
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
    """

    spectrum: SurfaceSpectrum
    coarsest: int
    projection: str
    e_star: float
    mean_pressure: float
    qoi_names: tuple[str, ...]
    qoi_scales: tuple[float, ...]
    seed: int
    tol: float = 1e-8
    max_iter: int = 10_000
    warm_start: bool = True
    threads: int = 1
    connectivity: int | str = 4
    critical_pressure: float | None = None
    area_estimator: str = "corrected"
    fft_wisdom: tuple[bytes, ...] | None = field(default=None, repr=False, compare=False)

    def grid(self, level: int) -> int:
        """Nodes per side of ``level``."""
        return self.coarsest * 2**level

    @property
    def n_qoi(self) -> int:
        """Number of quantities of interest."""
        return len(self.qoi_names)


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


def _solve_cost(n: int, n_iter: np.ndarray) -> np.ndarray:
    per_iteration = COST_PER_POINT * n * n * math.log2(n * n) + COST_PER_ITERATION
    return (n_iter + COST_EXTRA_ITERATIONS) * per_iteration


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


def _solve(model: ContactModel, heights: np.ndarray, initial: np.ndarray | None) -> tuple[ContactSolution, int]:
    """Solve, continuing once with ``RETRY_FACTOR * max_iter`` iterations if needed; total iterations."""
    options = dict(
        system_size=model.spectrum.system_size,
        mean_pressure=model.mean_pressure,
        e_star=model.e_star,
        tol=model.tol,
        threads=model.threads,
    )
    solution = solve_contact(heights, max_iter=model.max_iter, initial_pressure=initial, **options)
    n_iter = solution.n_iter
    if not solution.converged:
        solution = solve_contact(
            heights,
            max_iter=RETRY_FACTOR * model.max_iter,
            initial_pressure=solution.pressure,
            **options,
        )
        n_iter += solution.n_iter
    return solution, n_iter


def _qoi(model: ContactModel, solution: ContactSolution) -> np.ndarray:
    values = evaluate_qoi(
        model.qoi_names,
        pressure=solution.pressure,
        gap=solution.gap,
        connectivity=model.connectivity,
        critical_pressure=model.critical_pressure,
        area_estimator=model.area_estimator,
    )
    return values * np.asarray(model.qoi_scales)


@dataclass(frozen=True)
class SampleSolution:
    """The fields behind one sample (:func:`solve_sample`).

    Attributes
    ----------
    heights : ndarray, shape (n_l, n_l)
        The surface on the sample's grid.
    fine : ContactSolution
        Its contact solution.
    n_iter : int
        Iterations of the fine solve, retry included.
    coarse : ContactSolution or None
        The solution on the coarser grid of the same surface (coupled samples).
    coarse_n_iter : int
        Iterations of the coarse solve (0 without one).
    """

    heights: np.ndarray
    fine: ContactSolution
    n_iter: int
    coarse: ContactSolution | None = None
    coarse_n_iter: int = 0


def solve_sample(model: ContactModel, *, stage: int, level: int, index: int) -> SampleSolution:
    """Surface and contact solution(s) of sample ``(stage, level, index)``.

    Samples of coupled stages (:func:`is_coupled_stage`) pair the level-``l``
    solve with the coarse solve of the same surface
    (:func:`~rough_uq.physics.surface.sample_coupled`), and with ``warm_start`` the
    fine solve starts from the coarse pressure; samples of MC stages and of
    level 0 solve the fine grid only. The result depends only on ``model``
    and ``(stage, level, index)`` (and, at the level of rounding, on the FFT
    plans: every process plans from ``model.fft_wisdom``).
    """
    use_wisdom(model.fft_wisdom)
    rng = sample_rng(model.seed, stage, level, index)
    n_fine = model.grid(level)
    if not (is_coupled_stage(stage) and level > 0):
        heights = sample_surface(model.spectrum, n_fine, rng)
        solution, n_iter = _solve(model, heights, None)
        return SampleSolution(heights=heights, fine=solution, n_iter=n_iter)
    heights, coarse_heights = sample_coupled(model.spectrum, n_fine, rng, projection=model.projection)
    coarse, coarse_n_iter = _solve(model, coarse_heights, None)
    solution, n_iter = _solve(model, heights, coarse.pressure if model.warm_start else None)
    return SampleSolution(heights=heights, fine=solution, n_iter=n_iter, coarse=coarse, coarse_n_iter=coarse_n_iter)


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
        fine[row] = _qoi(model, sample.fine)
        n_iter[row] = (sample.n_iter, sample.coarse_n_iter)
        converged[row, 0] = sample.fine.converged
        if sample.coarse is not None:
            coarse[row] = _qoi(model, sample.coarse)
            converged[row, 1] = sample.coarse.converged
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
