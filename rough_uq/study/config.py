"""The study configuration: a strict, versioned schema read from YAML.

This is the only module that reads YAML and the only one that uses pydantic.
A study file looks like (every section is a mapping; see the shipped
``rough_uq/study/configs/*.yaml``, written out by ``roughuq init NAME``)::

    schema_version: 1          # required; the only version this code reads
    seed: 2024                 # study seed (SPEC section 7)
    surface:
      system_size: 2.0         # box side L (length unit)
      wavelengths: {lambda_l: 1.0, lambda_r: 1.0, lambda_s: 0.015625}
      # ... or, instead: wavenumbers: {k_l: 2, k_r: 2, k_s: 128}
      hurst: 0.8
      rms_height: 1.0          # length unit
    material: {e_star: 1.0}    # pressure unit
    load: {relative: 0.1}      # or {absolute: <mean pressure, unit of E*>}; a list = a load curve
    qoi:
      contact_area: {unit: percent, tol: 0.5}
    grid: {coarsest: 256, max_level: 3}
    # optional sections: solver, screening, estimation, output

Units (SPEC section 7): lengths are in the unit of ``surface.system_size``,
pressures in the unit of ``material.e_star``; wave numbers are counted in
periods per box, ``k = L / lambda``.

Choices where the specification is silent
-----------------------------------------
* ``schema_version`` is *required*, so that a file written for a future
  schema is never silently read with this one's defaults.
* Required sections: ``seed``, ``surface``, ``material``, ``load``, ``qoi``,
  ``grid``. ``solver``, ``screening``, ``estimation`` and ``output`` have
  defaults for every field.
* Numbers must be finite; booleans are not accepted where a number is
  expected; duplicate YAML keys are an error; ``1e-8`` (no dot) is read as a
  number, not as the string YAML 1.1 would make of it, and ``15:25:41`` as
  text, not as the base-60 integer 55541 of YAML 1.1.
* ``grid.projection: injection`` requires the spectrum to be band limited
  below the Nyquist wave number of the coarsest grid (``k_s < n_0 / 2``); with
  content above it injection aliases and the MLMC coupling is inconsistent
  (SPEC section 3).
* The band ``k_l <= |k| <= k_s`` must contain at least one non-zero integer
  wave vector, otherwise the RMS height cannot be reached.
* Memory estimate of the finest grid: a solve holds about
  :data:`SOLVER_ARRAYS_PER_NODE` (= 20) float64 arrays of ``n x n`` (pressure,
  gap, displacement, surface, search direction, residuals, FFT work arrays and
  the warm-start guess), i.e. ``160 n^2`` bytes. It is not a validation rule
  (a cluster config must validate on a laptop): :func:`memory_warning` says,
  when samples of a level are about to be computed here, whether that many
  solves at once (one per worker) exceed this machine's physical memory.
* ``output.path`` is a plain string, relative to the working directory; a
  leading ``~`` is expanded to the home directory, as a shell would.
* ``config_hash`` hashes the spectrum as resolved wave numbers, so the same
  surface given as wavelengths or as wave numbers has the same hash, and
  keeps the order of the quantities of interest (it is the column order of
  the stored samples). It leaves out ``output``, which changes no computed
  number, and ``solver.threads``, which changes them only in their last bits
  (FFTW's threaded plans and the passes' sums split over threads round
  differently: 4e-12 to 2e-10 relative L2 in the pressure of classic samples
  at 256^2 and 512^2 with 1 and 2 threads, same contact sets, measured on
  2026-11-25), as FFT plans measured on another machine do. Keep it fixed for
  bit-identical reruns.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import re
import reprlib
import sys
from collections.abc import Hashable, Mapping, Sequence
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from rough_uq.errors import ConfigError, is_integer, is_real_number
from rough_uq.multilevel.allocation import MAX_TOL, MIN_TOL
from rough_uq.multilevel.drivers import MAX_PLANNED_SAMPLES
from rough_uq.problem.columns import column_name, column_of_load
from rough_uq.problem.memory import SOLVER_ARRAYS_PER_NODE, physical_memory_bytes, solver_memory_bytes
from rough_uq.problem.memory import memory_warning as grid_memory_warning

__all__ = [
    "sweep_configs",
    "SCHEMA_VERSION",
    "SOLVER_ARRAYS_PER_NODE",
    "QOI_NAMES",
    "Wavelengths",
    "Wavenumbers",
    "SurfaceConfig",
    "MaterialConfig",
    "LoadConfig",
    "SolverConfig",
    "ContactAreaQoi",
    "ClustersQoi",
    "MeanGapQoi",
    "MaxPressureQoi",
    "AreaAboveQoi",
    "QoiConfig",
    "GridConfig",
    "ScreeningConfig",
    "EstimationConfig",
    "DistributionConfig",
    "ThresholdGrid",
    "OutputConfig",
    "StudyConfig",
    "load_config",
    "config_from_dict",
    "config_from_stored_text",
    "resolved_yaml",
    "config_hash",
    "config_differences",
    "memory_warning",
    "solver_memory_bytes",
]

SCHEMA_VERSION = 1
"""The config schema version this code reads and writes."""

_ERROR_TYPE = "roughuq_config"


# ---------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------


def _reject_non_number(value: object) -> object:
    # pydantic's lax mode would turn `true` into 1 and the string '0.8' into
    # 0.8; a boolean or a quoted number where a number belongs is a typo (or a
    # value meant for another field), not a value.
    if isinstance(value, bool):
        raise PydanticCustomError("bool_not_number", "must be a number, not a boolean")
    if isinstance(value, str):
        # Only a string that reads as a number was (probably) quoted: `tol: abc` has no quotes to remove.
        hint = " (remove the quotes)" if _reads_as_number(value) else ""
        raise PydanticCustomError("str_not_number", "must be a number, not a string" + hint)
    return value


def _reads_as_number(text: str) -> bool:
    """Whether ``text`` is a finite number written as text (``'0.5'``, ``' 1e-7'``; not ``'abc'``, ``'nan'``)."""
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _reject_non_bool(value: object) -> object:
    # lax pydantic reads 'yes', 'off', 1 or 0 as booleans; YAML's own true/false
    # (and yes/no unquoted) are already booleans when they get here.
    if not isinstance(value, bool):
        raise PydanticCustomError("not_bool", "must be true or false")
    return value


Int = Annotated[int, BeforeValidator(_reject_non_number)]
Float = Annotated[float, BeforeValidator(_reject_non_number)]
Bool = Annotated[bool, BeforeValidator(_reject_non_bool)]


def _field(default: Any = ..., *, description: str, allowed: str, **constraints: Any) -> Any:
    """A pydantic field that also records, for error messages, what it accepts."""
    return Field(default, description=description, json_schema_extra={"allowed": allowed}, **constraints)


class _Described(str):
    """A description standing in for a value in a message; shown without quotes."""

    def __repr__(self) -> str:
        return str(self)


def _problem(field: str, what: str, value: object, allowed: str) -> dict[str, object]:
    return {"field": field, "what": what, "value": value, "allowed": allowed}


def _fail(problems: list[dict[str, object]]) -> None:
    """Raise the validation error that carries one or more field problems.

    ``field`` in each problem is relative to the model being validated;
    :func:`_format_errors` prefixes the model's location.
    """
    text = "; ".join(f"{p['field']}: {p['what']}" for p in problems)
    raise PydanticCustomError(_ERROR_TYPE, "{text}", {"text": text, "problems": problems})


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# ---------------------------------------------------------------------------
# Surface
# ---------------------------------------------------------------------------


#: The largest grid (nodes per side) of a study: ``rough_uq.problem.contact.MAX_GRID``, which
#: says why (a copy: that module loads numba and pyFFTW, which reading a config does not need;
#: tests/test_config.py checks they agree).
MAX_GRID = 65536

#: The largest short cut-off wave number: ``rough_uq.physics.surface.MAX_K_S``, half of MAX_GRID
#: (tests/test_problem_arguments.py checks they agree).
MAX_K_S = MAX_GRID // 2


class Wavelengths(_Section):
    """Spectrum cut-offs as wavelengths (length unit)."""

    lambda_l: Float = _field(
        description="Largest wavelength of the spectrum, lambda_l = L / k_l (length unit)",
        allowed="number > 0",
        gt=0,
    )
    lambda_r: Float = _field(
        description="Roll-off wavelength, lambda_r = L / k_r (length unit)",
        allowed="number > 0",
        gt=0,
    )
    lambda_s: Float = _field(
        description="Shortest wavelength (short cut-off), lambda_s = L / k_s (length unit)",
        allowed="number > 0",
        gt=0,
    )


class Wavenumbers(_Section):
    """Spectrum cut-offs as wave numbers (periods per box, dimensionless)."""

    k_l: Float = _field(
        description="Lower cut-off wave number k_l (periods per box, dimensionless; 0 = no lower cut-off)",
        allowed="number >= 0",
        ge=0,
    )
    k_r: Float = _field(
        description="Roll-off wave number k_r (periods per box, dimensionless)",
        allowed="number > 0",
        gt=0,
    )
    k_s: Float = _field(
        description="Short cut-off wave number k_s (periods per box, dimensionless)",
        allowed=f"number > 0 and <= {MAX_K_S} (half the largest grid, {MAX_GRID}, resolves no larger k_s)",
        gt=0,
        le=MAX_K_S,
    )


def _band_has_wave_vector(k_l: float, k_s: float) -> bool:
    """Whether some integer wave vector k != 0 has k_l <= |k| <= k_s."""
    slack = 1e-9 * max(1.0, k_s * k_s)
    lo2 = k_l * k_l - slack
    hi2 = k_s * k_s + slack
    for i in range(int(math.floor(k_s)) + 1):
        j_min = math.ceil(math.sqrt(max(0.0, lo2 - i * i)))
        rest = hi2 - i * i
        if rest < 0:
            break
        j_max = math.floor(math.sqrt(rest))
        if i == 0:
            j_min = max(j_min, 1)
        if j_min <= j_max:
            return True
    return False


class SurfaceConfig(_Section):
    """The random rough surface (SPEC section 3)."""

    system_size: Float = _field(
        description="Side length L of the periodic square box (length unit; defines it)",
        allowed="number > 0",
        gt=0,
    )
    wavelengths: Wavelengths | None = _field(
        None,
        description="Spectrum cut-offs as wavelengths lambda_l, lambda_r, lambda_s (length unit); "
        "give this or wavenumbers",
        allowed="a mapping with keys lambda_l, lambda_r, lambda_s",
    )
    wavenumbers: Wavenumbers | None = _field(
        None,
        description="Spectrum cut-offs as wave numbers k_l, k_r, k_s (periods per box, dimensionless); "
        "give this or wavelengths",
        allowed="a mapping with keys k_l, k_r, k_s",
    )
    hurst: Float = _field(
        description="Hurst exponent H of the self-affine part (dimensionless)",
        allowed="number in [0, 1]",
        ge=0,
        le=1,
    )
    rms_height: Float = _field(
        description="RMS height sigma of the surface (length unit)",
        allowed="number > 0",
        gt=0,
    )

    @model_validator(mode="after")
    def _check_spectrum(self) -> SurfaceConfig:
        if (self.wavelengths is None) == (self.wavenumbers is None):
            got = "both" if self.wavelengths is not None else "neither"
            _fail(
                [
                    _problem(
                        "wavelengths",
                        "give the spectrum exactly once, as wavelengths or as wavenumbers",
                        _Described(f"{got} of wavelengths and wavenumbers"),
                        "exactly one of wavelengths, wavenumbers",
                    )
                ]
            )
        k_l, k_r, k_s = self.k_l, self.k_r, self.k_s
        if not (0 <= k_l <= k_r <= k_s):
            if self.wavelengths is not None:
                w = self.wavelengths
                _fail(
                    [
                        _problem(
                            "wavelengths",
                            "cut-offs are out of order",
                            _Described(f"lambda_l={w.lambda_l:g}, lambda_r={w.lambda_r:g}, lambda_s={w.lambda_s:g}"),
                            "lambda_l >= lambda_r >= lambda_s",
                        )
                    ]
                )
            _fail(
                [
                    _problem(
                        "wavenumbers",
                        "cut-offs are out of order",
                        _Described(f"k_l={k_l:g}, k_r={k_r:g}, k_s={k_s:g}"),
                        "0 <= k_l <= k_r <= k_s",
                    )
                ]
            )
        if self.wavelengths is not None and not k_s <= MAX_K_S:
            lambda_s, smallest = self.wavelengths.lambda_s, self.system_size / MAX_K_S
            _fail([_problem("wavelengths.lambda_s", f"is shorter than system_size / {MAX_K_S} = {smallest!r}",
                            lambda_s, f"number >= system_size / {MAX_K_S} (k_s = system_size / lambda_s <= "
                            f"{MAX_K_S}: half the largest grid, {MAX_GRID}, resolves no larger k_s)")])
        if not _band_has_wave_vector(k_l, k_s):
            name = "wavelengths" if self.wavelengths is not None else "wavenumbers"
            _fail(
                [
                    _problem(
                        name,
                        "the band k_l <= |k| <= k_s contains no non-zero integer wave vector, "
                        "so the surface would be flat",
                        _Described(f"k_l={k_l:g}, k_s={k_s:g}"),
                        "a band containing some |k| = sqrt(i^2 + j^2) > 0",
                    )
                ]
            )
        return self

    @property
    def k_l(self) -> float:
        """Lower cut-off wave number (periods per box)."""
        if self.wavenumbers is not None:
            return self.wavenumbers.k_l
        assert self.wavelengths is not None  # guaranteed by the validator
        return self.system_size / self.wavelengths.lambda_l

    @property
    def k_r(self) -> float:
        """Roll-off wave number (periods per box)."""
        if self.wavenumbers is not None:
            return self.wavenumbers.k_r
        assert self.wavelengths is not None
        return self.system_size / self.wavelengths.lambda_r

    @property
    def k_s(self) -> float:
        """Short cut-off wave number (periods per box)."""
        if self.wavenumbers is not None:
            return self.wavenumbers.k_s
        assert self.wavelengths is not None
        return self.system_size / self.wavelengths.lambda_s


# ---------------------------------------------------------------------------
# Material, load, solver
# ---------------------------------------------------------------------------


class MaterialConfig(_Section):
    """The elastic half-space."""

    e_star: Float = _field(
        description="Effective (plane-strain) modulus E* = E / (1 - nu^2) (pressure unit; defines it)",
        allowed="number > 0",
        gt=0,
    )


_LOAD_ALLOWED = "number > 0, or a non-empty list of distinct numbers > 0 (a load curve)"


def _load_value(value: object) -> object:
    """A load field as given: None, a number > 0, or a load curve (a list of distinct numbers > 0).

    A one-element list is the single load itself, so ``[0.1]`` and ``0.1``
    are the same study (same resolved config, same hash, bare QoI names).
    """
    if value is None:
        return None
    # is_real_number refuses an integer beyond the floats (10**400), where math.isfinite raised OverflowError.
    is_load = lambda v: is_real_number(v) and math.isfinite(v) and v > 0  # noqa: E731
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not is_load(value):
            _fail([_problem("", "must be a finite number > 0", value, _LOAD_ALLOWED)])
        return float(value)
    if not isinstance(value, (list, tuple)):
        _fail([_problem("", "must be a number or a list of numbers", value, _LOAD_ALLOWED)])
    if not value:
        _fail([_problem("", "a load curve needs at least one load", _Described("an empty list"), _LOAD_ALLOWED)])
    problems = [
        _problem(str(i), "must be a finite number > 0", v, "number > 0")
        for i, v in enumerate(value)
        if not is_load(v)
    ]
    if problems:
        _fail(problems)
    values = [float(v) for v in value]
    repeated = sorted({v for v in values if values.count(v) > 1})
    if repeated:
        what = "each load of a load curve must be given once; repeated: " + ", ".join(f"{v:g}" for v in repeated)
        _fail([_problem("", what, list(value), _LOAD_ALLOWED)])
    return values[0] if len(values) == 1 else values


class LoadConfig(_Section):
    """The imposed mean pressure, relative to E* sqrt(m2) or absolute; one load or a load curve.

    A list of loads (e.g. ``relative: [0.01, 0.02, 0.05, 0.1]``) is a load
    curve: each surface is solved along the increasing loads with warm
    starts and every quantity of interest becomes one column per load, named
    ``<qoi>@<load>`` (``contact_area@0.05``; :mod:`rough_uq.problem.loads`),
    in the order given. A quantity's ``tol`` applies to each of its columns:
    the whole curve is estimated to that RMS error at every load. ``roughuq
    mlmc --tol NAME@LOAD=EPS`` sets one column apart.
    """

    relative: float | list[float] | None = _field(
        None,
        description=(
            "Mean pressure p_mean / (E* sqrt(m2)), m2 from the spectral model (dimensionless); "
            "a list of distinct values is a load curve"
        ),
        allowed=_LOAD_ALLOWED,
    )
    absolute: float | list[float] | None = _field(
        None,
        description="Mean pressure p_mean (pressure unit, i.e. unit of E*); a list of distinct values is a load curve",
        allowed=_LOAD_ALLOWED,
    )

    @field_validator("relative", "absolute", mode="before")
    @classmethod
    def _check_value(cls, value: object) -> object:
        return _load_value(value)

    @model_validator(mode="after")
    def _check_one(self) -> LoadConfig:
        if (self.relative is None) == (self.absolute is None):
            got = "both" if self.relative is not None else "neither"
            _fail(
                [
                    _problem(
                        "relative",
                        "give the load exactly once, as relative or as absolute",
                        _Described(f"{got} of relative and absolute"),
                        "exactly one of relative, absolute",
                    )
                ]
            )
        return self

    @property
    def kind(self) -> Literal["relative", "absolute"]:
        """Which of the two load forms was given."""
        return "relative" if self.relative is not None else "absolute"

    @property
    def value(self) -> float | tuple[float, ...]:
        """The given load (dimensionless if relative, unit of E* if absolute); a tuple for a load curve."""
        values = self.values
        return values[0] if len(values) == 1 else values

    @property
    def values(self) -> tuple[float, ...]:
        """The given loads, in order (one for a single load)."""
        value = self.relative if self.relative is not None else self.absolute
        return tuple(value) if isinstance(value, list) else (value,)  # type: ignore[arg-type]

    @property
    def n_loads(self) -> int:
        """Number of loads per surface."""
        return len(self.values)


#: The smallest solver tolerance: ``rough_uq.problem.contact.MIN_SOLVER_TOL``, which says why (a copy, as
#: MAX_GRID; tests/test_problem_arguments.py checks they agree).
MIN_SOLVER_TOL = 1e-14
#: The largest: ``rough_uq.problem.contact.MAX_SOLVER_TOL``, which says why (a copy, checked alike).
MAX_SOLVER_TOL = 1e-2

#: The most threads per solve: ``rough_uq.problem.contact.MAX_THREADS``, which says why (a copy, as MAX_GRID;
#: tests/test_problem_arguments.py checks they agree). A run on local workers also refuses more than 4 per core.
MAX_THREADS = 1024


class SolverConfig(_Section):
    """The constrained conjugate-gradient contact solver (SPEC section 2)."""

    tol: Float = _field(
        1e-7,
        description=(
            "Relative stopping tolerance of the complementarity/gap error (dimensionless). At the default 1e-7 "
            "the mean contact area moves by at most 0.0003 percentage points and the mean cluster density "
            "(4- or 8-connectivity) by at most 0.014 per unit area on the classic settings against tol 1e-10, "
            "under 1 % of the tightest classic tolerances (scripts/tolerance_study.py, README)"
        ),
        allowed=f"number in [{MIN_SOLVER_TOL:g}, {MAX_SOLVER_TOL:g}] (below it rounding stops the solver before "
        "the tolerance; above it a solve is no contact solution: at 0.1 contact areas were off by up to 30 %)",
        ge=MIN_SOLVER_TOL,
    )
    max_iter: Int = _field(
        10000,
        description="Maximum number of CG iterations per solve (count)",
        allowed="integer >= 1",
        ge=1,
    )
    warm_start: Bool = _field(
        True,
        description="Start the fine solve from the coarse solution of the same sample",
        allowed="true or false",
    )
    threads: Int = _field(
        1,
        description="FFTW and numba threads per solve (count; changes results only by rounding)",
        allowed=f"integer in 1..{MAX_THREADS}",
        ge=1,
        le=MAX_THREADS,
    )

    @field_validator("tol")
    @classmethod
    def _gives_contact_solutions(cls, value: float, info: ValidationInfo) -> float:
        # MAX_SOLVER_TOL holds for new configs; a study file's stored config from before it (any tol < 1) is
        # read as it was, so that its report and samples stay readable (its ContactProblem warns).
        if (info.context or {}).get("stored"):
            if not value < 1:
                raise PydanticCustomError("solver_tol", "must be less than 1")
        elif value > MAX_SOLVER_TOL:
            raise PydanticCustomError("solver_tol", f"must be less than or equal to {MAX_SOLVER_TOL:g}")
        return value


# ---------------------------------------------------------------------------
# Quantities of interest
# ---------------------------------------------------------------------------

_TOL_DESCRIPTION = "Target root-mean-square error of the estimate, in the unit of this quantity"
# The range every run takes (rough_uq.multilevel.allocation.MIN_TOL): errors are compared in squares.
_TOL_ALLOWED = f"number in [{MIN_TOL:g}, {MAX_TOL:g}] or null"


class _QoiSection(_Section):
    """Settings of one quantity of interest; each model declares its ``kind`` (the key in the ``qoi`` mapping)."""

    @property
    def name(self) -> str:
        """The QoI's name, its ``kind``."""
        return self.kind


