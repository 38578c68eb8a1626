"""The ``roughuq`` command line: thin click commands over :mod:`rough_uq.study.pipeline`.

``roughuq mlmc`` estimates the mean (``--tol``), the variance (``--tol-var``,
on the RMS error of ``Var(Q)``, the QoI's unit squared) or one QoI's
distribution function with quantiles (``--tol-cdf``, on the largest RMS error
of ``F`` over ``--thresholds``); exactly one of them per run.

Exit status (also in ``roughuq --help`` and the README):

* 0: done (for ``mlmc`` / ``mc``: the tolerance was met);
* 2: nothing was computed because of what was typed: bad config, option
  value, missing / mismatched / locked study file, unwritable output, or a
  tolerance refused before the first sample (unreachable with
  ``grid.max_level``, or predicted beyond ``--max-cost``); one line
  ``error: ...``, no traceback; click's own usage errors too (an unknown
  option or command, a missing argument, a value its type refuses: the line
  names the command and its ``--help``; :class:`_OneLineUsage`);
* 3: an ``mlmc`` / ``mc`` run finished without meeting its tolerance (bias
  beyond ``grid.max_level``, ``--max-cost`` reached); its result is stored and
  printed, with what to change;
* 130 / 143: stopped by Ctrl-C / SIGTERM; completed samples are saved
  (``sample`` writes its shard whole or not at all: nothing);
* 141: the reader of the output went away (``roughuq report FILE | head``),
  as for a program that SIGPIPE ends; nothing is printed;
* 1: a bug (a traceback follows).
"""

from __future__ import annotations

import errno
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import click

from rough_uq import __version__
from rough_uq import console
from rough_uq.console import EXIT_INTERRUPTED, stop_loading
from rough_uq.errors import InvalidParameterError, MisplacedOptionError, RoughUQError

DEFAULT_STUDY = "results.h5"
#: Exit status of a run that ended without meeting its tolerance (its result is stored).
EXIT_TOL_NOT_MET = 3
#: Exit status when the reader of the output has gone (a closed pipe), 128 + SIGPIPE as for a program it ends.
EXIT_BROKEN_PIPE = 141
#: Exit status of a command stopped by SIGTERM (its completed samples are saved), 128 + SIGTERM.
EXIT_TERMINATED = 143
#: A kernel warm-up slower than this (seconds) is announced as compilation.
COMPILE_NOTICE_SECONDS = 2.0
#: Most thresholds ``--thresholds START:STOP:COUNT`` takes (COUNT); finer grids say nothing more.
MAX_THRESHOLDS = 10_000
#: Largest stage number and sample index: the study file stores both as int64.
MAX_INT64 = 2**63 - 1

_EXIT_CODES = """\b
Exit status: 0 done (mlmc/mc: tolerance met; mc --level: its statistical
error within it); 2 an error in what was typed (config, options, files, a
tolerance refused before starting: nothing computed; or refused on the way,
e.g. a plan over 10^7 samples: the run is recorded as refused), one line
'error: ...'; 3 mlmc/mc finished without meeting the tolerance (result
stored; the message says what to change); 130 Ctrl-C, 143 SIGTERM (completed
samples saved; a stopped `sample` writes no shard); 141 the output's reader
went away (| head); 1 a bug (traceback)."""


class _Terminated(KeyboardInterrupt):
    """SIGTERM (a batch system's time limit, ``kill``): stop as cleanly as on Ctrl-C."""


class _StopRequest:
    """The signal that asked the running command to stop, if any.

    A signal handler's exception is lost when the signal lands while Python
    runs a callback it cannot propagate from (a weakref callback, a
    ``__del__``: "Exception ignored in ..."); the command would then run to
    its end. Recording the request lets the next batch boundary raise it
    again (:func:`_check_stop`, called by the progress of every command).
    """

    signum: int | None = None


_STOP = _StopRequest()


def _stop_exception(signum: int) -> KeyboardInterrupt:
    import signal

    return _Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _raise_terminated(signum: int, frame: object) -> None:
    _STOP.signum = signum
    raise _stop_exception(signum)


def _quiet_unraisable(previous: Callable[[Any], None]) -> Callable[[Any], None]:
    """``sys.unraisablehook`` that drops the traceback of a recorded stop swallowed by a callback.

    Python would print "Exception ignored in ..." with a traceback for it, as
    if something had gone wrong; the stop is recorded and raised again at the
    next batch (:func:`_check_stop`), which reports it. Everything else goes
    to ``previous``.
    """

    def hook(unraisable: Any) -> None:
        if _STOP.signum is not None and isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        previous(unraisable)

    return hook


def _check_stop() -> None:
    """Raise the recorded stop request (a Ctrl-C or SIGTERM whose first raise was swallowed)."""
    if _STOP.signum is not None:
        raise _stop_exception(_STOP.signum)


#: The errors of a write that the machine refuses (full disk, quota, file size limit, I/O error): reported in one line.
_WRITE_FAILURES = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})


#: What a command stopped by Ctrl-C or SIGTERM leaves, by command ("": the commands that store samples as they go).
_STOPPED_TEXT = {
    "": "every completed sample is saved; run the same command to continue",
    "sample": "nothing was written (a shard is written whole or not at all); run the same command to compute it",
    # Commands that read, or compute without storing: nothing to continue.
    **dict.fromkeys(("report", "solve", "validate", "show"), "nothing was stored"),
}

#: Key of ``click.Context.meta`` under which the group keeps the arguments it was given.
_ARGUMENTS = "roughuq.arguments"


def _stopped_text(name: str) -> str:
    """What a stopped command leaves, and the command to run again, spelled out (another config, theta or
    tolerance starts another run: "the same command" left that to memory)."""
    import shlex

    text = _STOPPED_TEXT.get(name, _STOPPED_TEXT[""])
    context = click.get_current_context(silent=True)
    arguments = None if context is None else context.meta.get(_ARGUMENTS)
    if not arguments or "run the same command" not in text:
        return text
    # The program as it was called: "roughuq", or "python -m rough_uq.cli" (the cluster scripts' ROUGHUQ).
    return f"{text}: {context.find_root().info_name or 'roughuq'} {shlex.join(arguments)}"


def _user_errors(command: Callable[..., Any]) -> Callable[..., Any]:
    """Turn a RoughUQError into one line on stderr and exit status 2; Ctrl-C and SIGTERM into a clean stop."""
    import functools
    import signal
    import threading

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        on_main_thread = threading.current_thread() is threading.main_thread()
        _STOP.signum = None
        previous = {}
        previous_unraisable = sys.unraisablehook
        sys.unraisablehook = _quiet_unraisable(previous_unraisable)
        previous_format = warnings.formatwarning
        warnings.formatwarning = _warning_line
        if on_main_thread:
            previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, _raise_terminated)
            # Ctrl-C is taken over only where Python's default handler has it, or the console script's quiet stop
            # while it loads (not where it is ignored).
            if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, stop_loading):
                if console.stopped():  # the quiet stop's SystemExit was lost (console.run): stop before the command
                    sys.exit(EXIT_INTERRUPTED)
                previous[signal.SIGINT] = signal.signal(signal.SIGINT, _raise_terminated)
        try:
            return command(*args, **kwargs)
        except RoughUQError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)
        except KeyboardInterrupt as exc:
            terminated = isinstance(exc, _Terminated)
            what, status = ("terminated", EXIT_TERMINATED) if terminated else ("interrupted", EXIT_INTERRUPTED)
            click.echo(f"{what}: {_stopped_text(command.__name__)}", err=True)
            sys.exit(status)
        except MemoryError as exc:
            # A grid beyond the machine's memory (warned of before the run): numpy's "Unable to allocate ..." was a
            # traceback, status 1, which says "a bug". Completed samples are stored batch by batch.
            reason = str(exc) or "out of memory"
            click.echo(f"error: {reason} (got a solve larger than this process could allocate; allowed: grids whose "
                       "solves fit the machine's memory: see the forecast's memory, and use a looser --tol, fewer "
                       "--workers or a machine with more memory; completed samples are saved)", err=True)
            sys.exit(2)
        except BrokenPipeError:
            # The reader of the output has gone (`roughuq report FILE | head`): stop quietly, as a program that
            # SIGPIPE ends does (status 141), instead of click's status 1, which says "a bug" here.
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - the interpreter's final flush must not fail again
            sys.exit(EXIT_BROKEN_PIPE)
        except OSError as exc:
            if exc.errno == errno.ENAMETOOLONG:
                # A path the file system cannot name (a typo, a pasted paragraph) is what was typed: one line.
                name = str(exc.filename) if exc.filename is not None else "a path"
                shown = name if len(name) <= 60 else name[:57] + "..."
                click.echo(f"error: {shown}: file name too long ({len(name)} characters; {exc.strerror})", err=True)
                sys.exit(2)
            if exc.errno not in _WRITE_FAILURES:
                raise
            # A full disk or quota under the output (`roughuq report FILE > report.txt`) is the machine's, not a
            # bug: one line and status 2, as for a study file that cannot be written (was a traceback, status 1).
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - the interpreter's final flush must not fail again
            where = "the output" if exc.filename is None else exc.filename
            click.echo(f"error: could not write {where} ({exc.strerror})", err=True)
            sys.exit(2)
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
            sys.unraisablehook = previous_unraisable
            warnings.formatwarning = previous_format

    return wrapper


def _warning_line(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  line: str | None = None) -> str:
    """A Python warning that reaches the terminal as the commands' own: ``warning: ...`` (it printed
    ``<string>:19: EstimationWarning: ...``, the place in the code, which says nothing to a user)."""
    return f"warning: {message}\n"


def _console() -> Any:
    from rich.console import Console

    class _PipedConsole(Console):
        def on_broken_pipe(self) -> None:
            # rich exits with status 1 (a bug, here); the commands' wrapper stops with EXIT_BROKEN_PIPE instead.
            self.quiet = True
            raise BrokenPipeError

    # Logs and pipes get full-width tables rather than rich's default of 80 columns, and lines of text that are
    # not broken at that width (soft wrap): a run's sample counts or a command in a warning stay on one line, for
    # grep and copy-paste. A width asked for in COLUMNS is kept, as on a terminal.
    is_free_width = not sys.stdout.isatty() and not os.environ.get("COLUMNS")
    return _PipedConsole(width=160 if is_free_width else None, soft_wrap=is_free_width)


