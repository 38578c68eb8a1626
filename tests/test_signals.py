"""Ctrl-C and SIGTERM held back while a study file is written (rough_uq.study.signals)."""

from __future__ import annotations

import os
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
    os.kill(os.getpid(), signum)
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
