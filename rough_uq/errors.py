"""The exceptions and warnings roughuq raises for conditions a user can act on.

Every user-facing failure derives from :class:`RoughUQError`; the CLI prints
its message on one line and exits with status 2. Anything else is a bug and
keeps its traceback. The warnings (:class:`EstimationWarning`,
:class:`DuplicateSampleWarning`) say that a result stands on weak ground or
that input was skipped; the run goes on.
"""

from __future__ import annotations

import math
import numbers
import os
import sys
import warnings
from collections.abc import Collection, Sequence
from types import FrameType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np


class RoughUQError(Exception):
    """Base class of all errors a user can act on.

    Every one pickles with its attributes (:meth:`__reduce__`), so that an
    error raised in a pool or dask worker reaches the caller as itself.
    """

    def __reduce__(self) -> tuple:
        # Exception's own reduction calls ``type(self)(*self.args)``, and args is
        # the message alone: the subclasses whose __init__ takes the fields
        # (InvalidParameterError and others) failed to unpickle, and a process
        # pool reported the failure as a worker "terminated abruptly".
        return _rebuilt_error, (type(self), self.args, self.__dict__)


def _rebuilt_error(cls: type[RoughUQError], args: tuple, state: dict) -> RoughUQError:
    """An error of class ``cls`` with ``args`` and attributes ``state``, without calling its ``__init__``."""
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


def is_real_number(value: object) -> bool:
    """A real number (numpy's too), not a boolean (``True`` would pass for 1) nor a string (``"0.5"``).

    The one test of "is this a number" behind the :class:`InvalidParameterError`
    checks of every layer: strings and booleans are refused, never converted. So
    is an integer beyond the range of a float (``10**400``): every check and
    computation after this test works in floats.
    """
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        return False
    if isinstance(value, numbers.Integral):
        try:
            float(value)
        except OverflowError:
            return False
    return True


def scalar_refusal(name: str, value: object, allowed: str) -> InvalidParameterError:
    """The :class:`InvalidParameterError` of a scalar parameter; for a 0-d array, ``allowed`` says that a plain
    number is meant ("got array(1.); allowed: a finite number > 0" read as a contradiction)."""
    if type(value).__name__ == "ndarray" and getattr(value, "shape", None) == ():
        allowed += " (a number, not a 0-d array: x.item() is one)"
    return InvalidParameterError(name, value, allowed)


def is_one_of(value: object, allowed: Collection[object]) -> bool:
    """``value in allowed`` for any value: an array that is not 0-d (its ``==`` compares elementwise: in a tuple
    it raised "the truth value of an array ... is ambiguous") or an unhashable value (in a dict or a set:
    TypeError) is in none. A numpy scalar (``np.str_``, ``np.int64``) is compared as its value."""
    if getattr(value, "ndim", 0) != 0:
        return False
    try:
        return value in allowed
    except TypeError:  # unhashable, in a dict or set
        return False