class _MemoryWatch(NamedTuple):
    """What the memory warnings of a command's progress need: where it runs, and how it gets to a lower level
    (``lower_with``; ``least_level`` the lowest it can stay at: below it only a smaller grid.coarsest helps)."""

    config: Any
    pool: Any
    executor: str
    lower_with: str
    least_level: int = 0


def _progress(quiet: bool, watch: _MemoryWatch | None = None) -> Any:
    """Progress output; with ``watch`` also the memory warnings.

    The pipeline announces every plan (screening levels, MLMC levels added
    as the run adapts, a shard's level) before computing it; the warning for
    the finest level still to compute is printed then, even when quiet.
    """
    from rough_uq.study.progress import Progress, make_progress

    inner = _stop_aware(make_progress(is_quiet=quiet))
    if watch is None:
        return inner

    class MemoryWatch(Progress):
        def __init__(self) -> None:
            self.checked = -1  # the finest level checked so far

        def start(self, title: str) -> None:
            inner.start(title)

        def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None:
            todo = [int(lv) for lv, planned, done in zip(levels, n_planned, n_done) if planned > done]
            if todo and max(todo) > self.checked:
                self.checked = max(todo)
                _warn_memory(watch.config, self.checked, watch.pool, watch.executor, lower_with=watch.lower_with,
                             least_level=watch.least_level)
            inner.plan(levels, n_planned, n_done)

        def advance(self, level: int, n: int) -> None:
            inner.advance(level, n)

        def note(self, text: str) -> None:
            inner.note(text)

        def stop(self, *, is_complete: bool = True) -> None:
            inner.stop(is_complete=is_complete)

    return MemoryWatch()


def _stop_aware(inner: Any) -> Any:
    """``inner`` progress that raises a recorded stop request at every plan and batch (:class:`_StopRequest`)."""
    from rough_uq.study.progress import Progress

    class StopAware(Progress):
        def start(self, title: str) -> None:
            inner.start(title)

        def plan(self, levels: Sequence[int], n_planned: Sequence[int], n_done: Sequence[int]) -> None:
            _check_stop()
            inner.plan(levels, n_planned, n_done)

        def advance(self, level: int, n: int) -> None:
            inner.advance(level, n)
            _check_stop()

        def note(self, text: str) -> None:
            inner.note(text)

        def stop(self, *, is_complete: bool = True) -> None:
            inner.stop(is_complete=is_complete)

    return StopAware()


def _executor(config: Any, workers: int | None, executor: str, scheduler: str | None) -> Any:
    from rough_uq.study.executors import make_executor

    return make_executor(executor, workers=workers, threads=config.solver.threads, scheduler=scheduler)


def _check_executor_options(executor: str, scheduler: str | None, workers: int | None) -> None:
    """Refuse ``--scheduler`` without ``--executor dask``, ``--workers`` with it, dask without a scheduler or with
    a malformed address, and more ``--workers`` than :func:`~rough_uq.study.executors.max_workers` (before anything
    is created)."""
    from rough_uq.study.executors import check_scheduler_address, check_workers

    if executor != "dask" and scheduler is not None:
        raise MisplacedOptionError("--scheduler", scheduler, context="without --executor dask",
                                   allowed="it applies only with --executor dask (the dask scheduler's address)")
    if executor == "dask" and workers is not None:
        raise MisplacedOptionError("--workers", workers, context="with --executor dask", allowed="it applies only "
                                   "to local processes; a dask cluster has the workers started for it")
    if executor == "dask" and not scheduler:
        raise MisplacedOptionError("--executor", executor, context="without --scheduler ADDRESS", allowed="it "
                                   "needs the address of a running dask scheduler, e.g. --scheduler tcp://host:8786")
    if executor == "dask":
        check_scheduler_address(scheduler, name="--scheduler")
    if workers is not None:
        check_workers(workers, name="--workers")


def _warn_memory(config: Any, level: int, pool: Any, executor: str = "local", *,
                 lower_with: str = "a smaller grid.max_level", least_level: int = 0) -> None:
    """Warn (one line on stderr) if ``level``'s solves, one per local worker, exceed this machine's memory.

    Nothing is said for a dask cluster: its workers run on other machines.
    """
    from rough_uq.study.config import memory_warning

    if executor == "dask":
        return
    text = memory_warning(config, level, getattr(pool, "n_workers", 1), lower_with=lower_with,
                          least_level=least_level)
    if text:
        click.echo(f"warning: {text}", err=True)


