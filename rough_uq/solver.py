"""Normal contact of a rigid rough surface on an elastic half-space (FFT-BEM).

Problem (SPEC sections 1-2)
---------------------------
On an ``n x n`` periodic grid find the pressure ``p >= 0`` with
``mean(p) = mean_pressure`` such that the gap

    g = u - s + d,        u = K p  (Westergaard, :mod:`rough_uq.elastic`)

is zero where ``p > 0`` and non-negative elsewhere. ``s`` are the surface
heights (larger heights touch first), ``d`` is the rigid-body approach (the
Lagrange multiplier of the mean-pressure constraint); ``u`` has zero mean.

Algorithm
---------
The constrained conjugate gradient of Polonsky & Keer (1999), pressure
controlled: the mean pressure is imposed exactly after every step, CG works
on the active set ``I = {p > 0}``, and is restarted (``delta = 0``) when
nodes out of contact overlap the surface and are added to the active set.

Two implementation choices make one iteration cost about one FFT pair:

* The solver keeps ``w = u - s`` and updates it with the conjugate direction's
  response, ``w <- w - tau K t``, as ordinary CG updates its residual. This is
  exact as long as no node is clamped to zero pressure or added from the
  overlap set; in iterations where that happens ``w`` is recomputed from
  ``p`` (a second FFT pair). It is also recomputed every
  ``_REFRESH_EVERY`` iterations, and always before convergence is declared,
  so the reported error is that of the returned pressure field.
* The elementwise work is done in a few fused, compiled passes (numba)
  instead of numpy's one-pass-per-operation expressions.

Convergence criterion
---------------------
With ``g`` the gap of the current iterate (``d`` chosen so that the mean gap
over the active set is zero),

    error = ( sum_{p>0} p |g|  +  mean_pressure * sum_{p=0} max(-g, 0) )
            / ( N * mean_pressure * s_rms ),

``N = n^2``, ``s_rms`` the RMS of ``s`` about its mean (1 for a flat
surface). The first term is the complementarity residual (work of the
pressure on the residual gaps), the second the interpenetration of nodes out
of contact, both relative to the natural scale ``mean_pressure * s_rms``.
The solve stops when ``error < tol``; ``tol`` is therefore dimensionless and
invariant under scaling heights, loads or the modulus.

Scaled units
------------
The problem is invariant under ``(s, d, u, p) -> (a s, a d, a u, a p)``
(linearity), ``(p, E*) -> (b p, b E*)`` and ``(L, s, d, u) -> (c L, c s, c d,
c u)`` (lengths). The solver subtracts the mean height and works in the
units where the heights have unit RMS, ``E* = 1`` and ``L = 1``; the only
parameter left is the dimensionless load

    load = mean_pressure * L / (E* * s_rms),

the load relative to the pressure scale ``E* s_rms / L`` of the surface's
slopes (full contact sets in at a load of order ``2 pi k_s``). Results are
scaled back. Iterates therefore neither overflow nor underflow whatever units
the caller uses (heights of ``1e-300`` or ``1e300``, ``E*`` of ``1e-6`` or
``1e9``), and the solution of a scaled problem is the scaled solution, to
rounding. ``load`` must lie in ``[2.2e-308, 1e100]``: below, it is not a
normal float; above, the rounding error of ``p = load + O(1)`` exceeds the
surface itself by some 80 orders of magnitude (no solve can succeed) and
squares of the residual would overflow.

A solve that reaches ``max_iter`` returns ``converged=False`` with the last
iterate; no field of a returned solution is ever NaN or infinite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .elastic import HalfSpace
from .errors import ConvergenceError, InvalidParameterError

__all__ = ["ContactSolution", "solve_contact", "resample_pressure"]

#: Iterations after which ``w`` is recomputed from ``p`` to bound the drift of
#: the recursive update.
_REFRESH_EVERY = 50

#: Range of the dimensionless load ``mean_pressure * L / (E* * s_rms)`` (module docstring).
_MIN_LOAD = float(np.finfo(np.float64).tiny)
_MAX_LOAD = 1e100


@dataclass(frozen=True)
class ContactSolution:
    """Result of :func:`solve_contact`.

    Attributes
    ----------
    pressure : ndarray, shape (n, n)
        Contact pressure, ``>= 0``, mean equal to ``mean_pressure`` (unit of ``E*``).
    displacement : ndarray, shape (n, n)
        Surface displacement of the half-space, zero mean (unit of ``L``).
    gap : ndarray, shape (n, n)
        ``displacement - heights + approach``: zero (to ``tol``) in contact,
        positive elsewhere (unit of ``L``).
    approach : float
        Rigid-body approach ``d`` (unit of ``L``).
    n_iter : int
        Conjugate-gradient iterations taken.
    error : float
        Final value of the convergence measure (see module docstring).
    converged : bool
        Whether ``error < tol`` was reached within ``max_iter``.
    n_restarts : int
        Times the iteration was restarted from uniform pressure because the
        initial guess gave no descent direction.
    message : str
        Why the solver stopped, in words.
    """

    pressure: np.ndarray
    displacement: np.ndarray
    gap: np.ndarray
    approach: float
    n_iter: int
    error: float
    converged: bool
    n_restarts: int = 0
    message: str = ""

    @property
    def contact(self) -> np.ndarray:
        """Boolean contact map ``pressure > 0``, shape (n, n)."""
        return self.pressure > 0


# --------------------------------------------------------------------------
# Fused passes. Each loops once over the grid; ``p > 0`` defines the active
# set I. Real-space arrays are (n, n); spectra are (n, n // 2 + 1).


@numba.njit(cache=True, parallel=True)
def _gap_pass(u, s, p, t, w):  # pragma: no cover - compiled
    # w <- u - s everywhere. Returns (sum_I w, |I|, sum_I t).
    n0, n1 = w.shape
    s_w = 0.0
    s_t = 0.0
    count = 0
    for i in numba.prange(n0):
        for j in range(n1):
            wij = u[i, j] - s[i, j]
            w[i, j] = wij
            if p[i, j] > 0.0:
                s_w += wij
                s_t += t[i, j]
                count += 1
    return s_w, count, s_t


@numba.njit(cache=True, parallel=True)
def _residuals(w, p, gbar):  # pragma: no cover - compiled
    # Returns (sum_I g^2, sum_I p |g|, sum_{not I} max(-g, 0)) with g = w - gbar.
    n0, n1 = w.shape
    g_norm = 0.0
    complementarity = 0.0
    overlap = 0.0
    for i in numba.prange(n0):
        for j in range(n1):
            g = w[i, j] - gbar
            if p[i, j] > 0.0:
                g_norm += g * g
                complementarity += p[i, j] * abs(g)
            elif g < 0.0:
                overlap -= g
    return g_norm, complementarity, overlap


@numba.njit(cache=True, parallel=True)
def _direction(w, p, gbar, beta, t_mean, t, out):  # pragma: no cover - compiled
    # t <- g + beta (t - t_mean) on I, 0 elsewhere, and copy into ``out`` (the
    # FFT input). With sum_I g = 0 and t_mean = mean_I(t), t has zero sum on I,
    # so the step keeps the total force. Returns sum_I g t.
    n0, n1 = w.shape
    s_gt = 0.0
    for i in numba.prange(n0):
        for j in range(n1):
            if p[i, j] > 0.0:
                g = w[i, j] - gbar
                tij = g + beta * (t[i, j] - t_mean)
                s_gt += g * tij
            else:
                tij = 0.0
            t[i, j] = tij
            out[i, j] = tij
    return s_gt


@numba.njit(cache=True, parallel=True)
def _energy(spectrum, weights, copy):  # pragma: no cover - compiled
    # Parseval: <K t, t> = sum_k weights_k |T_k|^2 with weights = K * (rfft
    # multiplicity) / N. Also keeps a copy of the spectrum.
    n0, n1 = spectrum.shape
    total = 0.0
    for i in numba.prange(n0):
        for j in range(n1):
            v = spectrum[i, j]
            copy[i, j] = v
            total += weights[i, j] * (v.real * v.real + v.imag * v.imag)
    return total


@numba.njit(cache=True, parallel=True)
def _step(w, p, t, gbar, tau):  # pragma: no cover - compiled
    # One Polonsky-Keer update of p, in place:
    #   active nodes: p <- max(p - tau t, 0)
    #   nodes at zero pressure with g < 0 (overlap): p <- -tau g
    # Returns (sum of new p, number of clamped nodes, number of overlap nodes).
    n0, n1 = w.shape
    total = 0.0
    n_clamped = 0
    n_overlap = 0
    for i in numba.prange(n0):
        for j in range(n1):
            pij = p[i, j]
            if pij > 0.0:
                pij = pij - tau * t[i, j]
                if pij <= 0.0:
                    pij = 0.0
                    n_clamped += 1
            if pij == 0.0:
                g = w[i, j] - gbar
                if g < 0.0:
                    pij = -tau * g
                    n_overlap += 1
            p[i, j] = pij
            total += pij
    return total, n_clamped, n_overlap


@numba.njit(cache=True, parallel=True)
def _advance_spectrum(p_hat, t_hat, tau, kernel, out):  # pragma: no cover - compiled
    # p_hat <- p_hat - tau t_hat (the step, when nothing was clamped or added);
    # out <- kernel * p_hat (ready for the inverse transform).
    n0, n1 = p_hat.shape
    for i in numba.prange(n0):
        for j in range(n1):
            v = p_hat[i, j] - tau * t_hat[i, j]
            p_hat[i, j] = v
            out[i, j] = v * kernel[i, j]


@numba.njit(cache=True, parallel=True)
def _store_spectrum(spectrum, kernel, p_hat):  # pragma: no cover - compiled
    # p_hat <- spectrum; spectrum <- kernel * spectrum.
    n0, n1 = spectrum.shape
    for i in numba.prange(n0):
        for j in range(n1):
            v = spectrum[i, j]
            p_hat[i, j] = v
            spectrum[i, j] = v * kernel[i, j]


@numba.njit(cache=True, parallel=True)
def _scale_and_copy(p, factor, out):  # pragma: no cover - compiled
    n0, n1 = p.shape
    for i in numba.prange(n0):
        for j in range(n1):
            v = p[i, j] * factor
            p[i, j] = v
            out[i, j] = v


# --------------------------------------------------------------------------


def resample_pressure(pressure: np.ndarray, n: int) -> np.ndarray:
    """Transfer a pressure field to an ``n x n`` grid for a warm start.

    Grids are nested (node ``i`` of grid ``m`` sits at ``i L / m``); the sizes
    must differ by a power of two. A finer field is restricted by periodic
    full weighting (stencil 1/4, 1/2, 1/4 per axis, evaluated at the coarse
    nodes); a coarser field is prolonged by periodic bilinear interpolation.
    Both keep ``p >= 0``; the solver rescales the mean.

    Parameters
    ----------
    pressure : ndarray, shape (m, m)
        Pressure on the source grid.
    n : int
        Target grid size.

    Returns
    -------
    ndarray, shape (n, n)
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        # Checked first: n = 0 would divide by zero in the ratio below.
        raise InvalidParameterError("n", n, "a positive integer grid size")
    field = np.asarray(pressure, dtype=np.float64)
    if field.ndim != 2 or field.shape[1] != field.shape[0] or field.size == 0:
        raise InvalidParameterError("initial_pressure", f"array of shape {field.shape}", "a non-empty square 2-D array")
    m = field.shape[0]
    ratio = max(m, n) / min(m, n)
    if ratio != 2 ** round(math.log2(ratio)) or max(m, n) % min(m, n):
        raise InvalidParameterError(
            "initial_pressure", f"grid {m} x {m}", f"a grid whose size differs from {n} by a power of two"
        )
    while field.shape[0] > n:
        for axis in (0, 1):
            field = 0.5 * field + 0.25 * (np.roll(field, 1, axis=axis) + np.roll(field, -1, axis=axis))
        field = field[::2, ::2]
    while field.shape[0] < n:
        m = field.shape[0]
        fine = np.empty((2 * m, 2 * m))
        fine[::2, ::2] = field
        fine[1::2, ::2] = 0.5 * (field + np.roll(field, -1, axis=0))
        fine[:, 1::2] = 0.5 * (fine[:, ::2] + np.roll(fine[:, ::2], -1, axis=1))
        field = fine
    return np.ascontiguousarray(field)


