"""roughuq: statistics of rough-surface contact with Multilevel Monte Carlo.

The public Python API, for notebooks and scripts (no config file, no study
file, no pydantic)::

    import numpy
    import rough_uq
    # A small surface (k_s = 16 on grids from 32^2): seconds on a laptop. The classic setting (k_s = 128,
    # coarsest=256, SPEC section 6) takes minutes per run: screen it first (rough_uq.screen, forecast).
    spectrum = rough_uq.SurfaceSpectrum(system_size=2, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=1)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32,
                                      seed=1)
    result = rough_uq.mlmc(problem, tol=0.5)   # or rough_uq.mc(problem, tol=..., level=...), rough_uq.screen(problem)
    result.estimate, result.rmse, result.levels
    spread = rough_uq.variance(problem, tol=1.0)  # Var(Q), in the QoI's unit squared
    law = rough_uq.distribution(problem, tol=0.05, thresholds=numpy.linspace(10, 40, 121))  # CDF, quantiles (15-40 s)

``estimate`` and ``rmse`` have shape ``(n_qoi,)`` (in the QoIs' units, here
percent), ``levels`` and ``n_samples`` shape ``(n_levels,)``
(:class:`EstimationResult`). The physics is exported too:
:class:`SurfaceSpectrum`, :func:`sample_surface`, :func:`sample_coupled`,
:func:`solve_contact`, the quantities of interest and the errors.

The core is pure numpy/scipy/pyfftw/numba: :mod:`rough_uq.physics` (FFTs,
surfaces, the elastic half-space, the contact solver, quantities of interest,
reference solutions), :mod:`rough_uq.multilevel` (level statistics, rates,
allocation, the MC/MLMC drivers) and :mod:`rough_uq.problem` (the contact
problem as a level sampler, and the functions above). The edges do the I/O:
:mod:`rough_uq.study` (config, study file, executors, pipeline),
:mod:`rough_uq.report` and :mod:`rough_uq.cli`. Importing the package has no
side effects and imports none of them: the names below are loaded on first
use, so that the CLI's commands that need no solver do not load numba and
pyFFTW.
"""

from __future__ import annotations

import importlib as _importlib
from importlib.metadata import PackageNotFoundError as _PackageNotFoundError
from importlib.metadata import version as _installed_version
from typing import TYPE_CHECKING

try:
    __version__ = _installed_version("roughuq")
except _PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

#: Public name -> module that defines it.
_EXPORTS = {
    # the contact problem and the estimators on it
    "ContactProblem": "rough_uq.problem.contact",
    "RelativeLoad": "rough_uq.problem.loads",
    "AbsoluteLoad": "rough_uq.problem.loads",
    "RunForecast": "rough_uq.problem.runs",
    "ScreeningResult": "rough_uq.problem.runs",
    "mlmc": "rough_uq.problem.runs",
    "mc": "rough_uq.problem.runs",
    "screen": "rough_uq.problem.runs",
    "variance": "rough_uq.problem.distribution",
    "distribution": "rough_uq.problem.distribution",
    "DistributionResult": "rough_uq.problem.distribution",
    "EstimationResult": "rough_uq.multilevel.drivers",
    "TargetEstimate": "rough_uq.multilevel.targets",
    "CdfEstimate": "rough_uq.multilevel.distribution",
    "Quantiles": "rough_uq.multilevel.distribution",
    "LevelStatistics": "rough_uq.multilevel.statistics",
    "Rates": "rough_uq.multilevel.rates",
    # the physics
    "SurfaceSpectrum": "rough_uq.physics.surface",
    "sample_surface": "rough_uq.physics.surface",
    "sample_coupled": "rough_uq.physics.surface",
    "solve_contact": "rough_uq.physics.solver",
    "ContactSolution": "rough_uq.physics.solver",
    "solve_load_curve": "rough_uq.physics.load_curve",
    "LoadCurveSolution": "rough_uq.physics.load_curve",
    "QOI_NAMES": "rough_uq.physics.qoi",
    "evaluate_qoi": "rough_uq.physics.qoi",
    "contact_area": "rough_uq.physics.qoi",
    "count_clusters": "rough_uq.physics.qoi",
    "label_clusters": "rough_uq.physics.qoi",
    "mean_gap": "rough_uq.physics.qoi",
    "max_pressure": "rough_uq.physics.qoi",
    "area_above": "rough_uq.physics.qoi",
    # errors and warnings
    "RoughUQError": "rough_uq.errors",
    "InvalidParameterError": "rough_uq.errors",
    "ConvergenceError": "rough_uq.errors",
    "EstimationError": "rough_uq.errors",
    "PlanTooLargeError": "rough_uq.errors",
    "ExecutorError": "rough_uq.errors",
    "EstimationWarning": "rough_uq.errors",
}

__all__ = [
    "__version__",
    "ContactProblem",
    "RelativeLoad",
    "AbsoluteLoad",
    "RunForecast",
    "ScreeningResult",
    "mlmc",
    "mc",
    "screen",
    "variance",
    "distribution",
    "DistributionResult",
    "EstimationResult",
    "TargetEstimate",
    "CdfEstimate",
    "Quantiles",
    "LevelStatistics",
    "Rates",
    "SurfaceSpectrum",
    "sample_surface",
    "sample_coupled",
    "solve_contact",
    "ContactSolution",
    "solve_load_curve",
    "LoadCurveSolution",
    "QOI_NAMES",
    "evaluate_qoi",
    "contact_area",
    "count_clusters",
    "label_clusters",
    "mean_gap",
    "max_pressure",
    "area_above",
    "RoughUQError",
    "InvalidParameterError",
    "ConvergenceError",
    "EstimationError",
    "PlanTooLargeError",
    "ExecutorError",
    "EstimationWarning",
]

if TYPE_CHECKING:  # for type checkers and IDEs; at run time names load on first use
    from rough_uq.errors import (
        ConvergenceError,
        EstimationError,
        EstimationWarning,
        ExecutorError,
        InvalidParameterError,
        PlanTooLargeError,
        RoughUQError,
    )
    from rough_uq.multilevel.distribution import CdfEstimate, Quantiles
    from rough_uq.multilevel.drivers import EstimationResult
    from rough_uq.multilevel.targets import TargetEstimate
    from rough_uq.multilevel.rates import Rates
    from rough_uq.multilevel.statistics import LevelStatistics
    from rough_uq.physics.qoi import (
        QOI_NAMES,
        area_above,
        contact_area,
        count_clusters,
        evaluate_qoi,
        label_clusters,
        max_pressure,
        mean_gap,
    )
    from rough_uq.physics.load_curve import LoadCurveSolution, solve_load_curve
    from rough_uq.physics.solver import ContactSolution, solve_contact
    from rough_uq.physics.surface import SurfaceSpectrum, sample_coupled, sample_surface
    from rough_uq.problem.contact import ContactProblem
    from rough_uq.problem.distribution import DistributionResult, distribution, variance
    from rough_uq.problem.loads import AbsoluteLoad, RelativeLoad
    from rough_uq.problem.runs import RunForecast, ScreeningResult, mc, mlmc, screen


def __getattr__(name: str) -> object:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'rough_uq' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names, the subpackages loaded so far and the dunders: what a notebook's completion should offer."""
    own = {
        name
        for name, value in globals().items()
        if (name.startswith("__") and name.endswith("__")) or getattr(value, "__name__", "") == f"{__name__}.{name}"
    }
    return sorted(own | set(__all__))