class ContactAreaQoi(_QoiSection):
    """Fraction of the nominal area in contact (``p > 0``).

    ``estimator`` was added after the first schema-1 files: a config without
    it gets the corrected estimator. Study files store their resolved config;
    one stored without the key was computed with the node count and is read
    back as ``nodes`` (:func:`config_from_stored_text`).
    """

    kind: Literal["contact_area"] = Field("contact_area", exclude=True)
    unit: Literal["fraction", "percent"] = _field(
        "percent",
        description="Report as a fraction (dimensionless) or in percent",
        allowed="'fraction' or 'percent'",
    )
    estimator: Literal["corrected", "nodes"] = _field(
        "corrected",
        description="Area estimator (dimensionless fraction of nodes): 'corrected' = (N_c - c P) / N with the "
        "contact perimeter P in grid edges and c = (pi - 1 + ln 2) / 24 (Yastrebov et al. 2017; bias much "
        "smaller than the node count's), 'nodes' = N_c / N (bias proportional to the grid spacing)",
        allowed="'corrected' or 'nodes'",
    )
    tol: Float | None = _field(
        None, description=_TOL_DESCRIPTION + " (fraction or percent)", allowed=_TOL_ALLOWED, ge=MIN_TOL, le=MAX_TOL
    )

    @property
    def unit_label(self) -> str:
        """Short unit label for reports."""
        return "%" if self.unit == "percent" else "fraction"


