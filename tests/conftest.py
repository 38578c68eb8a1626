"""Test-session settings shared by every test module."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True, scope="session")
def _fftw_wisdom_in_a_temporary_cache(tmp_path_factory):
    # Measured FFTW plans are cached per machine (rough_uq.study.fft_wisdom); the
    # tests keep theirs in a directory of their own, never in the user's cache.
    patch = pytest.MonkeyPatch()
    patch.setenv("ROUGHUQ_FFTW_WISDOM", str(tmp_path_factory.mktemp("fftw") / "wisdom.pickle"))
    yield
    patch.undo()


@pytest.fixture(autouse=True)
def _signal_handlers_restored():
    # ``rough_uq.cli.run`` ignores SIGINT/SIGTERM once its command has returned (the
    # work is saved; the process is exiting). Tests call it in this process, where
    # that would outlive the test: subprocesses started later inherit "ignore" and a
    # Ctrl-C sent to them would be lost (tests/test_faults.py).
    import signal

    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)