def _check_inputs(heights, system_size, mean_pressure, e_star, tol, max_iter) -> np.ndarray:
    s = np.asarray(heights)
    if s.ndim != 2 or s.shape[0] != s.shape[1]:
        raise InvalidParameterError("heights", f"array of shape {s.shape}", "a square n x n array")
    n = s.shape[0]
    if n < 2 or n % 2:
        raise InvalidParameterError("heights", f"{n} x {n} grid", "an even grid size n >= 2")
    if not np.issubdtype(s.dtype, np.floating) and not np.issubdtype(s.dtype, np.integer):
        raise InvalidParameterError("heights", f"dtype {s.dtype}", "real numbers")
    s = np.ascontiguousarray(s, dtype=np.float64)
    if not np.all(np.isfinite(s)):
        raise InvalidParameterError("heights", "non-finite values", "finite numbers")
    for name, value in (("system_size", system_size), ("mean_pressure", mean_pressure), ("e_star", e_star)):
        if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value > 0):
            raise InvalidParameterError(name, value, "a finite number > 0")
    if not (isinstance(tol, (int, float, np.floating)) and 0 < tol < 1):
        raise InvalidParameterError("tol", tol, "a number in (0, 1)")
    if not (isinstance(max_iter, (int, np.integer)) and max_iter >= 1):
        raise InvalidParameterError("max_iter", max_iter, "an integer >= 1")
    return s