def _counted(n: int, noun: str) -> str:
    """``1 sample``, ``2 samples``: a count in words ("1 samples" read as a typo)."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _check_not_empty(option: str, text: str | None) -> None:
    """Refuse an empty path (it would silently mean the working directory or the default)."""
    if text is not None and not text.strip():
        raise InvalidParameterError(option, text, "a non-empty path")


def _check_output_file(option: str, text: str) -> None:
    """Refuse an empty output file path, a directory's, or one in a directory that does not exist (none is created).

    A path ending in a separator names a directory: ``sub/`` wrote a file named ``sub``.
    """
    _check_not_empty(option, text)
    if text.endswith(("/", os.sep)) or Path(text).is_dir():
        raise InvalidParameterError(option, text, "a file path (this one names a directory)")
    parent = Path(text).parent
    if not parent.exists():
        raise InvalidParameterError(option, text, f"a file in an existing directory ({parent} does not exist; "
                                    "create it first)")


def _dump(data: Any) -> None:
    click.echo(json.dumps(data, indent=2, default=str))


class _PositiveFinite(click.ParamType):
    """A finite number > 0 (click's FloatRange lets nan and inf through)."""

    name = "float"

    def convert(self, value: Any, param: Any, ctx: Any) -> float:
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number.", param, ctx)
        if not (math.isfinite(number) and number > 0):
            self.fail(f"{value!r} is not a finite number > 0.", param, ctx)
        return number


#: ``--workers`` of the commands that compute only locally (``sample``, ``sweep``: no ``--executor``).
_local_workers_option = click.option(
    "--workers", type=click.IntRange(min=1), default=None,
    help="Local worker processes (default: cores // solver.threads; 1 = in this process; at most 4 per core: "
         "more only share the cores).",
)
_workers_option = click.option(
    "--workers", type=click.IntRange(min=1), default=None,
    help="Local worker processes (default: cores // solver.threads; 1 = in this process; at most 4 per core: "
         "more only share the cores; not with --executor dask).",
)
_executor_option = click.option(
    "--executor", type=click.Choice(["local", "dask"]), default="local", show_default=True,
    help="Where samples are computed: local processes or a dask.distributed cluster.",
)
_scheduler_option = click.option(
    "--scheduler", default=None, metavar="ADDRESS",
    help="dask scheduler address (needed by --executor dask, refused without it)."
)
_quiet_option = click.option(
    "--quiet", "-q", is_flag=True,
    help="Print only the result, warnings and errors: no progress, no forecast, no notices.",
)


class _UsageLine(click.ClickException):
    """A click usage error told as every other user error: one ``error: ...`` line, exit status 2."""

    exit_code = 2

    def __init__(self, exc: click.UsageError, fallback: click.Context | None) -> None:
        ctx = exc.ctx or fallback
        hint = _misplaced_option_hint(exc, ctx)
        if hint:
            exc.possibilities = []  # click's "Did you mean ..." of a group option would contradict the hint
        message = " ".join(exc.format_message().split()).removesuffix(".")
        path = ctx.command_path if ctx is not None else "roughuq"
        where = f"{ctx.info_name}: " if ctx is not None and ctx.parent is not None else ""
        super().__init__(f"{where}{message}{hint}; see `{path} --help`")

    def show(self, file: Any = None) -> None:
        click.echo(f"error: {self.format_message()}", file=file, err=file is None)


def _misplaced_option_hint(exc: click.UsageError, ctx: click.Context | None) -> str:
    """For an option of some commands given before the command (``roughuq --workers 1 mlmc``): where it goes."""
    if not isinstance(exc, click.NoSuchOption) or ctx is None or not isinstance(ctx.command, click.Group):
        return ""
    group = ctx.command
    owners = [name for name in group.list_commands(ctx)
              if any(exc.option_name in (*param.opts, *param.secondary_opts) for param in group.commands[name].params)]
    if not owners:
        return ""
    usage = f"roughuq COMMAND {exc.option_name} ..."
    return f" (it is an option of {', '.join(owners)}: put it after the command, `{usage}`)"


class _OneLineUsage:
    """Mixin of the ``roughuq`` group and its commands: a usage error in their arguments as one line.

    Unknown options, missing arguments and values a parameter type refuses
    (``click.Choice``, ``click.IntRange``, ...) come out as
    ``error: mlmc: No such option '--tool' ...; see `roughuq mlmc --help```
    with exit status 2, like a :class:`RoughUQError` (:func:`_user_errors`),
    instead of click's usage block. Parsing is where the command's context is
    at hand (click leaves it out of some errors, e.g. an option without its value).
    """

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        try:
            return super().parse_args(ctx, args)  # type: ignore[misc]
        except click.UsageError as exc:
            raise _one_line(exc, ctx) from None


class _Command(_OneLineUsage, click.Command):
    """A ``roughuq`` command (:class:`_OneLineUsage`) whose single-value options may be given once.

    click keeps the last of repeated values: ``mc --level 0 --level 1`` ran on level 1 and ``--tol-cdf 0.5
    --tol-cdf 0.6`` at 0.6 without a word, where a repeated ``--tol`` NAME is refused.
    """

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        try:
            _refuse_repeated_options(self, args)
        except click.UsageError as exc:
            raise _one_line(exc, ctx) from None
        return super().parse_args(ctx, args)


def _refuse_repeated_options(command: click.Command, args: list[str]) -> None:
    """A :class:`click.UsageError` for an option that takes one value and is given more than once."""
    single = {opt: param for param in command.params if isinstance(param, click.Option)
              and not (param.multiple or param.is_flag or param.count) for opt in param.opts}
    values: dict[str, list[str]] = {}
    tokens = iter(args)
    for token in tokens:
        if token == "--":
            break
        name, has_value, value = token.partition("=")
        param = single.get(name) if name.startswith("--") else single.get(token)
        if param is None:
            continue
        if not has_value:
            value = next(tokens, "")
        values.setdefault(param.opts[0], []).append(value)
    for name, given in values.items():
        if len(given) > 1:
            shown = ", ".join(repr(value) for value in given)
            times = "twice" if len(given) == 2 else f"{len(given)} times"
            raise click.UsageError(f"Option '{name}' given {times} ({shown}); give it once")


class _Group(_OneLineUsage, click.Group):
    """The ``roughuq`` group (:class:`_OneLineUsage`); also an unknown command as one line.

    Help stays as it is: ``--help`` and a bare ``roughuq`` (whose help click
    8.2+ raises as a usage error) print it.
    """

    command_class = _Command

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta[_ARGUMENTS] = list(args)  # for the message of a stopped command (_stopped_text)
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except click.UsageError as exc:
            raise _one_line(exc, ctx) from None


def _one_line(exc: click.UsageError, ctx: click.Context | None) -> click.ClickException:
    """``exc`` as a :class:`_UsageLine`; click's help shown for no arguments is left to click."""
    is_help = isinstance(exc, getattr(click.exceptions, "NoArgsIsHelpError", ()))
    return exc if is_help else _UsageLine(exc, ctx)


@click.group(cls=_Group, name="roughuq", context_settings={"help_option_names": ["-h", "--help"]},
             epilog=_EXIT_CODES)
@click.version_option(__version__, prog_name="roughuq")
def main() -> None:
    """roughuq: statistics of rough-surface contact with Multilevel Monte Carlo.

    A study is one YAML config and one HDF5 file: `roughuq screen CONFIG`
    creates it and fits the rates, `roughuq mlmc --tol EPS` and `roughuq mc
    --tol EPS` run estimations into it, `roughuq report FILE` shows it.
    """


@main.command()
@click.argument("config_paths", metavar="CONFIG...", nargs=-1, required=True, type=click.Path(dir_okay=False))
@_user_errors
def validate(config_paths: Sequence[str]) -> None:
    """Check study configs and summarise each (status 2 if any is invalid).

    A config is valid if `roughuq screen` would accept it up to its first
    solve: the file and its fields, then the surface spectrum, loads and
    quantities of interest built from them, and every load against the
    solver's range (a dimensionless load p_mean L / (E* rms_height) in about
    [2e-298, 1e15], and at most solver.tol / (0.02 eps), where rounding still
    lets solves converge). Nothing is solved.
    """
    from rough_uq.study.config import machine_memory_bytes, solver_memory_bytes

    n_bad = 0
    for config_path in config_paths:
        try:
            config, _ = _config_file(config_path)
        except RoughUQError as exc:
            if len(config_paths) == 1:
                raise
            # Several files: say which one (messages about the file itself name it already).
            where = "" if str(config_path) in str(exc) else f"{config_path}: "
            click.echo(f"error: {where}{exc}", err=True)
            n_bad += 1
            continue
        grids = [config.grid.n_at(level) for level in range(config.grid.max_level + 1)]
        click.echo(f"{config_path}: valid (schema version {config.schema_version})")
        click.echo(f"  QoIs: {', '.join(f'{n} [{s.unit_label}]' for n, s in config.qoi.items())}")
        if config.load.n_loads > 1:  # the columns a run estimates (and names in --tol QOI@LOAD=EPS)
            loads = ", ".join(f"{value:g}" for value in config.load.values)
            click.echo(f"  load curve: {config.load.n_loads} {config.load.kind} loads ({loads}), "
                       f"{len(config.qoi_names)} columns QOI@LOAD")
        # Information only: a config is valid whatever machine reads it; commands warn before computing.
        finest, memory = solver_memory_bytes(grids[-1]), machine_memory_bytes()
        here = "" if memory is None else f"; this machine has {_memory(memory)}" + (
            ", too little for it" if finest > memory else "")
        # Measured: a worker peaked at some 208 MiB after a 32^2 solve (libraries, plans), 233 MiB at 512^2.
        click.echo(f"  grids: {', '.join(str(n) for n in grids)} (finest solve about {_memory(finest)} "
                   f"per worker, beyond the some 200 MiB a process takes to start{here})")
        click.echo(f"  screening: {_screening_summary(config)}")
        if config.surface.k_s >= grids[-1] / 2:
            click.echo(f"  resolution: k_s = {config.surface.k_s:g} is not below the Nyquist wave number of the "
                       f"finest grid ({grids[-1]}^2: {grids[-1] // 2}); each level truncates the spectrum at its "
                       "n/2, so even the finest surface lacks the shortest wavelengths (runs estimate that bias; "
                       "one that needs more stops at grid.max_level)")
        click.echo(f"  study file: {config.output.path}")
    if n_bad:
        sys.exit(2)


def _screening_summary(config: Any) -> str:
    """What ``roughuq screen`` would screen for ``config``, or why it cannot (a study too shallow to screen)."""
    from rough_uq.problem.runs import MIN_SCREENED_LEVELS

    if config.grid.max_level + 1 < MIN_SCREENED_LEVELS:
        return (f"none: it needs levels 0..{MIN_SCREENED_LEVELS - 1} and grid.max_level is {config.grid.max_level}; "
                "runs without a screening only (mc --level; mlmc --tol-var / --tol-cdf from grid.max_level 1)")
    return f"levels 0..{config.screening.levels - 1}, {config.screening.samples} samples each"


def _warm_kernels(model: Any, *, quiet: bool = False) -> None:
    """Compile (or load from numba's disk cache) the solver and QoI kernels before anything is timed.

    :func:`~rough_uq.problem.sampler.warm_up` runs every kernel a sample uses.
    Loading cached kernels takes a fraction of a second; if it takes longer (a
    fresh install compiles them), say so while it happens. Then the objects
    made so far are frozen for the garbage collector (:func:`freeze_garbage`).
    """
    import threading

    from rough_uq.problem.sampler import warm_up
    from rough_uq.study.executors import freeze_garbage

    start = time.perf_counter()
    notice = threading.Timer(
        COMPILE_NOTICE_SECONDS, lambda: click.echo("compiling kernels (first run only) ...", err=True)
    )
    if not quiet:
        notice.start()
    try:
        warm_up(model)
    finally:
        notice.cancel()
    freeze_garbage()
    seconds = time.perf_counter() - start
    if not quiet and seconds > COMPILE_NOTICE_SECONDS:
        click.echo(f"kernels compiled in {seconds:.1f} s (cached for the next runs)", err=True)


@main.command()
@click.argument("config_path", metavar="[CONFIG]", type=click.Path(dir_okay=False), required=False)
@click.option("--level", type=click.IntRange(min=0), default=0, show_default=True, help="Grid level.")
@click.option("--index", type=click.IntRange(min=0, max=MAX_INT64), default=0, show_default=True,
              help="Sample index.")
@_user_errors
def solve(config_path: str | None, level: int, index: int) -> None:
    """Solve one sample and print its QoIs, iterations and time (a demo).

    Without CONFIG, the shipped quickstart config is used. The sample is
    screening sample INDEX of LEVEL, i.e. exactly what `roughuq screen` stores.
    The time excludes compiling the kernels (first run only, announced).
    """
    from rough_uq.study.config import config_from_yaml_text, load_config
    from rough_uq.problem.sampler import STAGE_SCREENING, compute_batch
    from rough_uq.study.pipeline import build_model

    if config_path is None:
        config = config_from_yaml_text(_shipped_config_text("quickstart"), source="quickstart")
    else:
        config = load_config(config_path)
    if level > config.grid.max_level:
        raise InvalidParameterError("--level", level, f"an integer in 0..{config.grid.max_level} (grid.max_level)")
    model = build_model(config, source=config_path or "quickstart")
    _warm_kernels(model)
    start = time.perf_counter()
    batch = compute_batch(model, stage=STAGE_SCREENING, level=level, indices=[index])
    seconds = time.perf_counter() - start
    n = model.grid(level)
    pressures = ", ".join(f"{p:.4g}" for p in model.loads)
    click.echo(f"grid {n} x {n}, mean pressure {pressures} (E* = {model.e_star:g})")
    for (name, _, settings), value in zip(config.qoi_columns, batch.fine[0]):
        click.echo(f"  {name}: {value:.6g} {settings.unit_label}")
    status = "converged" if batch.converged[0, 0] else "NOT converged"
    click.echo(f"  solver: {batch.n_iter[0, 0]} iterations ({status}), {seconds:.3f} s")


#: Configs shipped as package data (``rough_uq/study/configs/NAME.yaml``), for ``roughuq init NAME``.
SHIPPED_CONFIGS = ("quickstart", "classic-area", "classic-clusters")


def _has_text(path: Path, text: str) -> bool:
    """Whether the file at ``path`` holds exactly ``text`` (False if it cannot be read as UTF-8 text)."""
    try:
        return path.is_file() and path.read_text(encoding="utf-8") == text
    except (OSError, UnicodeDecodeError):
        return False


def _shipped_config_text(name: str) -> str:
    """The text of a shipped config, read through importlib.resources (works from a wheel too)."""
    from importlib.resources import files

    if name not in SHIPPED_CONFIGS:
        raise InvalidParameterError("NAME", name, "one of " + ", ".join(SHIPPED_CONFIGS))
    return files("rough_uq.study").joinpath("configs", f"{name}.yaml").read_text(encoding="utf-8")


@main.command()
@click.argument("name", required=False)
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="File to write (default: NAME.yaml in the working directory).")
@click.option("--force", is_flag=True, help="Overwrite an existing file.")
@click.option("--list", "show_list", is_flag=True, help="List the shipped configs and exit.")
@_quiet_option
@_user_errors
def init(name: str | None, out: str | None, force: bool, show_list: bool, quiet: bool) -> None:
    """Write a shipped study config to the working directory, to edit and run.

    NAME is one of: quickstart (a small study, about a minute), classic-area,
    classic-clusters (the classic studies of the README). Then e.g.
    `roughuq screen quickstart.yaml`.
    """
    if show_list:
        if name is not None or out is not None:
            given = f"NAME {name}" if name is not None else f"--out {out}"
            raise RoughUQError(f"--list lists the shipped configs and writes none: give it alone (got {given})")
        for shipped in SHIPPED_CONFIGS:
            first = _shipped_config_text(shipped).splitlines()[0].lstrip("# ").strip()
            click.echo(f"{shipped}: {first}")
        return
    if name is None:
        raise InvalidParameterError("NAME", "(none)", "one of " + ", ".join(SHIPPED_CONFIGS) + " (or --list)")
    if out is not None:
        _check_output_file("--out", out)
    text = _shipped_config_text(name)
    target = Path(out or f"{name}.yaml")
    if target.exists() and not force:
        if _has_text(target, text):
            # The README's quick start runs `roughuq init quickstart && roughuq screen ...`: a second time, go on.
            if not quiet:
                click.echo(f"{target} is already the shipped {name} config, unchanged; next: roughuq screen {target}")
            return
        raise RoughUQError(f"{target} already exists; add --force to overwrite it, or --out FILE to write elsewhere")
    try:
        target.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise InvalidParameterError("--out", str(target), f"a writable file path ({exc.strerror})") from exc
    if not quiet:
        click.echo(f"wrote {target}; next: roughuq screen {target}")


