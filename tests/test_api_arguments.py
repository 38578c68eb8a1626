"""Arguments of the public runs (mlmc, mc, variance, distribution) refused by name, before any sample is drawn."""

from __future__ import annotations

import dataclasses
import math

import warnings

import numpy as np
import pytest

import rough_uq
from rough_uq.multilevel.distribution import cdf_level_term
from rough_uq.multilevel.moments import central_moment_level_term, variance_level_term
from rough_uq.multilevel.targets import adaptive_mlmc


class _NoSampling:
    """An executor that fails the test if a run draws a sample."""

    def run(self, model, items):
        raise AssertionError(f"a sample was drawn: {list(items)[:1]}")


def _never_sampled(level, indices):
    raise AssertionError(f"a sample was drawn on level {level}")


def _problem(qoi=("contact_area",)) -> rough_uq.ContactProblem:
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    return rough_uq.ContactProblem(
        spectrum, load=rough_uq.RelativeLoad(0.2), qoi=list(qoi), coarsest=8, max_level=2, solver_tol=1e-8, seed=2026
    )


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def test_initial_samples_beyond_max_samples_are_refused_naming_n_initial_before_sampling():
    # Drew all 900 initial samples, then blamed the tolerance ("loosen the tolerance").
    problem = _problem()
    calls = [
        lambda: rough_uq.mlmc(problem, tol=2.0, n_initial=300, max_samples=100, executor=_NoSampling()),
        lambda: rough_uq.mc(problem, tol=2.0, level=1, n_initial=300, max_samples=100, executor=_NoSampling()),
        lambda: rough_uq.variance(problem, tol=20.0, n_initial=300, max_samples=100, executor=_NoSampling()),
        lambda: rough_uq.distribution(
            problem, tol=0.2, thresholds=[0, 50, 100], n_initial=10**8, max_samples=100, executor=_NoSampling()
        ),
    ]
    for call in calls:
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        assert caught.value.name == "n_initial" and "alone exceed max_samples = 100" in str(caught.value)
        assert "tolerance" not in str(caught.value) and "loosen" not in str(caught.value)
    with pytest.raises(rough_uq.InvalidParameterError, match=r"^n_initial: got 40; allowed: at most max_samples / "):
        adaptive_mlmc(_never_sampled, term=variance_level_term, tol=1.0, n_initial=40, max_samples=100)


def test_initial_samples_within_max_samples_still_run():
    problem = _problem()
    result = rough_uq.variance(problem, tol=1e3, n_initial=4, max_samples=12)
    assert result.n_samples.tolist() == [4, 4, 4]


@pytest.fixture(scope="module")
def two_qoi_screening() -> rough_uq.ScreeningResult:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rough_uq.screen(_problem(qoi=("contact_area", "mean_gap")), samples=2)


def test_a_screening_or_rates_of_other_qois_are_refused_by_name_before_sampling(two_qoi_screening):
    # Said "tol: got array([2., 2.]); allowed: a scalar or 1 values (one per QoI)" once sampling had begun.
    problem, none = _problem(), _NoSampling()
    for name, call in (
        ("screening", lambda: rough_uq.mlmc(problem, tol=2.0, screening=two_qoi_screening, executor=none)),
        ("screening", lambda: rough_uq.mlmc(problem, tol=2.0, screening=two_qoi_screening.statistics, executor=none)),
        ("rates", lambda: rough_uq.mlmc(problem, tol=2.0, rates=two_qoi_screening.rates, executor=none)),
        ("screening", lambda: rough_uq.mc(problem, tol=2.0, screening=two_qoi_screening, executor=none)),
        ("screening", lambda: rough_uq.mc(problem, tol=2.0, level=1, screening=two_qoi_screening, executor=none)),
    ):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        assert caught.value.name == name and str(caught.value).endswith("it has 2 QoIs, the problem 1")