class ClustersQoi(_QoiSection):
    """Number of connected contact patches on the periodic grid."""

    kind: Literal["clusters"] = Field("clusters", exclude=True)
    unit: Literal["absolute", "per_area"] = _field(
        "per_area",
        description="Count per box (dimensionless) or per unit area (1 / length unit^2)",
        allowed="'absolute' or 'per_area'",
    )
    connectivity: Literal[4, 8, "mean"] = _field(
        4,
        description=(
            "4: edge neighbours connect; 8: diagonal neighbours connect too; 'mean': the mean of the 4- and "
            "8-connected counts, which approach the limit from opposite sides (the classic cluster study's choice)"
        ),
        allowed="4, 8 or 'mean'",
    )
    tol: Float | None = _field(
        None, description=_TOL_DESCRIPTION + " (count or 1 / length^2)", allowed=_TOL_ALLOWED, ge=MIN_TOL, le=MAX_TOL
    )

    @property
    def unit_label(self) -> str:
        return "clusters per unit area" if self.unit == "per_area" else "clusters"


class MeanGapQoi(_QoiSection):
    """Mean gap between the surfaces over the box (length unit)."""

    kind: Literal["mean_gap"] = Field("mean_gap", exclude=True)
    tol: Float | None = _field(
        None, description=_TOL_DESCRIPTION + " (length unit)", allowed=_TOL_ALLOWED, ge=MIN_TOL, le=MAX_TOL
    )

    @property
    def unit_label(self) -> str:
        return "length"


class MaxPressureQoi(_QoiSection):
    """Largest nodal contact pressure (in the pressure unit material.e_star is given in)."""

    kind: Literal["max_pressure"] = Field("max_pressure", exclude=True)
    tol: Float | None = _field(
        None, description=_TOL_DESCRIPTION + " (the pressure unit of material.e_star)", allowed=_TOL_ALLOWED,
        ge=MIN_TOL, le=MAX_TOL,
    )

    @property
    def unit_label(self) -> str:
        # The unit e_star is given in: "E*" read as a multiple of E* (35.8 E* for 35.8 GPa at e_star 210 GPa).
        return "pressure"


class AreaAboveQoi(_QoiSection):
    """Fraction of the nominal area where the pressure exceeds a critical pressure."""

    kind: Literal["area_above"] = Field("area_above", exclude=True)
    critical_pressure: Float = _field(
        description="Critical pressure (unit of E*)",
        allowed="number > 0",
        gt=0,
    )
    unit: Literal["fraction", "percent"] = _field(
        "percent",
        description="Report as a fraction (dimensionless) or in percent",
        allowed="'fraction' or 'percent'",
    )
    tol: Float | None = _field(
        None, description=_TOL_DESCRIPTION + " (fraction or percent)", allowed=_TOL_ALLOWED, ge=MIN_TOL, le=MAX_TOL
    )

    @property
    def unit_label(self) -> str:
        return "%" if self.unit == "percent" else "fraction"


QoiConfig = Annotated[
    Union[ContactAreaQoi, ClustersQoi, MeanGapQoi, MaxPressureQoi, AreaAboveQoi],
    Field(discriminator="kind"),
]
"""Settings of one quantity of interest; the mapping key selects the model."""

_QOI_MODELS: dict[str, type[_Section]] = {
    "contact_area": ContactAreaQoi,
    "clusters": ClustersQoi,
    "mean_gap": MeanGapQoi,
    "max_pressure": MaxPressureQoi,
    "area_above": AreaAboveQoi,
}
QOI_NAMES: tuple[str, ...] = tuple(_QOI_MODELS)
"""Names of the quantities of interest a study may ask for."""


# ---------------------------------------------------------------------------
# Levels, screening, estimation, output
# ---------------------------------------------------------------------------