@main.command()
@click.argument("config_path", metavar="CONFIG", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="Study file (default: the config's output.path).")
@_workers_option
@_executor_option
@_scheduler_option
@_quiet_option
@click.option("--json", "as_json", is_flag=True, help="Print the screening record as JSON.")
@_user_errors
def screen(config_path: str, out: str | None, workers: int | None, executor: str, scheduler: str | None,
           quiet: bool, as_json: bool) -> None:
    """Screen the levels: fit alpha, beta, gamma and predict what accuracy will cost.

    Creates the study file (or continues an interrupted screening in it).
    """
    _check_not_empty("--out", out)
    from rough_uq.problem.runs import MIN_SCREENED_LEVELS
    from rough_uq.study.pipeline import create_study, removed_if_left_unused, run_screening
    from rough_uq.report.summary import render_screening, screening_json

    _check_executor_options(executor, scheduler, workers)
    config, model = _config_file(config_path)
    # The file is created before the screening's own checks: refused, or interrupted before a sample, it goes again.
    study_path = out or config.output.path
    with removed_if_left_unused(study_path), create_study(config, out, model=model, source=config_path) as study:
        _warm_kernels(study.model, quiet=quiet or as_json)
        with _executor(config, workers, executor, scheduler) as pool:
            # A screening needs levels 0..2: a smaller screening.levels cannot go below level 2.
            watch = _MemoryWatch(study.config, pool, executor, "a smaller screening.levels",
                                 least_level=MIN_SCREENED_LEVELS - 1)
            outcome = run_screening(study, executor=pool, progress=_progress(quiet or as_json, watch))
        path = study.store.path
    record = outcome.record
    if as_json:
        _dump(screening_json(record))
        return
    console = _console()
    grids = [config.grid.n_at(level) for level in range(config.grid.max_level + 1)]
    units = {name: settings.unit_label for name, settings in config.qoi.items()}
    render_screening(console, record, config.qoi_names, units, grids=grids)
    for diagnostic in record.diagnostics:
        click.echo(f"warning: {diagnostic.message}", err=True)
    if record.n_not_converged:
        click.echo(f"warning: {record.n_not_converged} screening samples have a solve that did not converge "
                   f"within solver.max_iter (even after the retry); raise solver.max_iter or loosen solver.tol",
                   err=True)
    console.print(f"study file: {path}")


@dataclass(frozen=True)
class _RunOptions:
    """The options of ``roughuq mlmc`` / ``mc`` that every run takes: files, budget, executor, output."""

    study_path: str
    config_path: str | None
    max_cost: float | None
    as_json: bool
    workers: int | None
    executor: str
    scheduler: str | None
    quiet: bool


def _estimation_command(method: str) -> Callable[..., Any]:
    """The ``roughuq mlmc`` / ``roughuq mc`` command (``method``), with its options."""

    def command(tol: Sequence[str], study_path: str, config_path: str | None, max_cost: float | None,
                show_plan: bool, shard_size: int | None, with_resources: bool, as_json: bool, workers: int | None,
                executor: str, scheduler: str | None, quiet: bool, level: int | None = None,
                choice: str = "mlmc", tol_var: Sequence[str] = (), tol_cdf: str | None = None,
                qoi: str | None = None, thresholds: str | None = None, probabilities: str | None = None) -> None:
        _check_tolerance_texts("--tol", tol)
        _check_tolerance_texts("--tol-var", tol_var)
        _check_not_empty("--config", config_path)
        _check_not_empty("--study", study_path)
        study_path = _default_study(study_path, config_path)
        target = _target_of(tol, tol_var, tol_cdf, qoi=qoi, thresholds=thresholds, probabilities=probabilities)
        _refuse_misplaced_options(target, choice, show_plan, shard_size, with_resources)
        _check_executor_options(executor, scheduler, workers)
        opts = _RunOptions(study_path, config_path, max_cost, as_json, workers, executor, scheduler, quiet)
        from rough_uq.study.pipeline import removed_if_left_unused

        with removed_if_left_unused(study_path):  # a study file created from --config, then refused
            if target is not None:
                _run_target(target, tol_var=tol_var, tol_cdf=tol_cdf, qoi=qoi, thresholds=thresholds,
                            probabilities=probabilities, opts=opts)
            else:
                _run_mean(tol, method=method, choice=choice, level=level, show_plan=show_plan,
                          shard_size=shard_size, with_resources=with_resources, opts=opts)

    command = _user_errors(command)
    for option in reversed(_estimation_options(method)):
        command = option(command)
    return command


def _default_study(study_path: str | None, config_path: str | None) -> str:
    """``--study``, or by default the study ``roughuq screen`` writes for ``--config`` (its ``output.path``).

    Without this a config whose ``output.path`` is not ``results.h5`` (the shipped classic ones) screened into
    its file, and ``mlmc --config`` looked for ``results.h5`` (or created a second study there).
    """
    if study_path is not None:
        return study_path
    if not config_path:
        return DEFAULT_STUDY
    from rough_uq.study.config import load_config

    return load_config(config_path).output.path


#: The runs of ``roughuq mlmc`` / ``mc`` that create a missing study file from ``--config`` (:func:`_run_mean`).
_CREATING_RUNS = {"mlmc": "runs with --tol-var or --tol-cdf", "mc": "runs with --level"}


def _estimation_options(method: str) -> list[Callable[[Any], Any]]:
    """The click options of ``roughuq mlmc`` / ``roughuq mc``, in the order ``--help`` lists them."""
    options = [
        click.option("--tol", "tol", multiple=True, metavar="EPS|NAME=EPS",
                     help="Target RMS error: a number (single QoI) or NAME=EPS per QoI (each QoI once); "
                          "default: the config's qoi tol."),
        click.option("--study", "study_path", type=click.Path(dir_okay=False), default=None,
                     help=f"Study file (default: the --config's output.path, without --config {DEFAULT_STUDY})."),
        click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
                     help="Config to take estimation settings and tolerances from (must match the study's); "
                          f"{_CREATING_RUNS[method]}, which need no screening, create a missing --study from it."),
        click.option("--max-cost", type=_PositiveFinite(), default=None, metavar="SECONDS",
                     help="Budget in modelled cost, a finite number > 0 (reference seconds, about CPU-seconds on the "
                          "calibration machine): a plan predicted above it is refused, a run reaching it stops; "
                          "a round is drawn at the costs measured so far, so the last one may end above it "
                          "(default: the config's estimation.max_cost; without any, plans over a week of "
                          "CPU time are refused)."),
        click.option("--plan", "show_plan", is_flag=True, help="Print the samples still missing; compute nothing."),
        click.option("--shards", "shard_size", type=click.IntRange(min=1), default=None, metavar="SIZE",
                     help="With --plan: print one line 'STAGE LEVEL A:B' per shard of at most SIZE samples "
                          "(with --json: a list 'shards' of {stage, level, indices, n_samples})."),
        click.option("--resources", "with_resources", is_flag=True,
                     help="With --shards: add each shard's estimated wall seconds and peak MiB for one process."),
        click.option("--json", "as_json", is_flag=True, help="Print the result (or the plan) as JSON."),
        _workers_option,
        _executor_option,
        _scheduler_option,
        _quiet_option,
    ]
    if method == "mc":
        return options + [click.option(
            "--level", type=click.IntRange(min=0), default=None,
            help="Sample this level (no screening needed; its bias is then not estimated).",
        )]
    return options + _mlmc_only_options()