@pytest.mark.parametrize("richardson", ["no", 0, None, "False"])
def test_a_richardson_flag_that_is_not_a_bool_is_refused_by_name_also_by_the_forecast(two_qoi_screening, richardson):
    # forecast(richardson="no") read the flag as True (bool("no")), where mlmc refused it.
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        two_qoi_screening.forecast(2.0, richardson=richardson)
    assert caught.value.name == "richardson"
    problem = _problem(qoi=("contact_area", "mean_gap"))
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.mlmc(problem, tol=2.0, screening=two_qoi_screening, richardson=richardson, executor=_NoSampling())
    assert caught.value.name == "richardson"
    assert repr(two_qoi_screening.forecast(2.0, richardson=np.bool_(False))) == repr(two_qoi_screening.forecast(2.0))


def test_a_min_finest_level_above_max_level_is_refused_naming_min_finest_level():
    # Said "max_level: got 2; allowed: an integer >= 3": the problem's max_level, not an argument of the call.
    problem, none = _problem(), _NoSampling()
    for call in (
        lambda: rough_uq.mlmc(problem, tol=2.0, min_finest_level=3, executor=none),
        lambda: rough_uq.variance(problem, tol=20.0, min_finest_level=3, executor=none),
        lambda: rough_uq.distribution(problem, tol=0.2, thresholds=[0, 50, 100], min_finest_level=3, executor=none),
    ):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        assert caught.value.name == "min_finest_level" and caught.value.value == 3
        assert caught.value.allowed == "an integer in 1..max_level = 2"
    # An MLMC run spans levels 0..2 at least; said "coarsest_level: got 0; allowed: at most max_level - 2 = -1".
    with pytest.raises(rough_uq.InvalidParameterError, match=r"^max_level: got 1; allowed: an integer >= 2: an MLMC "
                       r"run fits its rates on levels >= 1, two of them at least; on fewer levels use mc\(level="):
        rough_uq.mlmc(_problem_of_levels(1), tol=2.0, min_finest_level=1, executor=none)


def _problem_of_levels(max_level: int) -> rough_uq.ContactProblem:
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    return rough_uq.ContactProblem(
        spectrum, load=rough_uq.RelativeLoad(0.2), qoi=["contact_area"], coarsest=8, max_level=max_level, seed=2026
    )


def test_rates_of_another_type_are_refused_by_name():
    # An AttributeError deep in drivers.iter_mlmc.
    for rates in ("x", 0.5, {"alpha": 1.0}):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            rough_uq.mlmc(_problem(), tol=2.0, rates=rates, executor=_NoSampling())
        assert caught.value.name == "rates" and caught.value.value is rates and "a Rates" in caught.value.allowed


@pytest.mark.parametrize("field", ["alpha", "beta", "gamma", "c_alpha", "c_beta", "c_gamma"])
def test_rates_that_are_not_finite_are_refused_naming_the_field(field):
    # A NaN alpha read "alpha = nan: the bias does not decay with the level"; a NaN beta or an infinite gamma ran.
    rates = rough_uq.Rates(alpha=1.0, beta=1.5, gamma=2.0, c_alpha=1.0, c_beta=1.0, c_gamma=1.0)
    with pytest.raises(rough_uq.InvalidParameterError, match=f"^rates.{field}: got .*; allowed: finite numbers$"):
        rough_uq.mlmc(_problem(), tol=2.0, rates=dataclasses.replace(rates, **{field: np.nan}), executor=_NoSampling())


@pytest.mark.parametrize("bias", ["a", "0.5", True, np.bool_(True), [0.5, "1"], [True], np.array(["0.5"]), np.nan,
                                  [np.inf], [[0.5]]])
def test_a_bias_that_is_not_finite_numbers_is_refused_by_name(bias):
    # "a" was a bare ValueError; "0.5" and True were taken as 0.5 and 1.
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.mc(_problem(), tol=2.0, level=1, bias=bias, executor=_NoSampling())
    assert caught.value.name == "bias" and caught.value.value is bias


def test_a_bias_of_numbers_is_taken_as_before():
    problem = _problem()
    given = {"scalar": 0.5, "list": [0.5], "array": np.array([-0.5]), "numpy scalar": np.float32(0.5)}
    for bias in given.values():
        result = rough_uq.mc(problem, tol=20.0, level=0, bias=bias, n_initial=2)
        assert result.is_bias_estimated and float(np.ravel(result.bias_estimate)[0]) == 0.5