class GridConfig(_Section):
    """The grid hierarchy ``n_l = coarsest * 2**l``, ``l = 0..max_level``."""

    coarsest: Int = _field(
        description="Nodes per side n_0 of the coarsest grid, level 0 (count)",
        allowed="even integer >= 4",
        ge=4,
    )
    max_level: Int = _field(
        4,
        description="Finest level allowed; finest grid n_0 * 2**max_level, at most 65536 (count)",
        allowed="integer >= 0 with coarsest * 2**max_level <= 65536",
        ge=0,
    )
    projection: Literal["truncation", "injection"] = _field(
        "truncation",
        description="How a fine surface becomes the coarse one of the same sample: keep the "
        "representable Fourier coefficients (truncation) or every second node (injection)",
        allowed="'truncation' or 'injection'",
    )

    @field_validator("coarsest")
    @classmethod
    def _even(cls, value: int) -> int:
        if value % 2:
            raise PydanticCustomError("not_even", "must be even")
        return value

    @model_validator(mode="after")
    def _finest_at_most_max_grid(self) -> GridConfig:
        if self.coarsest > MAX_GRID:
            _fail([_problem("coarsest", f"larger than the largest grid, {MAX_GRID}", self.coarsest,
                            f"even integer >= 4 and <= {MAX_GRID}")])
        # The level first: coarsest * 2**max_level of a max_level such as 2**63 would never finish.
        if self.max_level > MAX_GRID.bit_length() or self.finest > MAX_GRID:
            _fail([_problem("max_level", f"makes the finest grid {self.coarsest} * 2**{self.max_level} larger than "
                            f"{MAX_GRID}", self.max_level, f"integer with coarsest * 2**max_level <= {MAX_GRID}")])
        return self

    def n_at(self, level: int) -> int:
        """Nodes per side of the grid of ``level``."""
        return self.coarsest * 2**level

    @property
    def finest(self) -> int:
        """Nodes per side of the finest allowed grid."""
        return self.n_at(self.max_level)


#: Fewest levels a screening covers: ``rough_uq.problem.runs.MIN_SCREENED_LEVELS``, which says why (a copy, as
#: MAX_GRID; tests/test_config.py checks they agree).
MIN_SCREENED_LEVELS = 3


class ScreeningConfig(_Section):
    """The screening phase that fits the rates alpha, beta, gamma."""

    levels: Int = _field(
        3,
        description="Number of levels screened, 0..levels-1, at least 3: the rates are fitted on levels >= 1, two "
        "of them at least; a study with grid.max_level < 2 cannot be screened (count)",
        allowed="integer >= 3 (the rates are fitted on levels 1..levels-1, two at least) and <= grid.max_level + 1",
        ge=MIN_SCREENED_LEVELS,
    )
    samples: Int = _field(
        20,
        description="Samples per screened level (count)",
        allowed="integer >= 2",
        ge=2,
    )


#: The most thresholds of a grid: ``roughuq --thresholds`` takes as many (``rough_uq.cli.MAX_THRESHOLDS``, a copy:
#: the command line loads no pydantic before it needs to; tests/test_config.py checks they agree).
MAX_THRESHOLDS = 10_000


class ThresholdGrid(_Section):
    """Equally spaced thresholds ``s_j`` of a distribution function, in the QoI's unit."""

    start: Float = _field(description="First threshold (the QoI's unit)", allowed="a number < stop")
    stop: Float = _field(description="Last threshold (the QoI's unit)", allowed="a number > start")
    count: Int = _field(
        description=f"Number of thresholds, ends included, at most {MAX_THRESHOLDS} as for --thresholds (count)",
        allowed="integer in 2..10000",
        ge=2,
        le=MAX_THRESHOLDS,
    )

    @model_validator(mode="after")
    def _increasing(self) -> ThresholdGrid:
        if not self.stop > self.start:
            _fail([_problem("stop", "must be larger than start", self.stop, f"a number > start = {self.start:g}")])
        problem = self._float_problem()
        if problem is not None:
            _fail([problem])
        return self

    def _float_problem(self) -> dict[str, object] | None:
        """Why floats cannot hold these thresholds (a span beyond them, neighbours that round to one), or None."""
        # -1e308..1e308 passed validate and the run said "--thresholds: got None" (the span overflowed).
        if not math.isfinite(self.stop - self.start):
            return _problem("stop", "is too far from start: stop - start exceeds the largest float", self.stop,
                            f"a number with stop - start <= {sys.float_info.max:.3g}")
        values = self.values()
        if any(later <= earlier for earlier, later in zip(values, values[1:])):
            return _problem("count", f"{self.count} thresholds from {self.start:g} to {self.stop:g} are not "
                            "distinct numbers (neighbours round to one float)", self.count,
                            "fewer thresholds, or a wider range")
        return None

    def values(self) -> list[float]:
        """The thresholds, ``count`` values from ``start`` to ``stop`` (the QoI's unit)."""
        step = (self.stop - self.start) / (self.count - 1)
        return [self.start + j * step for j in range(self.count - 1)] + [self.stop]


