"""Progress of long work: samples done / planned per level, elapsed time, ETA.

The pipeline reports to any object with the :class:`Progress` methods; the
core never imports this module. :func:`make_progress` picks rich progress bars
on an interactive terminal and plain, line-buffered lines otherwise (CI,
cluster jobs, pipes), at most one line every ``interval`` seconds per level
plus one when a level completes.

ETA: none until it means something. The first sample of a level carries the
start-up (worker processes, loading compiled kernels), so the rate is
measured from the first completion on, and an ETA is shown only once
:data:`ETA_MIN_SAMPLES` more samples and :data:`ETA_MIN_SECONDS` have passed.

Durations: :func:`format_duration` is the one formatter of every duration
roughuq prints (progress lines, forecasts, refusals, the report), so a time
reads the same everywhere.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from typing import IO

from rough_uq.errors import InvalidParameterError, is_real_number
from rough_uq.study.signals import signals_held

__all__ = [
    "ETA_MIN_SAMPLES", "ETA_MIN_SECONDS", "PlainProgress", "PrefixedProgress", "RichProgress", "format_duration",
    "make_progress",
]

#: Samples completed after a level's first one before its ETA is shown.
ETA_MIN_SAMPLES = 3
#: Seconds after a level's first completed sample before its ETA is shown.
ETA_MIN_SECONDS = 2.0


class Progress:
    """The interface the pipeline reports to (this base class ignores everything)."""

    def start(self, title: str) -> None:
        """A task begins (e.g. ``"screening"``, ``"mlmc tol 0.2"``)."""

    def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None:
        """Samples planned and already done per level (may be called again when the plan changes)."""

    def advance(self, level: int, n: int) -> None:
        """``n`` more samples of ``level`` are done."""

    def note(self, text: str) -> None:
        """A one-line message."""

    def stop(self, *, is_complete: bool = True) -> None:
        """The task ended (``is_complete=False``: it was interrupted or failed)."""


class PrefixedProgress(Progress):
    """Reports to ``inner`` with every task's title prefixed (a sweep's value: ``load.relative=0.2: mc ...``)."""

    def __init__(self, inner: Progress, prefix: str) -> None:
        self.inner, self.prefix = inner, prefix

    def start(self, title: str) -> None:
        self.inner.start(f"{self.prefix}: {title}")

    def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None:
        self.inner.plan(levels, n_planned, n_done)

    def advance(self, level: int, n: int) -> None:
        self.inner.advance(level, n)

    def note(self, text: str) -> None:
        self.inner.note(text)

    def stop(self, *, is_complete: bool = True) -> None:
        self.inner.stop(is_complete=is_complete)


#: ``(below, seconds per unit, unit)``: the unit of :func:`format_duration` by the duration's size.
_DURATION_UNITS = ((120.0, 1.0, "s"), (7200.0, 60.0, "min"), (math.inf, 3600.0, "h"))


def format_duration(seconds: float | None, *, digits: int = 3, clock: bool = False) -> str:
    """A duration as every roughuq text prints it, in the unit that suits its size.

    Parameters
    ----------
    seconds : float or None
        The duration (s); None or NaN is unknown.
    digits : int
        Significant digits (2 for the forecasts, which are approximate).
    clock : bool
        Whole seconds in the compact form of progress lines, which tick
        (``12s``, ``1m05s``, ``2h01m``), instead of ``12.3 s``, ``4.5 min``,
        ``2.1 h`` (seconds below 120 s, minutes below 2 h, else hours).

    Returns
    -------
    str
        The text; ``"-"`` for an unknown duration, ``"forever"`` for an infinite one.
    """
    if seconds is None or math.isnan(seconds):
        return "-"
    if math.isinf(seconds):
        return "forever"
    if clock:
        return _clock(int(round(seconds)))
    value, unit = next((seconds / size, unit) for limit, size, unit in _DURATION_UNITS if seconds < limit)
    text = f"{value:.{digits}g}"
    # 1e+02 s reads as 100 s; from a million hours on (114 years, a plan out of reach) the exponent stays.
    return f"{float(text):.0f} {unit}" if "e+" in text and float(text) < 1e6 else f"{text} {unit}"


def _clock(seconds: int) -> str:
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"


class PlainProgress(Progress):
    """Line-buffered text progress for logs.

    ETA of a level: its remaining samples times the mean time per sample
    since the level's first completed sample (see the module docstring).

    Parameters
    ----------
    stream : text stream or None
        Where the lines go (an object with ``write`` and ``flush``); None: ``sys.stderr``.
    interval : float
        Least seconds between two lines of one level, and between two lines of a changed plan (>= 0; 0: a
        line for every batch); a level's first line, a plan that adds a level and every level's last count
        (at the end) are printed whatever the interval.
    """

    def __init__(self, stream: IO[str] | None = None, *, interval: float = 10.0) -> None:
        # Checked here: a file name or a string interval failed at the first line, in the middle of a run.
        if stream is not None and not (callable(getattr(stream, "write", None))
                                       and callable(getattr(stream, "flush", None))):
            raise InvalidParameterError("stream", stream, "a text stream open for writing (e.g. sys.stderr or "
                                        "open(path, 'w')), or None for sys.stderr")
        if not (is_real_number(interval) and 0 <= interval < math.inf):
            raise InvalidParameterError("interval", interval, "a finite number of seconds >= 0 (0: every sample)")
        self._stream = stream if stream is not None else sys.stderr
        self._interval = float(interval)
        self._title = ""
        self._planned: dict[int, int] = {}
        self._done: dict[int, int] = {}
        self._started: dict[int, tuple[float, int]] = {}
        self._first: dict[int, tuple[float, int]] = {}
        self._last_line: dict[int, float] = {}
        self._printed: dict[int, int] = {}  # the count of a level's last line
        self._last_plan = -math.inf
        self._plan_text = ""  # the plan's last line
        self._t0 = time.monotonic()

    def _print(self, text: str) -> None:
        print(text, file=self._stream, flush=True)

    def start(self, title: str) -> None:
        self._title = title
        self._t0 = time.monotonic()
        self._planned.clear()
        self._done.clear()
        self._started.clear()
        self._first.clear()
        self._last_line.clear()
        self._printed.clear()
        self._last_plan = -math.inf
        self._plan_text = ""
        self._print(f"[{title}] started")

    def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None:
        now = time.monotonic()
        is_new_level = any(int(level) not in self._planned for level in levels)
        is_changed = False
        for level, planned, done in zip(levels, n_planned, n_done):
            level, planned, done = int(level), int(planned), int(done)
            is_changed |= self._planned.get(level) != planned
            self._planned[level] = planned
            self._done[level] = max(done, self._done.get(level, 0))
            self._started.setdefault(level, (now, self._done[level]))
        # The adaptive plan changes after every batch; say so when a level is
        # added, otherwise at most once per interval.
        if is_new_level or (is_changed and now - self._last_plan >= self._interval):
            self._last_plan = now
            self._print_plan()

    def _plan_now(self) -> str:
        return ", ".join(f"L{level}: {n}" for level, n in sorted(self._planned.items()))

    def _print_plan(self) -> None:
        self._plan_text = self._plan_now()
        self._print(f"[{self._title}] plan: samples per level {self._plan_text}")

    def advance(self, level: int, n: int) -> None:
        # At most one line per level and interval. A level that reaches its plan is not printed at once: the
        # adaptive plan grows after every batch, so "18/18", "21/21", ... would be a line per batch, each
        # saying done; stop() prints every level's last count instead.
        now = time.monotonic()
        self._done[level] = self._done.get(level, 0) + int(n)
        self._started.setdefault(level, (now, self._done[level] - int(n)))
        self._first.setdefault(level, (now, self._done[level]))
        if now - self._last_line.get(level, -1e9) >= self._interval:
            self._print_level(level, now, eta=True)

    def _print_level(self, level: int, now: float, *, eta: bool) -> None:
        self._last_line[level] = now
        self._printed[level] = self._done[level]
        self._print(f"[{self._title}] level {level}: {self._done[level]}/{self._planned.get(level, 0)} samples, "
                    f"elapsed {format_duration(now - self._t0, clock=True)}{self._eta(level, now) if eta else ''}")

    def _eta(self, level: int, now: float) -> str:
        t_first, done_at_first = self._first.get(level, (now, self._done[level]))
        computed = self._done[level] - done_at_first
        remaining = self._planned.get(level, 0) - self._done[level]
        if computed < ETA_MIN_SAMPLES or now - t_first < ETA_MIN_SECONDS or remaining <= 0:
            return ""
        return f", eta {format_duration(remaining * (now - t_first) / computed, clock=True)}"

    def note(self, text: str) -> None:
        self._print(f"[{self._title}] {text}")

    def stop(self, *, is_complete: bool = True) -> None:
        now = time.monotonic()
        # The last plan, where a change within the interval went unsaid ("plan: L3: 232" and then "225/225").
        if self._planned and self._plan_text != self._plan_now():
            self._print_plan()
        for level in sorted(self._done):
            is_idle = self._done[level] == 0 and self._planned.get(level, 0) == 0  # a level the plan leaves out
            if self._printed.get(level) != self._done[level] and not is_idle:
                self._print_level(level, now, eta=False)  # where every level ended
        what = "done in" if is_complete else "stopped after"
        self._print(f"[{self._title}] {what} {format_duration(now - self._t0, clock=True)}")


def _eta_column_class() -> type:
    from rich.progress import ProgressColumn
    from rich.text import Text

    class EtaColumn(ProgressColumn):
        """``eta 1m05s`` once the rate means something (module docstring), else nothing."""

        def render(self, task: object) -> Text:
            fields = task.fields
            first = fields.get("first")
            if first is None:
                if task.completed > fields.get("done_at_start", 0):
                    fields["first"] = (time.monotonic(), task.completed)
                return Text("")
            t_first, done_at_first = first
            computed = task.completed - done_at_first
            elapsed = time.monotonic() - t_first
            remaining = (task.total or 0) - task.completed
            if computed < ETA_MIN_SAMPLES or elapsed < ETA_MIN_SECONDS or remaining <= 0:
                return Text("")
            eta = format_duration(remaining * elapsed / computed, clock=True)
            return Text(f"eta {eta}", style="progress.remaining")

    return EtaColumn


def _EtaColumn() -> object:
    return _eta_column_class()()


class RichProgress(Progress):
    """rich progress bars, one per level, for an interactive terminal."""

    def __init__(self, console: object | None = None) -> None:
        from rich.console import Console

        if console is not None and not isinstance(console, Console):
            raise InvalidParameterError("console", console, "a rich.console.Console, or None for one on stderr")
        self._console = console if console is not None else Console(stderr=True)
        self._bars: object | None = None
        self._tasks: dict[int, int] = {}
        self._title = ""
        self._t0 = time.monotonic()

    def start(self, title: str) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress as Bars,
            TextColumn,
            TimeElapsedColumn,
        )

        self._title = title
        self._tasks = {}
        self._t0 = time.monotonic()
        self._bars = Bars(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("samples"),
            TimeElapsedColumn(),
            _EtaColumn(),
            console=self._console,
            transient=False,
        )
        with signals_held():  # a Ctrl-C inside rich's start left a half-started display whose stop() raised
            self._bars.start()

    def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None:
        if self._bars is None:
            return
        for level, planned, done in zip(levels, n_planned, n_done):
            level = int(level)
            if level not in self._tasks:
                self._tasks[level] = self._bars.add_task(
                    f"{self._title} level {level}", total=int(planned), completed=int(done), done_at_start=int(done)
                )
            else:  # done counts samples served from the store too, which advance() never saw
                task = self._tasks[level]
                completed = next(int(t.completed) for t in self._bars.tasks if t.id == task)
                self._bars.update(task, total=int(planned), completed=max(int(done), completed))

    def advance(self, level: int, n: int) -> None:
        if self._bars is not None and level in self._tasks:
            self._bars.advance(self._tasks[level], int(n))

    def note(self, text: str) -> None:
        self._console.print(text)

    def stop(self, *, is_complete: bool = True) -> None:
        if self._bars is not None:
            bars, self._bars = self._bars, None
            with signals_held():  # the terminal restored whole (cursor shown) before a Ctrl-C takes effect
                bars.stop()
            if not is_complete:  # frozen bars alone read as a run still going, or as one that ended
                self._console.print(f"[{self._title}] stopped after "
                                    f"{format_duration(time.monotonic() - self._t0, clock=True)}", markup=False)


def make_progress(*, is_quiet: bool = False, stream: IO[str] | None = None) -> Progress:
    """Rich bars on an interactive terminal, plain lines otherwise, nothing when quiet."""
    if is_quiet:
        return Progress()
    stream = stream if stream is not None else sys.stderr
    if stream.isatty():
        return RichProgress()
    return PlainProgress(stream)