@pytest.mark.parametrize(("bias", "theta", "remedy"), [(0.6, 0.5, "no theta does"), (0.4, 0.5, "at least 0.64"),
                                                       ([0.1, 0.45], 0.5, "at least 0.81")])
def test_a_given_bias_above_its_share_of_tol_is_refused_before_any_sample(bias, theta, remedy):
    # mc(bias=0.6, tol=0.5) drew its samples and then stopped "bias", not met.
    problem = _problem(qoi=("contact_area", "mean_gap")) if np.size(bias) == 2 else _problem()
    with pytest.raises(rough_uq.EstimationError, match=f"sqrt\\(theta\\) tol = .*; .*{remedy}"):
        rough_uq.mc(problem, tol=0.5, level=1, bias=bias, theta=theta, executor=_NoSampling())
    result = rough_uq.mc(_problem(), tol=20.0, level=0, bias=0.5, theta=0.5, n_initial=2)
    assert result.stop_reason == "tol_met"  # a bias within its share runs as before


def test_a_bias_of_another_length_is_refused_before_any_sample():
    # Two values for one column were refused only once the first batch had been drawn.
    with pytest.raises(rough_uq.InvalidParameterError, match="^bias: .*a number .*or 1 values") as caught:
        rough_uq.mc(_problem(), tol=0.5, level=1, bias=[0.1, 0.2], executor=_NoSampling())
    assert caught.value.value == [0.1, 0.2]
    # One number in a list for two columns was applied to both, where tol=[0.5] is refused.
    with pytest.raises(rough_uq.InvalidParameterError, match="one per QoI column: contact_area, mean_gap") as caught:
        rough_uq.mc(_problem(qoi=("contact_area", "mean_gap")), tol=0.5, level=1, bias=[0.1], executor=_NoSampling())
    assert caught.value.value == [0.1]


def test_a_bias_by_column_name_equals_the_bias_in_column_order():
    # tol= took a mapping by name, bias= only numbers in column order.
    problem = _problem(qoi=("contact_area", "mean_gap"))
    by_name = rough_uq.mc(problem, tol=[20.0, 0.5], level=0, bias={"mean_gap": -0.01, "contact_area": 0.5},
                          n_initial=2)
    in_order = rough_uq.mc(problem, tol=[20.0, 0.5], level=0, bias=[0.5, 0.01], n_initial=2)
    np.testing.assert_array_equal(by_name.bias_estimate, [0.5, 0.01])
    np.testing.assert_array_equal(by_name.estimate, in_order.estimate)


def test_a_bias_by_name_must_name_every_column_and_no_other_before_sampling():
    problem = _problem(qoi=("contact_area", "mean_gap"))
    cases = [
        ({"contact_area": 0.1}, "no bias for mean_gap", "one bias for every QoI column (contact_area, mean_gap)"),
        ({"contact_area": 0.1, "mean_gap": 0.0, "gap": 1.0}, "key 'gap'",
         "QoI or column names: contact_area, mean_gap"),
        ({"contact_area": 0.1, "mean_gap": np.inf}, "mean_gap: inf", "a finite number for every key"),
        ({"contact_area": "0.1", "mean_gap": 0.0}, "contact_area: '0.1'", "a finite number for every key"),
    ]
    for bias, value, allowed in cases:
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            rough_uq.mc(problem, tol=0.5, level=1, bias=bias, executor=_NoSampling())
        assert (caught.value.name, caught.value.value, caught.value.allowed) == ("bias", value, allowed)


@pytest.mark.parametrize("call", ["thresholds", "tol by name"])
def test_an_integer_beyond_the_float_range_is_refused_by_name(call):
    # 10**400 escaped as an OverflowError from numpy / math.isfinite.
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        if call == "thresholds":
            rough_uq.distribution(_problem(), tol=0.2, thresholds=[1.0, 10**400], executor=_NoSampling())
        else:
            rough_uq.mc(_problem(), tol={"contact_area": 10**400}, level=1, executor=_NoSampling())
    assert caught.value.name == ("thresholds" if call == "thresholds" else "tol")