def _mlmc_only_options() -> list[Callable[[Any], Any]]:
    """The options ``roughuq mlmc`` has and ``roughuq mc`` has not: the variance and cdf targets, ``--method``."""
    return [
        click.option("--tol-var", "tol_var", multiple=True, metavar="EPS|NAME=EPS",
                     help="Estimate Var(Q) instead of the mean: tolerance on the RMS error of the variance, "
                          "in the QoI's unit squared (e.g. %^2), a number (single QoI) or NAME=EPS per QoI."),
        click.option("--tol-cdf", "tol_cdf", default=None, metavar="EPS",
                     help="Estimate the distribution function F(s) = P(Q <= s) of --qoi on --thresholds, and "
                          "its quantiles: tolerance on the largest RMS error of F over the thresholds "
                          "(dimensionless, in (0, 1))."),
        click.option("--qoi", "qoi", default=None, metavar="NAME",
                     help="With --tol-cdf: the QoI column (default: the only one)."),
        click.option("--thresholds", "thresholds", default=None, metavar="START:STOP:COUNT",
                     help=f"With --tol-cdf: COUNT (2 to {MAX_THRESHOLDS}) equally spaced values s from START to "
                          "STOP in the QoI's unit (default: the config's estimation.distribution.NAME.thresholds)."),
        click.option("--probabilities", "probabilities", default=None, metavar="P,P,...",
                     help="With --tol-cdf: the quantiles reported, distinct numbers in (0, 1) (default: the "
                          "config's, else 0.05,0.5,0.95)."),
        click.option(
            "--method", "choice", type=click.Choice(METHODS), default="mlmc", show_default=True,
            help="mlmc: plain MLMC (Richardson if the config's estimation.richardson says so); richardson: "
                 "Richardson-extrapolated MLMC where the level means allow it; mc: plain MC on the level the "
                 "bias needs; auto: the cheapest of the three as predicted by the screening (says why).",
        ),
    ]


def _check_tolerance_texts(option: str, values: Sequence[str]) -> None:
    """Refuse an empty ``--tol`` / ``--tol-var`` value or list item, and ``=EPS`` without a name.

    :func:`~rough_uq.study.pipeline.parse_tolerances` skips empty items (so ``--tol ""`` fell back to the
    config's tolerance) and reads ``=2`` as a bare 2.
    """
    for text in values:
        for part in text.split(","):
            name, sep, _ = part.strip().rpartition("=")
            if not part.strip() or (sep and not name):
                raise InvalidParameterError(option, text, "EPS or NAME=EPS, comma-separated, e.g. 0.2 or "
                                            "contact_area=0.2 (no empty item, no '=' without a name)")


def _target_of(
    tol: Sequence[str], tol_var: Sequence[str], tol_cdf: str | None, **cdf_options: str | None
) -> str | None:
    """``variance``, ``cdf`` or None (the mean) from the tolerance options; at most one kind may be given."""
    options = (("--tol", tol), ("--tol-var", tol_var), ("--tol-cdf", tol_cdf))
    given = [(name, value) for name, value in options if value]
    if len(given) > 1:
        text = " ".join(f"{name} {' '.join(value) if isinstance(value, (tuple, list)) else value}"
                        for name, value in given)
        raise InvalidParameterError(" / ".join(name for name, _ in given), text, "exactly one of --tol (mean), "
                                    "--tol-var (variance) or --tol-cdf (distribution function)")
    extra = [f"--{name}" for name, value in cdf_options.items() if value is not None]
    if extra and tol_cdf is None:
        raise MisplacedOptionError(extra[0], cdf_options[extra[0][2:]], context="without --tol-cdf",
                                   allowed="it applies only with --tol-cdf (the distribution function)")
    if tol_var:
        return "variance"
    return "cdf" if tol_cdf is not None else None


def _mean_only_options(choice: str, show_plan: bool, shard_size: int | None,
                       with_resources: bool) -> list[tuple[str, Any]]:
    """The options given that only runs of the mean take, as ``(name, value)`` (value None for a flag)."""
    given = [("--method", choice, choice != "mlmc"), ("--plan", None, show_plan),
             ("--shards", shard_size, shard_size is not None), ("--resources", None, with_resources)]
    return [(name, value) for name, value, is_given in given if is_given]


def _refuse_misplaced_options(target: str | None, choice: str, show_plan: bool, shard_size: int | None,
                              with_resources: bool) -> None:
    """Refuse options given where they do not apply: mean-only ones with a target, plan ones without ``--plan``."""
    if target is not None:
        mean_only = _mean_only_options(choice, show_plan, shard_size, with_resources)
        if mean_only:
            name, value = mean_only[0]
            option = "--tol-var" if target == "variance" else "--tol-cdf"
            raise MisplacedOptionError(name, value, context=f"with {option}", allowed="--method, --plan, --shards "
                                       "and --resources apply only to runs of the mean (--tol)")
        return
    if shard_size is not None and not show_plan:
        raise MisplacedOptionError("--shards", shard_size, context="without --plan",
                                   allowed="it applies only with --plan (it splits the plan into shards)")
    if with_resources and (shard_size is None or not show_plan):
        missing = " ".join(name for name, is_given in (("--plan", show_plan), ("--shards SIZE", shard_size is not None))
                           if not is_given)
        raise MisplacedOptionError("--resources", None, context=f"without {missing}", allowed="it applies only "
                                   "with --plan --shards SIZE (it adds each shard's time and memory)")


def _cdf_tolerance(text: str) -> Any:
    """``--tol-cdf``: one number in [MIN_TOL, 1), as the array of one tolerance the pipeline takes."""
    import numpy as np

    from rough_uq.multilevel.distribution import check_cdf_tol

    try:
        eps = float(text)
    except ValueError:
        eps = math.nan
    try:
        return np.array([check_cdf_tol(eps, "--tol-cdf")])
    except InvalidParameterError as exc:
        raise InvalidParameterError("--tol-cdf", text, exc.allowed) from None


def _thresholds(text: str | None) -> Any:
    """``--thresholds START:STOP:COUNT`` as the array of COUNT equally spaced values (None if not given)."""
    import numpy as np

    if text is None:
        return None
    allowed = (f"START:STOP:COUNT with START < STOP (STOP - START a finite number) and an integer COUNT in "
               f"2..{MAX_THRESHOLDS}, in the QoI's unit (e.g. 15:25:41)")
    parts = text.split(":")
    try:
        start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
    except (ValueError, IndexError):
        raise InvalidParameterError("--thresholds", text, allowed) from None
    # A span beyond the floats (-1e308:1e308:5) made nan thresholds and numpy's overflow warnings.
    is_grid = math.isfinite(stop - start) and start < stop and 2 <= count <= MAX_THRESHOLDS
    if len(parts) != 3 or not is_grid:
        raise InvalidParameterError("--thresholds", text, allowed)
    values = np.linspace(start, stop, count)
    if np.any(np.diff(values) <= 0):
        raise InvalidParameterError("--thresholds", text, f"{allowed}; COUNT distinct numbers (here neighbours round "
                                    "to one float: fewer thresholds or a wider range)")
    return values


def _probabilities(text: str | None) -> tuple[float, ...] | None:
    """``--probabilities P,P,...`` (None if not given)."""
    if text is None:
        return None
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        values = ()
    if not values or not all(0 < p < 1 for p in values) or len(set(values)) != len(values):
        raise InvalidParameterError("--probabilities", text, "comma-separated distinct numbers in (0, 1), "
                                    "e.g. 0.05,0.95")
    return values


def _config_creating_study(opts: _RunOptions, *, may_create: bool = True,
                           check: Callable[[Any, Any], None] | None = None) -> Any:
    """The ``--config`` (None without one); if ``may_create``, a new study is created from it where none exists.

    Target runs and MC on a given ``--level`` need no screening. ``check(config,
    model)`` runs before the file is created: what the run refuses before its
    first sample would otherwise leave an empty study file behind.
    """
    from rough_uq.study.config import load_config
    from rough_uq.study.pipeline import create_study

    if not opts.config_path:
        return None
    if not (may_create and not Path(opts.study_path).exists()):
        return load_config(opts.config_path)
    config, model = _config_file(opts.config_path)  # a model build_model refuses: refused before the file exists
    if check is not None:
        check(config, model)
    create_study(config, opts.study_path, model=model).close()
    return config


def _config_file(config_path: str) -> tuple[Any, Any]:
    """The config in the file ``config_path`` and its contact model, whose refusals name the file too.

    :func:`~rough_uq.study.config.load_config` names the file in its errors;
    the model's refusals (``surface.rms_height, surface.system_size: got
    (1.0, 1e-300)``) are of the same file, and a loop over configs needs to
    know which one.
    """
    from rough_uq.study.config import load_config
    from rough_uq.study.pipeline import build_model

    config = load_config(config_path)
    return config, build_model(config, source=config_path)


def _run_target(target: str, *, tol_var: Sequence[str], tol_cdf: str | None, qoi: str | None,
                thresholds: str | None, probabilities: str | None, opts: _RunOptions) -> None:
    """``roughuq mlmc --tol-var`` / ``--tol-cdf``: run the target, print it as `roughuq report` does.

    Exits with status 3 if the tolerance was missed.
    """
    from rough_uq.study.pipeline import (
        cdf_request,
        check_target_run,
        open_existing_study,
        parse_tolerances,
        run_target,
    )

    grid, wanted = _thresholds(thresholds), _probabilities(probabilities)

    def requested(config: Any) -> tuple[Any, Any]:
        """The run's tolerances and (cdf) request of ``config``: refuses an unknown QoI, a bad value."""
        if target == "variance":
            return parse_tolerances(tol_var, config, option="--tol-var", use_config=False), None
        return _cdf_tolerance(tol_cdf), cdf_request(config, column=qoi, thresholds=grid, probabilities=wanted)

    def check(config: Any, model: Any) -> None:
        requested(config)
        check_target_run(config, max_cost=opts.max_cost, model=model, source=opts.config_path)

    config = _config_creating_study(opts, check=check)
    with open_existing_study(opts.study_path, config=config, source=opts.config_path) as study:
        tolerances, request = requested(study.config)
        with _executor(study.config, opts.workers, opts.executor, opts.scheduler) as pool:
            watch = _MemoryWatch(study.config, pool, opts.executor, "a looser tolerance")
            record = run_target(study, target=target, tol=tolerances, executor=pool, request=request,
                                progress=_progress(opts.quiet or opts.as_json, watch), max_cost=opts.max_cost)
    option = "--tol-var" if target == "variance" else "--tol-cdf"
    _show_finished_run(opts.study_path, record.run_id, record.outcome, as_json=opts.as_json, option=option)


