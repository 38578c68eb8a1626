"""Random rough surfaces: the spectral model (SPEC section 3) and its samples on periodic grids.

Conventions
-----------
* The box is ``[0, L)^2`` with ``L = system_size``; a grid of ``n x n`` nodes has
  node ``(i, j)`` at ``x = (i h, j h)``, ``h = L / n`` (as in :mod:`rough_uq.physics.fft`).
  Heights are in the unit of ``L``. Larger heights stick out further: the
  highest points of ``s`` touch the elastic body first.
* Wave vectors ``k = (k0, k1)`` are integer pairs counted in periods per box
  along axes 0 and 1; the wave number is ``k = |k|`` and the angular wave
  vector ``q = 2 pi k / L``.
* **Wave vectors a grid represents.** A grid with ``n`` (even) nodes per side
  represents ``G_n = {k : |k0| <= n/2 - 1 and |k1| <= n/2 - 1}``: the Nyquist row
  and column (``k0 = -n/2`` or ``k1 = -n/2`` in numpy's FFT order) are left out.
  ``G_n`` is symmetric (``k`` in it iff ``-k`` is), so taking the real part of a
  synthesis over ``G_n`` stays within ``G_n``; and ``G_{n/2}`` is a subset of
  ``G_n``, so spectral truncation onto the coarser grid commutes with taking the
  real part and is an exact projection. The price: a grid ``n`` resolves only
  ``|k0|, |k1| < n/2`` (e.g. with ``k_s = 128`` the four wave vectors
  ``(+-128, 0)``, ``(0, +-128)`` first appear on ``n = 512``, not 256). The mean
  (``k = 0``) is never sampled: surfaces are centred.
* **Band.** ``B = {k != 0 : k_l <= |k| <= k_s}``. Membership is decided on the
  exact integer ``|k|^2``, with a relative tolerance of ``1e-10`` on ``k_l^2``
  and ``k_s^2`` so that ``k = L / lambda`` computed in floating point does not
  lose a whole shell of wave vectors to rounding.
* **Normalisation.** ``C`` is fixed by ``sum_{k in B} Phi(|k|) = rms_height^2``
  over *all* integer wave vectors of the band, independent of any grid; the same
  ``C`` (the same random field) is used on every grid.
* **Sample.** ``s(x) = Re sum_{k in G_n & B} sqrt(Phi(|k|)) xi_k exp(i q.x)`` with
  ``xi_k = eta_k + i zeta_k`` and ``eta_k, zeta_k`` independent standard
  normals: an inverse DFT *without* the ``1 / n^2`` factor. Its covariance is
  ``sum_{G_n & B} Phi(|k|) cos(q.r)``, so ``Var s(x) = sum_{G_n & B} Phi``, which
  equals ``rms_height^2`` once the grid resolves the band
  (``n >= 2 floor(k_s) + 2``, see :meth:`SurfaceSpectrum.resolves`) and is the
  partial sum (:meth:`SurfaceSpectrum.grid_variance`) on coarser grids. The
  imaginary part (an independent second sample) is not used.
* **Draw order.** Only the wave vectors of ``G_n & B`` get random numbers. They
  are ordered by square shell ``max(|k0|, |k1|)``, then by ``k0``, then by
  ``k1`` (ascending), and the ``j``-th one gets ``(eta, zeta)`` = row ``j`` of
  ``rng.standard_normal((n_modes, 2))``. Because ``G_{n/2} & B`` is a prefix of
  that order, the draws of grid ``n/2`` are the first draws of grid ``n``: a
  generator seeded alike gives on grid ``n/2`` exactly the spectral truncation
  of the surface it gives on grid ``n``. The draw depends only on
  ``(spectrum, n, rng)``.

MLMC coupling (fine and coarse surface from one draw) lives here and only here:
:func:`sample_coupled`, with :func:`project_surface` the projection it applies.
"""

from __future__ import annotations

import functools
import math
import sys
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from rough_uq.errors import (
    InvalidParameterError, checked_real_array, is_integer, is_one_of, is_real_number, scalar_refusal,
)
from rough_uq.physics.fft import get_fft

__all__ = [
    "SurfaceSpectrum",
    "sample_surface",
    "sample_coupled",
    "project_surface",
    "PROJECTIONS",
    "MAX_K_S",
]

#: Relative tolerance on the squared band edges ``k_l^2`` and ``k_s^2``.
_EDGE_RTOL = 1e-10