@pytest.mark.parametrize("bandwidth", ["abc", "2", [1.0], True, np.array([1.0]), np.nan, -1.0])
def test_a_bandwidth_that_is_not_a_positive_number_is_refused_by_name(bandwidth):
    # "abc" was a bare ValueError, [1.0] and "2" a TypeError, and True was taken as 1.
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.distribution(
            _problem(), tol=0.2, thresholds=[0, 50, 100], bandwidth=bandwidth, executor=_NoSampling()
        )
    assert caught.value.name == "bandwidth" and caught.value.value is bandwidth


def test_a_bandwidth_rate_that_is_not_a_number_is_refused_by_name():
    fine = np.linspace(0.0, 1.0, 8)[:, None]
    for rate in ("1", True, [1.0]):
        with pytest.raises(rough_uq.InvalidParameterError, match="^bandwidth_rate: "):
            cdf_level_term(fine, None, 0, thresholds=[0.0, 1.0], bandwidth=0.5, bandwidth_rate=rate)
    numbers = [cdf_level_term(fine, None, 0, thresholds=[0.0, 1.0], bandwidth=b, bandwidth_rate=1) for b in (1, 1.0)]
    np.testing.assert_array_equal(numbers[0].mean, numbers[1].mean)


def test_tolerances_by_column_name_equal_those_in_column_order():
    # The CLI takes NAME=EPS and `units=` is a mapping: `tol=` takes one too, and gives the run of the same list.
    problem = _problem(qoi=("contact_area", "mean_gap"))
    by_name = rough_uq.mlmc(problem, tol={"mean_gap": 0.05, "contact_area": 4.0}, n_initial=4)
    in_order = rough_uq.mlmc(problem, tol=[4.0, 0.05], n_initial=4)
    np.testing.assert_array_equal(by_name.tol, [4.0, 0.05])
    np.testing.assert_array_equal(by_name.estimate, in_order.estimate)
    np.testing.assert_array_equal(by_name.n_samples, in_order.n_samples)


def test_tolerances_by_name_must_name_every_column_and_no_other_before_sampling():
    problem = _problem(qoi=("contact_area", "mean_gap"))
    cases = [
        ({"contact_area": 2.0}, "no tolerance for mean_gap",
         "one tolerance for every QoI column (contact_area, mean_gap)"),
        ({"contact_area": 2.0, "mean_gap": 0.1, "area": 1.0}, "key 'area'",
         "QoI or column names: contact_area, mean_gap"),
        ({"contact_area": 2.0, "mean_gap": -0.1}, "mean_gap: -0.1", "a finite number > 0 for every key"),
        ({"contact_area": 2.0, "mean_gap": "0.1"}, "mean_gap: '0.1'", "a finite number > 0 for every key"),
    ]
    for tol, value, allowed in cases:
        for refusal in _tol_refusals(problem, tol):
            assert refusal.name == "tol"
            assert refusal.value == value and refusal.allowed == allowed


def _tol_refusals(problem: rough_uq.ContactProblem, tol: object) -> list[rough_uq.InvalidParameterError]:
    """The refusals of ``tol`` by mlmc, mc and variance, each before any sample."""
    none, refusals = _NoSampling(), []
    for call in (
        lambda: rough_uq.mlmc(problem, tol=tol, executor=none),
        lambda: rough_uq.mc(problem, tol=tol, level=1, executor=none),
        lambda: rough_uq.variance(problem, tol=tol, executor=none),
    ):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        refusals.append(caught.value)
    return refusals


def test_a_tolerance_sequence_must_have_one_value_per_column():
    """``tol=[0.5]`` for two QoIs was broadcast to both (0.5 clusters per unit area too): a list is one per QoI."""
    problem = _problem(qoi=("contact_area", "mean_gap"))
    allowed = ("a number > 0 (for every QoI), a sequence of 2 (one per QoI column: contact_area, mean_gap, in its "
               "unit), or a mapping of every QoI column to one")
    for tol in ([0.5], (0.5,), np.array([0.5]), [0.5, 0.5, 0.5], [[0.5, 0.5]]):
        for refusal in _tol_refusals(problem, tol):
            assert refusal.name == "tol" and refusal.allowed == allowed
    single = _problem(qoi=("contact_area",))
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.mlmc(single, tol=[1.0, 2.0], executor=_NoSampling())
    assert caught.value.allowed == ("a number > 0 (for every QoI), a sequence of one (one per QoI column: "
                                    "contact_area), or a mapping of every QoI column to one")


