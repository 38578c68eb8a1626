"""Test-session settings and fixtures shared by the test modules."""

from __future__ import annotations

import signal

import pytest


@pytest.fixture(autouse=True, scope="session")
def _ctrl_c_as_in_a_terminal():
    # A shell starts a background job (`pytest &` in a script) with SIGINT ignored, and its children inherit that:
    # the Ctrl-C tests then saw no interruption at all (4 failures of a suite run in the background on 2026-11-29).
    # They test what a terminal's Ctrl-C does, so the session restores Python's handler, which children reset.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield


@pytest.fixture(autouse=True, scope="session")
def _fftw_wisdom_in_a_temporary_cache(tmp_path_factory):
    # Measured FFTW plans are cached per machine (rough_uq.study.fft_wisdom); the
    # tests keep theirs in a directory of their own, never in the user's cache.
    patch = pytest.MonkeyPatch()
    patch.setenv("ROUGHUQ_FFTW_WISDOM", str(tmp_path_factory.mktemp("fftw") / "wisdom.json"))
    yield
    patch.undo()



@pytest.fixture
def ctrl_c_after_one_sample(monkeypatch):
    """The CLI's executor computes one sample of a batch, then raises KeyboardInterrupt (as Ctrl-C would)."""
    import rough_uq.cli as cli
    from rough_uq.study.executors import SerialExecutor

    class Interrupting(SerialExecutor):
        n_workers = 1

        def run(self, model, items):
            yield from super().run(model, items[:1])
            raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_executor", lambda *args: Interrupting())
