"""The ``roughuq`` console script: a Ctrl-C while Python loads the command line ends it quietly.

Loading the command line (click, numpy, the study layer) takes some 0.3 s on first use, and Python's default
handler turned a Ctrl-C in that time into a ``KeyboardInterrupt`` traceback through the import machinery.
From the moment this module runs until a command takes Ctrl-C over, a Ctrl-C now exits with status 130 and
nothing on stderr; the commands handle Ctrl-C and SIGTERM themselves (exit 130 / 143, completed samples
saved). A Ctrl-C that is ignored (a background job of a script) stays ignored. Not covered: Python's own
start-up and ``import rough_uq`` before this module runs (some 60 ms), and ``python -m rough_uq.cli``, which
loads the command line before any of this.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

__all__ = ["EXIT_INTERRUPTED", "run", "stop_loading", "stopped"]

#: The exit status of a program stopped by Ctrl-C (128 + SIGINT), as the commands' own.
EXIT_INTERRUPTED = 130


def run() -> None:
    """Load the command line with Ctrl-C ending the program quietly, then run it (:func:`rough_uq.cli.run`).

    The quiet stop stays until a command takes Ctrl-C over (it does where it finds Python's default handler or
    this one): click, between loading and the command, turned a Ctrl-C into "Aborted!" and status 1.
    """
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, stop_loading)
    command = _load()
    if stopped():  # the handler's SystemExit was lost (raised while CPython compiled a module: it ran on)
        sys.exit(EXIT_INTERRUPTED)
    command()


def _load() -> Callable[[], None]:
    from rough_uq.cli import run as command

    return command


#: Whether :func:`stop_loading` ran: a SystemExit raised while CPython compiles a module's source (no bytecode
#: cache, ``PYTHONDONTWRITEBYTECODE``) is lost, and the command ran to its end with status 0 (3 of 40 Ctrl-Cs).
_stopped = False


def stopped() -> bool:
    """Whether :func:`stop_loading` ran (the command line checks it again where a command takes Ctrl-C over)."""
    return _stopped


def stop_loading(signum: int, frame: object) -> None:
    """Exit with status 130, quietly: a Ctrl-C before any command has started."""
    global _stopped
    _stopped = True
    sys.exit(EXIT_INTERRUPTED)