@pytest.mark.parametrize("tol", [["0.5"], [True], np.array(["0.5"]), [0.5, "1"], [10**400]])
def test_a_tolerance_sequence_of_other_than_numbers_is_refused_not_converted(tol):
    # ["0.5"] and [True] were taken as 0.5 and 1.0 while "0.5" and True were refused; 10**400 overflowed.
    problem = _problem(qoi=("contact_area",)) if np.size(tol) == 1 else _problem(qoi=("contact_area", "mean_gap"))
    for refusal in _tol_refusals(problem, tol):
        assert refusal.name == "tol" and refusal.value is tol


@pytest.mark.parametrize("thresholds", [["10", "20", "30"], [True, 2.0, 3.0], np.array(["10", "20"])])
def test_thresholds_of_other_than_numbers_are_refused_not_converted(thresholds):
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.distribution(_problem(), tol=0.2, thresholds=thresholds, executor=_NoSampling())
    assert caught.value.name == "thresholds" and caught.value.value is thresholds


@pytest.mark.parametrize("tol", [[0.2, 0.2], [0.2], 1.5, "0.2", 1e-200])
def test_a_distribution_tolerance_is_one_number_in_0_1_and_says_so(tol):
    # [0.2, 0.2] was told "a number > 0 (for every QoI), a sequence of one (one per QoI)", neither of which it takes.
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.distribution(_problem(), tol=tol, thresholds=[10.0, 20.0], executor=_NoSampling())
    assert caught.value.name == "tol" and caught.value.allowed.startswith("one number in [1e-140, 1)")


def test_a_screening_of_another_problem_is_refused_naming_what_differs():
    """A screening of another load and grid planned (and pooled its variances into) the run without a word."""
    problem = dataclasses.replace(_problem(), max_level=3)
    screening = rough_uq.screen(problem, levels=3, samples=3)
    none = _NoSampling()
    other = dataclasses.replace(problem, load=rough_uq.RelativeLoad(0.3), coarsest=2 * problem.coarsest)
    allowed = "a screening of this problem, rough_uq.screen(problem) (it may differ in seed, max_level, threads only)"
    for call in (lambda: rough_uq.mlmc(other, tol=2.0, screening=screening, executor=none),
                 lambda: rough_uq.mc(other, tol=2.0, screening=screening, executor=none)):
        with pytest.raises(rough_uq.InvalidParameterError) as caught:
            call()
        assert caught.value.name == "screening" and caught.value.allowed == allowed
        assert caught.value.value == "a screening of another problem (it differs in coarsest, load)"
    fraction = dataclasses.replace(problem, units={"contact_area": "fraction"})
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.mlmc(fraction, tol=0.02, screening=screening, executor=none)
    assert caught.value.value == "a screening of another problem (it differs in units)"
    # Another seed draws other samples of the same problem, and a run may stop at another finest level.
    same = dataclasses.replace(problem, seed=problem.seed + 1, max_level=4)
    result = rough_uq.mlmc(same, tol=2.0, screening=screening)
    assert result.tol_met
    # The same problem spelled otherwise: a list of one load, the default unit written out, settings of QoIs
    # it does not compute.
    for spelled in (dict(load=[rough_uq.RelativeLoad(0.2)]), dict(units={"contact_area": "percent"}),
                    dict(connectivity=8), dict(critical_pressure=0.5)):
        rough_uq.mlmc(dataclasses.replace(problem, **spelled), tol=2.0, screening=screening)
    # Statistics alone carry no problem: nothing to check.
    rough_uq.mlmc(problem, tol=2.0, screening=screening.statistics)


def test_a_screening_prints_as_a_one_line_summary(two_qoi_screening):
    # print(screening) dumped every per-level array, some 40 lines of numpy repr.
    text = repr(two_qoi_screening)
    assert "\n" not in text and len(text) < 300 and str(two_qoi_screening) == text
    assert text.startswith("ScreeningResult(levels=[0, 1, 2], n_samples=[2, 2, 2], alpha=[")
    rates = two_qoi_screening.rates
    assert f"alpha={[float(f'{a:.3g}') for a in rates.alpha]}" in text and f"gamma={rates.gamma:.3g}" in text