def _initial_guess(initial_pressure, n: int) -> np.ndarray | None:
    if initial_pressure is None:
        return None
    p0 = np.asarray(initial_pressure, dtype=np.float64)
    if p0.ndim != 2:
        # Checked here, before resample_pressure indexes p0.shape[0] of a scalar.
        raise InvalidParameterError("initial_pressure", f"array of shape {p0.shape}", "a square 2-D array")
    if not np.all(np.isfinite(p0)):
        raise InvalidParameterError("initial_pressure", "non-finite values", "finite, non-negative pressures")
    if np.any(p0 < 0):
        raise InvalidParameterError("initial_pressure", f"minimum {p0.min():g}", "non-negative pressures")
    peak = float(p0.max(initial=0.0))
    if not peak > 0:
        raise InvalidParameterError("initial_pressure", "all zeros", "a field with some positive pressure")
    # Only the shape of the guess matters (the solver rescales it to the load).
    # Dividing by its peak first keeps the sums that rescale it finite for
    # guesses near the overflow (1e308) or underflow (1e-320) thresholds.
    p0 = p0 / peak
    if p0.shape != (n, n):
        p0 = resample_pressure(p0, n)
    if not p0.sum() > 0:
        raise InvalidParameterError("initial_pressure", "all zeros", "a field with some positive pressure")
    return p0


