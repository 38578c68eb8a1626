"""MLMC estimation of central moments with unbiased h-statistics (SPEC section 5, "Beyond the mean").

h-statistics
------------
For a sample ``x_1..x_n`` with mean ``xbar`` and central sample moments
``m_k = (1/n) sum (x_i - xbar)^k``, the h-statistics are the unbiased
estimators of the central moments ``mu_k = E[(X - EX)^k]``:

    h2 = n m2 / (n - 1)
    h3 = n^2 m3 / ((n - 1)(n - 2))
    h4 = (n (n^2 - 2n + 3) m4 - 3 n (2n - 3) m2^2) / ((n - 1)(n - 2)(n - 3))

(Dwyer 1937; Krumscheid, Nobile & Pisaroni, J. Comput. Phys. 2020, Part I,
section 2; checked in the tests by exact enumeration of all samples of a
discrete distribution).

The variance as an MLMC target
------------------------------
On level ``l`` the pairs ``(X_i, Y_i) = (Q_l, Q_{l-1})`` of one random input
give the term ``T_l = h2(X) - h2(Y)``, unbiased for ``Var(Q_l) -
Var(Q_{l-1})`` (``T_0 = h2(Q_0)``), so ``sum_l T_l`` is unbiased for
``Var(Q_L)``. With ``D = X - Y`` and ``S = X + Y``, ``T_l`` is the unbiased
sample covariance of ``D`` and ``S``; it is the U-statistic of the kernel
``phi_ij = (D_i - D_j)(S_i - S_j) / 2``, so its variance is

    Var(T_l) = mu22 / n - (n - 2) / (n (n - 1)) sigma_DS^2 + sigma_D^2 sigma_S^2 / (n (n - 1))

(``mu22 = E[(D - ED)^2 (S - ES)^2]``), and ``T_l^2 - U4`` is an *unbiased*
estimator of it, ``U4`` the U-statistic of ``phi_ij phi_kl`` over distinct
``i, j, k, l`` (unbiased for ``E[T_l]^2``). With power sums
``P_pq = sum (D_i - Dbar)^p (S_i - Sbar)^q``,

    U4 = ((n-1)(n-2) P11^2 - n (n-1) P22 + P20 P02) / (n (n-1)(n-2)(n-3)),

(expanding ``(sum phi)^2`` into terms with four, three and two distinct
indices). This is the closed form Krumscheid et al. give in terms of
bivariate h-statistics; it needs ``n >= 4`` and, being unbiased, can be
negative or near 0 where few pairs differ (a discrete ``Q``). Clipped at 0
it made such a level look exact: it got no samples beyond its first and
added nothing to the error (a rounded ``Q`` at tol 0.05 reported an RMSE of
0.041 at an error of 0.52). The level's variance is therefore the larger of
``T_l^2 - U4`` and the plug-in leading-order estimate ``s^2(psi) / n`` of
the products ``psi_i = (D_i - Dbar)(S_i - Sbar)`` (the sample variance of
the summands of ``T_l``), which is positive as soon as one pair differs
from the others; where it is the larger the variance is overestimated, by
about the noise of ``T_l^2 - U4``. On level 0
(``Y`` absent) the same formula with ``D = S = X`` is the unbiased estimator
of ``Var(h2(X)) = (mu4 - (n-3)/(n-1) sigma^4) / n``.

The variance's remaining bias ``Var(Q) - Var(Q_L)`` follows from the decay
of ``|T_l|`` with the ``alpha`` model, and ``N_l`` from
``W_l = N_l Var(T_l)`` in place of ``V_l``
(:mod:`rough_uq.multilevel.targets`).

Third and fourth moments
------------------------
``h3(X) - h3(Y)`` and ``h4(X) - h4(Y)`` are the unbiased level terms of
``mu3`` and ``mu4``. Their variance is estimated to leading order in ``1/n``
from the influence functions ``psi_k(x) = (x - mu)^k - mu_k - k mu_(k-1) (x -
mu)``: ``Var(T_l) ~ Var(psi_k(X) - psi_k(Y)) / n`` with sample moments
plugged in (consistent, not unbiased); :func:`mlmc_central_moment` runs the
adaptive driver on them. Skewness ``mu3 / mu2^(3/2)`` and kurtosis ``mu4 /
mu2^2`` follow from the telescoped moments; their errors are not propagated
here.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rough_uq.errors import EstimationError, InvalidParameterError, is_one_of
from rough_uq.multilevel.drivers import Sampler
from rough_uq.multilevel.statistics import readonly_array
from rough_uq.multilevel.targets import LevelTerm, TargetEstimate, adaptive_mlmc, telescope

__all__ = [
    "central_moment_level_term",
    "h2",
    "h3",
    "h4",
    "h2_difference_variance",
    "mlmc_central_moment",
    "mlmc_variance",
    "variance_from_samples",
    "variance_level_term",
]

#: Fewest samples each h-statistic needs (its denominator vanishes below).
_MIN_SAMPLES = {2: 2, 3: 3, 4: 4}


def _as_columns(values: object, *, name: str, minimum: int) -> np.ndarray:
    """Samples as a float array of shape (n, k); a 1-d sample becomes one column."""
    array = np.asarray(values, dtype=float)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2:
        raise InvalidParameterError(name, f"array of shape {np.shape(values)}", "shape (n,) or (n, n_qoi)")
    if array.shape[0] < minimum:
        raise InvalidParameterError(name, f"{array.shape[0]} samples", f"at least {minimum} samples")
    if not np.all(np.isfinite(array)):
        raise InvalidParameterError(name, "non-finite values", "finite values")
    return array


def _shape_like(result: np.ndarray, values: object) -> float | np.ndarray:
    return float(result[0]) if np.ndim(values) == 1 else result


def _central_moments(x: np.ndarray) -> list[np.ndarray]:
    """``[m1, m2, m3, m4]`` of the columns (``m1 = 0``)."""
    centred = x - np.mean(x, axis=0)
    return [np.mean(centred**k, axis=0) for k in range(1, 5)]


def _h(x: np.ndarray, order: int) -> np.ndarray:
    n = x.shape[0]
    _, m2, m3, m4 = _central_moments(x)
    if order == 2:
        return n * m2 / (n - 1)
    if order == 3:
        return n**2 * m3 / ((n - 1) * (n - 2))
    return (n * (n**2 - 2 * n + 3) * m4 - 3 * n * (2 * n - 3) * m2**2) / ((n - 1) * (n - 2) * (n - 3))


def h2(sample: np.ndarray) -> float | np.ndarray:
    """Unbiased estimate of the variance ``mu2`` (module docstring).

    Parameters
    ----------
    sample : ndarray, shape (n,) or (n, k)
        ``n >= 2`` samples (per column).

    Returns
    -------
    float or ndarray, shape (k,)
        In the unit of the sample squared.
    """
    return _shape_like(_h(_as_columns(sample, name="sample", minimum=2), 2), sample)


def h3(sample: np.ndarray) -> float | np.ndarray:
    """Unbiased estimate of the third central moment ``mu3``; ``n >= 3`` (see :func:`h2`)."""
    return _shape_like(_h(_as_columns(sample, name="sample", minimum=3), 3), sample)


def h4(sample: np.ndarray) -> float | np.ndarray:
    """Unbiased estimate of the fourth central moment ``mu4``; ``n >= 4`` (see :func:`h2`)."""
    return _shape_like(_h(_as_columns(sample, name="sample", minimum=4), 4), sample)


def _pair(fine: object, coarse: object | None, minimum: int) -> tuple[np.ndarray, np.ndarray | None]:
    x = _as_columns(fine, name="fine", minimum=minimum)
    if coarse is None:
        return x, None
    y = _as_columns(coarse, name="coarse", minimum=minimum)
    if y.shape != x.shape:
        raise InvalidParameterError("coarse", f"shape {y.shape}", f"the shape of fine, {x.shape}")
    return x, y


def _h2_difference(x: np.ndarray, y: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``T = h2(x) - h2(y)`` and the unbiased estimate ``T^2 - U4`` of its variance (module docstring).

    From the power sums ``P_pq`` of ``D = X - Y``, ``S = X + Y`` (``D = S =
    X`` without ``Y``); needs ``n >= 4``.
    """
    n = x.shape[0]
    d = x if y is None else x - y
    s = x if y is None else x + y
    d = d - np.mean(d, axis=0)
    s = s - np.mean(s, axis=0)
    p11, p22 = np.sum(d * s, axis=0), np.sum(d**2 * s**2, axis=0)
    p20, p02 = np.sum(d**2, axis=0), np.sum(s**2, axis=0)
    u4 = ((n - 1) * (n - 2) * p11**2 - n * (n - 1) * p22 + p20 * p02) / (n * (n - 1) * (n - 2) * (n - 3))
    term = p11 / (n - 1)
    return term, term**2 - u4


