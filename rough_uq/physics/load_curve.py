"""Load curves: one surface solved at several mean pressures, each solve warm-started from the last.

The loads are solved in increasing order. The first (smallest) starts from
``initial_pressure`` (or cold); every next one starts from the previous
solution's pressure scaled by the load ratio ``p_next / p_prev`` (the solver
rescales any guess to its load, so the scaling only makes the guess a
pressure of the right size). The previous pressure has the shape of the
next one where they share contact, but not the contact the larger load adds,
and finding that takes most of the iterations: on the classic surface the
sequence saves only about 3 % of the iterations of independent cold solves
(``scripts/bench_load_curve.py``, README).

Where better guesses exist for every load (``initial_pressures``: on a
coupled multilevel sample, the coarse-grid solutions of the same surface at
the same loads), each load starts from its own guess instead. On two coupled
classic samples at 512^2 (coarse 256^2; relative loads 0.01 to 0.2) the fine
curve took 397 iterations started so, 470 started from the previous load and
498 started cold.

Every point is a complete solve to ``tol`` (the warm start changes the path,
not the stopping test), so each point equals an independent solve at that
load up to the solver tolerance. A solve that does not converge within
``max_iter`` is continued once from its last iterate for ``retry_iter`` more
iterations (none by default), as the level sampler does for single solves
(:mod:`rough_uq.problem.sampler`); a point still not converged keeps its last
iterate and says so (``converged``), and the next load starts from it anyway:
it is still the best guess at hand.

Equal loads are solved once and share the solution; the repeated entries
report zero iterations, so ``n_iter.sum()`` is the work done.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import InvalidParameterError, checked_integer, is_real_number
from rough_uq.physics.solver import ContactSolution, solve_contact

__all__ = ["LoadCurveSolution", "solve_load_curve", "check_mean_pressures"]


@dataclass(frozen=True, eq=False)  # arrays: no field-wise ==, which raised (as the other results)
class LoadCurveSolution:
    """Result of :func:`solve_load_curve`, in the caller's order of the loads.

    Attributes
    ----------
    mean_pressures : ndarray of float64, shape (n_loads,)
        The imposed mean pressures (unit of ``E*``), as given.
    solutions : tuple of ContactSolution, length n_loads
        The solution at each load; equal loads share one object.
    n_iter : ndarray of int64, shape (n_loads,)
        Iterations spent on each load, retry included (0 for a repeated load).
    """

    mean_pressures: np.ndarray
    solutions: tuple[ContactSolution, ...]
    n_iter: np.ndarray

    @property
    def n_loads(self) -> int:
        """Number of loads."""
        return len(self.solutions)

    @property
    def converged(self) -> np.ndarray:
        """Boolean array, shape (n_loads,): whether each solve reached ``tol``."""
        return np.array([solution.converged for solution in self.solutions], dtype=bool)

    @property
    def is_converged(self) -> bool:
        """Whether every solve of the curve converged."""
        return bool(np.all(self.converged))

    @property
    def total_iter(self) -> int:
        """Iterations of the whole curve."""
        return int(np.sum(self.n_iter))

    def __repr__(self) -> str:
        # A summary for notebooks and print(), without the solutions' fields (three (n, n) arrays per load).
        return (f"LoadCurveSolution(mean_pressures={self.mean_pressures.tolist()}, n_iter={self.n_iter.tolist()}, "
                f"converged={self.converged.tolist()})")


def check_mean_pressures(mean_pressures: object) -> np.ndarray:
    """``mean_pressures`` as a 1-D float64 array, or :class:`InvalidParameterError` naming ``mean_pressures``.

    Accepted: a number or a non-empty sequence (or 1-D array) of finite
    numbers > 0 (duplicates allowed). A 2-D array is refused, not flattened
    into one longer list of loads.
    """
    allowed = "a non-empty sequence of finite numbers > 0 (unit of E*)"
    values = (mean_pressures,) if isinstance(mean_pressures, numbers.Real) else mean_pressures
    is_sequence = isinstance(values, Sequence) and not isinstance(values, (str, bytes))
    if not (is_sequence or (isinstance(values, np.ndarray) and values.ndim <= 1)):
        raise InvalidParameterError("mean_pressures", mean_pressures, allowed)
    values = list(values.reshape(-1)) if isinstance(values, np.ndarray) else list(values)
    is_bad = [
        not is_real_number(v) or not (math.isfinite(v) and v > 0) for v in values  # refuses numpy's bools too
    ]
    if not values or any(is_bad):
        raise InvalidParameterError("mean_pressures", mean_pressures, allowed)
    return np.array(values, dtype=np.float64)


def _guess_fields(initial_pressures: object, n_loads: int) -> Sequence[np.ndarray]:
    """The fields of ``initial_pressures``: a sequence of ``n_loads`` fields, or an array stacking them."""
    allowed = f"a sequence of {n_loads} fields (2-D arrays), one per load, or an array of shape ({n_loads}, m, m)"
    if isinstance(initial_pressures, np.ndarray):
        # A single field (n, n) would be taken row by row: only a stack of fields is one per load.
        if initial_pressures.ndim != 3 or initial_pressures.shape[0] != n_loads:
            raise InvalidParameterError("initial_pressures", f"an array of shape {initial_pressures.shape}", allowed)
        return list(initial_pressures)
    if not isinstance(initial_pressures, Sequence) or isinstance(initial_pressures, (str, bytes)):
        given = f"an object of type {type(initial_pressures).__name__}"
        raise InvalidParameterError("initial_pressures", given, allowed)
    if len(initial_pressures) != n_loads:
        raise InvalidParameterError("initial_pressures", f"a sequence of {len(initial_pressures)} fields", allowed)
    return initial_pressures


def _given_guesses(pressures: np.ndarray, initial_pressure, initial_pressures) -> dict[float, tuple[str, object]]:
    """Load -> the caller's name of its warm start (``initial_pressures[i]``) and the field (the first one given
    for a repeated load)."""
    if initial_pressures is None:
        return {} if initial_pressure is None else {float(pressures.min()): ("initial_pressure", initial_pressure)}
    if initial_pressure is not None:
        raise InvalidParameterError("initial_pressure", "a field", "None when initial_pressures is given")
    guesses: dict[float, tuple[str, object]] = {}
    for i, (load, guess) in enumerate(zip(pressures.tolist(), _guess_fields(initial_pressures, pressures.size))):
        guesses.setdefault(load, (f"initial_pressures[{i}]", guess))
    return guesses


def _renamed_guess_error(error: InvalidParameterError, name: str) -> InvalidParameterError:
    """``error`` of :func:`solve_contact` about its ``initial_pressure``, naming the caller's field ``name``."""
    if error.name != "initial_pressure" or name == error.name:
        return error
    return InvalidParameterError(name, error.value, error.allowed)


