"""Arguments of the contact problem, its sampler and the physics functions behind it: refused by name."""

from __future__ import annotations

import numpy as np
import pytest

import rough_uq
from rough_uq.errors import ConfigError, InvalidParameterError
from rough_uq.problem.contact import MIN_SOLVER_TOL
from rough_uq.study import config as config_module


def _problem(**changes) -> rough_uq.ContactProblem:
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    settings = dict(load=rough_uq.RelativeLoad(0.2), qoi=["contact_area"], coarsest=8, max_level=2, solver_tol=1e-8,
                    seed=2026)
    return rough_uq.ContactProblem(spectrum, **{**settings, **changes})


@pytest.mark.parametrize("tol", [1e-17, 1e-16, 1e-15, 0.99e-14])
def test_a_solver_tolerance_below_what_rounding_allows_is_refused(tol) -> None:
    # 1e-17 was accepted, and every solve ran 10,000 iterations and a 100,000-iteration retry without converging.
    with pytest.raises(InvalidParameterError, match=r"^solver_tol: got .*allowed: a number in \[1e-14, 1\)") as caught:
        _problem(solver_tol=tol)
    assert "rounding" in caught.value.allowed


@pytest.mark.parametrize("tol", [MIN_SOLVER_TOL, 1e-13, 1e-12, 1e-7])
def test_solver_tolerances_the_solver_reaches_are_accepted(tol) -> None:
    assert _problem(solver_tol=tol).model.tol == tol


def test_the_config_takes_the_same_smallest_solver_tolerance() -> None:
    from tests.test_config import _base

    assert config_module.MIN_SOLVER_TOL == MIN_SOLVER_TOL
    data = _base()
    data["solver"] = {"tol": MIN_SOLVER_TOL}
    assert config_module.config_from_dict(data).solver.tol == MIN_SOLVER_TOL
    data["solver"] = {"tol": 1e-17}
    with pytest.raises(ConfigError, match=r"solver\.tol.*1e-14, 1\)"):
        config_module.config_from_dict(data)