def test_warnings_of_the_public_runs_name_the_callers_line():
    # They named lines inside the package (e.g. problem/distribution.py for thresholds that miss the samples): a
    # fixed stacklevel counted the frames of one call path only.
    problem = _problem()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rough_uq.distribution(problem, tol=0.1, thresholds=np.linspace(80, 99, 20), n_initial=4, max_samples=200)
        rough_uq.mlmc(problem, tol=2.0, n_initial=2)
    messages = [str(w.message) for w in caught]
    assert any("miss the samples" in text for text in messages), messages
    assert all(w.filename == __file__ for w in caught), [(w.filename, w.lineno) for w in caught]


def test_tolerances_by_name_of_a_load_curve_take_a_qoi_for_all_its_loads():
    # As `--tol contact_area=0.5` does; a column's own name takes precedence.
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    loads = [rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(0.2)]
    problem = rough_uq.ContactProblem(spectrum, load=loads, qoi=["contact_area", "mean_gap"], coarsest=8, max_level=2,
                                      seed=7)
    assert problem.columns == ("contact_area@0.1", "contact_area@0.2", "mean_gap@0.1", "mean_gap@0.2")
    with pytest.raises(rough_uq.InvalidParameterError) as caught:  # a sample would be drawn before the tolerances
        rough_uq.mlmc(problem, tol={"contact_area": 2.0, "mean_gap": 0.1, "area": 1.0}, executor=_NoSampling())
    assert caught.value.value == "key 'area'"
    result = rough_uq.mlmc(problem, tol={"contact_area": 2.0, "mean_gap": 0.1, "contact_area@0.2": 3.0}, n_initial=2)
    np.testing.assert_array_equal(result.tol, [2.0, 3.0, 0.1, 0.1])


def test_a_screening_whose_bias_does_not_decay_says_so_in_its_diagnostics():
    """roughuq refuses such a screening; the Python screening's diagnostics were empty (and printed alpha=-0.0)."""
    # Cluster counts on grids that resolve ever more of a spectrum up to k_s = 32: they grow from level to level.
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=32, hurst=0.8, rms_height=1.0)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.3), qoi=["contact_area", "clusters"],
                                      coarsest=16, max_level=2, seed=0)
    screening = rough_uq.screen(problem, levels=3, samples=6)
    assert screening.rates.alpha[0] > 0 and not screening.rates.alpha[1] > 0
    assert screening.diagnostics[-1] == (
        "the bias of clusters (alpha = -2.7) does not decrease from level to level on the screened grids, so no "
        "finest level can be chosen from this screening (roughuq mlmc refuses it); screen finer grids (a larger "
        "coarsest), or use mc(level=...) (bias not estimated)")
    # Its forecast refused without saying what would do (mlmc said it).
    with pytest.raises(rough_uq.EstimationError, match=r"no level can be chosen for a tolerance; screen finer grids "
                                                       r"\(a larger coarsest\), or use mc\(level=\.\.\.\)"):
        screening.forecast(tol=[2.0, 5.0])
    # Level means within their noise (clusters: 0.17 ± 0.17, -0.17 ± 0.17) fit an alpha of -0 that says nothing
    # of the decay: no such diagnostic, and the runs plan at the floor rate.
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    problem = rough_uq.ContactProblem(spectrum, load=rough_uq.RelativeLoad(0.5), qoi=["contact_area", "clusters"],
                                      coarsest=8, max_level=2, seed=5)
    noise = rough_uq.screen(problem, levels=3, samples=6)
    assert not noise.rates.alpha[1] > 0 and not any("does not decrease" in d for d in noise.diagnostics)
    assert "alpha=[" in repr(noise) and "-0.0" not in repr(noise)


def test_a_result_names_its_columns():
    """The per-QoI arrays of a result had to be matched against problem.columns by hand."""
    problem = _problem(qoi=("contact_area", "mean_gap"))
    for result in (rough_uq.mlmc(problem, tol=[4.0, 0.1], n_initial=4), rough_uq.mc(problem, tol=[4.0, 0.1], level=1)):
        assert result.qoi_names == problem.columns == ("contact_area", "mean_gap")
        assert "qoi_names=('contact_area', 'mean_gap')" in repr(result)


