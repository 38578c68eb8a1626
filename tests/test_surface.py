"""Tests of rough_uq.physics.surface: the PSD model, the sampler and the MLMC coupling.

Statistical checks use fixed seeds; their tolerances are four standard errors
estimated from the samples themselves, and each also asserts that this
tolerance is tight enough to catch a plausible bug (e.g. a factor 2 in the
variance or a wrong partial sum).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from rough_uq.errors import InvalidParameterError
from rough_uq.physics.surface import (
    MAX_K_S,
    SurfaceSpectrum,
    project_surface,
    sample_coupled,
    sample_surface,
)

# Resolved by n = 32 (n >= 2 * 10 + 2), not by n = 16.
SPECTRUM = SurfaceSpectrum(system_size=1.5, k_l=2.0, k_r=8.0, k_s=10.0, hurst=0.7, rms_height=0.8)


def brute_phi_shape(k: float, *, k_l: float, k_r: float, k_s: float, hurst: float) -> float:
    """Phi / C from SPEC section 3, written independently of the module."""
    if k == 0 or k < k_l or k > k_s:
        return 0.0
    if k <= k_r:
        return 1.0
    return (k / k_r) ** (-2.0 - 2.0 * hurst)


def brute_band(spectrum: SurfaceSpectrum) -> list[tuple[int, int]]:
    bound = int(math.ceil(spectrum.k_s)) + 1
    return [
        (k0, k1)
        for k0 in range(-bound, bound + 1)
        for k1 in range(-bound, bound + 1)
        if (k0, k1) != (0, 0) and spectrum.k_l <= math.hypot(k0, k1) <= spectrum.k_s
    ]


def brute_phi(spectrum: SurfaceSpectrum, k0: int, k1: int) -> float:
    return spectrum.C * brute_phi_shape(
        math.hypot(k0, k1), k_l=spectrum.k_l, k_r=spectrum.k_r, k_s=spectrum.k_s, hurst=spectrum.hurst
    )


def mean_within(samples: np.ndarray, expected: float, *, n_se: float = 4.0) -> tuple[float, float]:
    """Assert the sample mean is within ``n_se`` standard errors of ``expected``; return (mean, se)."""
    mean = float(np.mean(samples))
    se = float(np.std(samples, ddof=1) / math.sqrt(samples.size))
    assert abs(mean - expected) < n_se * se, f"mean {mean} vs expected {expected} (se {se})"
    return mean, se


# -- the spectral model -------------------------------------------------------


@pytest.mark.parametrize(
    "params",
    [
        dict(system_size=1.5, k_l=2.0, k_r=4.0, k_s=10.0, hurst=0.7, rms_height=0.8),
        dict(system_size=3.0, k_l=0.0, k_r=2.5, k_s=13.7, hurst=0.0, rms_height=2.0),
        dict(system_size=1.0, k_l=1.3, k_r=1.3, k_s=7.1, hurst=1.0, rms_height=0.1),
    ],
)
def test_amplitude_and_slope_match_brute_force_lattice_sums(params: dict) -> None:
    spectrum = SurfaceSpectrum(**params)
    band = brute_band(spectrum)
    variance = sum(brute_phi(spectrum, *k) for k in band)
    q_factor = (2 * math.pi / spectrum.system_size) ** 2
    m2 = sum(brute_phi(spectrum, k0, k1) * q_factor * (k0 * k0 + k1 * k1) for k0, k1 in band)
    assert spectrum.n_modes == len(band)
    assert variance == pytest.approx(spectrum.rms_height**2, rel=1e-12)
    assert spectrum.m2 == pytest.approx(m2, rel=1e-12)
    assert spectrum.rms_slope == pytest.approx(math.sqrt(m2), rel=1e-12)


def test_psd_values() -> None:
    spectrum = SurfaceSpectrum(system_size=2.0, k_l=0.0, k_r=4.0, k_s=10.0, hurst=0.5, rms_height=1.0)
    k = np.array([0.0, 0.5, 4.0, 8.0, 10.0, 10.5])
    expected = spectrum.C * np.array([0.0, 1.0, 1.0, 2.0**-3, 2.5**-3, 0.0])
    np.testing.assert_allclose(spectrum.psd(k), expected, rtol=1e-14)
    assert spectrum.psd(3.0).shape == ()


@pytest.mark.parametrize(
    "k",
    ["abc", "3", ["1", 2], np.array(["3"]), None, True, 1j, [1, None], [[1, 2], [3]],
     pytest.param(10**400, id="1e400"), math.nan, [3.0, math.nan], np.full((2, 2), np.nan)],
)
def test_psd_refuses_wave_numbers_that_are_not_real_numbers_by_name(k) -> None:
    # "abc" and the ragged list gave bare ValueErrors, 1j a TypeError, 10**400 an OverflowError; "3", ["1", 2]
    # and True were converted to numbers and None to NaN (Phi = 0); NaN itself gave Phi = 0 too.
    spectrum = SurfaceSpectrum(system_size=2.0, k_l=0.0, k_r=4.0, k_s=10.0, hurst=0.5, rms_height=1.0)
    with pytest.raises(InvalidParameterError, match=r"^k: got .*; allowed: a real number or an array of real") as info:
        spectrum.psd(k)
    assert info.value.value is k  # as given: psd(nan) said "got array(nan)"


def test_psd_is_radial_in_negative_wave_numbers() -> None:
    spectrum = SurfaceSpectrum(system_size=2.0, k_l=0.0, k_r=4.0, k_s=10.0, hurst=0.5, rms_height=1.0)
    k = np.array([0.5, 4.0, 7.0, 12.0])
    np.testing.assert_array_equal(spectrum.psd(-k), spectrum.psd(k))


def test_psd_takes_numbers_and_arrays_of_them_of_any_real_type() -> None:
    spectrum = SurfaceSpectrum(system_size=2.0, k_l=0.0, k_r=4.0, k_s=10.0, hurst=0.5, rms_height=1.0)
    expected = spectrum.C * np.array([[1.0, 2.0**-3], [2.5**-3, 0.0]])
    for k in ([[4, 8.0], [10, 11]], np.array([[4, 8], [10, 11]]), np.array([[4, 8], [10, 11]], dtype=np.float32)):
        np.testing.assert_allclose(spectrum.psd(k), expected, rtol=1e-14)
    for k in (8, np.int32(8), np.float32(8.0), 8.0):
        assert spectrum.psd(k) == expected[0, 1] and spectrum.psd(k).dtype == np.float64


def test_amplitude_does_not_depend_on_the_system_size_but_slope_does() -> None:
    small = SurfaceSpectrum(system_size=1.0, k_l=2, k_r=4, k_s=10, hurst=0.7, rms_height=0.8)
    large = SurfaceSpectrum(system_size=2.0, k_l=2, k_r=4, k_s=10, hurst=0.7, rms_height=0.8)
    assert small.C == large.C
    assert small.m2 == pytest.approx(4 * large.m2, rel=1e-14)


def test_from_wavelengths() -> None:
    spectrum = SurfaceSpectrum.from_wavelengths(
        system_size=2.0, lambda_l=1.0, lambda_r=1.0, lambda_s=1 / 64, hurst=0.8, rms_height=1.0
    )
    assert (spectrum.k_l, spectrum.k_r, spectrum.k_s) == (2.0, 2.0, 128.0)
    assert spectrum == SurfaceSpectrum(system_size=2, k_l=2, k_r=2, k_s=128, hurst=0.8, rms_height=1)
    assert spectrum.lambda_s == pytest.approx(1 / 64)
    unbounded = SurfaceSpectrum.from_wavelengths(
        system_size=1.0, lambda_l=math.inf, lambda_r=0.5, lambda_s=0.1, hurst=0.8, rms_height=1.0
    )
    assert unbounded.k_l == 0.0 and unbounded.lambda_l == math.inf


def test_band_edges_computed_in_floating_point_keep_their_shell() -> None:
    # 3 / (3 / 7) is 7.000000000000001 or 6.999999999999999 depending on rounding;
    # either way the shell |k| = 7 must be in the band.
    spectrum = SurfaceSpectrum.from_wavelengths(
        system_size=3.0, lambda_l=3.0 / 2.0, lambda_r=3.0 / 2.0, lambda_s=3.0 / 7.0, hurst=0.8, rms_height=1.0
    )
    exact = SurfaceSpectrum(system_size=3.0, k_l=2, k_r=2, k_s=7, hurst=0.8, rms_height=1.0)
    assert spectrum.n_modes == exact.n_modes == len(brute_band(exact))


BASE = dict(system_size=1.0, k_l=2.0, k_r=4.0, k_s=10.0, hurst=0.7, rms_height=0.8)


@pytest.mark.parametrize(
    ("name", "changes"),
    [
        ("system_size", dict(system_size=0.0)),
        ("system_size", dict(system_size=-1.0)),
        ("rms_height", dict(rms_height=0.0)),
        ("rms_height", dict(rms_height=float("nan"))),
        ("hurst", dict(hurst=-0.1)),
        ("hurst", dict(hurst=1.5)),
        ("k_s", dict(k_s=0.0)),
        ("k_s", dict(k_s=math.inf)),
        ("k_r", dict(k_r=11.0)),
        ("k_r", dict(k_r=0.0, k_l=0.0)),
        ("k_l", dict(k_l=5.0)),
        ("k_l", dict(k_l=-1.0)),
        ("k_l, k_s", dict(k_l=0.0, k_r=0.5, k_s=0.9)),
        ("k_l, k_s", dict(k_l=1.1, k_r=1.2, k_s=1.3)),
        # Not numbers: refused, not converted (the config refuses them too).
        ("system_size", dict(system_size="2")),
        ("hurst", dict(hurst="0.8")),
        ("k_s", dict(k_s=True)),
        ("rms_height", dict(rms_height=None)),
    ],
)
def test_invalid_spectrum_names_the_parameter(name: str, changes: dict) -> None:
    with pytest.raises(InvalidParameterError) as info:
        SurfaceSpectrum(**{**BASE, **changes})
    assert info.value.name == name


@pytest.mark.parametrize(
    ("name", "changes"),
    [
        ("lambda_s", dict(lambda_s=0.0)),
        ("lambda_r", dict(lambda_r=math.inf)),
        ("lambda_l", dict(lambda_l=0.1)),  # k_l = 10 > k_r
        ("system_size", dict(system_size=-2.0)),
        ("lambda_s", dict(lambda_s="0.1")),
    ],
)
def test_invalid_wavelengths_name_the_wavelength(name: str, changes: dict) -> None:
    params = dict(system_size=1.0, lambda_l=0.5, lambda_r=0.25, lambda_s=0.1, hurst=0.7, rms_height=0.8)
    with pytest.raises(InvalidParameterError) as info:
        SurfaceSpectrum.from_wavelengths(**{**params, **changes})
    assert info.value.name == name


def test_grid_psd_convention() -> None:
    n = 16
    phi = SPECTRUM.grid_psd(n)
    k = np.fft.fftfreq(n, d=1.0 / n).astype(int)
    expected = np.zeros((n, n))
    for a in range(n):
        for b in range(n):
            if abs(k[a]) < n // 2 and abs(k[b]) < n // 2:
                expected[a, b] = brute_phi(SPECTRUM, k[a], k[b])
    np.testing.assert_allclose(phi, expected, rtol=1e-13, atol=0)
    assert phi[0, 0] == 0 and not phi[n // 2].any() and not phi[:, n // 2].any()
    assert SPECTRUM.grid_variance(n) == pytest.approx(expected.sum(), rel=1e-13)
    assert SPECTRUM.grid_variance(n) < 0.95 * SPECTRUM.rms_height**2  # n = 16 does not resolve the band
    assert not SPECTRUM.resolves(n) and SPECTRUM.resolves(32) and not SPECTRUM.resolves(20)
    assert SPECTRUM.grid_variance(32) == pytest.approx(SPECTRUM.rms_height**2, rel=1e-13)
    assert SPECTRUM.grid_m2(32) == pytest.approx(SPECTRUM.m2, rel=1e-13)


# -- the sampler --------------------------------------------------------------


def test_sample_is_the_documented_spectral_sum() -> None:
    """Reimplement the documented draw order and the synthesis as a direct sum."""
    spectrum = SurfaceSpectrum(system_size=2.0, k_l=1.0, k_r=1.5, k_s=3.2, hurst=0.6, rms_height=1.0)
    n = 8
    m = n // 2 - 1
    modes = [
        (k0, k1)
        for k0 in range(-m, m + 1)
        for k1 in range(-m, m + 1)
        if (k0, k1) != (0, 0) and 1.0 <= math.hypot(k0, k1) <= 3.2
    ]
    modes.sort(key=lambda k: (max(abs(k[0]), abs(k[1])), k[0], k[1]))
    xi = np.random.default_rng(7).standard_normal((len(modes), 2))
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    expected = np.zeros((n, n))
    for (k0, k1), (eta, zeta) in zip(modes, xi):
        amplitude = math.sqrt(brute_phi(spectrum, k0, k1)) * complex(eta, zeta)
        expected += (amplitude * np.exp(2j * np.pi * (k0 * i + k1 * j) / n)).real
    surface = sample_surface(spectrum, n, np.random.default_rng(7))
    assert surface.shape == (n, n) and surface.dtype == np.float64
    np.testing.assert_allclose(surface, expected, rtol=0, atol=1e-12)


def test_same_seed_same_surface_and_zero_mean() -> None:
    first = sample_surface(SPECTRUM, 32, np.random.default_rng(3))
    second = sample_surface(SPECTRUM, 32, np.random.default_rng(3))
    other = sample_surface(SPECTRUM, 32, np.random.default_rng(4))
    np.testing.assert_array_equal(first, second)
    assert not np.allclose(first, other)
    assert abs(first.mean()) < 1e-14


def test_invalid_sampling_arguments() -> None:
    rng = np.random.default_rng(0)
    for n in (0, 7, 16.0, True, 2 * MAX_K_S + 2, 10**6):  # 10**6: a MemoryError of 7 TiB
        with pytest.raises(InvalidParameterError) as info:
            sample_surface(SPECTRUM, n, rng)
        assert info.value.name == "n"
    with pytest.raises(InvalidParameterError, match=r"<= 65536 \(the largest grid\)"):
        sample_coupled(SPECTRUM, 2**17, rng)
    with pytest.raises(InvalidParameterError) as info:
        sample_coupled(SPECTRUM, 18, rng)  # coarse grid 9 is odd
    assert info.value.name == "n"
    with pytest.raises(InvalidParameterError) as info:
        sample_coupled(SPECTRUM, 16, rng, projection="average")
    assert info.value.name == "projection"
    for rng_like in (np.random.RandomState(0), None, 0):  # the legacy generator, or none, or a seed
        with pytest.raises(InvalidParameterError) as info:
            sample_surface(SPECTRUM, 16, rng_like)  # type: ignore[arg-type]
        assert info.value.name == "rng"
    # The value, not its type's name: "rng: got 'int'" read as the text 'int'.
    with pytest.raises(InvalidParameterError, match=r"^rng: got 5; allowed: a numpy.random.Generator"):
        sample_surface(SPECTRUM, 16, 5)  # type: ignore[arg-type]
    with pytest.raises(InvalidParameterError, match=r"^spectrum: got None; allowed: a SurfaceSpectrum$") as info:
        sample_coupled(None, 16, rng)  # type: ignore[arg-type]
    assert info.value.name == "spectrum"


def test_pointwise_variance_on_a_resolving_grid() -> None:
    rng = np.random.default_rng(11)
    # Spatial means of s^2 are independent across samples, each with expectation Var s(x).
    mean_squares = np.array([np.mean(sample_surface(SPECTRUM, 32, rng) ** 2) for _ in range(300)])
    _, se = mean_within(mean_squares, SPECTRUM.rms_height**2)
    assert 4 * se < 0.05 * SPECTRUM.rms_height**2


def test_variance_on_a_coarse_grid_is_the_partial_sum() -> None:
    rng = np.random.default_rng(12)
    partial = SPECTRUM.grid_variance(16)
    mean_squares = np.array([np.mean(sample_surface(SPECTRUM, 16, rng) ** 2) for _ in range(400)])
    _, se = mean_within(mean_squares, partial)
    assert SPECTRUM.rms_height**2 - partial > 8 * se  # the test would see the full variance


def test_covariance_at_several_lags() -> None:
    n = 32
    lags = [(0, 0), (1, 0), (0, 2), (3, 1), (2, -5), (7, 7), (16, 0)]
    h = SPECTRUM.system_size / n
    band = brute_band(SPECTRUM)
    rng = np.random.default_rng(13)
    surfaces = [sample_surface(SPECTRUM, n, rng) for _ in range(300)]
    for lag in lags:
        r = np.array(lag) * h
        expected = sum(
            brute_phi(SPECTRUM, k0, k1) * math.cos(2 * math.pi / SPECTRUM.system_size * (k0 * r[0] + k1 * r[1]))
            for k0, k1 in band
        )
        products = np.array([np.mean(s * np.roll(s, (-lag[0], -lag[1]), axis=(0, 1))) for s in surfaces])
        _, se = mean_within(products, expected)
        assert 4 * se < 0.1 * SPECTRUM.rms_height**2


def test_marginals_are_gaussian() -> None:
    # Few modes, so a non-Gaussian white noise would not be hidden by the central limit theorem.
    spectrum = SurfaceSpectrum(system_size=1.0, k_l=1.0, k_r=1.0, k_s=2.0, hurst=0.5, rms_height=1.0)
    rng = np.random.default_rng(14)
    values = np.array([sample_surface(spectrum, 8, rng)[3, 5] for _ in range(2000)])
    sigma = math.sqrt(spectrum.grid_variance(8))
    assert stats.kstest(values / sigma, "norm").pvalue > 1e-3
    assert stats.kstest(values / (1.2 * sigma), "norm").pvalue < 1e-3  # the test has the power to see it


# -- coupling between grids ---------------------------------------------------


@pytest.mark.parametrize("n", [16, 32, 64])
def test_fine_coupled_surface_is_the_direct_sample(n: int) -> None:
    rng_direct = np.random.default_rng(21)
    rng_coupled = np.random.default_rng(21)
    direct = sample_surface(SPECTRUM, n, rng_direct)
    fine, coarse = sample_coupled(SPECTRUM, n, rng_coupled)
    np.testing.assert_array_equal(fine, direct)
    assert coarse.shape == (n // 2, n // 2)
    # Both calls consumed the same random numbers.
    assert rng_direct.bit_generator.state == rng_coupled.bit_generator.state


@pytest.mark.parametrize("n", [16, 32, 64])
def test_coarse_sample_is_the_projection_of_the_fine_one(n: int) -> None:
    fine, coarse = sample_coupled(SPECTRUM, n, np.random.default_rng(22))
    np.testing.assert_allclose(coarse, project_surface(fine, n // 2, method="truncation"), rtol=0, atol=1e-12)
    fine_i, coarse_i = sample_coupled(SPECTRUM, n, np.random.default_rng(22), projection="injection")
    np.testing.assert_array_equal(fine_i, fine)
    np.testing.assert_array_equal(coarse_i, fine[::2, ::2])
    np.testing.assert_array_equal(coarse_i, project_surface(fine, n // 2, method="injection"))


def test_truncated_surface_equals_the_direct_coarse_sample_from_the_same_seed() -> None:
    # The draw order makes the coarse draws a prefix of the fine ones (module docstring).
    _, coarse = sample_coupled(SPECTRUM, 32, np.random.default_rng(23))
    direct = sample_surface(SPECTRUM, 16, np.random.default_rng(23))
    np.testing.assert_allclose(coarse, direct, rtol=0, atol=1e-12)
    finer = sample_surface(SPECTRUM, 64, np.random.default_rng(23))
    np.testing.assert_allclose(project_surface(finer, 16), direct, rtol=0, atol=1e-12)


def test_injection_equals_truncation_when_the_band_is_resolved_by_the_coarse_grid() -> None:
    assert SPECTRUM.resolves(32)
    _, truncated = sample_coupled(SPECTRUM, 64, np.random.default_rng(24))
    _, injected = sample_coupled(SPECTRUM, 64, np.random.default_rng(24), projection="injection")
    np.testing.assert_allclose(injected, truncated, rtol=0, atol=1e-12)


def test_coarse_samples_have_the_distribution_of_direct_coarse_samples() -> None:
    rng = np.random.default_rng(25)
    n_samples = 300
    coupled = [sample_coupled(SPECTRUM, 32, rng)[1] for _ in range(n_samples)]
    direct = [sample_surface(SPECTRUM, 16, rng) for _ in range(n_samples)]
    partial = SPECTRUM.grid_variance(16)
    for group in (coupled, direct):
        mean_within(np.array([s[5, 2] for s in group]), 0.0)
        mean_within(np.array([np.mean(s**2) for s in group]), partial)
    # Two-sample comparison of the pointwise variance.
    a = np.array([np.mean(s**2) for s in coupled])
    b = np.array([np.mean(s**2) for s in direct])
    se = math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
    assert abs(a.mean() - b.mean()) < 4 * se
    assert SPECTRUM.rms_height**2 - partial > 8 * se


def test_injection_of_an_unresolved_band_keeps_the_fine_variance() -> None:
    # Why injection is not the default: the coarse nodes see the aliased fine modes.
    rng = np.random.default_rng(26)
    injected = np.array(
        [np.mean(sample_coupled(SPECTRUM, 32, rng, projection="injection")[1] ** 2) for _ in range(300)]
    )
    _, se = mean_within(injected, SPECTRUM.grid_variance(32))
    assert SPECTRUM.grid_variance(32) - SPECTRUM.grid_variance(16) > 8 * se


def test_project_surface_on_single_modes() -> None:
    n_fine, n_coarse, size = 32, 16, 1.0
    x = np.arange(n_fine) * size / n_fine
    xx, yy = np.meshgrid(x, x, indexing="ij")

    def mode(k0: int, k1: int) -> np.ndarray:
        return np.cos(2 * np.pi * (k0 * xx + k1 * yy) / size + 0.3)

    kept = mode(3, -7) + 0.25  # |k0|, |k1| <= n_coarse / 2 - 1, plus a mean
    np.testing.assert_allclose(project_surface(kept, n_coarse), kept[::2, ::2], rtol=0, atol=1e-12)
    for k in [(8, 0), (0, -8), (9, 3), (15, 15)]:  # at or beyond the coarse Nyquist wave number
        np.testing.assert_allclose(project_surface(mode(*k), n_coarse), 0.0, rtol=0, atol=1e-12)
    # On the 8 x 8 grid, k1 = -7 is beyond the Nyquist wave number: only the mean is left.
    np.testing.assert_allclose(project_surface(kept, 8), np.full((8, 8), 0.25), rtol=0, atol=1e-12)


def test_project_surface_rejects_bad_arguments() -> None:
    fine = np.zeros((16, 16))
    for n_coarse, name in ((6, "n_coarse"), (5, "n_coarse"), (0, "n_coarse")):
        with pytest.raises(InvalidParameterError) as info:
            project_surface(fine, n_coarse)
        assert info.value.name == name
    with pytest.raises(InvalidParameterError) as info:
        project_surface(fine, 8, method="spline")
    assert info.value.name == "method"
    with pytest.raises(InvalidParameterError) as info:
        project_surface(np.zeros((16, 8)), 8)
    assert info.value.name == "fine"