def _binary_ratio(numerators: tuple[float, ...], denominators: tuple[float, ...]) -> tuple[float, int]:
    """``(m, e)`` with ``prod(numerators) / prod(denominators) = m * 2**e`` (positive inputs).

    Mantissas and exponents are combined separately, so no intermediate
    product overflows or underflows where the result itself would not
    (e.g. ``1e200 * 1e200 / 1e300``); apply with ``math.ldexp``/``np.ldexp``.
    """
    mantissa, exponent = 1.0, 0
    for value in numerators:
        fraction, power = math.frexp(value)
        mantissa, exponent = mantissa * fraction, exponent + power
    for value in denominators:
        fraction, power = math.frexp(value)
        mantissa, exponent = mantissa / fraction, exponent - power
    return mantissa, exponent


def _scaled_heights(s: np.ndarray) -> tuple[float, float, np.ndarray]:
    """``(offset, scale, (s - offset) / scale)``: ``offset`` the mean, ``scale`` the RMS about it.

    Computed without squaring the raw heights, whose squares over- or
    underflow for heights beyond about ``1e+-154`` (``np.std`` would return
    ``inf`` or ``0``). A flat surface gets ``scale = 1``.

    Raises
    ------
    InvalidParameterError
        If the RMS height is not a normal float (subnormal heights).
    """
    peak = float(np.max(np.abs(s)))
    if peak == 0.0:
        return 0.0, 1.0, np.zeros_like(s)
    unit = s / peak  # in [-1, 1]
    mean_unit = float(np.mean(unit))
    deviation = unit - mean_unit  # in [-2, 2]
    spread = float(np.max(np.abs(deviation)))
    offset = peak * mean_unit
    if spread == 0.0:
        return offset, 1.0, np.zeros_like(s)
    deviation /= spread  # largest |value| is 1, so the mean square is >= 1 / N: no underflow
    rms = float(np.sqrt(np.mean(deviation * deviation)))
    scale = peak * (spread * rms)
    if not scale >= np.finfo(np.float64).tiny:
        raise InvalidParameterError("heights", f"RMS height {scale:g}", "an RMS height of at least 2.2e-308")
    return offset, scale, np.ascontiguousarray(deviation / rms)