def test_a_run_stopped_by_its_budget_says_what_to_change():
    """The warning said "loosen tol" where no tolerance mattered yet, and grouped the RMSEs as if tolerances."""
    loads = [rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(0.2)]
    problem = dataclasses.replace(_problem(), load=loads)

    def not_met(run) -> str:
        with pytest.warns(rough_uq.EstimationWarning, match="tolerance not met") as caught:
            result = run()
        (message,) = [str(w.message) for w in caught if "tolerance not met" in str(w.message)]
        errors = ", ".join(f"{name}={e:.3g}" for name, e in zip(problem.columns, result.rmse))
        if result.method == "mc":  # no bias, ever: the statistical error against its share of tol
            shares = ", ".join(f"{name}={math.sqrt(0.5):.3g}" for name in problem.columns)
            assert (f"statistical error {errors} against its share sqrt(1 - theta) tol = {shares} of tol "
                    "contact_area=1; ") in message
        else:
            assert f"RMSE {errors} (bias not estimated) against tol contact_area=1; " in message  # each column's own
        return message

    message = not_met(lambda: rough_uq.mlmc(problem, tol=1.0, n_initial=8, max_cost=1e-9))
    assert message.endswith("the run reached max_cost before its bias was estimated: raise max_cost or lower "
                            "n_initial")
    message = not_met(lambda: rough_uq.mc(problem, tol=1.0, level=1, n_initial=8, max_cost=1e-9))
    assert message.endswith("the run reached max_cost before its first n_initial samples: raise max_cost or lower "
                            "n_initial")


@pytest.mark.parametrize("samples", [10**11, 3_333_334])
def test_a_screening_over_the_planned_sample_cap_is_refused_before_sampling(samples):
    # As the config's screening.samples: 10**11 allocated the indices of every sample before any check.
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.screen(_problem(), levels=3, samples=samples, executor=_NoSampling())
    assert caught.value.name == "samples" and caught.value.value == samples
    assert caught.value.allowed.startswith("an integer in 2..3333333 (a screening of 3 levels; at most 10,000,000 ")


@pytest.mark.parametrize("value", [None, "3", 2.5, 0])
def test_min_finest_level_is_checked_before_the_screenings_plan_reads_it(two_qoi_screening, value):
    # With a screening, mlmc planned from it first: min_finest_level=None ended in a bare TypeError.
    problem = _problem(qoi=("contact_area", "mean_gap"))
    with pytest.raises(rough_uq.InvalidParameterError) as caught:
        rough_uq.mlmc(problem, tol=50.0, screening=two_qoi_screening, min_finest_level=value, executor=_NoSampling())
    assert caught.value.name == "min_finest_level"


def _load_curve_problem() -> rough_uq.ContactProblem:
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    loads = [rough_uq.RelativeLoad(0.1), rough_uq.RelativeLoad(0.05)]
    return rough_uq.ContactProblem(spectrum, load=loads, qoi=["contact_area", "clusters"], coarsest=8, max_level=2)


def test_a_tolerance_by_column_takes_the_load_written_as_column_takes_it():
    # distribution(column="contact_area@0.10") named the column contact_area@0.1; tol={"contact_area@0.10": ...}
    # was refused as an unknown key.
    problem = _load_curve_problem()
    spelled = {"contact_area@0.10": 20.0, "contact_area@5e-2": 30.0, "clusters": 1e3}
    exact = {"contact_area@0.1": 20.0, "contact_area@0.05": 30.0, "clusters": 1e3}
    result = rough_uq.mc(problem, tol=spelled, level=0, n_initial=2)
    assert result.tol.tolist() == [20, 30, 1e3, 1e3]
    assert rough_uq.mc(problem, tol=exact, level=0, n_initial=2).tol.tolist() == result.tol.tolist()
    twice = "^tol: got \"keys 'contact_area@0.10' and 'contact_area@0.1'\"; allowed: one key for contact_area@0.1$"
    with pytest.raises(rough_uq.InvalidParameterError, match=twice):
        rough_uq.mc(problem, tol={**spelled, "contact_area@0.1": 5.0}, level=0, executor=_NoSampling())