#: The largest short cut-off ``k_s`` (periods per box): half of the largest grid,
#: ``rough_uq.problem.contact.MAX_GRID`` = 65536 (tests/test_problem_arguments.py
#: checks they agree; physics may not import the problem). No grid resolves a
#: larger ``k_s`` (a grid ``n`` resolves ``|k0|, |k1| < n / 2``), and the band sums
#: over all its wave vectors take a time quadratic in ``k_s`` (some 7 s at 1e4),
#: memory linear in it (1e12: MemoryError) and overflow beyond (1e200).
MAX_K_S = 32768

#: Projections from a fine onto the nested coarse grid (see :func:`project_surface`).
PROJECTIONS = ("truncation", "injection")


_K_S_ALLOWED = f"a finite number > 0 and <= {MAX_K_S} (MAX_K_S: half the largest grid, 65536, resolves no larger k_s)"


def _check_real(name: str, value: object, *, allowed: str) -> float:
    """``value`` as a finite float, or :class:`InvalidParameterError` naming ``name``.

    Only real numbers are accepted: a string such as ``"2"`` (or a boolean) is
    refused rather than converted, as the config refuses it.
    """
    if not (is_real_number(value) and math.isfinite(value)):
        raise scalar_refusal(name, value, allowed)
    return float(value)


