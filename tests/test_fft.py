"""Cached real FFT plans: numpy's conventions, in double and in single precision."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

from rough_uq.physics import fft as fft_module
from rough_uq.physics.fft import get_fft


@pytest.mark.parametrize("single", [False, True])
def test_plans_follow_numpy_conventions_at_their_precision(single):
    n = 48
    x = np.random.default_rng(3).standard_normal((n, n))
    plan = get_fft(n, single=single)
    assert plan.real.dtype == (np.float32 if single else np.float64)
    assert plan.spectral.dtype == (np.complex64 if single else np.complex128)
    expected = np.fft.rfft2(x)
    spectrum = plan.forward(x).copy()
    rtol = 1e-5 if single else 1e-12
    np.testing.assert_allclose(spectrum, expected, rtol=0, atol=rtol * np.abs(expected).max())
    back = plan.inverse(spectrum)
    np.testing.assert_allclose(back, x, rtol=0, atol=rtol * np.abs(x).max())


def test_plans_are_cached_per_precision():
    assert get_fft(16) is get_fft((16, 16))
    assert get_fft(16, single=True) is get_fft(16, single=True)
    assert get_fft(16, single=True) is not get_fft(16)


def test_separate_output_keeps_the_input_across_a_round_trip():
    n = 32
    x = np.random.default_rng(5).standard_normal((n, n))
    plan = get_fft(n, separate_output=True)
    assert plan.output is not plan.real
    assert get_fft(n) is not plan
    plan.real[...] = x
    plan.forward()
    back = plan.inverse()
    assert back is plan.output
    np.testing.assert_array_equal(plan.real, x)
    np.testing.assert_allclose(back, x, rtol=0, atol=1e-12 * np.abs(x).max())


@pytest.mark.parametrize("single", [False, True])
def test_in_place_plans_share_one_padded_buffer_and_transform_alike(single):
    n = 40
    x = np.random.default_rng(7).standard_normal((n, n))
    plan = get_fft(n, single=single, in_place=True)
    assert plan is not get_fft(n, single=single)
    assert plan.padded.shape == (n, n + 2) and plan.padded.flags.c_contiguous
    assert np.shares_memory(plan.real, plan.padded) and np.shares_memory(plan.spectral, plan.padded)
    plan.padded[:, :n] = x
    assert np.array_equal(plan.real, x.astype(plan.real.dtype))
    expected = np.fft.rfft2(x)
    tolerance = 1e-5 if single else 1e-12
    spectrum = plan.forward().copy()
    np.testing.assert_allclose(spectrum, expected, rtol=0, atol=tolerance * np.abs(expected).max())
    back = plan.inverse(spectrum)
    assert back is plan.real
    np.testing.assert_allclose(plan.padded[:, :n], x, rtol=0, atol=tolerance * np.abs(x).max())
    # Unnormalised: n^2 times the inverse (the caller folds 1 / n^2 into a spectral multiply).
    scaled = plan.inverse(spectrum, normalise=False)
    np.testing.assert_allclose(scaled, n * n * x, rtol=0, atol=tolerance * n * n * np.abs(x).max())
    with pytest.raises(ValueError, match="in-place"):
        fft_module.RealFFT((n, n), in_place=True, separate_output=True)


def test_plans_from_shared_wisdom_are_the_measured_ones_and_round_alike(tmp_path):
    # Measured plans travel as wisdom: a fresh process planning from it only
    # (use_wisdom) transforms to the same bits as the measuring process.
    import subprocess
    import sys

    x = np.random.default_rng(3).standard_normal((48, 48))
    try:
        wisdom = fft_module.measure_plans([48], threads=1)
        plan = get_fft(48, separate_output=True)
        assert plan.flags == ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
        here = plan.forward(x).copy()
        # A grid the wisdom does not hold is estimated, never measured.
        assert get_fft(24).flags == ("FFTW_ESTIMATE",)
        np.save(tmp_path / "x.npy", x)
        (tmp_path / "wisdom.bin").write_bytes(pickle.dumps(wisdom))
        script = (
            "import pickle, sys, numpy as np\n"
            "from rough_uq.physics import fft\n"
            f"fft.use_wisdom(pickle.loads(open({str(tmp_path / 'wisdom.bin')!r}, 'rb').read()))\n"
            "plan = fft.get_fft(48, separate_output=True)\n"
            "assert plan.flags == ('FFTW_MEASURE', 'FFTW_WISDOM_ONLY'), plan.flags\n"
            f"np.save({str(tmp_path / 'y.npy')!r}, plan.forward(np.load({str(tmp_path / 'x.npy')!r})))\n"
        )
        subprocess.run([sys.executable, "-c", script], check=True)
        assert np.array_equal(np.load(tmp_path / "y.npy"), here)
    finally:
        fft_module.use_wisdom(None)
    assert get_fft(48).flags == ("FFTW_ESTIMATE",)


def test_going_back_to_estimated_plans_forgets_the_measured_wisdom():
    # FFTW serves FFTW_ESTIMATE requests from wisdom it holds: after
    # use_wisdom(None) none is left, so the plans are those of a fresh process.
    import pyfftw

    def holds_no_wisdom() -> bool:
        return all(len(part.splitlines()) == 2 for part in pyfftw.export_wisdom())  # a header and ")"

    x = np.random.default_rng(4).standard_normal((64, 64))
    try:
        fft_module.use_wisdom(None)
        estimated = get_fft(64, separate_output=True).forward(x).copy()
        fft_module.measure_plans([64], threads=1)  # now planning from its wisdom
        fft_module.use_wisdom(None)
        assert holds_no_wisdom()
        plan = get_fft(64, separate_output=True)
        assert plan.flags == ("FFTW_ESTIMATE",)
        assert np.array_equal(plan.forward(x), estimated)
        # A plan measured with explicit flags while estimating leaves wisdom too.
        fft_module.RealFFT((64, 64), separate_output=True, flags=("FFTW_MEASURE",))
        fft_module.use_wisdom(None)
        assert holds_no_wisdom()
    finally:
        fft_module.use_wisdom(None)


def test_wisdom_changes_wait_for_planning_in_other_threads():
    # FFTW's planner is not thread-safe: use_wisdom changes the wisdom under
    # the lock that get_fft plans under.
    import threading

    done = threading.Event()
    worker = threading.Thread(target=lambda: (fft_module.use_wisdom(None), done.set()))
    with fft_module._PLANS_LOCK:
        worker.start()
        assert not done.wait(0.2)
    worker.join(5.0)
    assert done.is_set()


def _planned_patiently(n: int, **layout) -> bool:
    # Whether the process's wisdom holds a plan of at least FFTW_PATIENT rigour
    # for this layout: otherwise planning from the wisdom only fails and
    # RealFFT falls back to an estimated plan.
    flags = ("FFTW_PATIENT", "FFTW_WISDOM_ONLY")
    return fft_module.RealFFT((n, n), flags=flags, **layout).flags == flags


def test_the_solvers_in_place_single_plans_are_patient_up_to_the_documented_grid(monkeypatch):
    import pyfftw

    try:
        pyfftw.forget_wisdom()
        fft_module.measure_plans([16, 24], threads=1)
        for n in (16, 24):
            assert _planned_patiently(n, single=True, in_place=True)
            # The other variants are measured only (the same wisdom, a less rigorous plan).
            assert not _planned_patiently(n, separate_output=True)
            assert not _planned_patiently(n, single=True)
        # Above the limit the in-place plans are measured too.
        pyfftw.forget_wisdom()
        monkeypatch.setattr(fft_module, "PATIENT_MAX_GRID", 16)
        fft_module.measure_plans([16, 24], threads=1)
        assert _planned_patiently(16, single=True, in_place=True)
        assert not _planned_patiently(24, single=True, in_place=True)
        assert fft_module.RealFFT((24, 24), single=True, in_place=True).flags == ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
        with pytest.raises(ValueError, match="effort"):
            fft_module.measure_plans([16], effort="FFTW_EXHAUSTIVE")
    finally:
        fft_module.use_wisdom(None)


@pytest.mark.parametrize("limits", ["patient", "both"])
def test_plans_whose_search_runs_out_of_time_are_still_planned_from_the_wisdom(monkeypatch, limits):
    # A search that reaches FFTW's time limit leaves no wisdom of its rigour, and
    # planning from the wisdom only then estimated: the in-place single-precision
    # plan of 1024^2 on two threads (patient, over 30 s) ran estimated in every solve.
    import pyfftw

    monkeypatch.setattr(fft_module, "_PATIENT_TIMELIMIT", 1e-9)
    if limits == "both":
        monkeypatch.setattr(fft_module, "_PLANNING_TIMELIMIT", 1e-9)
    try:
        pyfftw.forget_wisdom()
        wisdom = fft_module.measure_plans([64], threads=1)
        planned = fft_module.RealFFT((64, 64), single=True, in_place=True)
        assert planned.flags == ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
        for layout in ({}, {"separate_output": True}, {"single": True}):
            assert fft_module.RealFFT((64, 64), **layout).flags == ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
        # The next run takes the measured plan as known: no patient search again, out of time again.
        pyfftw.forget_wisdom()
        calls: list[list[int]] = []
        fft_module.measure_plans([64], threads=1, wisdom=wisdom, before_measuring=calls.append)
        assert calls == []
    finally:
        fft_module.use_wisdom(None)


@pytest.mark.slow
def test_a_patient_search_out_of_time_at_1024_leaves_a_measured_plan_in_the_wisdom(monkeypatch):
    # There the search out of time left solutions in FFTW's planner that served
    # the measured search at once without becoming wisdom (here with a 5 s limit
    # on one thread; with two threads the default 30 s ran out), and the
    # preconditioned solver's transforms ran estimated in every process.
    import pyfftw

    monkeypatch.setattr(fft_module, "_PATIENT_TIMELIMIT", 5.0)
    try:
        pyfftw.forget_wisdom()
        fft_module.measure_plans([1024], threads=1)
        planned = fft_module.RealFFT((1024, 1024), single=True, in_place=True)
        assert planned.flags == ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
    finally:
        fft_module.use_wisdom(None)


def test_pyfftw_is_imported_without_dask_and_scipy_fftpack_which_import_later_as_usual():
    code = (
        "import sys, rough_uq.physics.fft as f\n"
        "print(sorted(m for m in ('dask', 'dask.array', 'scipy.fftpack') if m in sys.modules))\n"
        "import dask.array, scipy.fftpack, numpy as np\n"
        "x = np.arange(16.0)\n"
        "print(np.allclose(scipy.fftpack.fft(x), np.fft.fft(x)), hasattr(dask.array, 'fft'))\n"
        "print(np.allclose(f.get_fft(8).forward(np.ones((8, 8)))[0, 0], 64))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split("\n")[:3] == ["[]", "True True", "True"]


def test_pyfftw_imported_after_dask_keeps_its_full_interfaces():
    code = "import dask.array, rough_uq.physics.fft as f; import pyfftw.interfaces.dask_fft; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "ok"


@pytest.mark.parametrize("preset", [None, "ACTIVE"])
def test_loading_the_ffts_lets_idle_openmp_threads_sleep_unless_the_environment_chose(preset):
    # From Python (not the CLI, not a pool worker) a 512^2 solve with threads=2 took 4.1 s instead of 0.17 s:
    # pyFFTW's and numba's OpenMP threads busy-waited against each other.
    env = {key: value for key, value in os.environ.items() if key != "OMP_WAIT_POLICY"}
    if preset is not None:
        env["OMP_WAIT_POLICY"] = preset
    # Nothing at import (STYLE); set when pyFFTW is first used, before its OpenMP runtime loads.
    code = ("import os, sys, rough_uq.physics.fft as fft; before = os.environ.get('OMP_WAIT_POLICY'); "
            "loaded = 'pyfftw' in sys.modules; fft.get_fft((8, 8)); "
            "print(before, loaded, 'pyfftw' in sys.modules, os.environ['OMP_WAIT_POLICY'])")
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [str(preset), "False", "True", preset or "PASSIVE"]