def solve_contact(
    heights: np.ndarray,
    *,
    system_size: float,
    mean_pressure: float,
    e_star: float = 1.0,
    tol: float = 1e-8,
    max_iter: int = 10_000,
    initial_pressure: np.ndarray | None = None,
    threads: int = 1,
) -> ContactSolution:
    """Solve the frictionless, non-adhesive periodic contact problem.

    Parameters
    ----------
    heights : ndarray, shape (n, n)
        Rigid surface heights ``s`` (unit of ``L``); ``n`` even.
    system_size : float
        Box side ``L``.
    mean_pressure : float
        Imposed mean (nominal) pressure, ``> 0`` (unit of ``E*``). Every load
        has a defined result: as the load tends to 0 the contact shrinks to
        the highest node(s), which carry the whole force ``n^2 mean_pressure``
        (the limit is reached well above the smallest representable loads);
        beyond the full-contact load every node is in contact and the
        pressure is :func:`~rough_uq.reference.full_contact_pressure`. Zero
        load itself is rejected: with no force there is no contact set to
        find (every ``p = 0`` is admissible and the approach ``d`` is not
        determined), so a defined answer would be an arbitrary convention.
        Loads are also rejected when the dimensionless load
        ``mean_pressure * system_size / (e_star * RMS height)`` lies outside
        ``[2.2e-308, 1e100]`` (module docstring) or ``n^2 mean_pressure``
        overflows. Far beyond full contact (at the default ``tol``, from
        some ``1e7`` to ``1e8`` times the full-contact load on) rounding of
        ``p = mean_pressure + (variation)`` limits the attainable error; the
        solve then ends with ``converged=False`` after ``max_iter``.
    e_star : float, optional
        Effective modulus ``E* = E / (1 - nu^2)``.
    tol : float, optional
        Target of the dimensionless convergence measure (module docstring).
    max_iter : int, optional
        Iteration budget; reaching it returns ``converged=False``.
    initial_pressure : ndarray, optional
        Warm start: a non-negative pressure on this grid or on a grid whose
        size differs by a power of two (it is resampled with
        :func:`resample_pressure` and rescaled to ``mean_pressure``). A guess
        that leaves no descent direction (e.g. all pressure on one node) is
        replaced by uniform pressure (counted in ``n_restarts``).
    threads : int, optional
        FFTW threads.

    Returns
    -------
    ContactSolution

    Raises
    ------
    InvalidParameterError
        For non-square, odd-sized or non-finite heights (or subnormal RMS
        height), non-positive ``mean_pressure`` (zero load included, see
        above), ``system_size`` or ``e_star``, a dimensionless load out of
        range (see ``mean_pressure``), or an invalid ``initial_pressure``
        (negative, all zero, not square, or from a grid whose size does not
        differ from ``n`` by a power of two).
    """
    s = _check_inputs(heights, system_size, mean_pressure, e_star, tol, max_iter)
    n = s.shape[0]
    n_nodes = n * n
    p0 = _initial_guess(initial_pressure, n)
    # Scaled units (module docstring): heights with zero mean and unit RMS, E* = 1, L = 1.
    # From here on s, p, w, gbar and ``load`` are in these units.
    offset, s_rms, s = _scaled_heights(s)
    if not math.isfinite(mean_pressure * n_nodes):
        # All the force may end up on one node: its pressure must be a float.
        raise InvalidParameterError(
            "mean_pressure", mean_pressure, f"a load whose total over the {n_nodes} nodes is finite"
        )
    try:
        load = math.ldexp(*_binary_ratio((mean_pressure, system_size), (e_star, s_rms)))
    except OverflowError:
        load = math.inf
    if not _MIN_LOAD <= load <= _MAX_LOAD:
        raise InvalidParameterError(
            "mean_pressure",
            mean_pressure,
            f"a dimensionless load mean_pressure * system_size / (e_star * RMS height) in "
            f"[{_MIN_LOAD:.2g}, {_MAX_LOAD:.0e}]; here it is {load:.3g} (system_size = {system_size:g}, "
            f"e_star = {e_star:g}, RMS height = {s_rms:.3g})",
        )
    total_force = load * n_nodes
    error_scale = total_force  # N * load * (unit RMS height)

    half_space = HalfSpace(n, system_size=1.0, e_star=1.0, threads=threads)
    fft = half_space.fft
    kernel = half_space.kernel
    # Parseval weights of <K t, t> in the rfft half spectrum: interior columns
    # stand for two modes (k and -k), the first and the Nyquist column for one.
    weights = kernel * (2.0 / n_nodes)
    weights[:, 0] *= 0.5
    weights[:, -1] *= 0.5

    p = np.full((n, n), load) if p0 is None else p0.copy()
    w = np.empty((n, n))
    t = np.zeros((n, n))
    p_hat = np.empty_like(fft.spectral)
    t_hat = np.empty_like(fft.spectral)

    def displacement_from_pressure() -> None:
        # Impose the mean pressure exactly, then fft.real <- K p; keeps p_hat.
        _scale_and_copy(p, total_force / p.sum(), fft.real)
        fft.forward()
        _store_spectrum(fft.spectral, kernel, p_hat)
        fft.inverse()

    previous_threads = numba.get_num_threads()
    numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
    try:
        displacement_from_pressure()
        is_exact = True
        n_restarts = 0
        delta = 0.0
        g_norm_old = 1.0
        since_refresh = 0
        n_iter = 0
        message = ""
        error = math.inf
        converged = False
        while True:
            # fft.real holds u = K p for the current p.
            active_total, n_active, t_total = _gap_pass(fft.real, s, p, t, w)
            gbar = active_total / n_active
            g_norm, complementarity, overlap = _residuals(w, p, gbar)
            error = (complementarity + load * overlap) / error_scale
            if not math.isfinite(error):
                raise ConvergenceError(
                    f"non-finite convergence measure at iteration {n_iter} (inputs were finite; this is a bug)"
                )
            if error < tol or n_iter >= max_iter:
                if not is_exact:
                    # Judge the exact displacement of the current p, not the
                    # recursively updated one.
                    displacement_from_pressure()
                    is_exact = True
                    since_refresh = 0
                    continue
                converged = error < tol
                if converged:
                    message = f"converged: error {error:.3g} < tol {tol:.3g}"
                else:
                    message = f"not converged: max_iter={max_iter} reached with error {error:.3g} (tol {tol:.3g})"
                break

            beta = delta * g_norm / g_norm_old if g_norm_old > 0 else 0.0
            s_gt = _direction(w, p, gbar, beta, t_total / n_active, t, fft.real)
            g_norm_old = g_norm
            fft.forward()
            curvature = _energy(fft.spectral, weights, t_hat)  # <K t, t>
            if not (s_gt > 0 and curvature > 0 and math.isfinite(s_gt / curvature)):
                if beta != 0.0:
                    # Rounding has spoilt the conjugate direction: retry with
                    # the steepest-descent direction (nothing has changed yet).
                    delta = 0.0
                    continue
                if n_iter == 0 and n_restarts == 0 and p0 is not None:
                    # The warm start leaves no descent direction on its active
                    # set (e.g. all pressure on one node): start again from
                    # uniform pressure.
                    n_restarts += 1
                    p.fill(load)
                    t.fill(0.0)
                    displacement_from_pressure()
                    is_exact = True
                    continue
                if not is_exact:
                    displacement_from_pressure()
                    is_exact = True
                    continue
                # Even steepest descent finds no decrease: the residual is at
                # the level of rounding errors and tol cannot be reached.
                message = (
                    f"not converged: stalled at error {error:.3g} after {n_iter} iterations "
                    f"(tol {tol:.3g} is below what rounding allows on this grid)"
                )
                break
            tau = s_gt / curvature
            total, n_clamped, n_overlap = _step(w, p, t, gbar, tau)
            n_iter += 1
            since_refresh += 1
            delta = 0.0 if n_overlap else 1.0
            if n_clamped or n_overlap or since_refresh >= _REFRESH_EVERY:
                if not total > 0:
                    # Every node was clamped and none overlapped (cannot happen
                    # for a descent step, but never divide by zero).
                    p.fill(load)
                    t.fill(0.0)
                    delta = 0.0
                displacement_from_pressure()
                is_exact = True
                since_refresh = 0
            else:
                _advance_spectrum(p_hat, t_hat, tau, kernel, fft.spectral)
                fft.inverse()
                is_exact = False
    finally:
        numba.set_num_threads(previous_threads)

    # Back from scaled units: heights, displacements and gaps times s_rms (the
    # approach also gets the mean height back), pressures times E* s_rms / L
    # (in binary, so that E* s_rms cannot overflow when the pressures do not).
    approach = -gbar
    displacement = (w + s) * s_rms
    gap = (w + approach) * s_rms
    mantissa, exponent = _binary_ratio((e_star, s_rms), (system_size,))
    pressure = np.ldexp(p * mantissa, exponent)
    return ContactSolution(
        pressure=pressure,
        displacement=displacement,
        gap=gap,
        approach=float(approach * s_rms + offset),
        n_iter=n_iter,
        error=float(error),
        converged=converged,
        n_restarts=n_restarts,
        message=message,
    )
