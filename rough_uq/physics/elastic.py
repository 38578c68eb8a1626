"""The periodic elastic half-space: pressure to surface displacement.

For a frictionless half-space with effective modulus ``E* = E / (1 - nu^2)``
the normal surface displacement produced by a periodic pressure field is,
mode by mode (Westergaard; Stanley & Kato 1997),

    u_hat(q) = 2 / (E* |q|) * p_hat(q),     q = 2 pi k / L,
    u_hat(0) = 0,

``k`` being the integer wave vector in periods per box (see :mod:`rough_uq.physics.fft`
for the transform conventions). The mean displacement is not fixed by the
kernel: it is the rigid-body approach, a Lagrange multiplier of the contact
problem. Displacements are in the unit of ``L`` when pressures are in the unit
of ``E*``.
"""

from __future__ import annotations

import numba
import numpy as np

from rough_uq.physics.fft import get_fft, rfft_wavenumbers

__all__ = ["westergaard_kernel", "HalfSpace"]


def westergaard_kernel(n: int, *, system_size: float, e_star: float = 1.0) -> np.ndarray:
    """Fourier multiplier of the half-space on an ``n x n`` periodic grid.

    Parameters
    ----------
    n : int
        Grid size (nodes per side).
    system_size : float
        Box side ``L`` (length unit).
    e_star : float
        Effective modulus ``E*`` (pressure unit).

    Returns
    -------
    ndarray of float64, shape (n, n // 2 + 1)
        ``2 / (E* |q|)`` in the rfft layout, zero at ``q = 0``.
    """
    k0, k1 = rfft_wavenumbers(n)
    # Built in place in one array (first use of fresh memory is what costs at large grids):
    # kernel = (2 / E*) / q with q = (2 pi / L) sqrt(k0^2 + k1^2), and zero where q = 0.
    kernel = k0**2 + k1**2
    np.sqrt(kernel, out=kernel)
    kernel *= 2.0 * np.pi / system_size
    np.divide(2.0 / e_star, kernel, out=kernel, where=kernel > 0)
    return kernel


@numba.njit(cache=True, parallel=True)
def multiply_spectrum(spectrum, kernel, scale):  # pragma: no cover - compiled
    # Multiply a complex spectrum by ``scale * kernel`` (real) in place, in one
    # fused pass; also used by the solver to apply the inverse operator in
    # single precision (``scale`` then of the kernel's type, to stay single).
    n0, n1 = spectrum.shape
    for i in numba.prange(n0):
        for j in range(n1):
            spectrum[i, j] = spectrum[i, j] * (scale * kernel[i, j])


class HalfSpace:
    """The pressure-to-displacement operator on one grid, with its FFT plans.

    Parameters
    ----------
    n : int
        Grid size (even).
    system_size : float
        Box side ``L``.
    e_star : float
        Effective modulus ``E*``.
    threads : int
        FFTW threads.
    separate_output : bool
        Plans whose result goes to ``fft.output`` instead of overwriting the
        input ``fft.real`` (see :class:`~rough_uq.physics.fft.RealFFT`).
    """

    def __init__(
        self, n: int, *, system_size: float, e_star: float = 1.0, threads: int = 1, separate_output: bool = False
    ) -> None:
        self.n = int(n)
        self.system_size = float(system_size)
        self.e_star = float(e_star)
        self.fft = get_fft((self.n, self.n), threads=threads, separate_output=separate_output)
        self.kernel = westergaard_kernel(self.n, system_size=self.system_size, e_star=self.e_star)

    def apply(self, scale: float = 1.0) -> np.ndarray:
        """Convolve the plan's input buffer with ``scale`` times the kernel; return its output buffer.

        This is the hot path of the solver: the caller fills ``self.fft.real``
        (saving a copy) and reads the displacement from ``self.fft.output``
        (the same buffer unless ``separate_output``); ``scale`` saves it a
        pass to normalise the pressure first.
        """
        self.fft.forward()
        multiply_spectrum(self.fft.spectral, self.kernel, float(scale))
        return self.fft.inverse()

    def displacement(self, pressure: np.ndarray) -> np.ndarray:
        """Surface displacement of a pressure field (a new array).

        Parameters
        ----------
        pressure : ndarray, shape (n, n)
            Pressure (unit of ``E*``).

        Returns
        -------
        ndarray, shape (n, n)
            Displacement with zero mean (unit of ``L``).
        """
        pressure = np.asarray(pressure, dtype=np.float64)
        if pressure.shape != (self.n, self.n):
            raise ValueError(f"pressure has shape {pressure.shape}, expected {(self.n, self.n)}")
        np.copyto(self.fft.real, pressure)
        return self.apply().copy()