class DistributionConfig(_Section):
    """Settings of ``roughuq mlmc --tol-cdf`` for one QoI: where the CDF is estimated and which quantiles."""

    thresholds: ThresholdGrid | None = _field(
        None,
        description="Grid of values s where F(s) = P(Q <= s) is estimated (the QoI's unit); it must bracket "
        "the quantiles, with a spacing well below their error bars; null = give --thresholds",
        allowed="a mapping with keys start, stop, count, or null",
    )
    probabilities: tuple[Float, ...] = _field(
        (0.05, 0.5, 0.95),
        description="Probabilities p of the quantiles q_p reported (dimensionless)",
        allowed="a non-empty list of distinct numbers in (0, 1)",
        min_length=1,
    )

    @field_validator("probabilities")
    @classmethod
    def _in_unit_interval(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if not all(0 < p < 1 for p in value) or len(set(value)) != len(value):
            raise PydanticCustomError("probabilities", "must be distinct numbers strictly between 0 and 1")
        return value


class EstimationConfig(_Section):
    """The estimation runs (SPEC section 5)."""

    theta: Float = _field(
        0.5,
        description="Share of eps^2 given to the squared bias (dimensionless)",
        allowed="number in (0, 1)",
        gt=0,
        lt=1,
    )
    max_cost: Float | None = _field(
        None,
        description=(
            "Budget of modelled cost per run (reference seconds, about CPU-seconds on the calibration machine); "
            "null = no budget"
        ),
        allowed="number > 0 or null",
        gt=0,
    )
    initial_samples: Int = _field(
        10,
        description=(
            "Samples per level before the first variance update in runs without a screening (mc --level, "
            "mlmc --tol-var and --tol-cdf; count; more of them steady the bias test of the latter two); "
            "runs started from a screening need only 2 per level"
        ),
        allowed=f"integer in 2..{MAX_PLANNED_SAMPLES} (runs of several levels allow fewer: at most "
        f"{MAX_PLANNED_SAMPLES:,} samples in all)",
        ge=2,
        le=MAX_PLANNED_SAMPLES,
    )
    batch_size: Int = _field(
        10,
        description="Samples computed and stored together (count); a run draws all a level misses before its next "
        "plan, so the size changes no result (but a max_cost budget cuts a round short)",
        allowed="integer >= 1",
        ge=1,
    )
    richardson: Bool = _field(
        False,
        description="MLMC: Richardson-extrapolate the finest level, w = 2^alpha / (2^alpha - 1), where the "
        "level means decay with stable ratios; refused with a message (plain MLMC) where they do not",
        allowed="true or false",
    )
    distribution: dict[str, DistributionConfig] = _field(
        {},
        description="Per QoI name, the thresholds and quantile probabilities of `roughuq mlmc --tol-cdf` runs; "
        "with a load curve also per column (`contact_area@0.1`), whose settings take precedence over its QoI's",
        allowed="a mapping of QoI names of the qoi section (or load-curve columns) to {thresholds, probabilities}",
    )


#: C0 and C1 controls (0x9b starts an escape sequence as 0x1b [ does) and the text-direction controls (U+202E
#: showed "results\u202e5h.txt" as "resultstxt.h5").
_CONTROL_CHARACTER = re.compile(r"[\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]")


class OutputConfig(_Section):
    """Where the study file goes."""

    path: str = _field(
        "results.h5",
        description="Study file (HDF5), relative to the working directory; a leading ~ is the home directory",
        allowed="a non-empty file path (no control characters)",
        min_length=1,
    )

    @field_validator("path")
    @classmethod
    def _names_a_file(cls, value: str) -> str:
        # '.', 'runs/' or 'a/..' name a directory whatever the disk holds: `screen` said only ". is not a file".
        if value.endswith(("/", os.sep)) or os.path.basename(value) in (".", ".."):
            raise PydanticCustomError("not_a_file_name", "names a directory, not a file")
        if "\0" in value:
            # No file system takes it: `screen` ended in "ValueError: embedded null byte".
            raise PydanticCustomError("not_a_file_name", "contains a NUL character, which no file name can")
        control = _CONTROL_CHARACTER.search(value)
        if control is not None:
            # "a\e[31mb.h5" was shown as "ab.h5" by `validate` (the terminal ate the escape) and written as typed.
            raise PydanticCustomError("not_a_file_name", f"contains the control character {control.group()!r}, "
                                      "which a terminal does not show as written")
        # `~/runs/x.h5` created a directory named `~` in the working directory: only a shell expands it.
        return os.path.expanduser(value)


# ---------------------------------------------------------------------------
# The study
# ---------------------------------------------------------------------------


def machine_memory_bytes() -> int | None:
    """This machine's physical memory (a name of this module, which the tests replace to stand in for one)."""
    return physical_memory_bytes()


def memory_warning(
    config: StudyConfig, level: int, n_workers: int = 1, *, lower_with: str = "a smaller grid.max_level",
    least_level: int = 0,
) -> str | None:
    """What to say before computing samples of ``level`` on this machine, or None if they fit.

    ``n_workers`` solves run at once, each needing about
    :func:`solver_memory_bytes` of the level's grid. If together they need
    more than this machine's physical memory (unknown: no warning), the
    returned line names the grid, the estimate, the machine's memory and
    what to change: fewer workers if one solve fits, else a lower level (or
    another machine); ``lower_with`` says how the caller's command gets to a
    lower level, ``least_level`` the lowest it can stay at
    (:func:`rough_uq.problem.memory.memory_warning`).
    """
    grids = [config.grid.n_at(lv) for lv in range(level + 1)]
    return grid_memory_warning(grids, level, n_workers, machine_memory_bytes(), lower_with=lower_with,
                               workers="--workers {}", smaller_coarsest="a smaller grid.coarsest",
                               least_level=least_level)


class StudyConfig(_Section):
    """A complete study. Frozen; build it with :func:`load_config` or :func:`config_from_dict`."""

    schema_version: Annotated[Literal[1], BeforeValidator(_reject_non_number)] = _field(
        description="Version of this config schema", allowed="1"
    )
    seed: Int = _field(
        description="Study seed of all random streams (SPEC section 7)",
        allowed="integer >= 0",
        ge=0,
    )
    surface: SurfaceConfig = _field(description="Random rough surface", allowed="a mapping")
    material: MaterialConfig = _field(description="Elastic half-space", allowed="a mapping")
    load: LoadConfig = _field(description="Mean pressure", allowed="a mapping")
    solver: SolverConfig = _field(SolverConfig(), description="Contact solver", allowed="a mapping")
    qoi: dict[str, QoiConfig] = _field(
        description="Quantities of interest, name -> settings; the order is the column order",
        allowed="a mapping of " + ", ".join(QOI_NAMES) + " to settings",
    )
    grid: GridConfig = _field(description="Grid hierarchy", allowed="a mapping")
    screening: ScreeningConfig = _field(ScreeningConfig(), description="Screening phase", allowed="a mapping")
    estimation: EstimationConfig = _field(
        EstimationConfig(), description="Estimation runs", allowed="a mapping"
    )
    output: OutputConfig = _field(OutputConfig(), description="Output files", allowed="a mapping")

    @field_validator("qoi", mode="before")
    @classmethod
    def _tag_qoi(cls, value: object) -> object:
        # The mapping key names the quantity; copy it into the settings as the
        # union's tag so pydantic picks the right model (and keeps key order).
        if not isinstance(value, Mapping):
            return value
        if not value:
            _fail([_problem("", "at least one quantity of interest is needed", {}, ", ".join(QOI_NAMES))])
        problems = []
        tagged: dict[object, object] = {}
        for name, settings in value.items():
            if name not in _QOI_MODELS:
                problems.append(_problem(str(name), "unknown quantity of interest", name, ", ".join(QOI_NAMES)))
                continue
            if settings is None:
                settings = {}
            if isinstance(settings, Mapping):
                if "kind" in settings:
                    allowed = _keys_of(_QOI_MODELS[name])
                    problems.append(_problem(f"{name}.kind", "unknown key", settings["kind"], allowed))
                    continue
                settings = {"kind": name, **settings}
            tagged[name] = settings
        if problems:
            _fail(problems)
        return tagged

    @model_validator(mode="after")
    def _cross_checks(self) -> StudyConfig:
        problems = []
        n_0 = self.grid.coarsest
        k_r, k_s = self.surface.k_r, self.surface.k_s
        if not k_r < n_0 / 2:
            needed = 2 * (math.floor(k_r) + 1)
            problems.append(
                _problem(
                    "grid.coarsest",
                    f"a {n_0} x {n_0} grid cannot resolve the roll-off wave number k_r = {k_r:g} "
                    f"periods per box: its Nyquist wave number is n_0/2 = {n_0 // 2}",
                    n_0,
                    f"even integer > 2 k_r, i.e. >= {needed}",
                )
            )
        if self.grid.projection == "injection" and not k_s < n_0 / 2:
            problems.append(
                _problem(
                    "grid.projection",
                    f"injection needs a spectrum band limited below the coarsest grid's Nyquist wave "
                    f"number n_0/2 = {n_0 // 2}, but k_s = {k_s:g}; injection would alias",
                    "injection",
                    f"'truncation', or injection with k_s < {n_0 // 2}",
                )
            )
        # A study too shallow to be screened at all stays valid for the runs that need no screening
        # (mlmc --tol-var / --tol-cdf, mc --level); `roughuq screen` refuses it, naming grid.max_level.
        is_screenable = self.grid.max_level + 1 >= MIN_SCREENED_LEVELS
        if is_screenable and self.screening.levels > self.grid.max_level + 1:
            problems.append(
                _problem(
                    "screening.levels",
                    f"cannot screen more levels than exist (levels 0..{self.grid.max_level})",
                    self.screening.levels,
                    f"integer >= {MIN_SCREENED_LEVELS} and <= grid.max_level + 1 = {self.grid.max_level + 1}",
                )
            )
        n_screened = self.screening.samples * self.screening.levels
        levels_fit = self.screening.levels <= self.grid.max_level + 1  # else that is the one error to show
        if is_screenable and levels_fit and n_screened > MAX_PLANNED_SAMPLES:
            # `screen` accepted 10^11 and failed allocating its progress (745 GiB), or began 6e7 solves.
            problems.append(
                _problem(
                    "screening.samples",
                    f"a screening of {n_screened:,} samples ({self.screening.levels} levels) exceeds the "
                    f"{MAX_PLANNED_SAMPLES:,} samples any run may plan",
                    self.screening.samples,
                    f"integer in 2..{MAX_PLANNED_SAMPLES // self.screening.levels}",
                )
            )
        problems += self._distribution_key_problems()
        if problems:
            _fail(problems)
        return self

    def _distribution_key_problems(self) -> list[dict[str, object]]:
        """Keys of ``estimation.distribution`` that name no QoI and no load column, or a load column twice."""
        problems: list[dict[str, object]] = []
        columns = self.qoi_names if len(self.load.values) > 1 else ()
        first: dict[str, str] = {}  # load column -> its first key (contact_area@0.1 and @0.10 name one)
        for name in self.estimation.distribution:
            column = column_of_load(name, columns)
            if name in self.qoi:
                continue
            if column not in columns:
                allowed = f"a QoI of the qoi section: {', '.join(self.qoi)}"
                allowed += f"; or one load's column: {', '.join(columns)}" if columns else ""
                what = "not a QoI or load column of this study" if columns else "not a QoI of this study"
                problems.append(_problem(f"estimation.distribution.{name}", what, name, allowed))
            elif column in first:
                problems.append(_problem(f"estimation.distribution.{name}", f"a second key for {column}", name,
                                         f"one key per column ({first[column]} is the first)"))
            else:
                first[column] = name
        return problems

    @property
    def qoi_names(self) -> tuple[str, ...]:
        """Names of the result columns, in order: the quantities of interest, or with a load curve
        ``<qoi>@<load>`` for each quantity and load, QoI-major (:class:`LoadConfig`)."""
        return tuple(column for column, _, _ in self.qoi_columns)

    @property
    def qoi_columns(self) -> tuple[tuple[str, str, Any], ...]:
        """``(column name, QoI name, QoI settings)`` of every result column, in column order."""
        values = self.load.values
        if len(values) == 1:
            return tuple((name, name, settings) for name, settings in self.qoi.items())
        return tuple(
            (column_name(name, value), name, settings)
            for name, settings in self.qoi.items()
            for value in values
        )


# ---------------------------------------------------------------------------
# Error messages
# ---------------------------------------------------------------------------


def _keys_of(model: type[BaseModel]) -> str:
    return ", ".join(name for name, info in model.model_fields.items() if not info.exclude)


_NOTHING = object()  # the "value" of a missing field


#: The repr of a refused value, bounded before it is cut to 80 characters: nested YAML aliases under an unknown key
#: (a 3.7 KB file) expand to 10^8 elements, whose full repr took minutes.
_SHORT_REPR = reprlib.Repr()
_SHORT_REPR.maxlevel, _SHORT_REPR.maxlist, _SHORT_REPR.maxdict, _SHORT_REPR.maxstring = 3, 8, 8, 80
_SHORT_REPR.maxlong, _SHORT_REPR.maxother = 80, 80


def _show(value: object) -> str:
    if value is _NOTHING:
        return "nothing"
    text = _SHORT_REPR.repr(value)
    if isinstance(value, Mapping):
        text = "a mapping " + text
    elif isinstance(value, list):
        text = "a list " + text
    return text if len(text) <= 80 else text[:77] + "..."


def _model_of(annotation: object) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()) or ():
        found = _model_of(arg)
        if found is not None:
            return found
    return None