def is_integer(value: object) -> bool:
    """An integer (numpy's too), not a boolean, a string nor a float with an integral value (``2.0``)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


class InvalidParameterError(RoughUQError, ValueError):
    """A physical or numerical parameter is outside its allowed range.

    Parameters
    ----------
    name : str
        The parameter (or config field path) that is wrong.
    value : object
        The value that was given.
    allowed : str
        What would have been accepted.
    text : str, optional
        The message, where ``NAME: got VALUE; allowed: ...`` reads badly (a value that is missing); it starts
        with ``name``.
    """

    def __init__(self, name: str, value: object, allowed: str, *, text: str | None = None) -> None:
        self.name = name
        self.value = value
        self.allowed = allowed
        super().__init__(f"{name}: got {_shown(value)}; allowed: {allowed}" if text is None else text)


def _shown(value: object) -> str:
    """``repr(value)``, but an integer of hundreds of digits as its size (``10**400`` was printed whole), also
    inside a list or tuple, and an array of more than one dimension or many values as its shape and dtype
    (an 11 x 11 array of thresholds made a message of 22 lines)."""
    shape = getattr(value, "shape", None)
    if isinstance(shape, tuple) and hasattr(value, "dtype") and (len(shape) > 1 or math.prod(shape) > 12):
        return f"an array of shape {shape} ({value.dtype})"
    if isinstance(value, int) and not isinstance(value, bool):
        digits = _digits(value)
        if digits > 30:
            return f"{'a negative' if value < 0 else 'an'} integer of {digits} digits"
    if isinstance(value, (list, tuple)) and any(isinstance(v, int) and _digits(v) > 30 for v in value):
        inner = ", ".join(_shown(v) for v in value)
        return f"[{inner}]" if isinstance(value, list) else f"({inner})"
    return repr(value)


def _digits(value: int) -> int:
    """Decimal digits of ``abs(value)``, without ``str()`` (refused beyond 4300 digits)."""
    magnitude = abs(value)
    digits = max(1, int(magnitude.bit_length() * 0.30102999566398120))  # log10(2): at most the true count
    while magnitude >= 10**digits:
        digits += 1
    return digits


def checked_integer(name: str, value: object, minimum: int, maximum: int | None = None) -> int:
    """``value`` as an int, or :class:`InvalidParameterError` naming ``name`` unless an integer ``>= minimum``
    (and ``<= maximum`` if given).

    The integer check of every layer (:func:`is_integer`: booleans, strings and
    floats are refused, never converted).
    """
    if not (is_integer(value) and minimum <= value and (maximum is None or value <= maximum)):
        allowed = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
        raise InvalidParameterError(name, value, f"an integer {allowed}")
    return int(value)


def checked_bool(name: str, value: object) -> bool:
    """``value`` as a bool, or :class:`InvalidParameterError` naming ``name`` unless ``True`` or ``False``.

    numpy's booleans count; anything else with a truth value (``"no"``, ``0``,
    ``None``) is refused rather than read as a flag.
    """
    import numpy as np  # here, not at the top: the CLI imports this module at startup, before it needs numpy

    if not isinstance(value, (bool, np.bool_)):
        raise InvalidParameterError(name, value, "True or False")
    return bool(value)


def checked_path(name: str, value: object) -> str:
    """``value`` as a path string (a ``str`` or an ``os.PathLike`` of one), or :class:`InvalidParameterError`.

    ``os.fspath`` raised a bare ``TypeError`` for ``None`` or a number.
    """
    import os

    text = os.fspath(value) if isinstance(value, (str, os.PathLike)) else None
    if not isinstance(text, str):
        raise InvalidParameterError(name, value, "a file path (a str or pathlib.Path)")
    return text


def is_real_array(value: object) -> bool:
    """A real number (:func:`is_real_number`), or an array or (nested) sequence of them: nothing to convert.

    An array (anything with a numpy ``dtype``, numpy's scalars too) counts by
    its dtype, integer or floating; strings, booleans, complex numbers and
    objects are refused, never converted (``"0.5"`` would pass for 0.5).
    """
    kind = getattr(getattr(value, "dtype", None), "kind", None)
    if kind is not None:
        return kind in "iuf"
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return all(is_real_array(item) for item in value)
    return is_real_number(value)


def checked_real_array(name: str, value: object, allowed: str) -> np.ndarray:
    """``value`` as a float64 ndarray, or :class:`InvalidParameterError` naming ``name`` unless a real array.

    Refused: what :func:`is_real_array` refuses, a ragged sequence (no array
    shape) and integers beyond the float range. The values themselves (sign,
    range, NaN) are the caller's to check.
    """
    import numpy as np  # here, not at the top: see checked_bool

    if is_real_array(value):
        try:
            return np.asarray(value, dtype=np.float64)
        except (ValueError, OverflowError):  # a ragged sequence; an integer such as 10**400
            pass
    raise InvalidParameterError(name, value, allowed)


#: What an array of a numpy dtype kind other than real numbers holds, for messages.
_NON_REAL_KINDS = {
    "b": "booleans", "c": "complex numbers", "U": "text", "S": "bytes", "O": "Python objects",
    "m": "time differences", "M": "dates",
}


def refuse_non_real(name: str, values: np.ndarray) -> None:
    """Refuse an array of anything but real numbers (text, booleans, complex numbers, times...) by name.

    By dtype kind, so that ``np.timedelta64``, a subtype of ``np.integer``, is
    refused too; the message says what the array holds, not its values.
    """
    if not is_real_array(values):
        held = _NON_REAL_KINDS.get(values.dtype.kind, f"values of dtype {values.dtype}")
        raise InvalidParameterError(name, f"an array of {held}", "real numbers (float or integer)")


class MisplacedOptionError(InvalidParameterError):
    """A command-line option was given where it does not apply (e.g. ``--resources`` without ``--plan``).

    The message says what was given, where, and where the option applies:
    ``--shards 3 was given without --plan; it applies only with --plan``.

    Parameters
    ----------
    name : str
        The option, e.g. ``"--shards"``.
    value : object or None
        Its value; None for a flag (an option that takes none).
    context : str
        Where it was given, e.g. ``"without --plan"``.
    allowed : str
        Where it applies, e.g. ``"it applies only with --plan"``.
    """

    def __init__(self, name: str, value: object | None, *, context: str, allowed: str) -> None:
        self.name = name
        self.value = value
        self.allowed = allowed
        self.context = context
        given = name if value is None else f"{name} {value}"
        RoughUQError.__init__(self, f"{given} was given {context}; {allowed}")


class ConvergenceError(RoughUQError):
    """A contact solve did not converge and the caller asked for a hard failure.

    Carries the non-converged :class:`~rough_uq.physics.solver.ContactSolution`
    (``solution``) so that the partial result can be inspected.
    """

    def __init__(self, message: str, solution: object | None = None) -> None:
        self.solution = solution
        super().__init__(message)


class ConfigError(RoughUQError):
    """The study configuration is invalid; the message lists every problem."""


class StudyFileError(RoughUQError):
    """A study or shard file is missing, unreadable, locked or belongs to another config."""

    def __init__(self, message: str, path: object | None = None) -> None:
        self.path = path
        super().__init__(message)


class EstimationError(RoughUQError):
    """The estimators cannot proceed (e.g. too few levels to fit rates)."""


#: The largest sample count a plan gives a level (2^52: float counts convert to integers exactly below it);
#: a plan that needs more is capped there (:mod:`rough_uq.multilevel.allocation`, ``drivers``).
PLANNED_COUNT_CAP = 2**52


class PlanTooLargeError(EstimationError):
    """A driver's plan asks for more than ``max_samples`` samples in all: the tolerance is out of reach.

    Raised before the planned samples are drawn. The message names the
    argument as the drivers know it, ``tol 1e-06 needs about 2e+11 samples
    (N_l ...), more than max_samples = 10000000: loosen the tolerance``; a
    caller that took the tolerance under another name (a command-line option)
    re-raises the refusal in its words with :meth:`named`.

    Parameters
    ----------
    n_planned : sequence of int
        Samples planned per level, coarsest first.
    total : float
        Samples planned in all.
    max_samples : int
        The limit the plan exceeds.
    tol : sequence of float
        The tolerances the plan is for (one per QoI, or per group of QoIs).
    advice : str
        What to change, ending the message.
    tolerance : str, optional
        How the message names the tolerance; default ``tol`` and the values
        of ``tol`` (``"tol 1e-06, 0.001"``).
    limit : str, optional
        How the message names the limit; default ``max_samples = N`` (a
        command-line run: ``the 1e+07 samples a roughuq run may plan``).
    """

    def __init__(
        self, *, n_planned: Sequence[int], total: float, max_samples: int, tol: Sequence[float], advice: str,
        tolerance: str | None = None, limit: str | None = None,
    ) -> None:
        self.n_planned = tuple(int(n) for n in n_planned)
        self.total = float(total)
        self.max_samples = int(max_samples)
        self.tol = tuple(float(eps) for eps in tol)
        self.advice = advice
        self.tolerance = "tol " + ", ".join(f"{eps:g}" for eps in self.tol) if tolerance is None else tolerance
        self.limit = f"max_samples = {self.max_samples}" if limit is None else limit
        # The planners cap a level's count at PLANNED_COUNT_CAP (exact as a float): the need is then larger.
        is_capped = any(n >= PLANNED_COUNT_CAP for n in self.n_planned)
        plan_text = " ".join(str(n) if n < 10**7 else f"{n:.3g}" for n in self.n_planned)
        super().__init__(
            f"{self.tolerance} needs {'more than' if is_capped else 'about'} {self.total:.3g} samples "
            f"(N_l {plan_text}), more than {self.limit}: {advice}"
        )

    def named(self, *, tolerance: str, advice: str, limit: str | None = None) -> PlanTooLargeError:
        """The same refusal naming the tolerance ``tolerance`` (e.g. ``"--tol-cdf 1e-05"``), ending in ``advice``;
        ``limit`` names the limit (default this refusal's, :attr:`limit`)."""
        return PlanTooLargeError(
            n_planned=self.n_planned, total=self.total, max_samples=self.max_samples, tol=self.tol, advice=advice,
            tolerance=tolerance, limit=self.limit if limit is None else limit,
        )


class ExecutorError(RoughUQError):
    """A worker process or the cluster failed; samples already stored are kept."""


class EstimationWarning(UserWarning):
    """Emitted when an MLMC diagnostic fails or an estimate rests on weak data.

    Examples: an inconsistent level (telescoping sum broken), a coupling that
    does not reduce the variance, a large kurtosis of ``Y_l``, a level with a
    single sample, a sampler that reports zero cost.
    """


class DuplicateSampleWarning(UserWarning):
    """Samples already stored (same stage, level and index) were skipped."""


#: The package's directory: frames of files under it are roughuq's own (:func:`warn_at_caller`).
_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn_at_caller(message: str | Warning, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` attributed to the first frame outside roughuq: the user's line that called it.

    A fixed ``stacklevel`` counts the frames of one call path; the same
    warning reached through ``rough_uq.mlmc``, a driver or the CLI pointed at
    a line inside the package from most of them. (Python 3.12's
    ``skip_file_prefixes`` does this; 3.11 does not have it.) Code that
    :mod:`dataclasses` generates for a roughuq class (its ``__init__``, file
    ``<string>``) is roughuq's too: a warning of ``__post_init__`` pointed at
    ``<string>:19``, one location for every caller, so that Python showed it once.
    """
    frame, level = sys._getframe(1), 2  # the caller of this function is stacklevel 2
    while frame.f_back is not None and _is_package_frame(frame):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)


def _is_package_frame(frame: FrameType) -> bool:
    """A frame of roughuq's files, of code generated for one of its modules (no file: ``<string>``), or of
    :mod:`dataclasses` on the way out of them (``dataclasses.replace(problem, ...)`` pointed at dataclasses.py)."""
    filename = frame.f_code.co_filename
    if filename.startswith(_PACKAGE_DIR):
        return True
    module = str(frame.f_globals.get("__name__", ""))
    return module == "dataclasses" or (filename.startswith("<") and module.startswith(f"{__package__}."))
