"""roughuq: statistics of rough-surface contact with Multilevel Monte Carlo.

The physics core (``fft``, ``elastic``, ``surface``, ``solver``, ``qoi``,
``reference``) and the estimators (``estimator``, ``screening``) are pure
numpy/scipy/pyfftw/numba; the edges (``config``, ``store``, ``pipeline``,
``executor``, ``progress``, ``report``, ``cli``) do the I/O. Importing the
package has no side effects.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("roughuq")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