_QOI_MAPPING = object()  # marks the qoi mapping while walking a location


@dataclass(frozen=True)
class _NamedSections:
    """Marks a mapping of names to ``section`` models (``estimation.distribution``) while walking a location."""

    section: type[BaseModel] | None


def _walk(loc: tuple[str, ...]) -> tuple[type[BaseModel] | None, Any]:
    """The model that holds the last element of ``loc``, and its FieldInfo (None if not a field)."""
    model: Any = StudyConfig
    for depth, part in enumerate(loc):
        is_last = depth == len(loc) - 1
        if model is None:
            return None, None
        if model is _QOI_MAPPING:
            model = _QOI_MODELS.get(part)
            if is_last:
                return None, None
            continue
        if isinstance(model, _NamedSections):
            model = model.section
            if is_last:
                return None, None
            continue
        info = model.model_fields.get(part)
        if info is None or info.exclude:
            return (model if is_last else None), None
        if is_last:
            return model, info
        if model is StudyConfig and part == "qoi":
            model = _QOI_MAPPING
        elif typing.get_origin(info.annotation) is dict:
            # A mapping of names to sections (estimation.distribution): skip the name.
            model = _NamedSections(_model_of(info.annotation))
        else:
            model = _model_of(info.annotation)
    return model, None


def _allowed(loc: tuple[str, ...]) -> str:
    parent, info = _walk(loc)
    if info is not None:
        extra = info.json_schema_extra or {}
        allowed = str(extra.get("allowed", "see the documentation"))
        section = _model_of(info.annotation)
        if section is not None and allowed == "a mapping":
            allowed = f"a mapping with keys {_keys_of(section)}"
        return allowed
    if loc and loc[0] == "qoi" and len(loc) == 2:
        model = _QOI_MODELS.get(loc[1])
        return f"a mapping with keys {_keys_of(model)}" if model else ", ".join(QOI_NAMES)
    if parent is not None:
        return f"keys {_keys_of(parent)}"
    if len(loc) > 1 and loc[-1].isdigit():  # an element of a list: what the list allows
        return _allowed(loc[:-1])
    _, holder = _walk(loc[:-1])
    if holder is not None and typing.get_origin(holder.annotation) is dict and _model_of(holder.annotation):
        # A named section of a mapping (estimation.distribution.<qoi>) said "see the documentation".
        return f"a mapping with keys {_keys_of(_model_of(holder.annotation))}"
    return "see the documentation"


def _clean_loc(loc: tuple[object, ...]) -> tuple[str, ...]:
    parts = tuple(str(p) for p in loc)
    # A discriminated union repeats the tag: ('qoi', 'clusters', 'clusters', ...).
    if len(parts) >= 3 and parts[0] == "qoi" and parts[1] == parts[2]:
        parts = parts[:2] + parts[3:]
    return parts


#: pydantic's bound errors: the key of the bound in the error's context and the words for it.
_BOUNDS = {
    "greater_than": ("gt", "greater than"),
    "greater_than_equal": ("ge", "greater than or equal to"),
    "less_than": ("lt", "less than"),
    "less_than_equal": ("le", "less than or equal to"),
}


def _number_text(value: object) -> str:
    """A bound as the user would write it: ``1e-14``, ``0.5``, ``10000`` (pydantic writes 0.00000000000001)."""
    if isinstance(value, float):
        return f"{value:.12g}"
    return str(value)


#: pydantic's own wording, in a config message's words ("valid tuple" is no word of a YAML file; "unable to
#: parse input string" was said of the number 1e29 in an integer field).
_PYDANTIC_WORDS = {
    "int_type": "must be an integer",
    "int_from_float": "must be an integer, not a number with a fractional part",
    "int_parsing_size": "is far beyond any integer allowed here",
    "float_type": "must be a number",
    "string_type": "must be text",
    "tuple_type": "must be a list",
    "list_type": "must be a list",
    "too_short": "must not be empty",  # every list field has min_length 1
}


def _pydantic_what(item: Mapping[str, Any]) -> str:
    """What is wrong, in the words of a config message, for one of pydantic's own errors."""
    if item["type"] in _PYDANTIC_WORDS:
        return _PYDANTIC_WORDS[item["type"]]
    bound = _BOUNDS.get(item["type"])
    context = item.get("ctx") or {}
    if bound is not None and bound[0] in context:
        return f"must be {bound[1]} {_number_text(context[bound[0]])}"
    msg = item["msg"]
    what = "must be " + msg[len("Input should be ") :] if msg.startswith("Input should be ") else msg
    return what[:1].lower() + what[1:]


def _format_errors(error: ValidationError) -> list[str]:
    lines: list[str] = []
    for item in error.errors(include_url=False):
        loc = _clean_loc(item["loc"])
        kind = item["type"]
        if kind == _ERROR_TYPE:
            for problem in item["ctx"]["problems"]:
                path = ".".join(p for p in (*loc, str(problem["field"])) if p)
                lines.append(
                    f"{path or 'config'}: {problem['what']} (got {_show(problem['value'])}; "
                    f"allowed: {problem['allowed']})"
                )
            continue
        path = ".".join(loc) or "config"
        value = item.get("input")
        if kind == "missing":
            _, info = _walk(loc)
            is_section = info is not None and _model_of(info.annotation) is not None
            what = "required section is missing" if is_section else "required field is missing"
            value = _NOTHING
        elif kind == "extra_forbidden":
            what = "unknown key"
        elif kind in ("model_type", "model_attributes_type", "dict_type"):
            what = "must be a mapping"
        else:
            what = _pydantic_what(item)
        lines.append(f"{path}: {what} (got {_show(value)}; allowed: {_allowed(loc)})")
    return lines


# ---------------------------------------------------------------------------
# YAML
# ---------------------------------------------------------------------------


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML loader that rejects duplicate keys, reads 1e-8 as a float and 1:30 as text."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[object] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, Hashable):
                # A complex key (`? [a, b]`) was a TypeError from `key in seen`: no field is named so.
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark, f"found a {type(key).__name__} as a key; "
                    "keys are field names", key_node.start_mark
                )
            if isinstance(key, bool):
                # `yes: 1` was "1: keys should be strings (got True; ...)": neither the key nor its line.
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark, f"found the key {key_node.value}, which YAML reads "
                    f"as {str(key).lower()}; keys are field names", key_node.start_mark
                )
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark, f"found duplicate key {key!r}", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        # YAML 1.1 reads 012345 as the octal 5349 (`seed: 012345` drew another surface, without a word; YAML 1.2
        # reads it as 12345): a leading zero is refused, with the line.
        text = self.construct_scalar(node).replace("_", "")
        if re.fullmatch(r"[-+]?0[0-7]+", text):
            octal = super().construct_yaml_int(node)
            raise yaml.constructor.ConstructorError(
                None, None, f"found {node.value}, which YAML reads as an octal number ({octal}); write it without the "
                "leading zero (or as 0x... for hexadecimal)", node.start_mark
            )
        return super().construct_yaml_int(node)