def h2_difference_variance(fine: np.ndarray, coarse: np.ndarray | None = None) -> float | np.ndarray:
    """Unbiased estimate of ``Var(h2(fine) - h2(coarse))`` from the pairs themselves.

    Parameters
    ----------
    fine, coarse : ndarray, shape (n,) or (n, k)
        ``n >= 4`` pairs ``(Q_l, Q_{l-1})`` of one random input each;
        ``coarse`` None gives ``Var(h2(fine))``.

    Returns
    -------
    float or ndarray, shape (k,)
        ``T^2 - U4`` (module docstring), unclipped: it may be negative
        when the true variance is small next to its sampling error.
    """
    return _shape_like(_h2_difference(*_pair(fine, coarse, 4))[1], fine)


def variance_level_term(fine: np.ndarray, coarse: np.ndarray | None, level: int = 0) -> LevelTerm:
    """Level term ``h2(Q_l) - h2(Q_{l-1})`` of the variance with its variance (module docstring: the larger of the
    unbiased estimate and the plug-in one).

    Parameters
    ----------
    fine, coarse : ndarray, shape (n, n_qoi)
        The level's pairs, ``n >= 4``; ``coarse`` None on the base level.
    level : int
        Unused (the term does not depend on the level; the argument makes
        this a :data:`~rough_uq.multilevel.targets.TermFunction`).

    Returns
    -------
    LevelTerm
        One component and one tolerance group per QoI.
    """
    x, y = _pair(fine, coarse, 4)
    term, variance = _h2_difference(x, y)
    return LevelTerm(
        mean=readonly_array(term),
        variance=readonly_array(np.maximum(variance, _influence_variance(x, y, 2))),
        n_samples=x.shape[0],
        groups=readonly_array(np.arange(x.shape[1])),
    )


