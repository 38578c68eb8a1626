"""Analytic reference solutions of periodic contact, used by tests and reports.

Westergaard's wavy surface (Johnson, *Contact Mechanics*, 1985, section 13.2):
a rigid sinusoid ``s(x) = h cos(2 pi x / lambda)`` pressed on a half-space with
effective modulus ``E*``. Complete contact needs the mean pressure

    p* = pi E* h / lambda.

Below it the contact patches are ``|x - j lambda| < a`` with

    p_mean = p* sin^2(pi a / lambda),

and the pressure inside a patch is

    p(x) = 2 p_mean cos(pi x / lambda) / sin^2(pi a / lambda)
           * sqrt(sin^2(pi a / lambda) - sin^2(pi x / lambda)).

At or above ``p*`` the contact is complete and
``p(x) = p_mean + p* cos(2 pi x / lambda)``.

Complete contact of any surface: where the whole surface is in contact the
displacement equals the heights up to a constant, so the pressure follows by
inverting the kernel, ``p = p_mean + K^{-1} (s - mean(s))``; it is the
solution whenever it is non-negative everywhere.
"""

from __future__ import annotations

import math

import numpy as np

from rough_uq.physics.elastic import westergaard_kernel
from rough_uq.errors import InvalidParameterError

__all__ = [
    "westergaard_full_contact_pressure",
    "westergaard_contact_half_width",
    "westergaard_pressure",
    "full_contact_pressure",
]


def westergaard_full_contact_pressure(*, amplitude: float, wavelength: float, e_star: float = 1.0) -> float:
    """Mean pressure ``p* = pi E* h / lambda`` at which a sinusoid makes complete contact."""
    return math.pi * e_star * amplitude / wavelength


def westergaard_contact_half_width(
    *, amplitude: float, wavelength: float, mean_pressure: float, e_star: float = 1.0
) -> float:
    """Half-width ``a`` of each contact patch (``lambda / 2`` at complete contact).

    Parameters
    ----------
    amplitude : float
        Height amplitude ``h`` of the sinusoid (unit of length).
    wavelength : float
        Wavelength ``lambda`` (unit of length).
    mean_pressure : float
        Mean pressure (unit of ``E*``), ``> 0``.
    e_star : float
        Effective modulus.
    """
    if not mean_pressure > 0:
        raise InvalidParameterError("mean_pressure", mean_pressure, "a number > 0")
    p_star = westergaard_full_contact_pressure(amplitude=amplitude, wavelength=wavelength, e_star=e_star)
    if mean_pressure >= p_star:
        return wavelength / 2
    return wavelength / math.pi * math.asin(math.sqrt(mean_pressure / p_star))


def westergaard_pressure(
    x: np.ndarray, *, amplitude: float, wavelength: float, mean_pressure: float, e_star: float = 1.0
) -> np.ndarray:
    """Exact pressure under the sinusoid ``h cos(2 pi x / lambda)`` at positions ``x``.

    Parameters
    ----------
    x : ndarray
        Positions (unit of length), any shape.
    amplitude, wavelength, mean_pressure, e_star : float
        As in :func:`westergaard_contact_half_width`.

    Returns
    -------
    ndarray
        Pressure (unit of ``E*``), same shape as ``x``.
    """
    x = np.asarray(x, dtype=np.float64)
    p_star = westergaard_full_contact_pressure(amplitude=amplitude, wavelength=wavelength, e_star=e_star)
    if mean_pressure >= p_star:
        return mean_pressure + p_star * np.cos(2 * np.pi * x / wavelength)
    a = westergaard_contact_half_width(
        amplitude=amplitude, wavelength=wavelength, mean_pressure=mean_pressure, e_star=e_star
    )
    sin2_a = math.sin(math.pi * a / wavelength) ** 2
    phase = np.pi * x / wavelength
    inside = sin2_a - np.sin(phase) ** 2
    # cos(phase) changes sign between neighbouring patches; its absolute value
    # makes every patch (centred on x = j lambda) positive.
    pressure = 2 * mean_pressure / sin2_a * np.abs(np.cos(phase)) * np.sqrt(np.clip(inside, 0, None))
    return np.where(inside > 0, pressure, 0.0)


def full_contact_pressure(
    heights: np.ndarray, *, system_size: float, mean_pressure: float, e_star: float = 1.0
) -> np.ndarray:
    """Pressure under complete contact, ``p_mean + K^{-1}(s - mean(s))``.

    It is the contact solution exactly when the result is non-negative
    everywhere (check ``result.min() >= 0``).

    Parameters
    ----------
    heights : ndarray, shape (n, n)
        Surface heights (unit of length).
    system_size : float
        Box side ``L``.
    mean_pressure : float
        Mean pressure (unit of ``E*``).
    e_star : float
        Effective modulus.

    Returns
    -------
    ndarray, shape (n, n)
    """
    s = np.asarray(heights, dtype=np.float64)
    n = s.shape[0]
    kernel = westergaard_kernel(n, system_size=system_size, e_star=e_star)
    inverse = np.zeros_like(kernel)
    np.divide(1.0, kernel, out=inverse, where=kernel > 0)
    return mean_pressure + np.fft.irfft2(np.fft.rfft2(s) * inverse, s=s.shape)
