"""Normal contact of a rigid rough surface on an elastic half-space (FFT-BEM).

Problem (SPEC sections 1-2)
---------------------------
On an ``n x n`` periodic grid find the pressure ``p >= 0`` with
``mean(p) = mean_pressure`` such that the gap

    g = u - s + d,        u = K p  (Westergaard, :mod:`rough_uq.physics.elastic`)

is zero where ``p > 0`` and non-negative elsewhere. ``s`` are the surface
heights (larger heights touch first), ``d`` is the rigid-body approach (the
Lagrange multiplier of the mean-pressure constraint); ``u`` has zero mean.

Algorithm
---------
The constrained conjugate gradient of Polonsky & Keer (1999), pressure
controlled: the mean pressure is imposed exactly after every step, CG works
on the active set ``I = {p > 0}``, and is restarted (``delta = 0``) when
nodes out of contact overlap the surface and are added to the active set.

It is preconditioned (``precondition=True``, the default) with the inverse
of the Westergaard operator restricted to the active set: the residual
``g`` (zero off ``I``) is mapped to ``y = M g`` with ``M = K^-1``
(multiplication by ``E* |q| / 2`` in Fourier space), and the search
direction is built from ``y`` projected on zero sum over ``I``,

    t = (y - mean_I y) + beta (t_old - mean_I t_old)   on I,
    beta = rho / rho_old,   rho = sum_I g (y - mean_I y).

On the whole grid ``M K`` is the identity. Restricted to a contact set the
two operators (of orders -1 and +1) are no longer exact inverses, but their
product stays well conditioned (the idea of operator, or Calderon,
preconditioning), so the iteration count grows slowly with the grid instead
of like the square root of the condition number of ``K`` (about ``n``). On the
reference surface of the benchmark it took 41 / 60 / 72 iterations at
256^2 / 512^2 / 1024^2 against 147 / 188 / 250 for plain Polonsky-Keer.
``M`` is applied with single-precision FFTs: it only shapes the direction
(the residual and the stopping test stay in double precision). The
curvature ``<t, K t>`` of the step length (by Parseval, from the forward
transform of ``t``) is computed in single precision too: a relative error of
1e-7 in the step length is harmless, since the residual is recomputed
from ``p`` in every iteration (below). This rounding changed no iteration
count in our benchmark runs, down to ``tol = 1e-12``. Nodes added from the
overlap get ``p = -tau m g`` with ``m = rho / sum_I g^2`` the Rayleigh
quotient of ``M`` on the current residual, the preconditioned analogue of
Polonsky-Keer's ``p = -tau g`` (see :func:`_overlap_scale` for why not the
diagonal of ``M``, which made the iteration diverge on some problems).

Safeguard: a preconditioned solve whose error has not halved within
``_STALL_WINDOW`` iterations hands over to plain Polonsky-Keer, which
starts afresh from uniform pressure (from the stalled pressure where its
error is below ``_FRESH_START_ERROR``, 1e-3: a stall at a tolerance below
what rounding allows, all but converged) and finishes the solve
(``ContactSolution.path`` says so and ``n_iter_plain`` counts its
iterations). Plain Polonsky-Keer is a projected conjugate gradient on a
convex problem and converged on every spectral problem we tried. With the
overlap scale above no randomised spectral problem of the test suite needs
the hand-over for a stall (for the lack of descent below, some do); it is
there so that a solve never ends in a wrong number after ``max_iter``
iterations. It is needed on a single tall spike (one
node, or a few, far above the rest) at loads just below those where the
rest of the surface starts to touch: the preconditioned direction of a
spike's residual is spread over the whole grid, and the iteration cycles
between contact sets of thousands of nodes (error 7-33 after 10 000
iterations, where the answer is the load on the spike). Plain
Polonsky-Keer handed the stalled pressure cycled as well (a 2-cycle of
contact sets of about 2100 and 2950 nodes at 64^2); started from uniform
pressure its first direction is the spike itself, and it converged in one
iteration on every spike on a flat surface we tried
(``tests/test_hard_cases.py``).

The preconditioned iteration hands over in the same way when it finds no
descent direction. With a single node in contact the residual on the
contact set is zero (its mean is removed), so no step is left even where
other nodes interpenetrate: just above the load at which a second node
touches, the iteration can reach the highest node alone and stopped there,
unconverged at an error of about 1e-6 (3 of 40 surfaces of 32^2 with
``k_s`` at the grid's Nyquist wave number; ``tests/test_solver_fuzz.py``).
Plain Polonsky-Keer adds the interpenetrating nodes (below) and converged
in one or two more iterations.

Plain Polonsky-Keer has a safeguard of its own. After each step it restores
the mean pressure by a factor ``c``; where the step length is set by a stiff
node (a tall spike: ``tau`` about ``1 / K_ii``), the same step gives the
long-wave residuals elsewhere pressures of many times the total force, the
factor (about 0.05) takes most of the spike's increase back, and the
iteration settles into a 2-cycle of contact sets (one node 1e4 above white
noise of unit RMS on 128^2 nodes, load 0.41: error 10-13 and some 10 900
nodes in contact, against one). A plain solve whose error has not halved in
``_PLAIN_STALL_WINDOW`` (100) iterations therefore restores the mean
pressure from then on by a uniform shift, ``p <- max(p - lam, 0)`` (the
Euclidean projection on the pressures of that total force), which takes the
excess from the small pressures: that problem then converges in 101
iterations, spikes at loads where most of the surface touches in 128-221,
integer terraces in 128-138, where the factor never converged. On ordinary
surfaces the error halves far more often (at most every 5 / 8 / 20
iterations at 32^2 / 64^2 / 128^2 over 300 random spectral problems), and
840 solves of them were unchanged to the bit. And a plain step with no
descent direction on the active set (a single active node has ``g = 0``
there) but with interpenetrating nodes adds those nodes alone, with the
pressure ``-g / K_ii`` that closes an isolated node's gap, instead of
stopping (all the load on one node of a 16^2 surface, where the answer has
two).

One preconditioned iteration costs two and a half single-precision FFT
pairs: the preconditioner, the transform of ``t``, and the displacement of
the step's pressure increment. That displacement is not updated as
``u <- u - tau K t``, because in almost every iteration some node is
clamped or added (a median of 45 nodes per iteration for plain
Polonsky-Keer, 97 preconditioned, on the benchmark surface at 512^2), so
that update would rarely be exact. The step writes its increment ``e``
(the new pressure, before the mean pressure is imposed again by a factor
``c``, minus the old one) in single precision, and the gap pass updates
the gap in place, ``w <- c w + (c - 1) s + K (c e)``, with ``K (c e)`` in
single precision (0.55-0.7 of the time of a double pair at
1024^2-2048^2). The rounding of each increment's displacement, about 1e-7
of it, shrinks with the increments and adds up between exact
displacements: whenever the error has fallen by ``_REFRESH_FACTOR`` (1e-2)
since the last exact displacement, the displacement is computed from the
pressure in double precision (one double pair), and every stop
(converged, ``max_iter``, stalled) is decided on an exact displacement. On
the benchmark surface the iteration counts did not change (73 at 1024^2; 88
to 92 at 2048^2, as the rounding falls) and a solve took 0.81-0.87 of the time of
exact double-precision displacements. The increments used to be counted from
a reference pressure kept with its exact displacement (``u = u_ref + K (p -
p_ref)``): two more double-precision arrays of the grid's size, which the
step and the gap pass read in every iteration. Without them an iteration
took 0.955-0.974 of the time at 1024^2 and 0.93 at 2048^2 (interleaved
solves, 16 and 6 pairs), with the same iterations and contact sets and
pressures within 3.4e-9 (relative L2) of those solves. The gap pass reads
the heights of its term ``(c - 1) s`` in single precision (a copy made once
per solve): their rounding, 6e-8 of ``s``, counts only times ``c - 1``, the
relative change of the total force by the step's clamped and added nodes;
0.986 of the time per iteration at 1024^2 and 0.979 at 2048^2 (16 and 6
interleaved pairs), the contact sets unchanged. The five single-precision half
transforms share one in-place buffer (FFTW's padded layout, see
:class:`~rough_uq.physics.fft.RealFFT`): one buffer instead of separate
real and spectral ones, less memory traffic, and an iteration took 0.94-0.96 /
0.83-0.92 of the time at 1024^2 / 2048^2 (three interleaved A/B runs on the
benchmark surface); its forward transform destroys its input, which the
iteration never reads again. Their inverse transforms are not normalised
(pyFFTW would scale the output in a pass of its own): the factor ``1 / N`` is
in the single-precision kernels of ``M`` and ``K``, and an iteration took
0.93 of the time at 1024^2 and 0.99 at 2048^2 (A/B, twice). Plain Polonsky-Keer
(``precondition=False``) costs one double pair (exact displacements) and
the single-precision forward transform of ``t``, which it keeps in single
precision (the direction needs no more; the iteration counts do not
change). The elementwise work is done in a few fused, branch-free passes
compiled with numba: plain Polonsky-Keer makes three passes over the grid per
iteration (gap and sums; error and direction; step), the preconditioned
iteration five. The pressure is stored unnormalised in the FFT input (the
mean pressure is imposed by a factor in the spectral multiply of ``K``), and
the gap overwrites the displacement: no pass to rescale and copy the
pressure, and two arrays fewer. The preconditioned passes are memory-bound
(at 1024^2 the iteration's arrays do not fit in the cache together), so they
read as little as they can: the active set from a one-byte mask kept by the
step instead of the pressure, the search direction in single precision, and
``rho``'s ``sum_I g y`` by Parseval in the spectral multiply of ``M``
(``<r, M r>``) instead of from the displacement; with the single-precision
kernel also in the curvature's Parseval sum, an iteration took 0.93 of the
time at 1024^2 and 2048^2 (A/B on the benchmark surface). The step length's
``sum_I g t`` is put together from ``rho`` and the residual pass's
``sum_I g t_old`` (``t = (y - mean_I y) + beta (t_old - mean_I t_old)`` on
``I``), so that the direction pass does not read the gap: 0.967 of the time
per iteration at 1024^2 (two runs of 16 interleaved pairs), even at 2048^2.

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
rounding with plain Polonsky-Keer and to about 1e-10 of the largest pressure
preconditioned (the single-precision increments of the displacement round
differently in the two problems, and the iterates drift apart by that much;
measured over 40 random problems scaled by 1e-300: at most 4e-11). ``load``
must lie in ``[2.2e-308, 1e25]`` (:data:`MIN_DIMENSIONLESS_LOAD`,
:data:`MAX_DIMENSIONLESS_LOAD`): below, it is not a normal float; above, the
rounding error of ``p = load + O(1)`` exceeds the surface itself by some 9
orders of magnitude (no solve can succeed: full contact sets in below
``2 pi k_s <= 2e5``, and from some 1e7 to 1e8 times that load on no solve
converges: a solve's error stops at about ``ROUNDING_FLOOR * eps * load``,
and a solve that ends unconverged above :func:`max_convergent_load` says so),
and the preconditioned iteration breaks down further up: its
convergence measure turned non-finite (a ``ConvergenceError``) from a load of
about 1e52 on 16^2 nodes, 1e44 on 1024^2 and 1e43 on 2048^2 (alike for four
spectra; some 1.3 decades less per doubling of ``n``: about 1e36 at 65536^2).

A solve that reaches ``max_iter`` returns ``converged=False`` with the last
iterate; no field of a returned solution is ever NaN or infinite.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np

from rough_uq.physics.elastic import HalfSpace, multiply_spectrum
from rough_uq.errors import (
    ConvergenceError, InvalidParameterError, checked_bool, checked_integer, is_integer, is_real_number, refuse_non_real,
    scalar_refusal,
)
from rough_uq.physics.fft import RealFFT, get_fft

__all__ = ["ContactSolution", "solve_contact", "resample_pressure"]

#: LLVM fast-math flags of the fused passes: reassociation only, so that the
#: sums vectorise; no assumptions about NaN, infinities or signed zeros.
_FASTMATH = {"reassoc"}

#: The smallest grid (in nodes) whose fused passes run on ``threads`` numba
#: threads; smaller grids run them on one. With two threads a parallel pass
#: cost some 45 us more per call on the development machine (the second
#: thread sleeps between passes, ``OMP_WAIT_POLICY=PASSIVE``, and waking it
#: takes that long): at 128^2 and 256^2 a pass took 50-60 us instead of 6-20 us
#: on one thread, and a quickstart sample at 256^2 twice as long (21-26 against
#: 45-50 samples/s, ``scripts/bench_throughput.py --threads 2``). At 512^2 it
#: is even (12.2-13.0 samples/s against 13.2 with one-thread passes); at 1024^2
#: every pass gains or ties (``scripts/profile_solver.py --threads 2``).
PARALLEL_PASS_MIN_NODES = 512 * 512

#: The most threads a solve takes. pyFFTW cannot pass 2**31 or more to FFTW (an OverflowError from deep inside
#: its planner), and a thousand threads on one grid are far beyond any machine's use; a larger count is a typo.
MAX_THREADS = 1024

#: Range of the dimensionless load ``mean_pressure * L / (E* * s_rms)`` a solve takes (module docstring,
#: "Scaled units"); ``s_rms`` is the RMS of the heights it is given. A contact problem checks its loads
#: against it when it is built (:func:`rough_uq.problem.contact.checked_mean_pressures`).
MIN_DIMENSIONLESS_LOAD = float(np.finfo(np.float64).tiny)
MAX_DIMENSIONLESS_LOAD = 1e25

#: The convergence measure of a solve cannot fall below about ``c * eps * load`` (``eps`` the double-precision
#: machine epsilon, ``load`` the dimensionless load): the pressures are about ``load`` and their rounding,
#: ``eps * load``, is a pressure field whose gap no iteration removes. ``c`` is this typical value: over 36
#: random spectral problems of 32^2-256^2 (``k_s`` up to ``n / 2``, ``H`` in [0, 1]) at loads 1e7, 1e9 and
#: 1e11, solved at ``tol = 1e-15``, the error stopped at 0.0065-0.115 ``eps * load`` (median 0.02), lowest on
#: the larger grids. Above :func:`max_convergent_load` half the solves or more end unconverged.
ROUNDING_FLOOR = 0.02


def max_convergent_load(tol: float) -> float:
    """The dimensionless load above which rounding keeps most solves from reaching ``tol``
    (:data:`ROUNDING_FLOOR`): ``tol / (ROUNDING_FLOOR * eps)``, 2.3e9 at ``tol = 1e-8``."""
    return tol / (ROUNDING_FLOOR * float(np.finfo(np.float64).eps))


@dataclass(frozen=True, eq=False)  # arrays: no field-wise ==, which raised (as the other results)
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
        Rigid-body term ``d`` of the gap ``displacement - heights + d`` (unit of ``L``). With this sign
        (SPEC's) it is the largest height at first contact and decreases as the load grows.
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
    path : str
        Which iteration produced the solution: ``"preconditioned"``,
        ``"plain"`` (``precondition=False``), or ``"preconditioned+plain"``
        when the preconditioned iteration stalled or found no descent
        direction and plain Polonsky-Keer finished the solve (module
        docstring, "Safeguard").
    n_iter_plain : int
        Iterations of plain Polonsky-Keer among ``n_iter``.
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
    path: str = "preconditioned"
    n_iter_plain: int = 0

    @property
    def contact(self) -> np.ndarray:
        """Boolean contact map ``pressure > 0``, shape (n, n)."""
        return self.pressure > 0

    def __repr__(self) -> str:
        # A summary for notebooks and print(): the three (n, n) fields printed some 30 lines of numbers.
        why = "" if self.converged else f", n_restarts={self.n_restarts}, message={self.message!r}"
        return (f"ContactSolution(grid={self.pressure.shape[0]}^2, converged={self.converged}, n_iter={self.n_iter}, "
                f"error={self.error:.3g}, path={self.path!r}, contact_fraction={np.mean(self.contact):.4g}, "
                f"approach={self.approach:.6g}{why})")


# --------------------------------------------------------------------------
# Fused passes. Each loops once over the grid; ``p > 0`` defines the active
# set I. Real-space arrays are (n, n); spectra are (n, n // 2 + 1).


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _gap_pass(w, s, active, shift, scale=1.0, v=None):  # pragma: no cover - compiled
    # w <- w - s everywhere, in place (w holds u = K p on entry); with the
    # displacement v of the last step's increment (single precision, see
    # _State.update_displacement) w <- scale w + (scale - 1) s + v instead
    # (w holds the last gap u - s on entry, scale is the new pressure's
    # factor). Returns sums over I: (sum w, |I|,
    # sum (w - shift)^2). With gbar = mean_I w,
    # sum_I (w - gbar)^2 = sum_I (w - shift)^2 - |I| (gbar - shift)^2; a shift
    # close to gbar (the previous one) keeps the difference free of
    # cancellation. ``active > 0`` defines I: the pressure p itself, or the
    # 0/1 mask of the preconditioned iteration (_State.active, an eighth of
    # the memory traffic). (Multiplying by the 0/1 indicator of I vectorises
    # better than selecting; numba compiles the cases apart: ``is None`` on a
    # None argument and the arrays' types are decided at compile time.)
    n0, n1 = w.shape
    s_w = 0.0
    s_sq = 0.0
    count = 0
    for i in numba.prange(n0):
        for j in range(n1):
            if v is None:
                wij = w[i, j] - s[i, j]
            else:
                wij = scale * w[i, j] + (scale - 1.0) * s[i, j] + v[i, j]
            w[i, j] = wij
            is_active = active[i, j] > 0
            weight = 1.0 if is_active else 0.0
            shifted = weight * (wij - shift)
            s_w += weight * wij
            s_sq += shifted * shifted
            count += is_active
    return s_w, count, s_sq


@numba.njit(inline="always")
def _error_terms(g, pij, weight):  # pragma: no cover - compiled
    # A node's share of the two sums of the error (module docstring):
    # p |g| (zero off I, where p = 0) and, off I, max(-g, 0). Written as
    # ``(1 - weight) min(g, 0)``, which vectorises; a test ``active or g >= 0``
    # does not.
    return pij * abs(g), -(1.0 - weight) * min(g, 0.0)


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _residual_pass(w, p, gbar, r, t):  # pragma: no cover - compiled
    # r <- g = w - gbar on I, 0 elsewhere (the input of the preconditioner).
    # Returns (sum_I p |g|, sum_{not I} max(-g, 0), sum_I g, sum_I g t): the two
    # terms of the error (p = 0 off I, so the first sum may run over all nodes;
    # p is the stored, unnormalised pressure), the rounding error of the mean
    # of g, and the old direction t's share of the next sum_I g t (_direction).
    n0, n1 = w.shape
    complementarity = 0.0
    overlap = 0.0
    s_g = 0.0
    s_gt = 0.0
    for i in numba.prange(n0):
        for j in range(n1):
            g = w[i, j] - gbar
            pij = p[i, j]
            weight = 1.0 if pij > 0.0 else 0.0
            node_complementarity, node_overlap = _error_terms(g, pij, weight)
            complementarity += node_complementarity
            overlap += node_overlap
            s_g += weight * g
            s_gt += weight * g * t[i, j]
            r[i, j] = weight * g
    return complementarity, overlap, s_g, s_gt


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _plain_direction(w, p, gbar, beta, t_mean, t):  # pragma: no cover - compiled
    # Unpreconditioned: the residual pass and the direction in one.
    # t <- g + beta (t - t_mean) on I, 0 elsewhere (g = w - gbar has zero sum
    # on I), in place (t is the single-precision FFT input; sum g t is taken
    # before rounding, a relative difference of 1e-7 in the step length, as
    # harmless as the single-precision curvature). Returns
    # (sum_I p |g|, sum_{not I} max(-g, 0), sum_I g t).
    n0, n1 = w.shape
    complementarity = 0.0
    overlap = 0.0
    s_gt = 0.0
    for i in numba.prange(n0):
        for j in range(n1):
            g = w[i, j] - gbar
            pij = p[i, j]
            weight = 1.0 if pij > 0.0 else 0.0
            node_complementarity, node_overlap = _error_terms(g, pij, weight)
            complementarity += node_complementarity
            overlap += node_overlap
            tij = weight * (g + beta * (t[i, j] - t_mean))
            t[i, j] = tij
            s_gt += g * tij
    return complementarity, overlap, s_gt


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _active_sum(y, active):  # pragma: no cover - compiled
    # Sum over I of the preconditioned residual y.
    n0, n1 = active.shape
    s_y = 0.0
    for i in numba.prange(n0):
        for j in range(n1):
            s_y += y[i, j] if active[i, j] > 0 else 0.0
    return s_y


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _direction(y, active, y_mean, beta, t_mean, t, out):  # pragma: no cover - compiled
    # t <- (y - y_mean) + beta (t - t_mean) on I, 0 elsewhere, written to t and
    # to ``out`` (the FFT input; may be y itself). Both brackets have zero sum
    # on I, so the step keeps the total force. (sum_I g t is put together from
    # the sums of _residual_pass and the preconditioner instead of read here
    # from the gap: a double-precision array fewer in this pass.)
    n0, n1 = active.shape
    for i in numba.prange(n0):
        for j in range(n1):
            weight = 1.0 if active[i, j] > 0 else 0.0
            tij = weight * ((y[i, j] - y_mean) + beta * (t[i, j] - t_mean))
            t[i, j] = tij
            out[i, j] = tij


@numba.njit(inline="always")
def _half_spectrum_row(spectrum, kernel, i, multiply):  # pragma: no cover - compiled
    # sum_k kernel_k |X_k|^2 over the full spectrum's modes of row i of the
    # rfft half spectrum: interior columns stand for two modes (k and -k),
    # the first and the Nyquist column for one. With ``multiply`` also
    # X <- kernel X in place.
    last = spectrum.shape[1] - 1
    first, nyquist = spectrum[i, 0], spectrum[i, last]
    edges = kernel[i, 0] * (first.real * first.real + first.imag * first.imag)
    edges += kernel[i, last] * (nyquist.real * nyquist.real + nyquist.imag * nyquist.imag)
    row = 0.0
    for j in range(last + 1):
        v = spectrum[i, j]
        row += kernel[i, j] * (v.real * v.real + v.imag * v.imag)
        if multiply:
            spectrum[i, j] = v * kernel[i, j]
    return 2.0 * row - edges


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _energy(spectrum, kernel):  # pragma: no cover - compiled
    # Parseval: <K t, t> = (1 / N) sum_k K_k |T_k|^2 for the transform T of t,
    # with ``kernel`` = K / N (in single precision, _Operators.kernel_single).
    total = 0.0
    for i in numba.prange(spectrum.shape[0]):
        total += _half_spectrum_row(spectrum, kernel, i, False)
    return total


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _multiply_energy(spectrum, kernel):  # pragma: no cover - compiled
    # X <- kernel X in place (the preconditioner, kernel = M / N); returns
    # (1 / N) sum_k M_k |R_k|^2 = <r, M r> (Parseval) of the input R.
    total = 0.0
    for i in numba.prange(spectrum.shape[0]):
        total += _half_spectrum_row(spectrum, kernel, i, True)
    return total


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _step(w, p, t, gbar, scale, tau, tau_overlap, increment=None, active=None):  # pragma: no cover - compiled
    # One Polonsky-Keer update of the pressure scale * p, in place:
    #   active nodes: p <- max(scale p - tau t, 0)  (t = 0 off I)
    #   nodes left at zero pressure with g < 0 (overlap): p <- -tau_overlap g
    # With ``increment`` it also writes the increment (new p) - scale * (old p)
    # in single precision (the input of the increment's displacement, see
    # _State.update_displacement); with ``active`` the 0/1 mask of the new
    # active set.
    # Returns (sum of new p, number of overlap nodes, sum of t over the new
    # active set, for the next direction; t = 0 on overlap nodes).
    n0, n1 = w.shape
    total = 0.0
    s_t = 0.0
    n_overlap = 0
    for i in numba.prange(n0):
        for j in range(n1):
            tij = t[i, j]
            old = scale * p[i, j]
            q = old - tau * tij
            q = q if q > 0.0 else 0.0
            s_t += tij if q > 0.0 else 0.0
            g = w[i, j] - gbar
            overlapping = q == 0.0 and g < 0.0
            q = -tau_overlap * g if overlapping else q
            p[i, j] = q
            if increment is not None:
                increment[i, j] = q - old
            if active is not None:
                active[i, j] = 1 if q > 0.0 else 0
            total += q
            n_overlap += overlapping
    return total, n_overlap, s_t


@numba.njit(cache=True)
def _single_kernels(kernel, n_nodes, kernel_single, inverse=None):  # pragma: no cover - compiled
    # kernel_single <- kernel / N and (``inverse`` given) inverse <- (1 / kernel) / N, zero at the zero mode
    # (where kernel is zero), rounded to single precision: the same IEEE operations as the numpy expressions
    # (kernel / N).astype(float32) and ((1 / kernel) / N).astype(float32), in one pass without grid-sized
    # temporaries (at large grids the first use of fresh memory costs more than the arithmetic).
    n0, n1 = kernel.shape
    for i in range(n0):
        for j in range(n1):
            k = kernel[i, j]
            kernel_single[i, j] = np.float32(k / n_nodes)
            if inverse is not None:
                inverse[i, j] = np.float32((1.0 / k) / n_nodes) if k > 0.0 else np.float32(0.0)


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
    if not (is_integer(n) and n >= 1):
        # Checked first: n = 0 would divide by zero in the ratio below.
        raise InvalidParameterError("n", n, "a positive integer grid size")
    field = np.asarray(pressure, dtype=np.float64)
    if field.ndim != 2 or field.shape[1] != field.shape[0] or field.size == 0:
        raise InvalidParameterError("pressure", f"array of shape {field.shape}", "a non-empty square 2-D array")
    m = field.shape[0]
    if not _differ_by_power_of_two(m, n):
        raise InvalidParameterError(
            "pressure", f"grid {m} x {m}", f"a grid whose size differs from {n} by a power of two"
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


def _differ_by_power_of_two(m: int, n: int) -> bool:
    """Whether grid sizes ``m`` and ``n`` (positive) differ by a factor ``2**k``, ``k >= 0``."""
    ratio = max(m, n) / min(m, n)
    return ratio == 2 ** round(math.log2(ratio)) and max(m, n) % min(m, n) == 0


def _check_inputs(heights, system_size, mean_pressure, e_star, tol, max_iter, threads) -> np.ndarray:
    s = _real_array("heights", heights)
    if s.ndim != 2 or s.shape[0] != s.shape[1]:
        raise InvalidParameterError("heights", f"array of shape {s.shape}", "a square n x n array")
    n = s.shape[0]
    if n < 2 or n % 2:
        raise InvalidParameterError("heights", f"{n} x {n} grid", "an even grid size n >= 2")
    s = np.ascontiguousarray(s, dtype=np.float64)
    if not np.all(np.isfinite(s)):
        raise InvalidParameterError("heights", "non-finite values", "finite numbers")
    for name, value in (("system_size", system_size), ("mean_pressure", mean_pressure), ("e_star", e_star)):
        if not (is_real_number(value) and math.isfinite(value) and value > 0):
            raise scalar_refusal(name, value, "a finite number > 0")
    if not (is_real_number(tol) and 0 < tol < 1):
        raise scalar_refusal("tol", tol, "a number in (0, 1)")
    checked_integer("max_iter", max_iter, 1)
    checked_integer("threads", threads, 1, MAX_THREADS)
    return s


def _real_array(name: str, values: object) -> np.ndarray:
    """``values`` as an array of real numbers, or :class:`InvalidParameterError` naming ``name`` (see below)."""
    if values is None:  # "an array of Python objects" said less than None
        raise InvalidParameterError(name, None, "a square 2-D array of real numbers")
    try:
        array = np.asarray(values)
    except ValueError:  # numpy refuses a ragged sequence (rows of different lengths)
        raise InvalidParameterError(
            name, "a ragged sequence (rows of different lengths)", "a square 2-D array"
        ) from None
    refuse_non_real(name, array)
    return array


def _initial_guess(initial_pressure, n: int) -> np.ndarray | None:
    if initial_pressure is None:
        return None
    p0 = np.asarray(_real_array("initial_pressure", initial_pressure), dtype=np.float64)
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
        if p0.shape[0] != p0.shape[1] or not _differ_by_power_of_two(p0.shape[0], n):
            raise InvalidParameterError(
                "initial_pressure", f"grid {p0.shape[0]} x {p0.shape[1]}",
                f"a square grid whose size is {n} or differs from {n} by a power of two",
            )
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
    ``inf`` or ``0``). A flat surface gets ``scale = 1``. The result is built
    in place in one new array, with one temporary on the way (the squares),
    instead of five grid-sized arrays: less memory at the largest grids.

    Raises
    ------
    InvalidParameterError
        If the RMS height is not a normal float (subnormal heights).
    """
    peak = _largest_magnitude(s)
    if peak == 0.0:
        return 0.0, 1.0, np.zeros_like(s)
    scaled = s / peak  # in [-1, 1]
    mean_unit = float(np.mean(scaled))
    scaled -= mean_unit  # the deviation, in [-2, 2]
    spread = _largest_magnitude(scaled)
    offset = peak * mean_unit
    if spread == 0.0:
        return offset, 1.0, np.zeros_like(s)
    scaled /= spread  # largest |value| is 1, so the mean square is >= 1 / N: no underflow
    rms = float(np.sqrt(np.mean(np.square(scaled))))
    scale = peak * (spread * rms)
    if not scale >= np.finfo(np.float64).tiny:
        raise InvalidParameterError("heights", f"RMS height {scale:g}", "an RMS height of at least 2.2e-308")
    scaled /= rms
    return offset, scale, scaled