def _run_mean(tol: Sequence[str], *, method: str, choice: str, level: int | None, show_plan: bool,
              shard_size: int | None, with_resources: bool, opts: _RunOptions) -> None:
    """A run of the mean (``--tol``): print its plan (``--plan``), or run it and show it; exit 3 if missed."""
    from rough_uq.study.pipeline import (
        check_initial_samples,
        choose_method,
        open_existing_study,
        parse_tolerances,
        run_id,
    )

    # Only MC on a given --level needs no screening: any other run would find the new study empty and refuse.
    def check(config: Any, model: Any) -> None:
        check_initial_samples(config, n_levels=1, run="mc --level", source=opts.config_path)

    config = _config_creating_study(opts, may_create=level is not None and not show_plan, check=check)
    with open_existing_study(opts.study_path, config=config, writable=not show_plan,
                             source=opts.config_path) as study:
        tolerances = parse_tolerances(tol, study.config)
        cap = study.config.estimation.max_cost if opts.max_cost is None else opts.max_cost
        run_method = _chosen_method(study, choice, method, tolerances, cap, choose_method, opts.quiet or opts.as_json)
        if show_plan:
            _show_missing(study, run_method, tolerances, cap, level, as_json=opts.as_json, shard_size=shard_size,
                          with_resources=with_resources)
            return
        record = _estimate(study, run_method, tolerances, cap, level, opts)
        estimation = study.config.estimation
        key = run_id(run_method, study.config.qoi_names, tolerances, estimation.theta, level,
                     richardson=estimation.richardson)
    _show_finished_run(opts.study_path, key, record.outcome, as_json=opts.as_json, option="--tol")


def _show_missing(study: Any, method: str, tolerances: Any, cap: float | None, level: int | None, *,
                  as_json: bool, shard_size: int | None, with_resources: bool) -> None:
    """``--plan``: print the samples the run still misses (a plan its forecast refuses is an error, as for the run)."""
    from rough_uq.study.pipeline import forecast_run, missing_samples

    forecast_run(study, method=method, tol=tolerances, max_cost=cap, level=level)
    work = missing_samples(study, method=method, tol=tolerances, max_cost=cap, level=level)
    if work.missing:  # as the run warns before its first sample there; for one solve (`sample` counts its workers)
        watch = _run_watch(study.config, None, "local", method, level)
        _warn_memory(study.config, max(work.missing), None, lower_with=watch.lower_with,
                     least_level=watch.least_level)
    resources = None
    if with_resources:
        from rough_uq.study.resources import shard_resources

        resources = shard_resources(study, stage=work.stage, levels=list(work.missing))
    _print_plan(work, as_json, shard_size, resources)


def _run_watch(config: Any, pool: Any, executor: str, method: str, level: int | None) -> _MemoryWatch:
    """The memory warnings of a run: a lower level by its option; an mlmc run samples levels 0..2 at least, so
    below level 2 only a smaller grid.coarsest helps."""
    if level is not None:
        return _MemoryWatch(config, pool, executor, "a smaller --level")
    return _MemoryWatch(config, pool, executor, "a looser --tol", least_level=2 if method == "mlmc" else 0)


def _estimate(study: Any, method: str, tolerances: Any, cap: float | None, level: int | None,
              opts: _RunOptions) -> Any:
    """Run the estimation into ``study`` (its forecast printed first, except as JSON or quiet); the run's record."""
    from rough_uq.study.pipeline import forecast_run, run_estimation

    with _executor(study.config, opts.workers, opts.executor, opts.scheduler) as pool:
        forecast = forecast_run(study, method=method, tol=tolerances, max_cost=cap, level=level,
                                n_workers=getattr(pool, "n_workers", 1))
        if not (opts.as_json or opts.quiet):
            _print_forecast(forecast, method)
        watch = _run_watch(study.config, pool, opts.executor, method, level)
        # The option itself (None: the config's estimation.max_cost, which the run then names so).
        return run_estimation(study, method=method, tol=tolerances, executor=pool,
                              progress=_progress(opts.quiet or opts.as_json, watch), max_cost=opts.max_cost,
                              level=level, forecast=forecast)


#: Choices of ``roughuq mlmc --method``.
METHODS = ("mlmc", "richardson", "mc", "auto")


def _chosen_method(study: Any, choice: str, method: str, tolerances: Any, cap: float | None, choose_method: Any,
                   quiet: bool) -> str:
    """The estimator ``--method`` asks for (``mc`` or ``mlmc``); Richardson is set in ``study.config``."""
    if method != "mlmc" or choice == "mlmc":
        return method
    richardson = choice == "richardson"
    if choice == "auto":
        chosen = choose_method(study, tol=tolerances, max_cost=cap)
        if not quiet:
            click.echo(f"method auto: {chosen.reason}", err=True)
        method, richardson = chosen.method, chosen.richardson
    elif choice == "mc":
        method = "mc"
    estimation = study.config.estimation.model_copy(update={"richardson": richardson})
    study.config = study.config.model_copy(update={"estimation": estimation})
    return method


def _show_finished_run(study_path: str, run_id: str, outcome: Any, *, as_json: bool, option: str) -> None:
    """Print a finished run as `roughuq report` does (the same numbers); exit 3 if its tolerance was not met."""
    from rough_uq.report.summary import ReportedRun, study_report
    from rough_uq.study.pipeline import open_existing_study

    with open_existing_study(study_path, writable=False) as study:
        report = study_report(study.store, study.config)
    shown = next(run for run in report["runs"] if run["run_id"] == run_id)
    if as_json:
        _dump(shown)
    else:
        _print_run(ReportedRun.from_json(shown), report)
    if not outcome.tol_met:
        click.echo(f"tolerance not met ({outcome.stop_reason}): {_what_to_change(outcome, option)}", err=True)
        sys.exit(EXIT_TOL_NOT_MET)


def _what_to_change(outcome: Any, option: str = "--tol") -> str:
    """What to change so that a run whose ``outcome`` missed its tolerance meets it (``option`` is its tolerance's)."""
    from rough_uq.multilevel.distribution import BANDWIDTH_TOO_WIDE, THRESHOLDS_MISS_SAMPLES
    from rough_uq.report.summary import is_bias_in_noise

    reason = outcome.stop_reason
    if reason == "max_cost" and not outcome.is_bias_estimated and option != "--tol":
        # A variance or cdf run estimates its bias once its first levels have their initial samples, whatever
        # the tolerance (rough_uq.multilevel.targets); the samples of a mean run follow --tol.
        return ("the run reached --max-cost before its bias was estimated; raise --max-cost (or estimation.max_cost) "
                f"or lower estimation.initial_samples (a looser {option} needs the same initial samples)")
    if reason == "max_cost":
        return f"the run reached --max-cost; raise --max-cost (or estimation.max_cost) or loosen {option}"
    if reason == "bias":
        return (f"the bias on this level exceeds the tolerance's share; loosen {option}, use `roughuq mlmc`, or "
                "a study with a larger grid.max_level")
    if reason == THRESHOLDS_MISS_SAMPLES:
        return ("the thresholds miss the samples of a level (see the warning); put thresholds among the values "
                "(extend --thresholds or the config's thresholds) or raise estimation.initial_samples")
    if reason == BANDWIDTH_TOO_WIDE:
        return ("the smoothing bandwidth, twice the thresholds' spacing, exceeds twice the spread of the values (see "
                "the warning); give finer thresholds (--thresholds or the config's thresholds)")
    if reason == "max_level" and is_bias_in_noise(outcome):
        return ("the bias estimate rests on level terms within their noise (see the warning); raise "
                f"estimation.initial_samples to measure it, loosen {option}, or use a study with a larger "
                "grid.max_level")
    if reason == "max_level":
        # Variance and cdf runs need no screening.
        where = "screen a new study" if option == "--tol" else "run it on a new study (no screening needed)"
        return (f"the bias needs a grid finer than grid.max_level; loosen {option}, or {where} with a larger "
                "grid.max_level")
    return f"loosen {option}, raise --max-cost, or use a study with a larger grid.max_level"


def _print_forecast(forecast: Any, method: str) -> None:
    """The prediction of a run, before its first sample (stderr: it is not the result; times to 2 digits)."""
    from rough_uq.study.progress import format_duration

    if forecast is None:
        click.echo("forecast: none (no usable screening to predict from)", err=True)
        return
    if method == "mc":
        samples = f"level {forecast.finest_level} ({forecast.grid}^2), N {forecast.n_samples[0]}"
    else:
        # From the plan's coarsest level, as the run reports its levels: "levels 0..3, N_l 0 11 2 2" read as
        # another hierarchy than the run's "levels 1..3, N_l 11 2 2".
        counts = list(forecast.n_samples)
        base = next((level for level, n in enumerate(counts) if n > 0), 0)
        samples = (f"levels {base}..{forecast.finest_level} (finest {forecast.grid}^2), "
                   f"N_l {' '.join(str(n) for n in counts[base:])}")
    click.echo(f"forecast: {samples}", err=True)
    elapsed, cpu = (format_duration(seconds, digits=2) for seconds in (forecast.wall_seconds, forecast.cpu_seconds))
    click.echo(f"forecast: about {elapsed} elapsed ({cpu} CPU, modelled cost {forecast.modelled_cost:.3g} ref-s), "
               f"memory about {_mib(forecast.memory_bytes)} MiB", err=True)
    if forecast.n_stored:
        rest = format_duration(forecast.wall_seconds * forecast.remaining_fraction, digits=2)
        click.echo(f"forecast: {_counted(sum(forecast.n_stored), 'sample')} of these are stored already (merged "
                   f"shards or an earlier run); about {rest} elapsed for the rest", err=True)
    if forecast.richardson_note:
        # The screening's level means decided; the run decides again from its own, and may extrapolate after all.
        click.echo(f"forecast: plain MLMC planned ({forecast.richardson_note}); the run decides again from its own "
                   "level means", err=True)


def _memory(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.1f} GiB" if n_bytes >= 2**30 else f"{_mib(n_bytes)} MiB"


def _mib(n_bytes: float) -> str:
    mib = n_bytes / 2**20
    return f"{mib:.2g}" if mib < 10 else f"{mib:.0f}"


