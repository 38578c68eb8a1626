"""Ctrl-C and SIGTERM held back while a study file is written (rough_uq.study.signals)."""

from __future__ import annotations

import signal
import threading
import time

import pytest

from rough_uq.study.signals import signals_held


@pytest.fixture
def recorded():
    """Python handlers for SIGINT and SIGTERM that record what they get; the previous ones restored after."""
    calls: list[int] = []
    previous = {signum: signal.signal(signum, lambda s, frame: calls.append(s))
                for signum in (signal.SIGINT, signal.SIGTERM)}
    yield calls
    for signum, handler in previous.items():
        signal.signal(signum, handler)


def _send(signum: int) -> None:
    # To the main thread: a process-directed signal (os.kill) may reach another thread of the test process, whose
    # C handler can run later under load.
    signal.pthread_kill(threading.main_thread().ident, signum)
    time.sleep(0.02)  # the handler runs at the next instruction of the main thread


def test_the_first_signal_reaches_its_handler_after_the_body(recorded) -> None:
    handlers = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    with signals_held():
        _send(signal.SIGTERM)
        _send(signal.SIGINT)
        _send(signal.SIGINT)
        assert recorded == []  # held back while the body runs
    assert recorded == [signal.SIGTERM]  # one stop: the later signals of the same write are dropped
    assert {signum: signal.getsignal(signum) for signum in handlers} == handlers


def test_an_exception_from_the_delivered_handler_leaves_the_body_done() -> None:
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    done = []
    try:
        with pytest.raises(KeyboardInterrupt):
            with signals_held():
                _send(signal.SIGINT)
                done.append(True)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert done == [True]


def test_ignored_signals_and_other_threads_are_left_alone(recorded) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with signals_held():
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        _send(signal.SIGINT)
    assert recorded == []
    seen = []

    def body() -> None:
        with signals_held():
            seen.append(signal.getsignal(signal.SIGTERM))

    thread = threading.Thread(target=body)
    thread.start()
    thread.join()
    assert seen == [signal.getsignal(signal.SIGTERM)] and seen[0] is not None


def test_a_failed_write_raises_its_own_error_not_the_held_stop(recorded) -> None:
    # A Ctrl-C raised in place of the failed write's error made roughuq say that every completed sample was saved.
    with pytest.raises(OSError, match="No space left"):
        with signals_held():
            _send(signal.SIGINT)
            raise OSError(28, "No space left on device")
    assert recorded == []
    assert signal.getsignal(signal.SIGINT) is not None and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN


def test_a_signal_while_the_handlers_are_put_back_leaves_none_behind(monkeypatch: pytest.MonkeyPatch) -> None:
    # One arriving after SIGINT's handler was back but before SIGTERM's raised from the first and left SIGTERM to a
    # handler that only recorded it: later SIGTERMs did nothing.
    previous = {signum: signal.signal(signum, signal.default_int_handler)
                for signum in (signal.SIGINT, signal.SIGTERM)}
    install = signal.signal
    sent = []

    def signal_then_interrupt(signum, handler):
        old = install(signum, handler)
        if handler is signal.default_int_handler and not sent:  # the first handler put back
            sent.append(signum)
            _send(signal.SIGINT)
        return old

    try:
        with pytest.raises(KeyboardInterrupt):
            with signals_held():
                monkeypatch.setattr(signal, "signal", signal_then_interrupt)
        monkeypatch.undo()
        assert sent
        assert all(signal.getsignal(signum) is signal.default_int_handler for signum in previous)
    finally:
        monkeypatch.undo()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