def _influence(x: np.ndarray, order: int) -> np.ndarray:
    """Sample influence values ``psi_k(x_i)`` of the central moment of ``order`` (module docstring)."""
    centred = x - np.mean(x, axis=0)
    below = np.mean(centred ** (order - 1), axis=0)
    return centred**order - order * below * centred


def _influence_variance(x: np.ndarray, y: np.ndarray | None, order: int) -> np.ndarray:
    """The leading-order variance of ``h_k(x) - h_k(y)``: the sample variance of ``psi_k(x) - psi_k(y)`` over ``n``.

    Never negative; for ``order=2`` the summands are ``(D_i - Dbar)(S_i - Sbar)`` (module docstring).
    """
    psi = _influence(x, order) - (0.0 if y is None else _influence(y, order))
    return np.var(psi, axis=0, ddof=1) / x.shape[0]


def central_moment_level_term(fine: np.ndarray, coarse: np.ndarray | None, level: int = 0, *, order: int) -> LevelTerm:
    """Level term ``h_k(Q_l) - h_k(Q_{l-1})`` of the central moment ``mu_k``, ``k`` in 2, 3, 4.

    The variance is the leading-order (influence-function) estimate of the
    module docstring; for ``order=2`` prefer :func:`variance_level_term`,
    whose variance is the larger of the unbiased and this plug-in estimate.

    Parameters
    ----------
    fine, coarse : ndarray, shape (n, n_qoi)
        The level's pairs, ``n >= order``; ``coarse`` None on the base level.
    level : int
        Unused (see :func:`variance_level_term`).
    order : int
        2, 3 or 4.

    Returns
    -------
    LevelTerm
    """
    if not is_one_of(order, _MIN_SAMPLES):
        raise InvalidParameterError("order", order, "2, 3 or 4")
    x, y = _pair(fine, coarse, max(_MIN_SAMPLES[order], 2))
    n = x.shape[0]
    mean = _h(x, order) - (0.0 if y is None else _h(y, order))
    return LevelTerm(
        mean=readonly_array(mean),
        variance=readonly_array(_influence_variance(x, y, order)),
        n_samples=n,
        groups=readonly_array(np.arange(x.shape[1])),
    )