def _print_plan(work: Any, as_json: bool, shard_size: int | None = None, resources: Any = None) -> None:
    if shard_size is not None:
        shards = _shards(work, shard_size, resources)
        if as_json:
            _dump({"run_id": work.run_id, "stage": work.stage, "n_missing": work.n_missing, "shard_size": shard_size,
                   "shards": shards})
            return
        # For shell loops: `while read stage level indices; do roughuq sample ...; done`.
        for shard in shards:
            extra = "" if resources is None else f" {shard['seconds']} {shard['memory_mib']}"
            click.echo(f"{shard['stage']} {shard['level']} {shard['indices']}{extra}")
        return
    rows = [{"level": level, "n_missing": int(indices.size), "indices": _ranges(indices)}
            for level, indices in work.missing.items()]
    if as_json:
        _dump({"run_id": work.run_id, "stage": work.stage, "n_missing": work.n_missing, "levels": rows})
        return
    click.echo(f"run {work.run_id} (stage {work.stage}): {_counted(work.n_missing, 'sample')} missing")
    for row in rows:
        click.echo(f"  level {row['level']}: {row['n_missing']} missing, indices {' '.join(row['indices'])}")


def _shards(work: Any, shard_size: int, resources: Any) -> list[dict[str, Any]]:
    """The shards of ``work`` (:meth:`~rough_uq.study.pipeline.WorkPlan.shards`): stage, level, indices ``A:B``, count.

    With ``resources``, also each shard's estimated wall seconds and peak MiB (rounded up), for batch
    systems' --time and --mem.
    """
    shards = []
    for level, first, last in work.shards(shard_size):
        shard = {"stage": int(work.stage), "level": int(level), "indices": f"{first}:{last}", "n_samples": last - first}
        if resources is not None:
            shard["seconds"] = math.ceil(resources.seconds(level, last - first))
            shard["memory_mib"] = math.ceil(resources.memory_bytes[level] / 2**20)
        shards.append(shard)
    return shards


def _ranges(indices: Any) -> list[str]:
    """Contiguous runs of sorted indices as ``A:B`` (half-open), the form `roughuq sample --indices` takes."""
    from rough_uq.study.pipeline import index_ranges

    return [f"{start}:{stop}" for start, stop in index_ranges(indices)]


def _print_run(run: Any, report: dict[str, Any]) -> None:
    """A finished :class:`~rough_uq.report.summary.ReportedRun` as `roughuq report` shows it, then its warnings."""
    from rough_uq.report.summary import format_run

    for line in format_run(run.record, report["qoi_names"], report["config"]["qoi"],
                           measured_ratio=run.measured_ratio):
        click.echo(line)
    outcome = run.record.outcome
    for diagnostic in outcome.diagnostics:
        click.echo(f"warning: {diagnostic.message}", err=True)
    if outcome.n_not_converged:
        click.echo(f"warning: {outcome.n_not_converged} samples with a non-converged solve are included", err=True)


main.command(name="mlmc", help="Multilevel Monte Carlo to a tolerance; samples and result go to the study file.")(
    _estimation_command("mlmc")
)
main.command(name="mc", help="Plain Monte Carlo on the finest level the tolerance needs, or on --level (the "
                              "baseline).")(
    _estimation_command("mc")
)


def _parse_indices(text: str) -> Any:
    """``A:B`` (half-open), ``I``, or a comma-separated list of those, as a sorted index array.

    At most :data:`~rough_uq.multilevel.drivers.adaptive.MAX_PLANNED_SAMPLES` samples (counted
    before overlaps are merged), each index at most :data:`MAX_INT64`.
    """
    import numpy as np

    from rough_uq.multilevel.drivers import MAX_PLANNED_SAMPLES

    ranges = [_index_range(text, part) for part in text.split(",")]
    if sum(last - first for first, last in ranges) > MAX_PLANNED_SAMPLES:
        raise InvalidParameterError("--indices", text, f"at most {MAX_PLANNED_SAMPLES} samples in one shard "
                                    "(split them over several shards)")
    # first + arange(n), not arange(first, last): a stop of 2^63 is beyond int64 and would make floats.
    return np.unique(np.concatenate([first + np.arange(last - first, dtype=np.int64) for first, last in ranges]))


def _index_range(text: str, part: str) -> tuple[int, int]:
    """One part ``A:B`` or ``I`` of ``--indices`` ``text`` as the half-open range ``(first, last)``."""
    start, sep, stop = part.strip().partition(":")
    try:
        first = int(start)
        last = int(stop) if sep else first + 1
    except ValueError:
        raise InvalidParameterError("--indices", text, "ranges A:B (half-open) or indices, comma-separated") from None
    if first < 0 or last <= first:
        raise InvalidParameterError("--indices", text, "ranges A:B with 0 <= A < B")
    if last > MAX_INT64 + 1:
        raise InvalidParameterError("--indices", text, f"indices in 0..{MAX_INT64} (stored as int64)")
    return first, last


@main.command()
@click.option("--study", "study_path", type=click.Path(dir_okay=False), default=DEFAULT_STUDY, show_default=True,
              help="Study file (only read).")
@click.option("--stage", required=True,
              help="Stage of the samples: 'screening', the number `--plan` prints, or a run id as `roughuq report` "
                   "prints it (as `show --stage`).")
@click.option("--level", type=click.IntRange(min=0), required=True, help="Level of the samples.")
@click.option("--indices", required=True, metavar="A:B[,C:D]",
              help="Sample indices, comma-separated half-open ranges A:B or single indices (at most 10^7 "
                   "samples per shard).")
@click.option("--out", "out", type=click.Path(dir_okay=False), required=True, help="Shard file to write.")
@_local_workers_option
@_quiet_option
@_user_errors
def sample(study_path: str, stage: str, level: int, indices: str, out: str, workers: int | None,
           quiet: bool) -> None:
    """Compute the given samples into a shard file (for cluster job arrays); merge it later.

    The shard is written under a temporary name and renamed when complete.
    """
    _check_not_empty("--study", study_path)
    from rough_uq.study.pipeline import compute_shard, open_existing_study

    _check_executor_options("local", None, workers)
    _check_output_file("--out", out)
    wanted = _parse_indices(indices)
    with open_existing_study(study_path, writable=False, options="--study") as study:
        stage_id = _stage_of(study, stage)  # a run id too, as `show --stage` takes it (it was refused here)
        with _executor(study.config, workers, "local", None) as pool:
            watch = _MemoryWatch(study.config, pool, "local", "a study with a smaller grid.max_level")
            path = compute_shard(study, stage=stage_id, level=level, indices=wanted, out=out, executor=pool,
                                 progress=_progress(quiet, watch))
    click.echo(f"{path}: {_counted(wanted.size, 'sample')} of stage {stage_id}, level {level}")


@main.command()
@click.argument("shards", metavar="SHARD...", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--into", "study_path", type=click.Path(dir_okay=False), default=DEFAULT_STUDY, show_default=True,
              help="Study file to add the samples to.")
@_quiet_option
@_user_errors
def merge(shards: Sequence[str], study_path: str, quiet: bool) -> None:
    """Add the samples of shard files to a study (duplicates are skipped with a warning)."""
    _check_not_empty("--into", study_path)
    from rough_uq.study.pipeline import merge_shards, open_existing_study

    with open_existing_study(study_path, options="--into") as study:
        counts = merge_shards(study, shards)
    click.echo(f"{study_path}: added {_counted(counts['added'], 'sample')} from {_counted(len(shards), 'shard')}")
    if counts["duplicates"]:
        click.echo(f"warning: skipped {_counted(counts['duplicates'], 'sample')} already in the study", err=True)
    if quiet:
        return
    for path in counts["studies"]:
        click.echo(f"note: {path} is a study file, not a shard: only its samples are merged (the new ones added), "
                   "not its screening or runs", err=True)


@main.command()
@click.argument("config_path", metavar="CONFIG", type=click.Path(dir_okay=False))
@click.option("--set", "assignments", required=True, multiple=True, metavar="KEY=V1,V2,...",
              help="Dotted config field and its distinct values, e.g. surface.system_size=1,2,3,4 (once; not "
                   "output.* or screening.*, which a sweep does not use).")
@click.option("--fixed-spacing", is_flag=True,
              help="With surface.system_size and a spectrum in surface.wavelengths: scale grid.coarsest with "
              "the box (same grid spacing).")
@click.option("--tol", "tol", multiple=True, metavar="EPS|NAME=EPS",
              help="MC tolerance (as for `roughuq mc`), in each study's unit of the QoI; not for a swept qoi.NAME.tol.")
@click.option("--level", type=click.IntRange(min=0), default=0, show_default=True, help="Level sampled by MC.")
@click.option("--dir", "directory", type=click.Path(file_okay=False), default=None,
              help="Where the configs and study files go (default: sweep-KEY, e.g. sweep-surface.system_size).")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
@_local_workers_option
@_quiet_option
@_user_errors
def sweep(config_path: str, assignments: Sequence[str], fixed_spacing: bool, tol: Sequence[str], level: int,
          directory: str | None, as_json: bool, workers: int | None, quiet: bool) -> None:
    """Plain MC estimates for several values of one config field, one study per value.

    E.g. the box-size question: `roughuq sweep classic-area.yaml --set
    surface.system_size=1,2,3,4 --fixed-spacing --tol 0.5`. Rerunning resumes.
    """
    from rough_uq.study.config import load_config, sweep_configs
    from rough_uq.study.pipeline import build_model, run_sweep

    _check_executor_options("local", None, workers)
    _check_tolerance_texts("--tol", tol)
    _check_not_empty("--dir", directory)
    key, values = _sweep_assignment(assignments)
    config = load_config(config_path)
    configs = sweep_configs(config, key=key, values=values, fixed_spacing=fixed_spacing)
    for value, swept in configs:  # every value, before the first one's study is made and run
        build_model(swept, source=f"--set {key}={value}")
    max_level = min(swept.grid.max_level for _, swept in configs)
    if level > max_level:  # before any study of the sweep is created
        raise InvalidParameterError("--level", level, f"an integer in 0..{max_level} (grid.max_level)")
    with _executor(config, workers, "local", None) as pool:
        largest = max((swept for _, swept in configs), key=lambda swept: swept.grid.n_at(level))
        _warn_memory(largest, level, pool, lower_with="a smaller --level")
        rows = run_sweep(configs, key=key, directory=directory or f"sweep-{key}", tol=tol, level=level, executor=pool,
                         progress=_progress(quiet or as_json), source=config_path)
    if as_json:
        _dump([row.to_json() for row in rows])
        return
    from rough_uq.report.summary import render_sweep

    # Each value's own units: qoi.NAME.unit may be the swept field.
    units = [{name: settings.unit_label for name, settings in swept.qoi.items()} for _, swept in configs]
    render_sweep(_console(), rows, key=key, level=level, units=units)


