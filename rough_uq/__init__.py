"""roughuq: statistics of rough-surface contact with Multilevel Monte Carlo.

The core is pure numpy/scipy/pyfftw/numba: :mod:`rough_uq.physics` (FFTs,
surfaces, the elastic half-space, the contact solver, quantities of interest,
reference solutions), :mod:`rough_uq.multilevel` (level statistics, rates,
allocation, the MC/MLMC drivers) and :mod:`rough_uq.problem` (the contact
problem as a level sampler). The edges do the I/O: :mod:`rough_uq.study`
(config, study file, executors, pipeline), :mod:`rough_uq.report` and
:mod:`rough_uq.cli`. Importing the package has no side effects.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("roughuq")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