_INT_TAG, _FLOAT_TAG = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
# YAML 1.1 reads `15:25:41` as the base-60 integer 55541 (and `1:30.5` as a float): a threshold grid written as
# --thresholds takes it read "thresholds: must be a mapping (got 55541)". The numbers stay YAML 1.1's otherwise
# (binary and hexadecimal integers, `_` separators, .inf and .nan; an octal 012 is refused,
# _StrictLoader.construct_yaml_int): only a colon now makes text.
_StrictLoader.add_constructor(_INT_TAG, _StrictLoader.construct_yaml_int)
_StrictLoader.yaml_implicit_resolvers = {
    first: [(tag, pattern) for tag, pattern in resolvers if tag not in (_INT_TAG, _FLOAT_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_StrictLoader.add_implicit_resolver(
    _INT_TAG,
    re.compile(r"^[-+]?(?:0b[01_]+|0x[0-9a-fA-F_]+|0[0-7_]+|0|[1-9][0-9_]*)$"),
    list("-+0123456789"),
)
_StrictLoader.add_implicit_resolver(
    _FLOAT_TAG,
    re.compile(r"^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+][0-9]+)?|\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?"
               r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."),
)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _yaml_error_line(path: str, error: yaml.YAMLError) -> str:
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{path}: not valid YAML{where}: {problem} (got a malformed file; allowed: a YAML mapping of sections)"


#: The largest config file read (a shipped config has some 3 kB; the cap keeps ``/dev/zero`` from
#: filling the memory).
MAX_CONFIG_BYTES = 2**20

#: The first bytes of an HDF5 file (a study file given where a config is expected).
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def load_config(path: str | os.PathLike[str]) -> StudyConfig:
    """Read and validate a study config file.

    Parameters
    ----------
    path : str or path-like
        The YAML file.

    Returns
    -------
    StudyConfig

    Raises
    ------
    ConfigError
        For a missing, unreadable, empty or malformed file and for every
        invalid field; the message has one line per problem,
        ``<file>: <field.path>: <what is wrong> (got <value>; allowed: <what>)``.
    """
    name = os.fspath(path)
    if not name:  # it said ": config file not found"
        raise _config_error(["config file: got ''; allowed: a non-empty path of a YAML file"])
    try:
        with open(name, "rb") as stream:
            head = stream.read(len(_HDF5_SIGNATURE))  # not the whole of a study file of gigabytes
            if head == _HDF5_SIGNATURE:
                raise _config_error([f"{name}: is an HDF5 file (a study file?), not a YAML config (got {name!r}; "
                                     "allowed: a YAML config file; a study file goes to --study, or to `roughuq "
                                     "report`)"])
            rest = stream.read(MAX_CONFIG_BYTES + 1 - len(head))  # not all of /dev/zero either
            if len(head) + len(rest) > MAX_CONFIG_BYTES:
                raise _config_error([f"{name}: larger than {MAX_CONFIG_BYTES // 2**20} MiB (got {name!r}; allowed: a "
                                     f"YAML config file of at most {MAX_CONFIG_BYTES} bytes)"])
            text = (head + rest).decode("utf-8")
    except FileNotFoundError:
        raise _config_error([f"{name}: config file not found (got {name!r}; allowed: an existing YAML file)"]) from None
    except IsADirectoryError:
        raise _config_error([f"{name}: is a directory (got {name!r}; allowed: a YAML file)"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        line = f"{name}: cannot be read: {exc} (got {name!r}; allowed: a readable UTF-8 YAML file)"
        raise _config_error([line]) from None
    try:
        return config_from_yaml_text(text, source=name)
    except ConfigError as error:
        # Each problem names the file: `roughuq screen a.yaml` in a loop over configs said which field, not where.
        lines = [line if line.startswith(f"{name}: ") else f"{name}: {line}" for line in error.problems]
        raise _config_error(lines) from None


def config_from_stored_text(text: str, *, source: str = "config") -> StudyConfig:
    """Parse the resolved config stored in a study file, as the code that wrote it meant it.

    Like :func:`config_from_yaml_text`, except that a ``qoi.contact_area``
    without ``estimator`` gets ``nodes``: a resolved config lists every field,
    so a stored one without the key was written before the corrected estimator
    existed, and its samples are node counts. A ``screening.levels`` below
    :data:`MIN_SCREENED_LEVELS` (2 was allowed before) is read as 3: such a
    screening never finished (the rates cannot be fitted on one level >= 1),
    and the screening section is not in the config hash.
    """
    data = _parsed_yaml(text, source)
    if isinstance(data, dict) and isinstance(data.get("qoi"), dict):
        area = data["qoi"].get("contact_area")
        if isinstance(area, dict) and "estimator" not in area:
            data["qoi"]["contact_area"] = {**area, "estimator": "nodes"}
    screening = data.get("screening") if isinstance(data, dict) else None
    if isinstance(screening, dict) and screening.get("levels") == MIN_SCREENED_LEVELS - 1:
        data["screening"] = {**screening, "levels": MIN_SCREENED_LEVELS}
    _accept_stored_forms(data)
    if data is None:
        raise _config_error([f"{source}: the file is empty (got no content; allowed: a YAML mapping of sections)"])
    return config_from_dict(data, source=source, stored=True)


def _accept_stored_forms(data: object) -> None:
    """Make values a study file may hold from before a rule was added read as the runs took them.

    ``estimation.initial_samples`` above :data:`MAX_PLANNED_SAMPLES` is read as that maximum (no run could draw
    more: they refused it), a threshold grid floats cannot hold as none (every cdf run on it failed), and an
    ``output.path`` with control characters with them escaped (it is shown, never opened, once the study exists):
    none of them is in the config hash.
    """
    estimation = data.get("estimation") if isinstance(data, dict) else None
    initial = estimation.get("initial_samples") if isinstance(estimation, dict) else None
    if is_integer(initial) and initial > MAX_PLANNED_SAMPLES:
        estimation["initial_samples"] = MAX_PLANNED_SAMPLES
    distribution = estimation.get("distribution") if isinstance(estimation, dict) else None
    for settings in distribution.values() if isinstance(distribution, dict) else ():
        if isinstance(settings, dict) and _is_unusable_grid(settings.get("thresholds")):
            settings["thresholds"] = None  # every cdf run on it failed; runs now ask for --thresholds
    output = data.get("output") if isinstance(data, dict) else None
    path = output.get("path") if isinstance(output, dict) else None
    if isinstance(path, str):
        output["path"] = _CONTROL_CHARACTER.sub(lambda match: match.group().encode("unicode_escape").decode(), path)


def _is_unusable_grid(grid: object) -> bool:
    """Whether ``grid`` is a threshold grid of numbers that floats cannot hold (:class:`ThresholdGrid`)."""
    if not isinstance(grid, dict) or not all(is_real_number(grid.get(key)) for key in ("start", "stop", "count")):
        return False
    start, stop, count = grid["start"], grid["stop"], grid["count"]
    if not (is_integer(count) and 2 <= count <= MAX_THRESHOLDS and math.isfinite(start) and math.isfinite(stop)
            and start < stop):
        return False
    return ThresholdGrid.model_construct(start=float(start), stop=float(stop), count=count)._float_problem() is not None


def config_from_yaml_text(text: str, *, source: str = "config") -> StudyConfig:
    """Parse and validate a config given as YAML text (e.g. the copy stored in a study file).

    ``source`` names the input in messages. Raises :class:`ConfigError` like
    :func:`load_config`.
    """
    data = _parsed_yaml(text, source)
    if data is None:
        raise _config_error([f"{source}: the file is empty (got no content; allowed: a YAML mapping of sections)"])
    return config_from_dict(data, source=source)


def _parsed_yaml(text: str, source: str) -> object:
    """The data of YAML ``text``; a malformed or too deeply nested text is a :class:`ConfigError`."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - _StrictLoader is a SafeLoader
    except yaml.YAMLError as exc:
        raise _config_error([_yaml_error_line(source, exc)]) from None
    except RecursionError:
        # PyYAML's parser recurses once per level of nesting: '[' * 5000 was a traceback.
        raise _config_error([f"{source}: not valid YAML: nested too deeply for the parser (got a malformed file; "
                             "allowed: a YAML mapping of sections)"]) from None


def _config_error(lines: list[str]) -> ConfigError:
    error = ConfigError("\n".join(lines))
    error.problems = tuple(lines)  # type: ignore[attr-defined]
    return error


def config_from_dict(data: object, *, source: str = "config", stored: bool = False) -> StudyConfig:
    """Validate an already-parsed config (a mapping of sections).

    ``source`` names the input in the message when the top level is not a mapping; ``stored`` reads a study
    file's stored config by the rules it was written under where a rule was tightened since (``solver.tol``).
    Raises :class:`ConfigError` like :func:`load_config`.
    """
    if not isinstance(data, Mapping):
        raise _config_error(
            [
                f"{source}: the top level must be a mapping of sections (got {_show(data)}; "
                f"allowed: a mapping with keys {_keys_of(StudyConfig)})"
            ]
        )
    try:
        return StudyConfig.model_validate(dict(data), context={"stored": stored})
    except ValidationError as exc:
        raise _config_error(_format_errors(exc)) from None


# ---------------------------------------------------------------------------
# Serialisation and hashing
# ---------------------------------------------------------------------------


def _resolved_dict(config: StudyConfig) -> dict[str, Any]:
    data = config.model_dump(mode="json")
    surface = data["surface"]
    for key in ("wavelengths", "wavenumbers"):
        if surface[key] is None:
            del surface[key]
    for key in ("relative", "absolute"):
        if data["load"][key] is None:
            del data["load"][key]
    return data


def resolved_yaml(config: StudyConfig) -> str:
    """The full config with every default filled in, as YAML text.

    Keys are in schema order (quantities of interest in the order given); of
    the two alternative spectrum and load forms only the given one appears.
    Loading the text gives back an equal config.
    """
    return yaml.safe_dump(_resolved_dict(config), sort_keys=False, default_flow_style=False, allow_unicode=True)


def config_hash(config: StudyConfig) -> str:
    """SHA-256 (hex) of everything in the config that affects computed numbers.

    The hashed document is the resolved config without what only steers a
    run and leaves every stored sample valid: ``output``, ``solver.threads``,
    the ``estimation`` and ``screening`` sections (screening more levels or
    samples only adds samples) and each quantity's ``tol`` (tolerances are
    per run; ``roughuq mlmc --tol`` overrides them anyway). The spectrum is
    replaced by its resolved wave numbers ``{k_l, k_r, k_s}``, and the
    quantities of interest become a list of ``[name, settings]`` pairs (their
    order is the column order), serialised as JSON with sorted keys and no
    whitespace.
    """
    data = _hashed_settings(config)
    data["qoi"] = [[name, settings] for name, settings in data["qoi"].items()]
    canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def _hashed_settings(config: StudyConfig) -> dict[str, Any]:
    """What :func:`config_hash` hashes, with the quantities of interest still a mapping (in column order)."""
    data = _resolved_dict(config)
    del data["output"]
    del data["solver"]["threads"]
    del data["estimation"]
    del data["screening"]
    for settings in data["qoi"].values():
        settings.pop("tol", None)
    surface = data["surface"]
    surface.pop("wavelengths", None)
    surface["wavenumbers"] = {"k_l": config.surface.k_l, "k_r": config.surface.k_r, "k_s": config.surface.k_s}
    return data


def config_differences(first: StudyConfig, second: StudyConfig) -> list[tuple[str, object, object]]:
    """The settings that make two configs hash differently (:func:`config_hash`).

    ``(key, value in first, value in second)`` for every dotted key (e.g.
    ``surface.hurst``) whose values differ, in key order; a key set in one
    config only has ``None`` in the other. Other quantities of interest give
    the key ``qoi`` with the two lists of names (their settings are not
    listed), the same ones in another order the key ``qoi (column order)``;
    either comes first. Empty if and only if the hashes are equal.
    """
    ours, theirs = _hashed_settings(first), _hashed_settings(second)
    names, other_names = list(ours["qoi"]), list(theirs["qoi"])
    for settings, shared in ((ours, other_names), (theirs, names)):
        settings["qoi"] = {name: value for name, value in settings["qoi"].items() if name in shared}
    flat_ours, flat_theirs = _flattened(ours), _flattened(theirs)
    differences = [
        (key, flat_ours.get(key), flat_theirs.get(key))
        for key in sorted(flat_ours.keys() | flat_theirs.keys())
        if _canonical(flat_ours.get(key)) != _canonical(flat_theirs.get(key))
    ]
    # First: other QoIs, or another column order, matter more than any one setting.
    if set(names) != set(other_names):
        differences.insert(0, ("qoi", names, other_names))
    elif names != other_names:
        differences.insert(0, ("qoi (column order)", names, other_names))
    return differences


def _canonical(value: object) -> str:
    """A value as :func:`config_hash` serialises it (so that ``1`` and ``1.0`` differ there and here alike)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _flattened(data: dict[str, Any], prefix: str = "") -> dict[str, object]:
    """Nested mappings as one mapping of dotted keys to the values that are not mappings."""
    flat: dict[str, object] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            flat.update(_flattened(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _coarsest_at_fixed_spacing(config: StudyConfig, text: object, value: object) -> int:
    """``grid.coarsest`` for the box ``value`` (``text`` as typed) at the grid spacing of ``config``."""
    spacing = config.surface.system_size / config.grid.coarsest
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ConfigError(f"--set surface.system_size={text}: --fixed-spacing needs a box size (got {value!r}; "
                          "allowed: a finite number > 0)")
    n_0 = config.grid.coarsest * value / config.surface.system_size
    if not (math.isfinite(n_0) and n_0 == round(n_0) and round(n_0) % 2 == 0):  # 1e308: n_0 overflows
        raise ConfigError(
            f"--fixed-spacing: box {value} needs grid.coarsest = {n_0:g} for the spacing {spacing:g} (got "
            f"{value!r}; allowed: a box size giving an even integer n_0)"
        )
    return int(round(n_0))


def _parse_scalar(text: str, key: str) -> object:
    # The config file's reading of a value, so that 1e-8 is a number here too.
    try:
        value = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - _StrictLoader is a SafeLoader
    except yaml.YAMLError as exc:  # 012: an octal number (_StrictLoader.construct_yaml_int)
        raise ConfigError(f"--set {key}={text}: {getattr(exc, 'problem', None) or exc} (got {text!r}; allowed: a "
                          "value as a config file writes it)") from None
    return value if value is None or isinstance(value, (int, float, str, bool)) else text


#: What the text of a swept value may be: it becomes part of a file name, so no separator, space or quote.
_FILE_NAME_PART = re.compile(r"[A-Za-z0-9._+-]+")


def _swept_file_name(path: str, key: str, text: str) -> str:
    """The study file name of value ``text`` of ``key``: the name in ``path`` with ``-<key>-<text>`` before its suffix.

    Raises :class:`ConfigError` for a value whose text (without surrounding
    spaces) is no safe part of a file name.
    """
    part = text.strip()
    if not _FILE_NAME_PART.fullmatch(part):
        raise ConfigError(f"--set {key}={text}: the value's text becomes part of the study's file name (got "
                          f"{text!r}; allowed: letters, digits and . _ + - only, e.g. 0.25, 1e-8 or true)")
    stem, dot, suffix = os.path.basename(path).rpartition(".")
    if not dot:
        stem, suffix = os.path.basename(path), "h5"
    return f"{stem}-{key}-{part}.{suffix}"


def _refuse_scaled_spectrum(config: StudyConfig) -> None:
    """Refuse ``--fixed-spacing`` on a spectrum in wave numbers: periods per box grow with the box, so every box
    is the same surface magnified and resolved more finely, which answers no box-size question (the quickstart's
    contact areas came out 20.51 and 20.34 % for boxes 1 and 2, the difference a discretisation bias)."""
    size, k = config.surface.system_size, config.surface.wavenumbers
    equivalent = ", ".join(f"lambda_{name}: {size / value:g}" if value > 0 else f"lambda_{name}: (k_{name} = 0: none)"
                           for name, value in (("l", k.k_l), ("r", k.k_r), ("s", k.k_s)))
    raise ConfigError(
        "--fixed-spacing: the spectrum is given as surface.wavenumbers (periods per box), which grow with the box: "
        "every box would be the same surface magnified and resolved more finely, not a larger piece of it (got "
        f"surface.wavenumbers; allowed: the spectrum as surface.wavelengths, which stay fixed as the box grows; "
        f"here {equivalent})"
    )


def sweep_configs(
    config: StudyConfig, *, key: str, values: Sequence[str], fixed_spacing: bool = False
) -> list[tuple[str, StudyConfig]]:
    """One config per value of a dotted ``key`` (e.g. ``surface.system_size``): a parameter sweep.

    Parameters
    ----------
    config : StudyConfig
        The base study.
    key : str
        Dotted path of a field of the resolved config (``load.relative``,
        ``surface.hurst``, ``surface.system_size``, ...).
    values : sequence of str
        The values, as written on the command line (parsed as the config file
        parses a value, so ``1e-8`` is a number).
    fixed_spacing : bool
        Only with ``key = surface.system_size`` and a spectrum given as
        ``surface.wavelengths``: scale ``grid.coarsest`` with the box so that
        the grid spacing ``L / n_0`` stays that of the base config (the new
        ``n_0`` must come out an even integer).

    Returns
    -------
    list of (str, StudyConfig)
        The value as given and the validated config; the file name of each
        config's ``output.path`` gets ``-<key>-<value>`` before its suffix
        (``results.h5`` -> ``results-surface.system_size-2.h5``): the full
        dotted key, as in the sweep's folder ``sweep-<key>``, so sweeps of
        ``solver.tol`` and ``qoi.contact_area.tol`` never share a file name;
        the value's text without surrounding spaces.

    Raises
    ------
    ConfigError
        Unknown key, a value that makes the config invalid (the message
        names the value), a value whose text is no safe part of a file name
        (only letters, digits and ``. _ + -``: a ``/`` would make it a path),
        two values that would name the same file (``0.1`` twice, or texts
        that differ only in case: one file on macOS and Windows), and two
        values that make the same study under two file names (``0.1`` and
        ``1e-1``: it would be computed twice).
    """
    base = _resolved_dict(config)
    parts = key.split(".")
    parent = base
    for part in parts[:-1]:
        if not isinstance(parent, dict) or part not in parent:
            parent = None
            break
        parent = parent[part]
    if not isinstance(parent, dict) or parts[-1] not in parent or isinstance(parent[parts[-1]], dict):
        raise ConfigError(f"--set {key}: not a field of this config (got {key!r}; allowed: a dotted path to a "
                          f"value, e.g. surface.system_size or load.relative)")
    if fixed_spacing and key != "surface.system_size":
        raise ConfigError(f"--fixed-spacing: only for surface.system_size (got {key!r}; allowed: surface.system_size)")
    if fixed_spacing and config.surface.wavenumbers is not None:
        _refuse_scaled_spectrum(config)
    out = []
    names: dict[str, str] = {}
    studies: list[tuple[str, dict[str, Any]]] = []
    given = f"--set: got {key + '=' + ','.join(map(str, values))!r}; allowed: distinct values"
    for text in values:
        name = _swept_file_name(config.output.path, key, str(text))
        if name.casefold() in names:
            raise ConfigError(f"{given}: {text} is the same as {names[name.casefold()]} (both would be the study "
                              f"file {name})")
        names[name.casefold()] = str(text)
        data = copy.deepcopy(base)
        target = data
        for part in parts[:-1]:
            target = target[part]
        value = _parse_scalar(str(text), key)
        target[parts[-1]] = value
        if fixed_spacing:
            data["grid"]["coarsest"] = _coarsest_at_fixed_spacing(config, text, value)
        data["output"]["path"] = os.path.join(os.path.dirname(config.output.path), name)
        try:
            swept = config_from_dict(data)
        except ConfigError as exc:
            raise ConfigError(f"--set {key}={text}: {exc}") from None
        study = _resolved_dict(swept)
        del study["output"]  # the one field every value changes: its file name
        twin = next((earlier for earlier, other in studies if other == study), None)
        if twin is not None:
            raise ConfigError(f"{given}: {text} is the same as {twin} (one study, which would be computed twice)")
        studies.append((str(text), study))
        out.append((str(text), swept))
    return out