def _solve_with_retry(heights, *, initial, mean_pressure, max_iter, retry_iter, options) -> tuple[ContactSolution, int]:
    solution = solve_contact(
        heights, mean_pressure=mean_pressure, max_iter=max_iter, initial_pressure=initial, **options
    )
    n_iter = solution.n_iter
    if not solution.converged and retry_iter > 0:
        solution = solve_contact(
            heights, mean_pressure=mean_pressure, max_iter=retry_iter, initial_pressure=solution.pressure, **options
        )
        n_iter += solution.n_iter
    return solution, n_iter


def solve_load_curve(
    heights: np.ndarray,
    *,
    system_size: float,
    mean_pressures: Sequence[float] | np.ndarray,
    e_star: float = 1.0,
    tol: float = 1e-8,
    max_iter: int = 10_000,
    threads: int = 1,
    initial_pressure: np.ndarray | None = None,
    initial_pressures: Sequence[np.ndarray] | None = None,
    retry_iter: int = 0,
) -> LoadCurveSolution:
    """Solve the contact of one surface at several loads, in increasing order with warm starts.

    Parameters
    ----------
    heights : ndarray, shape (n, n)
        Rigid surface heights (unit of ``L``), as for :func:`~rough_uq.physics.solver.solve_contact`.
    system_size : float
        Box side ``L``.
    mean_pressures : sequence of float, length n_loads
        Imposed mean pressures (unit of ``E*``), > 0, in any order; repeats allowed.
    e_star, tol, max_iter, threads
        As for :func:`~rough_uq.physics.solver.solve_contact`, for every solve.
    initial_pressure : ndarray, optional
        Warm start of the smallest load; the others start from the previous
        load's solution.
    initial_pressures : sequence of ndarray, or ndarray of shape (n_loads, m, m), optional
        One warm start per load, in the order of ``mean_pressures`` (e.g. the
        coarse solutions of the same surface, on a grid whose size differs by
        a power of two), used instead of the previous load's solution; not
        together with ``initial_pressure``.
    retry_iter : int, optional
        Iterations of the one continuation of a solve that did not converge
        within ``max_iter`` (module docstring); 0: no continuation.

    Returns
    -------
    LoadCurveSolution
        Solutions in the order of ``mean_pressures``.

    Raises
    ------
    InvalidParameterError
        For an empty or non-positive ``mean_pressures``, a negative
        ``retry_iter``, an ``initial_pressures`` that is not one field per
        load, and whatever :func:`~rough_uq.physics.solver.solve_contact`
        refuses (a bad field of ``initial_pressures`` named by its index,
        ``initial_pressures[i]``).
    """
    pressures = check_mean_pressures(mean_pressures)
    checked_integer("retry_iter", retry_iter, 0)
    given = _given_guesses(pressures, initial_pressure, initial_pressures)
    options = dict(system_size=system_size, e_star=e_star, tol=tol, threads=threads)
    distinct = np.unique(pressures)  # sorted increasingly
    solved: dict[float, tuple[ContactSolution, int]] = {}
    guess, previous_load, guess_name = None, None, "initial_pressure"
    for load in distinct:
        if float(load) in given:
            guess_name, guess = given[float(load)]
        elif previous_load is not None:
            guess = guess * (load / previous_load)
        try:
            solution, n_iter = _solve_with_retry(
                heights, initial=guess, mean_pressure=float(load), max_iter=max_iter, retry_iter=int(retry_iter),
                options=options,
            )
        except InvalidParameterError as error:  # a bad guess said "initial_pressure", which was not given
            raise _renamed_guess_error(error, guess_name) from None
        solved[float(load)] = (solution, n_iter)
        guess, previous_load = solution.pressure, load
    n_iter = np.zeros(len(pressures), dtype=np.int64)
    seen: set[float] = set()
    for i, load in enumerate(pressures.tolist()):
        if load not in seen:
            n_iter[i] = solved[load][1]
            seen.add(load)
    return LoadCurveSolution(
        mean_pressures=pressures,
        solutions=tuple(solved[load][0] for load in pressures.tolist()),
        n_iter=n_iter,
    )
