"""Richardson extrapolation of the MLMC estimate: the finest level's weight, the bias left, when it is sound.

This module gives the weight of the finest level in the extrapolated estimate
(:func:`richardson_weight`), the bias the extrapolation leaves
(:func:`richardson_bias`) and the check whether the level means allow it
(:func:`ratio_instability`). It needs only numpy and the standard library and
has no state.

Conventions
-----------
Levels ``l``, ``Y_l = Q_l - Q_{l-1}`` and ``V_l = Var(Y_l)`` are those of
:mod:`~rough_uq.multilevel.statistics`; ``alpha`` is the bias rate of
:mod:`~rough_uq.multilevel.rates` (``|E[Y_l]| ~ c 2^(-alpha l)``, SPEC
section 5), ``L`` the finest level of an estimator and ``N_l`` its number of
level-``l`` samples. ``RATIO_LOG2_TOLERANCE`` is the constant of
:mod:`~rough_uq.multilevel.rates`, where the fit of ``alpha`` uses it too.

Richardson extrapolation
------------------------
Where ``E[Y_l] = c 2^(-alpha l)`` holds, ``E[Q] - E[Q_L]`` is the geometric
tail ``E[Y_L] / (2^alpha - 1)``, so

    R_L = sum_{l<L} mean(Y_l) + w mean(Y_L),    w = 2^alpha / (2^alpha - 1),

removes the leading bias term (Giles 2015, section 3.1; Lemaire & Pages,
multilevel Richardson-Romberg). Its variance is ``sum_{l<L} V_l / N_l + w^2
V_L / N_L``, so the allocation treats the finest level as having variance
``w^2 V_L`` (:func:`~rough_uq.multilevel.allocation.optimal_samples` with
scaled ``V_L``). What remains is the next term of the expansion; this module
estimates it from the change of the extrapolated value between successive
finest levels,

    D_L = R_L - R_{L-1} = w E[Y_L] - E[Y_{L-1}] / (2^alpha - 1),

and, if the next term decays like ``2^(-alpha2 l)``, the remaining bias is
``|D_L| / (2^alpha2 - 1)`` (:func:`richardson_bias`; as for the plain bias the
maximum with the same tail taken from ``D_{L-1}`` guards against a ``D_L``
that happens to be near 0). ``alpha`` itself is fitted, and on
pre-asymptotic levels it differs from the local rate of the two finest
levels; the extrapolation then leaves part of the leading term, about
``|w - w_L| |E[Y_L]|`` with ``w_L`` the weight of the local ratio, and the
reported remaining bias is the larger of the two. On such levels the local
ratio itself still drifts towards its limit (``Y_l = 2^-l + 6 4^-l``: ratios
0.31, 0.35, 0.39, 0.43, ... towards 1/2, a fitted ``alpha`` of 1.3-1.6), and
``w_L`` misses most of what is left: mlmc runs on that hierarchy claimed tol
0.02 at an RMS error of 0.037 (20 seeds). With three levels ``>= 1`` the
drift of the last two ratios is therefore continued as the next term makes
it (the ratio's distance to its limit shrinks by ``q = 2^-(alpha2 - alpha) =
2^-min(alpha, 1)`` per level, ``alpha`` here the smaller of the fitted and the
local rate ``-log2 r_L``): ``r_inf = r_L + (r_L - r_{L-1}) q / (1 - q)``,
clipped to ``[1e-12, 0.9]`` (:data:`MAX_LIMIT_RATIO`), and its weight enters
like ``w_L``. On exact means of that hierarchy (finest level 3 to 7) the
estimate is then 0.63-1.06 of the bias left (0.20-0.82 before). On a
hierarchy already at its rate the drift is noise: counted whole it made one
of 40 runs at tol 0.02 cost 3.4 times plain MLMC (a bias estimate of 6.6 tol
from ratios 0.50 -> 0.66). So with the means' standard errors the drift of
``log2 r`` counts only beyond :data:`DRIFT_NOISE_GATE` (0.5) standard errors
of its own (first order in the three means' relative errors), which about
halves what pure noise adds (it exceeds half a standard error 62 % of the
time): the costliest of those 40 runs then costs 1.05 times plain MLMC
(median 0.23), and 40 runs on ``2^-l + 6 4^-l`` end at an RMS error of 0.77
tol (0.97 with a gate of one standard error, 1.5 with two, 0.016 = 0.80 tol
for the 20 runs above). The gate was tuned on that one hierarchy: at rate on
``v1 = 1, beta = 1.5, gamma = 1`` the costliest of 40 runs cost 1.59 times
plain MLMC at ``alpha = 0.7`` and 1.28 at ``alpha = 1`` (1.26 and 1.22
before the drift term). Where the true rate is below 1 (``2^-0.7l + b
2^-1.4l``, tol 0.05, 40 runs, ``beta`` 1.5-2, ``gamma`` 1-2) the drift is
slower and partly within the noise: RMS errors of 1.1-1.45 tol at ``b = 1``
and 1.5-2.1 at ``b = 3`` (1.09 / 1.47 on ``v1 = 1, beta = 1.5, gamma = 1``,
1.17 / 1.70 there before; plain MLMC 0.85-0.92), a limit of extrapolating on
pre-asymptotic levels. A plan's projection to levels
beyond its screened ones (``beyond``) shrinks the next-order tail by
``2^-alpha2`` per level and the rate part, proportional to ``E[Y_L]``, by
``2^-alpha`` (before, everything by ``2^-alpha2``: 0.06-0.42 of what the run
then estimated on those levels, now 0.23-0.84). ``alpha2`` is not fitted (it
would need four or more levels with small noise): it is taken as
``min(2 alpha, alpha + 1)``, the next order of an expansion in powers of
``h^alpha`` or in integer powers of ``h``, whichever decays more slowly (the
conservative choice).

Extrapolation is only sound where the ratios ``E[Y_l] / E[Y_{l-1}]`` are
stable; :func:`ratio_instability` says why they are not (too few levels, a
mean indistinguishable from zero, a change of sign, no decay, or successive
ratios differing by more than a factor ``2^RATIO_LOG2_TOLERANCE`` beyond
their noise), and callers fall back to plain MLMC.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rough_uq.errors import EstimationError
from rough_uq.multilevel.rates import RATIO_LOG2_TOLERANCE, remaining_bias
from rough_uq.multilevel.statistics import checked_names

__all__ = [
    "RICHARDSON_MIN_LEVELS",
    "ratio_instability",
    "richardson_bias",
    "richardson_weight",
    "second_order_rate",
]


def richardson_weight(alpha: np.ndarray) -> np.ndarray:
    """Weight ``w = 2^alpha / (2^alpha - 1)`` of the finest level in the extrapolated estimate.

    Parameters
    ----------
    alpha : ndarray, shape (n_qoi,)
        Bias rate, positive.

    Returns
    -------
    ndarray, shape (n_qoi,)
    """
    alpha = np.asarray(alpha, dtype=float)
    remaining_bias(np.zeros_like(alpha), alpha)  # alpha <= 0: raises the explanatory error
    return -1.0 / np.expm1(-alpha * math.log(2.0))


def second_order_rate(alpha: np.ndarray) -> np.ndarray:
    """Assumed rate ``alpha2 = min(2 alpha, alpha + 1)`` of the bias left by extrapolation (module docstring)."""
    alpha = np.asarray(alpha, dtype=float)
    return np.minimum(2.0 * alpha, alpha + 1.0)


def richardson_bias(
    mean_diff: np.ndarray, alpha: np.ndarray, mean_se: np.ndarray | None = None, *, beyond: int = 0
) -> np.ndarray:
    """Remaining bias of the extrapolated estimate from the change ``D_L`` of the extrapolated values.

    Parameters
    ----------
    mean_diff : ndarray, shape (n, n_qoi)
        ``E[Y_l]`` of consecutive levels ``l >= 1`` (not the base level, whose
        ``Y = Q``), the finest last; ``n >= 2``.
    alpha : ndarray, shape (n_qoi,)
        Bias rate of the extrapolation.
    mean_se : ndarray, shape (n, n_qoi), optional
        Standard errors of ``mean_diff``: the drift of the local ratio counts
        only beyond :data:`DRIFT_NOISE_GATE` standard errors of its own (module
        docstring). Without them the means are taken as exact.
    beyond : int
        Levels past the finest of ``mean_diff`` whose bias is wanted (a plan's
        projection): the next-order tail shrinks by ``2^-alpha2`` per level,
        the rest (proportional to ``E[Y_L]``) by ``2^-alpha``.

    Returns
    -------
    ndarray, shape (n_qoi,)
        The larger of the next-order tail ``max(|D_L|, |D_{L-1}| 2^-alpha2) /
        (2^alpha2 - 1)`` (``alpha2`` from :func:`second_order_rate`; the
        ``D_{L-1}`` term only with ``n >= 3``) and the sensitivity to the rate,
        ``|w - w_L| |E[Y_L]|`` with ``w_L = 1 / (1 - r_L)`` the weight of the
        local ratio ``r_L = E[Y_L] / E[Y_{L-1}]`` (where ``0 < r_L < 1``), and
        with ``n >= 3`` the same with the ratio's limit ``r_inf`` where it
        drifts (module docstring).

    Raises
    ------
    EstimationError
        With fewer than two levels (no ``D_L``) or a non-positive ``alpha``.
    """
    mean_diff = np.asarray(mean_diff, dtype=float)
    if mean_diff.ndim != 2 or mean_diff.shape[0] < 2:
        raise EstimationError(
            f"Richardson's remaining bias needs the means of two levels >= 1 (an array of shape (levels, QoIs)), "
            f"got shape {mean_diff.shape}"
        )
    weight = richardson_weight(alpha)
    alpha = np.asarray(alpha, dtype=float)
    alpha2 = second_order_rate(alpha)
    changes = weight * mean_diff[1:] - (weight - 1.0) * mean_diff[:-1]  # D_l; w - 1 = 1 / (2^alpha - 1)
    terms = [np.abs(changes[-1])]
    if len(changes) >= 2:
        terms.append(np.abs(changes[-2]) * 2.0 ** (-alpha2))
    next_order = remaining_bias(np.max(terms, axis=0), alpha2)
    rate_error = _rate_sensitivity(mean_diff, weight, alpha, mean_se)
    return np.maximum(next_order * 2.0 ** (-alpha2 * beyond), rate_error * 2.0 ** (-alpha * beyond))


def _rate_sensitivity(
    mean_diff: np.ndarray, weight: np.ndarray, alpha: np.ndarray, mean_se: np.ndarray | None
) -> np.ndarray:
    """``|w - w_r| |E[Y_L]|`` for the local ratio and, with three levels, its limit (module docstring)."""
    # A fitted alpha off the local rate of the two finest levels leaves part of the leading
    # term; the difference of the two extrapolations measures it.
    finest = mean_diff[-1]
    with np.errstate(over="ignore"):  # a ratio of 1e300 / 1e-10 is inf: outside (0, 1), no weight of its own
        ratios = _ratios(mean_diff[-3:])
    rate_error = _rate_error(ratios[-1], weight, finest)
    if len(ratios) < 2:
        return rate_error
    is_drift = (ratios[-2] > 0) & (ratios[-2] < 1) & (ratios[-1] > 0) & (ratios[-1] < 1)
    # Ratios outside (0, 1) are masked by is_drift; errors of 1e200 times their mean square to inf (no drift).
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        drift = np.log2(ratios[-1]) - np.log2(ratios[-2])
        if mean_se is not None:
            noise = DRIFT_NOISE_GATE * _log_ratio_noise(mean_diff, mean_se)
            drift = np.sign(drift) * np.maximum(np.abs(drift) - noise, 0.0)
        previous = ratios[-1] * 2.0 ** (-drift)
        local_alpha = -np.log2(ratios[-1])
    # The local ratio still drifting: its limit, the drift continued geometrically.
    factor = _drift_factor(np.minimum(alpha, np.where(is_drift, local_alpha, alpha)))
    limit = np.clip(ratios[-1] + factor * (ratios[-1] - previous), _MIN_LIMIT_RATIO, MAX_LIMIT_RATIO)
    return np.maximum(rate_error, np.where(is_drift, _rate_error(limit, weight, finest), 0.0))


#: Standard errors of its own that the drift of ``log2 r`` must exceed to count (module docstring).
DRIFT_NOISE_GATE = 0.5

#: The largest limit of the local ratio :func:`richardson_bias` takes from a drift (a weight of at most 10:
#: a ratio drifting towards 1 makes the remaining bias large but finite).
MAX_LIMIT_RATIO = 0.9

#: The smallest: a drift towards 0 counts as a weight near 1 (the whole correction in doubt), not as no ratio.
_MIN_LIMIT_RATIO = 1e-12


def _ratios(means: np.ndarray) -> np.ndarray:
    """``r_l = E[Y_l] / E[Y_{l-1}]`` of consecutive rows of ``means`` (0 where ``E[Y_{l-1}] = 0``)."""
    return np.divide(means[1:], means[:-1], out=np.zeros_like(means[1:]), where=means[:-1] != 0)


def _log_ratio_noise(mean_diff: np.ndarray, mean_se: np.ndarray) -> np.ndarray:
    """Standard error of ``log2 r_L - log2 r_{L-1}`` from the three finest means (first order; rows are levels)."""
    means, errors = np.abs(mean_diff[-3:]), np.asarray(mean_se, dtype=float)[-3:]
    relative = np.divide(errors, means, out=np.full_like(means, np.inf), where=means > 0)
    return np.sqrt(relative[2] ** 2 + 4.0 * relative[1] ** 2 + relative[0] ** 2) / math.log(2.0)


def _rate_error(ratio: np.ndarray, weight: np.ndarray, finest: np.ndarray) -> np.ndarray:
    """``|w_r - w| |E[Y_L]|`` with ``w_r = 1 / (1 - r)`` the weight of ``ratio`` (0 where it is not in (0, 1))."""
    has_local = (ratio > 0) & (ratio < 1)
    local_weight = np.divide(1.0, 1.0 - ratio, out=np.ones_like(ratio), where=has_local)
    return np.where(has_local, np.abs(local_weight - weight) * np.abs(finest), 0.0)


def _drift_factor(alpha: np.ndarray) -> np.ndarray:
    """``q / (1 - q)``, ``q = 2^-(alpha2 - alpha) = 2^-min(alpha, 1)``: the drift still to come, per last step."""
    gap = np.clip(alpha, _MIN_DRIFT_RATE, 1.0)  # alpha2 - alpha for alpha2 = min(2 alpha, alpha + 1)
    return 1.0 / np.expm1(gap * math.log(2.0))


#: The smallest rate the drift factor takes (a factor of about 1440): a local ratio of almost 1 is clipped by
#: :data:`MAX_LIMIT_RATIO` in any case.
_MIN_DRIFT_RATE = 1e-3


#: Levels ``>= 1`` (two ratios of successive means) needed before Richardson extrapolation is trusted.
RICHARDSON_MIN_LEVELS = 3


def ratio_instability(
    mean_diff: np.ndarray,
    mean_se: np.ndarray,
    levels: Sequence[int],
    *,
    min_levels: int = RICHARDSON_MIN_LEVELS,
    window: int = 3,
    names: Sequence[str] | None = None,
) -> str:
    """Why the ratios of successive level means are not stable enough to extrapolate ("" if they are).

    Parameters
    ----------
    mean_diff, mean_se : ndarray, shape (n, n_qoi)
        ``E[Y_l]`` and its standard error ``sqrt(V_l / N_l)`` of consecutive
        levels ``l >= 1``, the finest last.
    levels : sequence of int, length n
        The level indices (for the message).
    min_levels : int
        Fewest levels needed (two ratios by default).
    window : int
        Number of finest ratios checked.
    names : sequence of str, optional
        Names of the QoI columns, length ``n_qoi``: the reason names the QoI
        that failed (``(contact_area)``); without them it gives its column
        index (``(QoI 0)``), and nothing for a single QoI.

    Returns
    -------
    str
        The first failed check for some QoI, or "" when, on the ``window``
        finest levels, every mean is at least two standard errors from 0, all
        have the same sign, every ratio ``r_l = E[Y_l] / E[Y_{l-1}]`` is below
        1, and successive ratios agree: ``|log2 r_l - log2 r_{l-1}| <=
        RATIO_LOG2_TOLERANCE`` plus two standard errors of that difference.
    """
    mean_diff = np.asarray(mean_diff, dtype=float)
    mean_se = np.asarray(mean_se, dtype=float)
    levels = [int(level) for level in levels]
    if len(levels) < min_levels:
        return (
            f"needs the means of {min_levels} levels >= 1 to check the ratios of successive means, "
            f"has {len(levels)} ({levels})"
        )
    rows = slice(max(0, len(levels) - window - 1), len(levels))
    means, errors, shown = mean_diff[rows], mean_se[rows], levels[rows]
    names = checked_names(names, means.shape[1])
    for q in range(means.shape[1]):
        m, se = means[:, q], errors[:, q]
        if not np.any(m) and not np.any(se):
            continue  # exact on these levels (every difference 0): nothing to extrapolate, no ratio to take
        tag = f" ({names[q]})" if names is not None else (f" (QoI {q})" if means.shape[1] > 1 else "")
        weak = np.flatnonzero(np.abs(m) < 2.0 * se)
        if weak.size:
            row = int(weak[0])
            return (
                f"the mean of Y_{shown[row]} = {m[row]:.3g} is within two standard errors "
                f"(2 x {se[row]:.2g} = {2.0 * se[row]:.2g}) of 0"
                f"{tag}: its ratio to the next level is noise"
            )
        with np.errstate(divide="ignore", invalid="ignore"):  # a mean of exactly 0 (se 0): inf or nan, refused below
            ratios = m[1:] / m[:-1]
        for k, ratio in enumerate(ratios):
            if ratio <= 0:
                return (
                    f"the level means change sign between levels {shown[k]} and {shown[k + 1]} "
                    f"({m[k]:.3g}, {m[k + 1]:.3g}){tag}: the bias is not in its asymptotic regime"
                )
            if ratio >= 1:
                return (
                    f"the level means do not decay between levels {shown[k]} and {shown[k + 1]} "
                    f"({m[k]:.3g}, {m[k + 1]:.3g}){tag}"
                )
        log_ratios = np.log2(ratios)
        for k in range(1, len(ratios)):
            spread = abs(log_ratios[k] - log_ratios[k - 1])
            noise = _log_ratio_noise(m[k - 1 : k + 2], se[k - 1 : k + 2])
            if spread > RATIO_LOG2_TOLERANCE + 2.0 * noise:
                return (
                    f"the ratios of successive level means are not stable: E[Y_l] / E[Y_l-1] = "
                    f"{ratios[k - 1]:.3g} at level {shown[k]} and {ratios[k]:.3g} at level {shown[k + 1]}{tag}"
                )
    return ""

