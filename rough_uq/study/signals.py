"""Ctrl-C and SIGTERM held back while a study file is written.

``roughuq`` (and Python in a notebook) stops on Ctrl-C or SIGTERM by raising
an exception wherever the main thread happens to be. Raised inside a write of
the study file, it abandons the write: the file stays consistent (the commit
protocol and the copy-on-write transactions of :mod:`rough_uq.study.store`),
but the batch being saved is lost while the command reports "every completed
sample is saved". A second Ctrl-C did that, landing in the final save the
first one had started (3 of 19 double Ctrl-Cs in an audit lost 3-10 samples,
which the resumed run computed again); a single one landing in a periodic
save could too.

:func:`signals_held` records such a signal during the write and hands the
first one to the handler it was meant for once the write is done; later ones
of the same write are dropped (two Ctrl-Cs in a row ask for one stop). A
write that fails raises its own error instead, which ends the command anyway
and says what was not saved (a Ctrl-C raised in its place claimed that every
completed sample was). Only
signal handlers written in Python are held back: a signal that is ignored,
left to the system's default, or handled outside Python, and any signal off
the main thread (where Python runs no handler), is left alone.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType

#: The signals that stop a command.
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def signals_held() -> Iterator[None]:
    """Hold back Ctrl-C and SIGTERM in the body; deliver the first one received when it ends."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[tuple[int, FrameType | None]] = []

    def record(signum: int, frame: FrameType | None) -> None:
        received.append((signum, frame))

    previous = {}
    for signum in HELD_SIGNALS:
        handler = signal.getsignal(signum)
        if callable(handler):
            previous[signum] = signal.signal(signum, record)
    try:
        yield
    except BaseException:
        _restore(previous)  # the body's own error (a failed write) is what the caller must see
        raise
    _restore(previous)
    if received:
        signum, frame = received[0]
        previous[signum](signum, frame)


def _restore(handlers: dict[int, Callable[..., object]]) -> None:
    """Put ``handlers`` back, each in the ``finally`` of the one before: a signal arriving between two raises from
    the handler already restored, and the others must still be restored (left to ``record``, a later SIGTERM did
    nothing). Blocking the signals meanwhile would not do: another thread may take a signal the main thread
    blocks, and Python runs its handler in the main thread all the same."""
    items = list(handlers.items())
    if not items:
        return
    (signum, handler), rest = items[0], dict(items[1:])
    try:
        signal.signal(signum, handler)
    finally:
        _restore(rest)