def _largest_magnitude(values: np.ndarray) -> float:
    """``max |values|`` without an array of the magnitudes."""
    return max(float(values.max()), -float(values.min()))


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
    precondition: bool = True,
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
        pressure is :func:`~rough_uq.physics.reference.full_contact_pressure`. Zero
        load itself is rejected: with no force there is no contact set to
        find (every ``p = 0`` is admissible and the approach ``d`` is not
        determined), so a defined answer would be an arbitrary convention.
        Loads are also rejected when the dimensionless load
        ``mean_pressure * system_size / (e_star * RMS height)`` lies outside
        ``[2.2e-308, 1e25]`` (module docstring) or ``n^2 mean_pressure``
        overflows. Far beyond full contact (at the default ``tol``, from
        some ``1e7`` to ``1e8`` times the full-contact load on) rounding of
        ``p = mean_pressure + (variation)`` limits the attainable error; the
        solve then ends with ``converged=False`` after ``max_iter``.
    e_star : float, optional
        Effective modulus ``E* = E / (1 - nu^2)``.
    tol : float, optional
        Target of the dimensionless convergence measure (module docstring), in ``(0, 1)``. Above 1e-2
        (``rough_uq.problem.contact.MAX_SOLVER_TOL``) a solve is no contact solution to compute a QoI from:
        at 0.1 contact areas were off by up to 30 %, and 0.9 "converges" at full contact after no iteration.
    max_iter : int, optional
        Iteration budget; reaching it returns ``converged=False``.
    initial_pressure : ndarray, optional
        Warm start: a non-negative pressure on this grid or on a grid whose
        size differs by a power of two (it is resampled with
        :func:`resample_pressure` and rescaled to ``mean_pressure``). A guess
        that leaves no descent direction (e.g. all pressure on one node) is
        replaced by uniform pressure (counted in ``n_restarts``).
    threads : int, optional
        FFTW threads, and numba threads of the fused passes on grids of at
        least :data:`PARALLEL_PASS_MIN_NODES` nodes (on smaller grids a pass
        takes less time than waking a second thread; it runs on one); 1 to
        :data:`MAX_THREADS`.
    precondition : bool, optional
        Precondition the conjugate gradient with the inverse Westergaard
        operator restricted to the contact set (module docstring). ``False``
        runs plain Polonsky-Keer (for comparison; about three times as many
        iterations on rough surfaces).

    Returns
    -------
    ContactSolution

    Raises
    ------
    InvalidParameterError
        For non-square, odd-sized or non-finite heights (or subnormal RMS
        height), non-positive ``mean_pressure`` (zero load included, see
        above), ``system_size`` or ``e_star``, a dimensionless load out of
        range (see ``mean_pressure``), ``threads`` not an integer >= 1,
        ``precondition`` not a bool (numpy's too; a string such as ``"no"``
        is refused, not read by its truth value), or an invalid
        ``initial_pressure`` (negative, all zero, not square, or from a grid
        whose size does not differ from ``n`` by a power of two).
    """
    s = _check_inputs(heights, system_size, mean_pressure, e_star, tol, max_iter, threads)
    precondition = checked_bool("precondition", precondition)  # a truthy "no" would run preconditioned
    p0 = _initial_guess(initial_pressure, s.shape[0])
    # Scaled units (module docstring): heights with zero mean and unit RMS, E* = 1, L = 1.
    # From here on heights, pressures, gaps and the load are in these units.
    offset, s_rms, s = _scaled_heights(s)
    load = _dimensionless_load(mean_pressure, system_size, e_star, s_rms, n_nodes=s.size)
    ops = _Operators.build(s, load, threads=threads, precondition=precondition)
    state = _State.start(ops, p0, precondition=precondition)
    previous_threads = numba.get_num_threads()
    numba.set_num_threads(_pass_threads(threads, s.size))
    try:
        status = _iterate(ops, state, precondition=precondition, tol=tol, max_iter=max_iter)
        n_iter_first, handed_over = state.n_iter, status
        if status in ("stalled", "no_descent") and precondition:
            ops = ops.for_plain()
            state.switch_to_plain(ops)
            status = _iterate(ops, state, precondition=False, tol=tol, max_iter=max_iter)
    finally:
        numba.set_num_threads(previous_threads)
    if not precondition:
        path, n_iter_plain = "plain", state.n_iter
    elif state.is_plain:
        path, n_iter_plain = "preconditioned+plain", state.n_iter - n_iter_first
    else:
        path, n_iter_plain = "preconditioned", 0
    return _solution(
        ops,
        state,
        scales=(offset, s_rms, system_size, e_star),
        converged=status == "converged",
        message=_message(status, state, tol=tol, max_iter=max_iter, n_iter_plain=n_iter_plain, path=path,
                         load=load, handed_over=handed_over),
        path=path,
        n_iter_plain=n_iter_plain,
    )


def _pass_threads(threads: int, n_nodes: int) -> int:
    """numba threads of the fused passes of a solve on ``n_nodes`` nodes (:data:`PARALLEL_PASS_MIN_NODES`)."""
    if n_nodes < PARALLEL_PASS_MIN_NODES:
        return 1
    return min(int(threads), numba.config.NUMBA_NUM_THREADS)


def _dimensionless_load(mean_pressure, system_size, e_star, s_rms, *, n_nodes: int) -> float:
    """``mean_pressure * L / (E* s_rms)``, checked against the range of the module docstring."""
    if not math.isfinite(mean_pressure * n_nodes):
        # All the force may end up on one node: its pressure must be a float.
        raise InvalidParameterError(
            "mean_pressure", mean_pressure, f"a load whose total over the {n_nodes} nodes is finite"
        )
    try:
        load = math.ldexp(*_binary_ratio((mean_pressure, system_size), (e_star, s_rms)))
    except OverflowError:
        load = math.inf
    if not MIN_DIMENSIONLESS_LOAD <= load <= MAX_DIMENSIONLESS_LOAD:
        raise InvalidParameterError(
            "mean_pressure",
            mean_pressure,
            f"a dimensionless load mean_pressure * system_size / (e_star * RMS height) in "
            f"[{MIN_DIMENSIONLESS_LOAD:.2g}, {MAX_DIMENSIONLESS_LOAD:.0e}]; here it is {load:.3g} "
            f"(system_size = {system_size:g}, e_star = {e_star:g}, RMS height = {s_rms:.3g})",
        )
    return load


@dataclass(frozen=True)
class _Operators:
    """What a solve computes once: scaled heights and load, the operators, the FFT plans and their buffers."""

    heights: np.ndarray
    # The heights in single precision, for the term (c - 1) s of the preconditioned gap update (_gap_pass):
    # c - 1 is small, and the rounding of s, 6e-8 of it, counts only times c - 1. None for plain solves.
    heights_single: np.ndarray | None
    load: float
    total_force: float
    half_space: HalfSpace
    # In single precision and divided by N (the inverse transforms run unnormalised; the Parseval sums):
    kernel_single: np.ndarray  # K: the curvature <K t, t>, the increments (_State.update_displacement)
    inverse_kernel: np.ndarray | None  # M = K^-1, preconditioned solves
    # Single precision: the preconditioner, the transform of t and the
    # increments (preconditioned: an in-place plan, whose compiled loops get
    # its padded buffer); plain: the transform of t, which it keeps in .real.
    direction_fft: RealFFT

    @classmethod
    def build(cls, s: np.ndarray, load: float, *, threads: int, precondition: bool) -> _Operators:
        n = s.shape[0]
        # Separate output: the pressure stays in fft.real, u = K p lands in fft.output.
        half_space = HalfSpace(n, system_size=1.0, e_star=1.0, threads=threads, separate_output=True)
        # With the factor 1 / N of the inverse transforms, which are run
        # unnormalised (RealFFT.inverse): a pass over the grid fewer per inverse.
        kernel_single = np.empty(half_space.kernel.shape, dtype=np.float32)
        inverse_kernel = np.empty_like(kernel_single) if precondition else None
        _single_kernels(half_space.kernel, float(s.size), kernel_single, inverse_kernel)
        return cls(
            heights=s,
            heights_single=s.astype(np.float32) if precondition else None,
            load=load,
            total_force=load * s.size,
            half_space=half_space,
            kernel_single=kernel_single,
            inverse_kernel=inverse_kernel,
            direction_fft=get_fft(n, threads=threads, single=True, in_place=precondition),
        )

    def for_plain(self) -> _Operators:
        """These operators with the single-precision plan of plain Polonsky-Keer (the hand-over).

        The forward transform of an in-place plan destroys its input, and plain
        Polonsky-Keer keeps its direction in the plan's input across it.
        """
        fft = self.direction_fft
        return dataclasses.replace(self, direction_fft=get_fft(fft.shape, threads=fft.threads, single=True))

    @property
    def error_scale(self) -> float:
        """``N * load * (unit RMS height)``, the scale of the convergence measure."""
        return self.total_force

    def precondition(self) -> tuple[np.ndarray, float]:
        """``y = M r`` for the residual ``r`` in :attr:`direction_fft` ``.real``, and ``<r, y>`` (Parseval).

        ``y`` is returned as the plan buffer that holds it (``.padded``).
        """
        self.direction_fft.forward()
        r_y = _multiply_energy(self.direction_fft.spectral, self.inverse_kernel)
        self.direction_fft.inverse(normalise=False)
        return self.direction_fft.padded, r_y

    def increment_displacement(self, scale: float) -> np.ndarray:
        """``K (scale e)`` in single precision, ``e`` the increment in :attr:`direction_fft` ``.real``.

        Returns the plan buffer that holds the result (``.padded``).
        """
        self.direction_fft.forward()
        multiply_spectrum(self.direction_fft.spectral, self.kernel_single, np.float32(scale))
        self.direction_fft.inverse(normalise=False)
        return self.direction_fft.padded

    def curvature(self) -> float:
        """``<K t, t>`` for the direction ``t`` in :attr:`direction_fft` ``.real`` (Parseval)."""
        self.direction_fft.forward()
        return _energy(self.direction_fft.spectral, self.kernel_single)


@dataclass
class _State:
    """The iterate and the conjugate-gradient memory, updated in place by :func:`_iterate`.

    The pressure is ``p_scale * p``: ``p`` lives unnormalised in the input buffer
    of the ``K`` plan and the mean pressure is imposed in the spectral multiply
    of ``u = K p``, which saves a pass over the grid. ``w`` (the plan's output)
    holds ``u = K p`` at the top of an iteration and ``w = u - s`` after the gap pass.

    Preconditioned solves update the displacement step by step between exact
    ones (:meth:`update_displacement`): ``w`` gets the displacement of each
    step's pressure increment, in single precision (``exact`` is False then).
    They also keep the active set ``p > 0`` as a 0/1 mask (``active``, one
    byte per node), which the passes that only need the set read instead of
    the pressure; ``active`` is None in plain Polonsky-Keer, whose
    displacements are all exact.
    """

    p: np.ndarray
    w: np.ndarray
    t: np.ndarray  # the search direction, zero off the active set
    has_guess: bool
    is_plain: bool
    active: np.ndarray | None = None  # uint8, 1 where p > 0 (preconditioned)
    exact: bool = True  # w holds the double-precision displacement of p (not updated by increments)
    exact_error: float = math.inf  # the error at the last exact evaluation
    p_scale: float = 1.0
    sum_t: float = 0.0  # sum of t over the active set
    gbar: float = 0.0  # mean of w over the active set: minus the approach
    delta: float = 0.0  # 0 restarts the conjugate directions
    rho_old: float = 1.0
    n_iter: int = 0
    n_restarts: int = 0
    error: float = math.inf
    # Plain only: impose the mean pressure after a step by a uniform shift (p <- max(p - lam, 0)) instead of a
    # factor; set when the plain iteration stalls (_iterate, _shift_to_force).
    shift_force: bool = False

    @classmethod
    def start(cls, ops: _Operators, p0: np.ndarray | None, *, precondition: bool) -> _State:
        fft = ops.half_space.fft
        fft.real[...] = ops.load if p0 is None else p0
        # The direction is kept in single precision (the curvature transform
        # sees it so anyway): with the preconditioner in an array of its own
        # (the in-place transform destroys its input), without it in the FFT
        # input of the curvature transform.
        t = np.zeros(ops.heights.shape, dtype=np.float32) if precondition else ops.direction_fft.real
        t.fill(0.0)
        state = cls(p=fft.real, w=fft.output, t=t, has_guess=p0 is not None, is_plain=not precondition)
        if precondition:
            state.active = np.empty(fft.real.shape, dtype=np.uint8)
        state.update_displacement(ops, uniform=p0 is None)
        return state

    def update_displacement(self, ops: _Operators, *, uniform: bool = False) -> None:
        """``w <- u = K (p_scale p)`` in double precision, with ``p_scale`` imposing the mean pressure.

        Preconditioned solves also normalise ``p`` (``p_scale = 1``): between
        two such updates each step adds the displacement of its pressure
        increment to ``u``, computed in single precision (one single-precision
        FFT pair per iteration instead of a double one; :func:`_gap_pass`).
        Its rounding, about 1e-7 of the displacement of each increment,
        shrinks with the increments; an update whenever the error has fallen
        by :data:`_REFRESH_FACTOR` keeps the sum far below the error, and
        every stop is decided on an exact displacement.

        ``uniform`` says that ``p`` is uniform (the cold start): its
        displacement is zero, since the kernel's zero mode is, and is written
        without a transform (which returns exact zeros too: the same bits, one
        double-precision FFT pair less per solve).
        """
        self.p_scale = ops.total_force / self.p.sum()
        if self.active is None:
            self._displace(ops, self.p_scale, uniform=uniform)
            return
        self.p *= self.p_scale
        self.p_scale = 1.0
        np.greater(self.p, 0.0, out=self.active.view(bool))
        self._displace(ops, 1.0, uniform=uniform)
        self.exact = True

    def restart_uniform(self, ops: _Operators) -> None:
        """Back to uniform pressure, with no conjugate memory."""
        self.p.fill(ops.load)
        self._forget_directions()
        self.update_displacement(ops, uniform=True)

    def _forget_directions(self) -> None:
        """No conjugate memory: the next direction is (preconditioned) steepest descent."""
        self.t.fill(0.0)
        self.sum_t = 0.0
        self.delta = 0.0

    def _displace(self, ops: _Operators, scale: float, *, uniform: bool) -> None:
        """``w <- K (scale p)`` in double precision; zero without a transform if ``p`` is ``uniform``."""
        if uniform:
            self.w.fill(0.0)
        else:
            ops.half_space.apply(scale)

    def switch_to_plain(self, ops: _Operators) -> None:
        """Hand over to plain Polonsky-Keer: from the current pressure where its error is below
        :data:`_FRESH_START_ERROR`, else afresh from uniform pressure (module docstring, "Safeguard")."""
        self.t = ops.direction_fft.real
        self.active = None
        self.rho_old = 1.0
        self.is_plain = True
        if self.error < _FRESH_START_ERROR:
            self._forget_directions()
            self.update_displacement(ops)
        else:
            self.restart_uniform(ops)


#: A stalled preconditioned solve whose error is below this hands its pressure to plain Polonsky-Keer, which
#: goes on from it; above, plain starts afresh from uniform pressure (module docstring, "Safeguard"). Stalls on
#: tall spikes came at errors of 7-33; a solve asked for a tolerance below what rounding allows stalls at
#: 1e-16-1e-15, where a fresh start lost the answer (error 0.44 after the same 100 iterations on 128^2).
_FRESH_START_ERROR = 1e-3


#: Between two exact displacements of the preconditioned iteration the error
#: falls by at most this factor (:meth:`_State.update_displacement`).
_REFRESH_FACTOR = 1e-2


#: A preconditioned solve whose error has not halved in this many iterations
#: hands over to plain Polonsky-Keer (:func:`_iterate`). Converging solves
#: halve their error every two to four iterations (88 iterations from 1 to
#: 1e-10 at 2048^2 on the benchmark surface).
_STALL_WINDOW = 50


#: Plain Polonsky-Keer whose error has not halved in this many iterations imposes the mean pressure by a
#: shift from then on (:func:`_shift_to_force`). On 300 random spectral problems of 32^2-128^2 its error never
#: went more than 20 iterations without halving (5 / 8 / 20 at 32^2 / 64^2 / 128^2); on a tall spike or on
#: integer terraces it cycles between two contact sets and the error never halves again.
_PLAIN_STALL_WINDOW = 100


def _overlap_scale(rho: float, g_squares: float) -> float:
    """Scale of the pressure ``-tau * scale * g`` given to nodes added from the overlap (preconditioned).

    ``rho / sum_I g^2 = <g, P M P g> / <g, g>`` is the Rayleigh quotient of
    the preconditioner on the current residual: the stiffness per unit gap at
    the wave numbers the residual has now. With the preconditioned step
    ``tau`` (close to 1 when ``M`` is a good inverse) the new nodes get the
    pressure that closes a gap of that wave content, as in plain
    Polonsky-Keer, where ``tau = <g, g> / <g, K g>``. The diagonal of ``M``,
    ``(1 / N) sum_k E* |q| / 2``, weights every wave number alike and so
    overestimates it for the smooth overlaps of a load step: it made the
    contact set oscillate by thousands of nodes per iteration and the
    iteration diverge on about one problem in 600 of the randomised test
    (and on a classic 2048^2 sample).
    """
    return rho / g_squares if g_squares > 0 else 0.0


def _iterate(ops: _Operators, st: _State, *, precondition: bool, tol: float, max_iter: int) -> str:
    """Conjugate-gradient iterations from ``st`` until a stop; returns why.

    ``"converged"`` (``error < tol``), ``"max_iter"`` (``st.n_iter`` reached
    it), ``"stalled"`` (preconditioned only: no halving of the error in
    :data:`_STALL_WINDOW` iterations; plain Polonsky-Keer then shifts instead,
    module docstring) or ``"no_descent"`` (even steepest descent finds no
    decrease, and in plain Polonsky-Keer no node interpenetrates either: the
    residual is at the level of rounding).
    On return ``st.w`` holds ``u - s`` and ``st.gbar`` its mean on the active set.
    """
    checkpoint_error, checkpoint_iter = math.inf, st.n_iter
    while True:
        active = st.p if st.active is None else st.active  # what defines I: the pressure or its mask
        n_active, g_squares = _gap(ops, st, active)
        t_mean = st.sum_t / n_active
        if precondition:
            residual = ops.direction_fft.padded
            complementarity, overlap, sum_g, sum_gt_old = _residual_pass(st.w, st.p, st.gbar, residual, st.t)
        else:
            rho = g_squares
            beta = _beta(st, rho)
            complementarity, overlap, s_gt = _plain_direction(st.w, st.p, st.gbar, beta, t_mean, st.t)
        _set_error(ops, st, complementarity, overlap)
        window = st.n_iter - checkpoint_iter  # iterations since the error last halved
        stall = precondition and window >= _STALL_WINDOW
        if not precondition and window >= _PLAIN_STALL_WINDOW and not st.error < 0.5 * checkpoint_error:
            # Plain Polonsky-Keer stalled (a cycle of contact sets, e.g. on a tall spike): it imposes the mean
            # pressure by a shift from now on (_shift_to_force); it never stops as stalled.
            st.shift_force = True
        status = _stop(st, tol=tol, max_iter=max_iter, stall=stall, checkpoint_error=checkpoint_error)
        if not st.exact and (status or st.error < _REFRESH_FACTOR * st.exact_error):
            # Every stop is decided on an exact displacement (_State.update_displacement).
            st.update_displacement(ops)
            continue
        if st.exact:
            st.exact_error = st.error
        if status:
            return status
        if st.error < 0.5 * checkpoint_error:
            checkpoint_error, checkpoint_iter = st.error, st.n_iter

        overlap_scale = 1.0
        if precondition:
            s_gt, beta, rho, overlap_scale = _preconditioned_direction(
                ops, st, active, residual, n_active=n_active, t_mean=t_mean, g_squares=g_squares,
                sum_g=sum_g, sum_gt_old=sum_gt_old,
            )
        st.rho_old = rho
        curvature = ops.curvature()
        if not (s_gt > 0 and curvature > 0 and math.isfinite(s_gt / curvature)):
            if _prepare_retry(ops, st, beta):
                continue
            if not precondition and overlap > 0:
                # No descent on I (a single active node has g = 0 there) but nodes out of contact
                # interpenetrate: add them alone, with the pressure that closes an isolated node's gap.
                _advance(ops, st, tau=0.0, tau_overlap=1.0 / _self_compliance(ops))
                continue
            return "no_descent"
        tau = s_gt / curvature
        _advance(ops, st, tau=tau, tau_overlap=tau * overlap_scale)


def _gap(ops: _Operators, st: _State, active: np.ndarray) -> tuple[int, float]:
    """The gap pass: ``st.w <- u - s`` and ``st.gbar`` its mean over I; returns ``|I|`` and ``sum_I g^2``."""
    if st.exact:
        active_total, n_active, shifted_squares = _gap_pass(st.w, ops.heights, active, st.gbar)
    else:
        increment = ops.direction_fft.padded  # the displacement of the last step's increment
        active_total, n_active, shifted_squares = _gap_pass(
            st.w, ops.heights_single, active, st.gbar, st.p_scale, increment
        )
    previous_gbar, st.gbar = st.gbar, active_total / n_active
    return n_active, max(shifted_squares - n_active * (st.gbar - previous_gbar) ** 2, 0.0)


def _beta(st: _State, rho: float) -> float:
    """The conjugate-gradient weight of the old direction (0 after a restart, ``st.delta = 0``)."""
    return st.delta * rho / st.rho_old if st.rho_old > 0 else 0.0


def _set_error(ops: _Operators, st: _State, complementarity: float, overlap: float) -> None:
    """``st.error`` from the residual pass's sums (module docstring); a non-finite one is a bug, raised."""
    st.error = (st.p_scale * complementarity + ops.load * overlap) / ops.error_scale
    if not math.isfinite(st.error):
        raise ConvergenceError(
            f"non-finite convergence measure at iteration {st.n_iter} (inputs were finite; this is a bug)"
        )


def _preconditioned_direction(
    ops: _Operators, st: _State, active: np.ndarray, residual: np.ndarray, *,
    n_active: int, t_mean: float, g_squares: float, sum_g: float, sum_gt_old: float,
) -> tuple[float, float, float, float]:
    """The search direction from ``y = M r`` into ``st.t`` and ``residual`` (the curvature's FFT input).

    Returns ``sum_I g t``, ``beta``, ``rho`` and the scale of the overlap's new pressures (:func:`_overlap_scale`).
    ``sum_g`` and ``sum_gt_old`` are the sums over I of ``g`` and of ``g`` times the old direction (from
    :func:`_residual_pass`).
    """
    y, sum_gy = ops.precondition()  # M applied to r = g on I, 0 elsewhere; <r, y> = sum_I g y
    y_mean = _active_sum(y, active) / n_active
    # rho = <g, P M P g> over I, P the projection on zero sum over I.
    rho = sum_gy - y_mean * sum_g
    beta = _beta(st, rho)
    _direction(y, active, y_mean, beta, t_mean, st.t, residual)
    # sum_I g t with t = (y - y_mean) + beta (t_old - t_mean) on I: rho + beta sum_I g (t_old - t_mean).
    s_gt = rho + beta * (sum_gt_old - t_mean * sum_g)
    return s_gt, beta, rho, _overlap_scale(rho, g_squares)


def _prepare_retry(ops: _Operators, st: _State, beta: float) -> bool:
    """After a direction without descent: set up a retry and return True, or False if none is left."""
    if beta != 0.0:
        # Rounding has spoilt the conjugate direction: retry with the
        # (preconditioned) steepest-descent direction.
        st.delta = 0.0
        st.update_displacement(ops)
        return True
    if st.n_iter == 0 and st.n_restarts == 0 and st.has_guess:
        # The warm start leaves no descent direction on its active set
        # (e.g. all pressure on one node): start again from uniform pressure.
        st.n_restarts += 1
        st.restart_uniform(ops)
        return True
    if not st.exact:
        st.update_displacement(ops)
        return True
    return False


def _advance(ops: _Operators, st: _State, *, tau: float, tau_overlap: float) -> None:
    """The step of length ``tau`` along ``st.t`` (clamped, overlap added), and the new displacement."""
    # Preconditioned, the step also writes its pressure increment into the single-precision FFT input.
    increment = None if st.active is None else ops.direction_fft.padded
    total, n_overlap, st.sum_t = _step(
        st.w, st.p, st.t, st.gbar, st.p_scale, tau, tau_overlap, increment, st.active
    )
    st.n_iter += 1
    # Nodes added from the overlap restart the conjugate directions.
    st.delta = 0.0 if n_overlap else 1.0
    if total > 0:
        _update_displacement_after_step(ops, st, total)
    else:
        # Every node was clamped and none overlapped (cannot happen for a
        # descent step, but never divide by zero).
        st.restart_uniform(ops)


def _stop(st: _State, *, tol: float, max_iter: int, stall: bool, checkpoint_error: float) -> str:
    """Why :func:`_iterate` stops at the current error, or ``""`` (``stall``: the stall window is over)."""
    if st.error < tol:
        return "converged"
    if st.n_iter >= max_iter:
        return "max_iter"
    if stall and not st.error < 0.5 * checkpoint_error:
        return "stalled"
    return ""


def _update_displacement_after_step(ops: _Operators, st: _State, total: float) -> None:
    """Impose the mean pressure and compute the displacement of the new pressure (exact or as an increment)."""
    if st.active is None and st.shift_force and total > ops.total_force:
        total = _shift_to_force(st.p, ops.total_force)
        st.delta = 0.0  # the shift moves every pressure, not along the directions: restart them
    st.p_scale = ops.total_force / total
    if st.active is None:
        ops.half_space.apply(st.p_scale)
    else:
        # The step wrote e = p - c_old p_old (p the new unnormalised pressure, c_old p_old the old pressure);
        # the new pressure is c p (c = p_scale), so u_new = K (c p) = c u_old + K (c e): the increment's
        # displacement is computed with the factor c, the gap pass scales u_old (and folds in the heights).
        ops.increment_displacement(st.p_scale)
        st.exact = False


def _shift_to_force(p: np.ndarray, force: float) -> float:
    """``p <- max(p - lam, 0)`` with ``lam >= 0`` such that ``sum p = force`` (``p >= 0``, ``sum p > force``).

    The Euclidean projection on ``{p >= 0, sum p = force}``. The factor ``force / sum p`` that plain
    Polonsky-Keer applies after a step scales every pressure alike: when the step length is set by a stiff
    node (a tall spike, ``tau`` about ``1 / K_ii``) the same step gives long-wave residuals elsewhere many
    times the total force, and the factor takes most of the spike's increase back in every step (a 2-cycle of
    contact sets). The shift removes the excess from the small pressures instead. Returns the new sum.

    ``lam`` by Michelot's iteration: ``lam <- (sum_S p - force) / |S|`` over ``S = {p > lam}``, from
    ``lam = 0``; ``lam`` grows and ``S`` shrinks until it stays the same. Each round is a pass over the grid
    without temporaries (sorting the pressures peaked at 3.6 MB at 512^2 with half the nodes in contact,
    some 230 MB at 4096^2); after :data:`_MAX_SHIFT_ROUNDS` rounds (a set shrinking a node or two at a time)
    the sorted pressures finish it.
    """
    grid = p if p.ndim == 2 else p.reshape(1, -1)  # the passes loop over rows (a view: they write into p)
    total, count = _sum_above(grid, 0.0)
    for _ in range(_MAX_SHIFT_ROUNDS):
        lam = max((total - force) / count, 0.0)
        total, new_count = _sum_above(grid, lam)
        if new_count == 0:
            return _carry_on_largest(p, force)
        if new_count >= count:  # S stayed the same (or grew by rounding): lam is the projection's
            return _shift_down(grid, lam)
        count = new_count
    lam = _sorted_shift(p, force)
    return _carry_on_largest(p, force) if lam is None else _shift_down(grid, lam)


#: Rounds of Michelot's iteration before :func:`_shift_to_force` sorts; the sets of the shifts in
#: ``tests/test_hard_cases.py`` (stalled spikes and terraces, random pressures) settled in 1-9 rounds.
_MAX_SHIFT_ROUNDS = 50


def _sorted_shift(p: np.ndarray, force: float) -> float | None:
    """The ``lam`` of :func:`_shift_to_force` from the sorted positive pressures; None where no pressure stays
    above it (a force below the rounding of the largest pressure)."""
    values = np.sort(p[p > 0.0])[::-1]
    shifts = (np.cumsum(values) - force) / np.arange(1, values.size + 1)
    kept = np.flatnonzero(values > shifts)
    return max(float(shifts[kept[-1]]), 0.0) if kept.size else None


def _carry_on_largest(p: np.ndarray, force: float) -> float:
    """All the force on the largest pressure: the shift of a force below the rounding of that pressure."""
    largest = int(np.argmax(p))
    p.fill(0.0)
    p.flat[largest] = force
    return force


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _sum_above(p, lam):  # pragma: no cover - compiled
    # (sum of p over p > lam, how many): a round of _shift_to_force.
    total = 0.0
    count = 0
    for i in numba.prange(p.shape[0]):
        for j in range(p.shape[1]):
            above = p[i, j] > lam
            total += p[i, j] if above else 0.0
            count += above
    return total, count


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _shift_down(p, lam):  # pragma: no cover - compiled
    # p <- max(p - lam, 0) in place; returns the new sum.
    total = 0.0
    for i in numba.prange(p.shape[0]):
        for j in range(p.shape[1]):
            q = p[i, j] - lam
            q = q if q > 0.0 else 0.0
            p[i, j] = q
            total += q
    return total


def _self_compliance(ops: _Operators) -> float:
    """``K_ii``: the displacement of a node under unit pressure on that node alone, ``(1 / N) sum_k K_k``."""
    kernel = ops.half_space.kernel
    full_sum = 2.0 * float(kernel.sum()) - float(kernel[:, 0].sum()) - float(kernel[:, -1].sum())
    return full_sum / ops.heights.size


def _result_arrays(ops: _Operators, st: _State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arrays for the pressure, displacement and gap of the result: the scaled heights become the gap.

    The heights are new for every solve (:func:`_scaled_heights`) and their memory has been used already; a
    new array is fresh memory, whose first use costs more than filling it (1.5-1.8 ms per MB on the
    development VM). The pressure and the displacement need new arrays: the solve's are the FFT plan's buffers.
    """
    return np.empty_like(st.p), np.empty_like(st.w), ops.heights


#: Why the preconditioned iteration handed over to plain Polonsky-Keer, in words (:func:`_message`).
_HAND_OVER_REASONS = {"stalled": "stalled", "no_descent": "found no descent direction"}


def _message(status: str, st: _State, *, tol: float, max_iter: int, n_iter_plain: int, path: str,
             load: float, handed_over: str) -> str:
    """Why the solver stopped, in words (with the dimensionless ``load`` where rounding is the likely cause;
    ``handed_over``: why the first iteration stopped, when plain Polonsky-Keer took over)."""
    if status == "converged":
        text = f"converged: error {st.error:.3g} < tol {tol:.3g}"
    elif status == "max_iter":
        text = f"not converged: max_iter={max_iter} reached with error {st.error:.3g} (tol {tol:.3g})"
    else:
        text = (
            f"not converged: stalled at error {st.error:.3g} after {st.n_iter} iterations "
            f"(tol {tol:.3g} is below what rounding allows on this grid)"
        )
    if path == "preconditioned+plain":
        text += (
            f"; the preconditioned iteration {_HAND_OVER_REASONS[handed_over]} after {st.n_iter - n_iter_plain} "
            f"iterations and plain Polonsky-Keer took over for {n_iter_plain}"
        )
    limit = max_convergent_load(tol)
    if status != "converged" and load > limit:
        text += (
            f"; the dimensionless load mean_pressure * system_size / (e_star * RMS height) is {load:.3g}, above "
            f"{limit:.3g}, where the rounding of the pressures (about the load) alone leaves an "
            f"error above tol (full contact sets in below 2 pi k_s)"
        )
    return text


def _solution(
    ops: _Operators, st: _State, *, scales, converged: bool, message: str, path: str, n_iter_plain: int
) -> ContactSolution:
    """The result in the caller's units, from the scaled iterate."""
    offset, s_rms, system_size, e_star = scales
    # Heights, displacements and gaps times s_rms (the approach also gets the
    # mean height back), pressures times E* s_rms / L (in binary, so that
    # E* s_rms cannot overflow when the pressures do not).
    approach = -st.gbar
    mantissa, exponent = _binary_ratio((e_star, s_rms), (system_size,))
    # In place: the same numbers as ldexp((p * p_scale) * mantissa, exponent), (w + s) * s_rms, (w + approach) * s_rms.
    pressure, displacement, gap = _result_arrays(ops, st)
    np.multiply(st.p, st.p_scale, out=pressure)
    pressure *= mantissa
    if exponent:
        np.ldexp(pressure, exponent, out=pressure)
    np.add(st.w, ops.heights, out=displacement)
    displacement *= s_rms
    np.add(st.w, approach, out=gap)  # overwrites the scaled heights, read for the last time above
    gap *= s_rms
    return ContactSolution(
        pressure=pressure,
        displacement=displacement,
        gap=gap,
        approach=float(approach * s_rms + offset),
        n_iter=st.n_iter,
        error=float(st.error),
        converged=converged,
        n_restarts=st.n_restarts,
        message=message,
        path=path,
        n_iter_plain=n_iter_plain,
    )
