"""Loads and units of a contact problem: what the user says, in the numbers the solver takes.

Load
----
A :class:`RelativeLoad` ``r`` is the mean pressure ``p = r * E* * sqrt(m2)``
(SPEC section 6), ``m2`` the slope variance of the spectrum
(:attr:`~rough_uq.physics.surface.SurfaceSpectrum.rms_slope` is ``sqrt(m2)``);
an :class:`AbsoluteLoad` is ``p`` itself, in the unit of ``E*``.

"The unit of ``E*``" (here and throughout, SPEC section 7) is the pressure
unit in which ``e_star`` is given, as "the unit of ``L``" is the length unit
of ``system_size``: pressures are not divided by ``E*``. With ``e_star=210``
(GPa, say) an :class:`AbsoluteLoad` of 0.5 is 0.5 GPa, and ``max_pressure``
and ``critical_pressure`` are in GPa too; a relative load and the contact
area do not change with the unit.

Load curves
-----------
A problem may carry several loads of one kind (:func:`load_sequence`): each
surface is then solved along the increasing loads with warm starts
(:func:`~rough_uq.physics.load_curve.solve_load_curve`) and every quantity of
interest becomes a curve, one result column per load. The columns are named
``<qoi>@<load>`` (:func:`column_names`), ``<load>`` the load as given (the
relative value, or the absolute pressure), written as Python's shortest
round-trip form of the float (``contact_area@0.05``, ``clusters@1e-05``), so
that distinct loads never share a name. Columns are QoI-major: all loads of
the first QoI in the given order, then those of the next. A single load keeps
the bare QoI names, so single-load problems and their files are unchanged.

Units of the quantities of interest
-----------------------------------
:data:`QOI_UNITS` lists the units each quantity may be reported in, its
default first (the config's defaults): ``contact_area`` and ``area_above`` in
``"percent"`` (or ``"fraction"``), ``clusters`` in ``"per_area"`` (count per
unit area, ``1 / L^2``; or ``"absolute"``, count per box), ``mean_gap`` in the
length unit (``"length"``), ``max_pressure`` in ``"pressure"``, the unit ``E*`` is given in (not a multiple
of ``E*``: with ``e_star=210`` in GPa a maximum pressure of 35.8 is 35.8 GPa). Tolerances are in the
same units. :func:`qoi_scale` is the factor from the raw value of
:func:`~rough_uq.physics.qoi.evaluate_qoi` to the unit.

Range of the loads
------------------
:func:`checked_mean_pressures` refuses, before any solve, a load whose dimensionless load ``mean_pressure *
system_size / (e_star * rms_height)`` lies outside the solver's range (within :data:`LOAD_MARGIN`), and
:func:`refuse_loads_beyond_rounding` one at which rounding alone keeps most solves from their tolerance;
:class:`~rough_uq.problem.contact.ContactProblem` applies both when it is built.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rough_uq.errors import InvalidParameterError, is_one_of, is_real_number, scalar_refusal
from rough_uq.physics.surface import SurfaceSpectrum
from rough_uq.problem.columns import LOAD_SEPARATOR, column_name, load_label

__all__ = [
    "QOI_UNITS",
    "AbsoluteLoad",
    "RelativeLoad",
    "LOAD_SEPARATOR",
    "qoi_scale",
    "load_sequence",
    "load_label",
    "column_names",
    "LOAD_MARGIN",
    "checked_mean_pressures",
    "refuse_loads_beyond_rounding",
]

#: Units each quantity of interest may be reported in; the first is the default.
QOI_UNITS: dict[str, tuple[str, ...]] = {
    "contact_area": ("percent", "fraction"),
    "clusters": ("per_area", "absolute"),
    "mean_gap": ("length",),
    "max_pressure": ("pressure",),
    "area_above": ("percent", "fraction"),
}


def qoi_scale(name: str, unit: str, *, system_size: float) -> float:
    """Factor from the raw value of QoI ``name`` to its value in ``unit``.

    Raw values are those of :func:`~rough_uq.physics.qoi.evaluate_qoi`
    (fractions, counts per box, lengths, pressures).

    Parameters
    ----------
    name : str
        A name of :data:`QOI_UNITS`.
    unit : str
        One of ``QOI_UNITS[name]``.
    system_size : float
        Box side ``L`` (for ``"per_area"``: counts are divided by ``L^2``).

    Returns
    -------
    float
    """
    if not is_one_of(name, QOI_UNITS):
        raise InvalidParameterError("qoi", name, "one of " + ", ".join(QOI_UNITS))
    if not is_one_of(unit, QOI_UNITS[name]):
        raise InvalidParameterError(f"units.{name}", unit, " or ".join(repr(u) for u in QOI_UNITS[name]))
    if unit == "percent":
        return 100.0
    if unit == "per_area":
        return 1.0 / system_size**2
    return 1.0


def positive(name: str, value: object) -> float:
    """``value`` as a float, or :class:`InvalidParameterError` naming ``name`` unless finite and > 0."""
    if not is_real_number(value) or not (math.isfinite(value) and value > 0):
        raise scalar_refusal(name, value, "a finite number > 0")
    return float(value)


def load_value(name: str, value: object) -> float:
    """A load as a float > 0 (:func:`positive`); a single- or half-precision number at its shortest decimal.

    ``numpy.float32(0.05)`` is 0.05000000074505806 as a double; taken as it is, it named its load-curve column
    ``contact_area@0.05000000074505806``, which no tolerance mapping written ``contact_area@0.05`` matched. Its
    shortest decimal (numpy's ``str``) is what the user wrote, and differs from it by at most half a unit in the
    last place of that precision (up to 6e-8 of the load for float32).
    """
    if isinstance(value, np.floating) and value.dtype.itemsize < 8 and np.isfinite(value):
        value = float(str(value))
    return positive(name, value)


@dataclass(frozen=True)
class RelativeLoad:
    """Mean pressure relative to ``E* sqrt(m2)`` (SPEC section 6).

    Parameters
    ----------
    value : float
        ``p_mean / (E* sqrt(m2))``, dimensionless, > 0 (the classic study uses 0.1).
    """

    value: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "value", load_value("load.relative", self.value))

    def mean_pressure(self, *, spectrum: SurfaceSpectrum, e_star: float) -> float:
        """The mean pressure ``value * e_star * sqrt(m2)`` (unit of ``E*``)."""
        return self.value * e_star * spectrum.rms_slope


@dataclass(frozen=True)
class AbsoluteLoad:
    """Mean pressure given directly.

    Parameters
    ----------
    value : float
        ``p_mean`` in the unit of ``E*``, > 0.
    """

    value: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "value", load_value("load.absolute", self.value))

    def mean_pressure(self, *, spectrum: SurfaceSpectrum, e_star: float) -> float:
        """The mean pressure ``value`` (unit of ``E*``); ``spectrum`` and ``e_star`` are not used."""
        return self.value


_LOAD_ALLOWED = (
    "rough_uq.RelativeLoad(value), rough_uq.AbsoluteLoad(value), or a non-empty list of distinct loads "
    "of one kind (a load curve)"
)


def load_sequence(load: object) -> tuple[RelativeLoad | AbsoluteLoad, ...]:
    """The loads of a problem: ``(load,)`` for one load, the tuple of a load curve.

    Parameters
    ----------
    load : RelativeLoad, AbsoluteLoad or sequence of them
        One load, or a load curve: a non-empty sequence of distinct loads,
        all relative or all absolute, in any order.

    Raises
    ------
    InvalidParameterError
        Naming ``load``: an empty sequence, mixed kinds, repeated values or
        anything that is not a load.
    """
    if isinstance(load, (RelativeLoad, AbsoluteLoad)):
        return (load,)
    if not isinstance(load, (list, tuple)) or not load:
        raise InvalidParameterError("load", load, _LOAD_ALLOWED)
    loads = tuple(load)
    kinds = {type(item) for item in loads}
    if len(kinds) != 1 or not kinds <= {RelativeLoad, AbsoluteLoad}:
        raise InvalidParameterError("load", load, _LOAD_ALLOWED)
    values = [item.value for item in loads]
    if len(set(values)) != len(values):
        raise InvalidParameterError("load", load, "distinct load values (each load once)")
    return loads


def column_names(qoi_names: tuple[str, ...], load_values: tuple[float, ...]) -> tuple[str, ...]:
    """Names of the result columns: ``qoi_names`` for one load, else ``<qoi>@<load>``, QoI-major.

    Parameters
    ----------
    qoi_names : tuple of str
        The quantities of interest, in order.
    load_values : tuple of float
        The loads as given (relative values or absolute pressures), in order.
    """
    if len(load_values) == 1:
        return tuple(qoi_names)
    return tuple(column_name(name, v) for name in qoi_names for v in load_values)


#: Factor kept from each end of the solver's range of the dimensionless load
#: (:data:`~rough_uq.physics.solver.MIN_DIMENSIONLESS_LOAD`, ``MAX_DIMENSIONLESS_LOAD``)
#: when a problem's loads are checked with the spectrum's nominal RMS height.
#: A solve divides by the RMS height of its own sample instead: a coarse grid
#: misses the band above its Nyquist wave number, and a draw dominated by a
#: few long-wavelength modes may be much rougher or smoother than the mean.
#: No finite margin bounds that for every draw, but 1e10 is beyond any draw
#: one will meet (even a surface of one random mode, whose variance is
#: exponentially distributed, has a variance below 1e-20 of its mean with a
#: probability of 1e-20), and it costs nothing: the range left, about
#: [2e-298, 1e15], still takes every load a solve can converge at (full
#: contact sets in below 2 pi k_s <= 2e5, and from some 1e8 times that load
#: on no solve converges; :func:`refuse_loads_beyond_rounding` refuses those).
LOAD_MARGIN = 1e10


def checked_mean_pressures(
    loads: Sequence[RelativeLoad | AbsoluteLoad], *, spectrum: SurfaceSpectrum, e_star: float, finest: int
) -> tuple[float, ...]:
    """The mean pressure of every load (unit of ``E*``), refused before any solve where a solve would refuse it.

    A solve takes a mean pressure whose total over its nodes is a finite
    float, and a dimensionless load ``mean_pressure * system_size / (e_star *
    RMS height)`` in the range of :mod:`rough_uq.physics.solver`. Checked here
    with the spectrum's nominal ``rms_height``, within :data:`LOAD_MARGIN` of
    both ends, and on the ``finest`` grid (the most nodes).

    Parameters
    ----------
    loads : sequence of RelativeLoad or AbsoluteLoad
        One load, or the loads of a load curve in their order.
    spectrum : SurfaceSpectrum
    e_star : float
        Effective modulus (finite, > 0).
    finest : int
        Nodes per side of the finest grid the problem may solve on.

    Raises
    ------
    InvalidParameterError
        Naming the load as a config does: ``load.relative`` or
        ``load.absolute``, with the position in a load curve
        (``load.relative.1``), the value, the allowed range and the
        dimensionless load it gives.
    """
    from rough_uq.physics.solver import MAX_DIMENSIONLESS_LOAD, MIN_DIMENSIONLESS_LOAD  # loads numba: not at import

    lowest, highest = MIN_DIMENSIONLESS_LOAD * LOAD_MARGIN, MAX_DIMENSIONLESS_LOAD / LOAD_MARGIN
    size, height = spectrum.system_size, spectrum.rms_height
    pressures = []
    for position, load in enumerate(loads):
        name = _load_field(load, position, len(loads))
        pressure = load.mean_pressure(spectrum=spectrum, e_star=e_star)
        if not (pressure > 0 and math.isfinite(pressure * float(finest) ** 2)):
            raise InvalidParameterError(
                name, load.value, f"a load whose mean pressure (here {pressure:.3g}, unit of E*) is a float > 0 and "
                f"whose total over the finest grid's {finest}^2 nodes is finite"
            )
        exponent = _load_exponent(pressure, spectrum, e_star)
        if not math.log10(lowest) <= exponent <= math.log10(highest):
            raise InvalidParameterError(
                name, load.value, f"a dimensionless load mean_pressure * system_size / (e_star * rms_height) in "
                f"[{lowest:.2g}, {highest:.2g}] (the solver's range within a margin of {LOAD_MARGIN:.0e} for a "
                f"sample's RMS height); here it is {_power_of_ten(exponent)} (mean_pressure = "
                f"{pressure:.3g}, system_size = {size:g}, e_star = {e_star:g}, rms_height = {height:g})"
            )
        pressures.append(pressure)
    return tuple(pressures)


def refuse_loads_beyond_rounding(
    loads: Sequence[RelativeLoad | AbsoluteLoad], pressures: Sequence[float], *, spectrum: SurfaceSpectrum,
    e_star: float, solver_tol: float,
) -> None:
    """Raise :class:`~rough_uq.errors.InvalidParameterError` for a load at which rounding keeps most solves from
    reaching ``solver_tol``: a dimensionless load (with the nominal RMS height) above
    :func:`~rough_uq.physics.solver.max_convergent_load`.

    Such a load is many orders of magnitude beyond full contact (a unit taken for another, as a rule): most
    solves would run ``max_iter`` iterations and be stored as not converged.
    """
    from rough_uq.physics.solver import max_convergent_load  # loads numba: not when the loads are imported

    limit = math.log10(max_convergent_load(solver_tol))
    for position, (load, pressure) in enumerate(zip(loads, pressures)):
        exponent = _load_exponent(pressure, spectrum, e_star)
        if exponent > limit:
            raise InvalidParameterError(
                _load_field(load, position, len(loads)), load.value,
                f"a dimensionless load mean_pressure * system_size / (e_star * rms_height) at most "
                f"{_power_of_ten(limit)} at solver tol {solver_tol:g}; here it is {_power_of_ten(exponent)}, where "
                "the rounding of the pressures (about the load) alone keeps most solves from reaching the tolerance "
                f"(full contact sets in at a load of order 2 pi k_s = {2 * math.pi * spectrum.k_s:.3g})"
            )


def _load_field(load: RelativeLoad | AbsoluteLoad, position: int, n_loads: int) -> str:
    """The config field of a load: ``load.relative``, or ``load.relative.1`` in a load curve."""
    name = "load." + ("relative" if isinstance(load, RelativeLoad) else "absolute")
    return name + (f".{position}" if n_loads > 1 else "")


def _load_exponent(pressure: float, spectrum: SurfaceSpectrum, e_star: float) -> float:
    """``log10`` of the dimensionless load ``pressure L / (E* rms_height)`` (nominal RMS height), in logarithms:
    the load itself may be beyond the float range."""
    return (math.log10(pressure) + math.log10(spectrum.system_size) - math.log10(e_star)
            - math.log10(spectrum.rms_height))


def _power_of_ten(exponent: float) -> str:
    """``10**exponent`` written with two significant digits, also beyond the float range (``3.2e+400``)."""
    whole = math.floor(exponent)
    mantissa = round(10 ** (exponent - whole), 1)
    if mantissa >= 10:
        mantissa, whole = mantissa / 10, whole + 1
    return f"{mantissa:g}e{whole:+d}"