#: Config sections a sweep does not use, and why sweeping them means nothing.
UNSWEPT_SECTIONS = {
    "output": "the sweep names each value's study file itself",
    "screening": "a sweep runs plain MC on --level, without a screening",
}


def _sweep_assignment(assignments: Sequence[str]) -> tuple[str, list[str]]:
    """``--set KEY=V1,V2,...`` (given once) as the dotted key and its values as written."""
    if len(assignments) > 1:
        raise InvalidParameterError("--set", " ".join(assignments), "one --set KEY=V1,V2,... (a sweep varies one "
                                    "field; sweep the others in a second sweep)")
    key, sep, values = assignments[0].partition("=")
    if not sep or not key or not values:
        raise InvalidParameterError("--set", assignments[0], "KEY=V1,V2,... e.g. surface.system_size=1,2,3,4")
    section = key.split(".")[0]
    if section in UNSWEPT_SECTIONS:
        raise InvalidParameterError("--set", assignments[0], f"a field outside {section}.*: "
                                    f"{UNSWEPT_SECTIONS[section]}")
    return key, values.split(",")


@main.command()
@click.argument("study_path", metavar="FILE", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@click.option("--plots", "plots_dir", type=click.Path(file_okay=False), default=None,
              help="Also write PNG figures to this folder, those the study has data for: rates, cost vs "
                   "tolerance, samples per level, the load curve (several loads), one CDF per column (cdf runs).")
@_user_errors
def report(study_path: str, as_json: bool, plots_dir: str | None) -> None:
    """Show what a study file holds: config, screening, rates, every run, warnings."""
    _check_not_empty("FILE", study_path)
    from rough_uq.report.summary import read_report, render_report

    _check_not_empty("--plots", plots_dir)
    data = read_report(study_path)
    written = []
    is_new_folder = plots_dir is not None and not Path(plots_dir).exists()
    if plots_dir is not None:
        from rough_uq.report.figures import write_report_plots

        written = _writing(plots_dir, lambda: write_report_plots(data, plots_dir))
    if as_json:
        _dump({**data, "plots": [str(path) for path in written]} if plots_dir is not None else data)
        return
    render_report(data, _console())
    for path in written:
        click.echo(f"wrote {path}")
    if plots_dir is not None and not written:
        where = f"(and made no folder {plots_dir})" if is_new_folder else f"to {plots_dir}"
        click.echo(f"wrote no figure {where}: the figures draw a screening, finished mlmc and mc --tol runs, load "
                   "curves and cdf runs, and this study has none of them yet (an mc --level run has no figure of its "
                   "own: its estimate is in the report above)")


def _writing(target: str, write: Callable[[], Any]) -> Any:
    """Run ``write``; an output that cannot be written becomes one ``error:`` line (status 2)."""
    try:
        return write()
    except OSError as exc:
        reason = exc.strerror or str(exc)
        where = exc.filename or target
        raise RoughUQError(f"cannot write {where}: {reason}; choose another place") from None


def _stage_of(study: Any, text: str) -> int:
    """``--stage``: 'screening', a run id (as `roughuq report` prints it) or a stage number."""
    return _stage_and_name(study, text)[0]


def _stage_and_name(study: Any, text: str) -> tuple[int, str]:
    """The stage of ``--stage`` (:func:`_stage_of`) and its name as typed: the screening, run <id> or stage <n>."""
    from rough_uq.study.records import read_run_records

    if text == "screening":
        return 0, "the screening"
    runs = read_run_records(study.store)
    for run in runs:
        if run.run_id == text and run.stage is not None:
            return run.stage, f"run {text}"
    try:
        stage = int(text)
    except ValueError:
        known = ", ".join(run.run_id for run in runs) or "none"
        raise InvalidParameterError("--stage", text, f"'screening', a run id of this study ({known}) "
                                    "or a stage number") from None
    if not 0 <= stage <= MAX_INT64:
        raise InvalidParameterError("--stage", text, f"'screening', a run id or a stage number in 0..{MAX_INT64}")
    return stage, f"stage {stage}"


def _load_index(load: Any, text: str | None) -> int:
    """``show --load``: the position of the load ``text`` among the config's ``load`` values (0 without it)."""
    from rough_uq.problem.columns import load_label

    if text is None:
        return 0
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if value not in load.values:
        loads = ", ".join(load_label(v) for v in load.values)
        raise InvalidParameterError("--load", text, f"one of the study's {load.kind} loads ({loads})")
    return load.values.index(value)


@main.command()
@click.option("--study", "study_path", type=click.Path(dir_okay=False), default=DEFAULT_STUDY, show_default=True,
              help="Study file (only read).")
@click.option("--stage", default="screening", show_default=True,
              help="'screening', a run id as `roughuq report` prints it (e.g. mlmc_contact_area-0.5_theta-0.5), "
                   "or a stage number.")
@click.option("--level", type=click.IntRange(min=0), required=True, help="Level of the sample.")
@click.option("--index", type=click.IntRange(min=0, max=MAX_INT64), required=True,
              help="Index of a stored sample.")
@click.option("--load", "load_text", default=None, metavar="LOAD",
              help="Of a load-curve study, the load to draw, as the config gives it (e.g. 0.05); "
                   "default: the config's first.")
@click.option("--out", "out", type=click.Path(dir_okay=False), required=True, help="PNG file to write.")
@_user_errors
def show(study_path: str, stage: str, level: int, index: int, load_text: str | None, out: str) -> None:
    """Recompute one stored sample from its seed and draw heights, pressure and contact clusters.

    Of a load curve, the pressure and the clusters at one load (--load).
    """
    _check_not_empty("--study", study_path)
    from rough_uq.study.pipeline import open_existing_study
    from rough_uq.report.figures import write_sample_figure

    _check_output_file("--out", out)
    if Path(out).suffix.lower() != ".png":  # it wrote PNG bytes into x.pdf, and into x
        raise InvalidParameterError("--out", out, "a file name ending in .png (the figure is written as PNG)")
    with open_existing_study(study_path, writable=False, options="--study") as study:
        if level > study.config.grid.max_level:
            raise InvalidParameterError("--level", level, f"an integer in 0..{study.config.grid.max_level}")
        load_index = _load_index(study.config.load, load_text)
        stage_id, name = _stage_and_name(study, stage)  # the title names the stage as typed (a run's is a hash)
        stored = study.store.sample_indices(level=level, stage=stage_id)
        model = study.model_for(level)  # the FFT plans the sample was computed with
    if index not in set(int(i) for i in stored):
        have = f"stored: {' '.join(_ranges(sorted(int(i) for i in stored)))}" if stored.size else "none stored"
        raise InvalidParameterError("--index", index, f"a sample of stage {stage} on level {level} ({have})")

    def write() -> Any:
        return write_sample_figure(model=model, stage=stage_id, level=level, index=index, path=out,
                                   load_index=load_index, stage_name=name)

    click.echo(f"wrote {_writing(out, write)}")


@main.command()
@click.argument("run_ids", metavar="RUN_ID...", nargs=-1, required=True)
@click.option("--study", "study_path", type=click.Path(dir_okay=False), default=DEFAULT_STUDY, show_default=True,
              help="Study file.")
@_user_errors
def drop(run_ids: Sequence[str], study_path: str) -> None:
    """Forget abandoned run records; their samples stay in the file.

    A dropped run no longer appears in reports; running the same command
    again brings it back with a record of its own (timed afresh) and reuses
    its stored samples.
    """
    _check_not_empty("--study", study_path)
    from rough_uq.study.pipeline import open_existing_study
    from rough_uq.study.records import read_run_records

    run_ids = list(dict.fromkeys(run_ids))  # one each, in the order given

    with open_existing_study(study_path, options="--study") as study:
        runs = {run.run_id: run for run in read_run_records(study.store)}
        for key in run_ids:
            if key not in runs or runs[key].status == "dropped":
                known = ", ".join(k for k, run in runs.items() if run.status != "dropped") or "none"
                shown = f"{key} (dropped already)" if key in runs else key  # it read as a typo
                raise InvalidParameterError("RUN_ID", shown, f"a run of this study ({known})")
        for key in run_ids:
            study.store.write_run(key, replace(runs[key], status="dropped").to_json())
    finished = [key for key in run_ids if runs[key].is_finished]
    click.echo(f"{study_path}: dropped {', '.join(run_ids)} (samples kept)")
    if finished:
        # `drop` is meant for abandoned runs: say so when a finished result went with it.
        click.echo(f"note: finished runs dropped too: {', '.join(finished)} (no longer reported; the same command "
                   "brings a result back from the kept samples)")


def run() -> None:
    """The ``roughuq`` program: :func:`main`, and no signal handling left behind once a command has ended.

    Ctrl-C and SIGTERM during a command are handled by the command itself
    (exit 130 / 143, samples saved). One that arrives after the command has
    finished, while the interpreter shuts down, would otherwise kill the
    process with a signal status (or a traceback) although the work is done
    and saved; from then on both are ignored.
    """
    import signal

    try:
        main()
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


if __name__ == "__main__":  # pragma: no cover
    run()