@pytest.mark.parametrize(("tol", "index"), [([1.0, 1.0, 30.0, float("nan")], 3), ([1.0, -1.0, 2.0, 3.0], 1)])
def test_a_bad_tolerance_in_a_list_is_named_by_its_index_and_column(tol, index):
    # "allowed: ... a sequence of 4" for a list of 4 said nothing of which entry was bad.
    problem = _load_curve_problem()
    with pytest.raises(rough_uq.InvalidParameterError, match=rf"^tol\[{index}\]: got .*; allowed: a finite number > 0 "
                                                             rf"\(column {problem.columns[index]}\)$"):
        rough_uq.mc(problem, tol=tol, level=0, executor=_NoSampling())


_SPECTRUM = rough_uq.SurfaceSpectrum(system_size=2, k_l=2, k_r=2, k_s=16, hurst=0.8, rms_height=1)


@pytest.mark.parametrize(("name", "call"), [
    ("connectivity", lambda v: rough_uq.ContactProblem(_SPECTRUM, load=rough_uq.RelativeLoad(0.1), qoi=["clusters"],
                                                       coarsest=32, connectivity=v)),
    ("projection", lambda v: rough_uq.ContactProblem(_SPECTRUM, load=rough_uq.RelativeLoad(0.1),
                                                     qoi=["contact_area"], coarsest=32, projection=v)),
    ("projection", lambda v: rough_uq.sample_coupled(_SPECTRUM, 64, np.random.default_rng(0), projection=v)),
    ("column", lambda v: rough_uq.distribution(_problem(("contact_area", "clusters")), tol=0.2,
                                               thresholds=[15, 20, 25], column=v)),
    ("order", lambda v: central_moment_level_term(np.ones((8, 1)), None, order=v)),
    ("qoi", lambda v: rough_uq.ContactProblem(_SPECTRUM, load=rough_uq.RelativeLoad(0.1), qoi=[v], coarsest=32)),
])
@pytest.mark.parametrize("kind", ["array", "unhashable"])
def test_an_array_or_an_unhashable_value_where_one_choice_is_taken_is_refused_by_name(name, call, kind):
    # A numpy array gave numpy's "truth value of an array ... is ambiguous" ValueError, a list or a dict
    # where a dict was searched a TypeError.
    value = np.array([4, 8]) if kind == "array" else [4, 8]
    with pytest.raises(rough_uq.InvalidParameterError, match=f"^{name}: got "):
        call(value)


def test_a_numpy_string_unit_is_kept_as_plain_text():
    # units={"contact_area": np.str_("fraction")} showed as np.str_('fraction') in the problem's and results' units.
    problem = rough_uq.ContactProblem(_SPECTRUM, load=rough_uq.RelativeLoad(0.1), qoi=["contact_area"], coarsest=32,
                                      units={"contact_area": np.str_("fraction")})
    assert problem.units == (("contact_area", "fraction"),) and type(problem.units[0][1]) is str
    assert problem.qoi_units == ("fraction",) and "np.str_" not in repr(problem)


@pytest.mark.parametrize("method", ["mlmc", "mc"])
def test_an_initial_count_beyond_the_plans_integers_is_refused_by_name(method):
    # n_initial=10**20 ended in OverflowError ("Python int too large to convert to C long") from the first plan.
    options = dict(tol=2.0, n_initial=10**20, executor=_NoSampling()) | ({"level": 1} if method == "mc" else {})
    with pytest.raises(rough_uq.InvalidParameterError, match=r"^n_initial: got 100000000000000000000; allowed: at "
                                                              r"most 2\^52 = 4503599627370496, the largest count"):
        getattr(rough_uq, method)(_problem(), **options)


def test_a_huge_given_bias_is_refused_without_numpy_overflow_warnings():
    # bias=1e300 printed two "overflow encountered in square" RuntimeWarnings from inside the package first.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(rough_uq.EstimationError, match="no theta does: loosen tol above the bias"):
            rough_uq.mc(_problem(), tol=2.0, level=1, bias=1e300, executor=_NoSampling())
