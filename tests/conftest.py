"""Test-session settings shared by every test module."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True, scope="session")
def _fftw_wisdom_in_a_temporary_cache(tmp_path_factory):
    # Measured FFTW plans are cached per machine (rough_uq.study.fft_wisdom); the
    # tests keep theirs in a directory of their own, never in the user's cache.
    patch = pytest.MonkeyPatch()
    patch.setenv("ROUGHUQ_FFTW_WISDOM", str(tmp_path_factory.mktemp("fftw") / "wisdom.json"))
    yield
    patch.undo()