@dataclass(frozen=True, kw_only=True)
class SurfaceSpectrum:
    """Radial power spectral density of an isotropic, self-affine rough surface.

    ``Phi(k) = C`` for ``k_l <= k <= k_r``, ``C (k / k_r)^(-2 - 2H)`` for
    ``k_r < k <= k_s`` and 0 otherwise (and at ``k = 0``: surfaces are centred),
    with wave numbers in periods per box (module docstring).

    Parameters
    ----------
    system_size : float
        Box size ``L`` (length unit of the study), > 0.
    k_l : float
        Lower cut-off wave number (periods per box), ``0 <= k_l <= k_r``.
        ``k_l = 0`` keeps every wave vector up to ``k_r`` except the mean.
    k_r : float
        Roll-off wave number (periods per box), ``0 < k_r <= k_s``.
    k_s : float
        Upper (short-wavelength) cut-off wave number (periods per box), > 0
        and <= :data:`MAX_K_S` (32768: the largest grid resolves no larger one).
    hurst : float
        Hurst exponent ``H``, dimensionless, ``0 <= H <= 1``.
    rms_height : float
        RMS height ``sigma`` of the surface over the full band (unit of ``L``), > 0.

    Attributes
    ----------
    C : float
        PSD amplitude (unit of ``L^2``): ``sum_{k in band} Phi(|k|) = rms_height^2``.
    m2 : float
        Second spectral moment ``sum_{k in band} Phi(|k|) |q|^2``, ``q = 2 pi k / L``
        (dimensionless): the variance of the surface gradient ``<|grad s|^2>``.
    n_modes : int
        Number of integer wave vectors in the band.

    Raises
    ------
    InvalidParameterError
        A parameter is out of range (the error names it), the band holds no
        non-zero integer wave vector (named ``"k_l, k_s"``), or ``C`` or
        ``m2`` would leave the normal float range (named ``"rms_height"`` or
        ``"rms_height, system_size"``; roughly ``rms_height / system_size``
        beyond ``1e+-150``).
    """

    system_size: float
    k_l: float
    k_r: float
    k_s: float
    hurst: float
    rms_height: float
    C: float = field(init=False, repr=False, compare=False)
    m2: float = field(init=False, repr=False, compare=False)
    n_modes: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        positive = "a finite number > 0"
        values = {
            "system_size": _check_real("system_size", self.system_size, allowed=positive),
            "rms_height": _check_real("rms_height", self.rms_height, allowed=positive),
            "hurst": _check_real("hurst", self.hurst, allowed="a number in [0, 1]"),
            "k_l": _check_real("k_l", self.k_l, allowed="a finite number with 0 <= k_l <= k_r"),
            "k_r": _check_real("k_r", self.k_r, allowed="a finite number with 0 < k_r <= k_s"),
            "k_s": _check_real("k_s", self.k_s, allowed=_K_S_ALLOWED),
        }
        if values["system_size"] <= 0:
            raise InvalidParameterError("system_size", self.system_size, positive)
        if values["rms_height"] <= 0:
            raise InvalidParameterError("rms_height", self.rms_height, positive)
        if not 0.0 <= values["hurst"] <= 1.0:
            raise InvalidParameterError("hurst", self.hurst, "a number in [0, 1]")
        if not 0 < values["k_s"] <= MAX_K_S:
            raise InvalidParameterError("k_s", self.k_s, _K_S_ALLOWED)
        # k_r = 0 would make the self-affine branch C (k / k_r)^(-2-2H) undefined.
        if not 0.0 < values["k_r"] <= values["k_s"]:
            raise InvalidParameterError("k_r", self.k_r, f"0 < k_r <= k_s = {values['k_s']}")
        if not 0.0 <= values["k_l"] <= values["k_r"]:
            raise InvalidParameterError("k_l", self.k_l, f"0 <= k_l <= k_r = {values['k_r']}")
        for name, value in values.items():
            object.__setattr__(self, name, value)

        shape_sum, shape_k2_sum, n_modes = self._band_sums()
        if n_modes == 0:
            raise InvalidParameterError(
                "k_l, k_s",
                (self.k_l, self.k_s),
                "a band k_l <= |k| <= k_s that contains at least one non-zero integer wave vector",
            )
        # Squares of extreme heights or box sizes leave the float range: C (or m2)
        # would be 0 -- a silently flat surface, or zero slope and hence zero
        # paper-style load -- or overflow. Refuse them, naming the culprits.
        normal = "a value for which C = rms_height^2 / sum(Phi / C) is a normal, finite float (change units)"
        try:
            amplitude = self.rms_height**2 / shape_sum
        except OverflowError:
            amplitude = math.inf
        if not sys.float_info.min <= amplitude < math.inf:
            raise InvalidParameterError("rms_height", self.rms_height, normal)
        try:
            m2 = amplitude * (2.0 * math.pi / self.system_size) ** 2 * shape_k2_sum
        except OverflowError:
            m2 = math.inf
        if not sys.float_info.min <= m2 < math.inf:
            raise InvalidParameterError(
                "rms_height, system_size",
                (self.rms_height, self.system_size),
                "values for which the slope variance m2 ~ (2 pi rms_height k / system_size)^2 is a normal, "
                "finite float (change units)",
            )
        object.__setattr__(self, "C", amplitude)
        object.__setattr__(self, "m2", m2)
        object.__setattr__(self, "n_modes", n_modes)

    @classmethod
    def from_wavelengths(
        cls,
        *,
        system_size: float,
        lambda_l: float,
        lambda_r: float,
        lambda_s: float,
        hurst: float,
        rms_height: float,
    ) -> SurfaceSpectrum:
        """The spectrum with cut-offs given as wavelengths (unit of ``L``), ``k = L / lambda``.

        ``lambda_l = math.inf`` gives ``k_l = 0``. Errors name the wavelength
        parameters (``lambda_l`` for ``k_l``, ...).
        """
        size = _check_real("system_size", system_size, allowed="a finite number > 0")
        if size <= 0:
            raise InvalidParameterError("system_size", system_size, "a finite number > 0")
        wave_numbers = {}
        for name, wavelength in (("lambda_l", lambda_l), ("lambda_r", lambda_r), ("lambda_s", lambda_s)):
            allow_inf = name == "lambda_l"
            value = float(wavelength) if is_real_number(wavelength) else math.nan
            if not (value > 0 and (math.isfinite(value) or (allow_inf and value == math.inf))):
                raise InvalidParameterError(
                    name, wavelength, "a wavelength > 0" + (" (inf for k_l = 0)" if allow_inf else "")
                )
            wave_numbers["k" + name[-2:]] = size / value
        if not wave_numbers["k_s"] <= MAX_K_S:
            raise InvalidParameterError(
                "lambda_s", lambda_s, f"a wavelength >= system_size / {MAX_K_S} = {size / MAX_K_S!r} (k_s = "
                f"system_size / lambda_s <= MAX_K_S: half the largest grid, 65536, resolves no larger k_s)"
            )
        try:
            return cls(system_size=size, hurst=hurst, rms_height=rms_height, **wave_numbers)
        except InvalidParameterError as error:
            renamed = {"k_l": "lambda_l", "k_r": "lambda_r", "k_s": "lambda_s", "k_l, k_s": "lambda_l, lambda_s"}
            if error.name not in renamed:
                raise
            raise InvalidParameterError(
                renamed[error.name], error.value, error.allowed + f" (with k = {size} / lambda)"
            ) from error

    # -- wavelengths -------------------------------------------------------

    @property
    def lambda_l(self) -> float:
        """Longest wavelength ``L / k_l`` (unit of ``L``; ``inf`` if ``k_l = 0``)."""
        return math.inf if self.k_l == 0 else self.system_size / self.k_l

    @property
    def lambda_r(self) -> float:
        """Roll-off wavelength ``L / k_r`` (unit of ``L``)."""
        return self.system_size / self.k_r

    @property
    def lambda_s(self) -> float:
        """Shortest wavelength ``L / k_s`` (unit of ``L``)."""
        return self.system_size / self.k_s

    @property
    def rms_slope(self) -> float:
        """RMS slope ``sqrt(m2) = sqrt(<|grad s|^2>)`` of the full band (dimensionless)."""
        return math.sqrt(self.m2)

    # -- the PSD -----------------------------------------------------------

    def _shape_k2(self, k2: np.ndarray) -> np.ndarray:
        """``Phi / C`` as a function of the squared wave number (0 outside the band and at 0)."""
        k2 = np.asarray(k2, dtype=np.float64)
        lower = self.k_l**2 * (1.0 - _EDGE_RTOL)
        upper = self.k_s**2 * (1.0 + _EDGE_RTOL)
        inside = (k2 > 0.0) & (k2 >= lower) & (k2 <= upper)
        k_r2 = self.k_r**2
        ratio = np.where(k2 > k_r2, k2 / k_r2, 1.0)
        return np.where(inside, ratio ** (-1.0 - self.hurst), 0.0)

    def psd(self, k: np.ndarray | float) -> np.ndarray:
        """Radial PSD ``Phi(k)`` (unit of ``L^2``) at wave numbers ``k`` (periods per box).

        Parameters
        ----------
        k : array_like, any shape
            Wave numbers; the spectrum is radial, so ``-k`` gives ``Phi(|k|)``.

        Returns
        -------
        ndarray of float64, shape of ``k``
            ``Phi(k)``; 0 at ``k = 0`` (the mean is not part of the surface).

        Raises
        ------
        InvalidParameterError
            If ``k`` is not a real number or an array of them (strings such
            as ``"3"``, booleans, complex numbers, ``None`` or a ragged list)
            or holds NaN (which came back as ``Phi = 0``), naming ``k``.
        """
        allowed = "a real number or an array of real numbers, none NaN (wave numbers, periods per box)"
        wave_numbers = checked_real_array("k", k, allowed)
        if np.isnan(wave_numbers).any():
            raise InvalidParameterError("k", k, allowed)  # as given (nan, not array(nan))
        return self.C * self._shape_k2(wave_numbers * wave_numbers)

    def grid_psd(self, n: int) -> np.ndarray:
        """``Phi(|k|)`` at every wave vector of the ``n x n`` grid, in numpy's FFT order.

        Parameters
        ----------
        n : int
            Even number of nodes per side.

        Returns
        -------
        ndarray of float64, shape (n, n)
            Entry ``[a, b]`` belongs to ``k = (fftfreq(n, 1/n)[a], fftfreq(n, 1/n)[b])``.
            Zero at ``k = 0`` and on the Nyquist row and column (``k0 = -n/2``
            or ``k1 = -n/2``), which the grid does not represent.
        """
        n = _check_grid_size("n", n)
        k = np.fft.fftfreq(n, d=1.0 / n)
        k2 = k.reshape(-1, 1) ** 2 + k.reshape(1, -1) ** 2
        phi = self.C * self._shape_k2(k2)
        phi[n // 2, :] = 0.0
        phi[:, n // 2] = 0.0
        return phi

    def grid_variance(self, n: int) -> float:
        """Pointwise variance ``sum_{G_n & band} Phi`` of surfaces sampled on grid ``n`` (unit ``L^2``)."""
        return float(self.grid_psd(n).sum())

    def grid_m2(self, n: int) -> float:
        """Gradient variance ``sum_{G_n & band} Phi |q|^2`` of surfaces sampled on grid ``n`` (dimensionless)."""
        n = _check_grid_size("n", n)
        k = np.fft.fftfreq(n, d=1.0 / n)
        k2 = k.reshape(-1, 1) ** 2 + k.reshape(1, -1) ** 2
        return float((self.grid_psd(n) * k2).sum() * (2.0 * math.pi / self.system_size) ** 2)

    def resolves(self, n: int) -> bool:
        """Whether grid ``n`` represents every wave vector of the band (then ``Var s = rms_height^2``)."""
        n = _check_grid_size("n", n)
        return n // 2 - 1 >= self._k_max()

    def _k_max(self) -> int:
        """Largest ``|k0|`` (or ``|k1|``) of a wave vector in the band."""
        upper = self.k_s**2 * (1.0 + _EDGE_RTOL)
        return math.isqrt(math.floor(upper))

    def _band_sums(self) -> tuple[float, float, int]:
        """``sum Phi/C``, ``sum Phi/C |k|^2`` and the count over all integer wave vectors of the band."""
        k_max = self._k_max()
        k1 = np.arange(-k_max, k_max + 1, dtype=np.float64)
        k1_squared = k1 * k1
        shape_sum = 0.0
        shape_k2_sum = 0.0
        count = 0
        # One row k0 at a time keeps memory O(k_s) for k_s in the thousands; rows
        # k0 and -k0 are equal, so only k0 >= 0 is visited.
        for k0 in range(k_max + 1):
            weight = 1 if k0 == 0 else 2
            k2 = k0 * k0 + k1_squared
            shape = self._shape_k2(k2)
            shape_sum += weight * float(shape.sum())
            shape_k2_sum += weight * float((shape * k2).sum())
            count += weight * int(np.count_nonzero(shape))
        return shape_sum, shape_k2_sum, count


# -- sampling ---------------------------------------------------------------


def _check_grid_size(name: str, n: object, *, multiple: int = 2) -> int:
    """``n`` as an int, or :class:`InvalidParameterError` unless a multiple of ``multiple`` in ``[multiple,
    2 MAX_K_S]`` (the largest grid of ``rough_uq.problem.contact.MAX_GRID``: 10^6 was a MemoryError of 7 TiB)."""
    allowed = f"an integer multiple of {multiple}, >= {multiple} and <= {2 * MAX_K_S} (the largest grid)"
    if not is_integer(n):
        raise InvalidParameterError(name, n, allowed)
    n = int(n)
    if n < multiple or n % multiple or n > 2 * MAX_K_S:
        raise InvalidParameterError(name, n, allowed)
    return n


def _check_inputs(spectrum: object, rng: object) -> None:
    # InvalidParameterError, as for every other argument (a RoughUQError, so the CLI and callers catch one kind).
    # The value itself ("rng: got 5"); its type's name read as a value ("rng: got 'int'").
    if not isinstance(spectrum, SurfaceSpectrum):
        raise InvalidParameterError("spectrum", spectrum, "a SurfaceSpectrum")
    if not isinstance(rng, np.random.Generator):
        raise InvalidParameterError("rng", rng, "a numpy.random.Generator (e.g. numpy.random.default_rng(seed))")


@dataclass(frozen=True)
class _Modes:
    """The wave vectors of ``G_n & band`` in draw order, with what synthesis needs.

    ``amplitude[j] = sqrt(Phi(|k_j|))``. The synthesis writes ``a_j / 2`` at
    ``k_j`` and ``conj(a_j) / 2`` at ``-k_j`` into the flattened half spectrum
    ``(n, n // 2 + 1)``: the modes selected by ``first`` (``k1 >= 0``) go to
    the flat indices ``first_target`` (of ``k_j``), those selected by ``second``
    (``k1 <= 0``) to ``second_target`` (of ``-k_j``). Each target list is free
    of repeats, so plain fancy-index assignment and addition are exact. Only
    what synthesis needs is kept (about 14 bytes per mode), since these are cached.
    """

    amplitude: np.ndarray
    first: np.ndarray
    first_target: np.ndarray
    second: np.ndarray
    second_target: np.ndarray

    @property
    def size(self) -> int:
        return int(self.amplitude.size)


@functools.lru_cache(maxsize=8)
def _grid_modes(spectrum: SurfaceSpectrum, n: int) -> _Modes:
    """The modes of grid ``n`` (cached: surfaces of one study are sampled on a few grids)."""
    k_box = min(n // 2 - 1, spectrum._k_max())
    k1_row = np.arange(-k_box, k_box + 1, dtype=np.int64)
    rows0, rows1 = [], []
    for k0 in range(-k_box, k_box + 1):
        inside = spectrum._shape_k2(k0 * k0 + k1_row * k1_row) > 0.0
        rows1.append(k1_row[inside])
        rows0.append(np.full(rows1[-1].size, k0, dtype=np.int64))
    k0 = np.concatenate(rows0)
    k1 = np.concatenate(rows1)
    # (k0, k1) is in lexicographic order; a stable sort by shell keeps it within shells.
    order = np.argsort(np.maximum(np.abs(k0), np.abs(k1)), kind="stable")
    k0 = k0[order]
    k1 = k1[order]
    amplitude = np.sqrt(spectrum.C * spectrum._shape_k2(k0 * k0 + k1 * k1))

    n_half = n // 2 + 1
    index_type = np.int32 if n * n_half < 2**31 else np.int64
    first = k1 >= 0
    first_target = ((k0[first] % n) * n_half + k1[first]).astype(index_type)
    second = k1 <= 0
    second_target = (((-k0[second]) % n) * n_half - k1[second]).astype(index_type)
    arrays = (amplitude, first, first_target, second, second_target)
    for array in arrays:
        array.flags.writeable = False
    return _Modes(*arrays)


def _draw(modes: _Modes, rng: np.random.Generator) -> np.ndarray:
    """Complex amplitudes ``sqrt(Phi) (eta + i zeta)`` of the modes, in draw order."""
    xi = rng.standard_normal((modes.size, 2))
    # Row j of xi is (eta_j, zeta_j): viewing the C-ordered pairs as complex numbers is exact.
    return modes.amplitude * xi.view(np.complex128).reshape(-1)


def _synthesise(n: int, modes: _Modes, amplitudes: np.ndarray) -> np.ndarray:
    """``Re sum_j amplitudes_j exp(i q_j . x)`` on the ``n x n`` grid (no ``1 / n^2`` factor).

    The real part equals the inverse DFT of the Hermitian part
    ``(a_k + conj(a_{-k})) / 2``, so one real (c2r) transform does it.
    """
    plan = get_fft(n)
    spectral = plan.spectral.reshape(-1)  # a view: the plan's buffer is contiguous
    spectral[:] = 0.0
    spectral[modes.first_target] = 0.5 * amplitudes[modes.first]
    spectral[modes.second_target] += 0.5 * np.conj(amplitudes[modes.second])
    # plan.inverse carries 1 / n^2; the spectral sum has none. The product is a new array,
    # so the result does not alias the plan's buffer.
    return plan.inverse() * float(n * n)


def sample_surface(spectrum: SurfaceSpectrum, n: int, rng: np.random.Generator) -> np.ndarray:
    """One random surface on the ``n x n`` grid by spectral filtering of white noise.

    Parameters
    ----------
    spectrum : SurfaceSpectrum
        The PSD model.
    n : int
        Even number of nodes per side.
    rng : numpy.random.Generator
        Source of the normals; ``rng.standard_normal`` is called once, with
        shape ``(number of wave vectors in G_n & band, 2)`` (module docstring).

    Returns
    -------
    ndarray of float64, shape (n, n)
        Heights ``s[i, j] = s(i h, j h)`` (unit of ``L``), mean zero (to rounding),
        pointwise variance ``spectrum.grid_variance(n)``.

    Notes
    -----
    Any even ``n`` works, whether or not the grid resolves the band: a grid
    that cannot represent ``k_s`` (``spectrum.resolves(n)`` False) gets the
    spectral truncation of the field (the modes of ``G_n``; module
    docstring), and a grid that represents no wave vector of the band at all
    (e.g. ``n = 4`` with ``k_l = 2``) gets an identically zero surface.
    """
    _check_inputs(spectrum, rng)
    n = _check_grid_size("n", n)
    modes = _grid_modes(spectrum, n)
    return _synthesise(n, modes, _draw(modes, rng))


def sample_coupled(
    spectrum: SurfaceSpectrum,
    n: int,
    rng: np.random.Generator,
    *,
    projection: Literal["truncation", "injection"] = "truncation",
) -> tuple[np.ndarray, np.ndarray]:
    """A fine surface on grid ``n`` and its projection on grid ``n / 2``, from one draw (MLMC).

    The fine surface is identical to ``sample_surface(spectrum, n, rng)`` for an
    identically seeded ``rng``, and the generator is advanced identically.

    Parameters
    ----------
    spectrum : SurfaceSpectrum
        The PSD model.
    n : int
        Fine grid size, a multiple of 4 (the coarse grid ``n / 2`` is even).
    rng : numpy.random.Generator
        Source of the normals.
    projection : {"truncation", "injection"}
        ``"truncation"`` (default) keeps the Fourier coefficients of ``G_{n/2}``:
        the coarse surface is exactly ``sample_surface(spectrum, n // 2, .)``
        with the same normals for those wave vectors, hence has exactly the
        distribution of a direct coarse sample. ``"injection"`` takes every
        second node (``fine[::2, ::2]``); its distribution is that of a direct
        coarse sample only if the band lies inside ``G_{n/2}``
        (``spectrum.resolves(n // 2)``); otherwise finer modes alias onto the
        coarse grid and, e.g., its pointwise variance is the fine one.

    Returns
    -------
    fine : ndarray of float64, shape (n, n)
    coarse : ndarray of float64, shape (n // 2, n // 2)
        Coarse node ``(i, j)`` sits at fine node ``(2 i, 2 j)``.
    """
    _check_inputs(spectrum, rng)
    n = _check_grid_size("n", n, multiple=4)
    if not is_one_of(projection, PROJECTIONS):
        raise InvalidParameterError("projection", projection, " or ".join(repr(p) for p in PROJECTIONS))
    modes = _grid_modes(spectrum, n)
    amplitudes = _draw(modes, rng)
    fine = _synthesise(n, modes, amplitudes)
    if projection == "injection":
        return fine, fine[::2, ::2].copy()
    coarse_modes = _grid_modes(spectrum, n // 2)
    # The coarse modes are the first ones of the fine draw order (shell ordering).
    coarse = _synthesise(n // 2, coarse_modes, amplitudes[: coarse_modes.size])
    return fine, coarse


def project_surface(
    fine: np.ndarray,
    n_coarse: int,
    *,
    method: Literal["truncation", "injection"] = "truncation",
) -> np.ndarray:
    """Project a periodic height field onto a nested coarser grid.

    Parameters
    ----------
    fine : array_like of float, shape (n, n)
        Heights on the fine grid (unit of ``L``).
    n_coarse : int
        Even number of coarse nodes per side dividing ``n``; coarse node
        ``(i, j)`` sits at fine node ``(i n / n_coarse, j n / n_coarse)``.
    method : {"truncation", "injection"}
        ``"truncation"``: keep the Fourier coefficients of the wave vectors
        ``G_{n_coarse}`` (module docstring; the mean is kept, the coarse Nyquist
        row and column are dropped). ``"injection"``: sample the fine field at
        the coarse nodes.

    Returns
    -------
    ndarray of float64, shape (n_coarse, n_coarse)
    """
    if not is_one_of(method, PROJECTIONS):
        raise InvalidParameterError("method", method, " or ".join(repr(p) for p in PROJECTIONS))
    fine = np.asarray(fine, dtype=np.float64)
    if fine.ndim != 2 or fine.shape[0] != fine.shape[1]:
        raise InvalidParameterError("fine", f"array of shape {fine.shape}", "a square 2-d array")
    n_fine = _check_grid_size("fine.shape[0]", fine.shape[0])
    n_coarse = _check_grid_size("n_coarse", n_coarse)
    if n_fine % n_coarse:
        raise InvalidParameterError("n_coarse", n_coarse, f"an even divisor of the fine grid size {n_fine}")
    if method == "injection":
        stride = n_fine // n_coarse
        return fine[::stride, ::stride].copy()
    fine_hat = get_fft(n_fine).forward(fine)
    m = n_coarse // 2 - 1
    coarse_hat = np.zeros((n_coarse, n_coarse // 2 + 1), dtype=np.complex128)
    coarse_hat[: m + 1, : m + 1] = fine_hat[: m + 1, : m + 1]
    if m > 0:
        coarse_hat[n_coarse - m :, : m + 1] = fine_hat[n_fine - m :, : m + 1]
    # The forward DFT is unnormalised and the inverse carries 1 / n_coarse^2, so
    # the amplitudes sum_x s(x) e^{-iqx} / n_fine^2 need the factor (n_coarse / n_fine)^2.
    return get_fft(n_coarse).inverse(coarse_hat) * (n_coarse / n_fine) ** 2