def variance_from_samples(
    *,
    fine: Sequence[np.ndarray],
    coarse: Sequence[np.ndarray],
    tol: float | np.ndarray | None = None,
) -> TargetEstimate:
    """MLMC estimate of ``Var(Q)`` from given level samples (levels ``0, 1, ..., L``).

    Parameters
    ----------
    fine, coarse : sequence of ndarray, each shape (n_l,) or (n_l, n_qoi)
        Per level, ``Q_l`` and ``Q_{l-1}`` of the same samples (``coarse`` of
        level 0 is ignored); ``n_l >= 4``.
    tol : float or ndarray, optional
        Tolerance on the RMS error per QoI (sets ``tol_met``).

    Returns
    -------
    TargetEstimate
        ``estimate`` of ``Var(Q_L)``, its statistical error, and the
        remaining bias ``Var(Q) - Var(Q_L)`` from the decay of the terms.
    """
    if len(fine) != len(coarse) or len(fine) == 0:
        raise EstimationError(f"fine and coarse need one entry per level, got {len(fine)} and {len(coarse)}")
    terms = [
        variance_level_term(f, None if level == 0 else c, level)
        for level, (f, c) in enumerate(zip(fine, coarse))
    ]
    return telescope(terms, tol=tol)


def mlmc_variance(sampler: Sampler, *, tol: float | np.ndarray, **options: object) -> TargetEstimate:
    """Adaptive MLMC estimate of ``Var(Q)`` to the RMS tolerance ``tol`` (per QoI).

    Parameters
    ----------
    sampler : callable
        ``sampler(level, indices) -> (fine, coarse, cost)``.
    tol : float or ndarray, shape (n_qoi,)
        Tolerance on the RMS error of the variance, in the unit of ``Q``
        squared.
    **options
        Keyword arguments of :func:`~rough_uq.multilevel.targets.adaptive_mlmc`
        (``theta``, ``n_initial``, ``min_finest_level``, ``max_level``,
        ``max_cost``, ``batch_size``).

    Returns
    -------
    TargetEstimate
        One component per QoI.
    """
    return adaptive_mlmc(sampler, term=variance_level_term, tol=tol, **({"label": "variance"} | options))


def mlmc_central_moment(sampler: Sampler, *, order: int, tol: float | np.ndarray, **options: object) -> TargetEstimate:
    """Adaptive MLMC estimate of the central moment ``mu_order`` (3 or 4) of ``Q`` to the RMS tolerance ``tol``.

    The level terms are :func:`central_moment_level_term` (their variance is
    the leading-order estimate of the module docstring); ``options`` as for
    :func:`mlmc_variance`. Skewness and kurtosis follow by dividing by the
    power of :func:`mlmc_variance`'s estimate.
    """
    if order not in (3, 4):
        raise InvalidParameterError("order", order, "3 or 4 (use mlmc_variance for the variance)")

    def term(fine: np.ndarray, coarse: np.ndarray | None, level: int) -> LevelTerm:
        return central_moment_level_term(fine, coarse, level, order=order)

    return adaptive_mlmc(sampler, term=term, tol=tol, **({"label": f"central moment {order}"} | options))
