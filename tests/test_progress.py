"""Plain progress for logs: line-buffered, throttled, with ETA."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

import rough_uq.study.progress as progress_module
from rough_uq.errors import InvalidParameterError
from rough_uq.study.progress import (
    ETA_MIN_SAMPLES,
    ETA_MIN_SECONDS,
    PlainProgress,
    Progress,
    RichProgress,
    format_duration,
    make_progress,
)


def test_plain_progress_lines_are_throttled_and_complete():
    stream = io.StringIO()
    progress = PlainProgress(stream, interval=3600)
    progress.start("mlmc")
    progress.plan([0, 1], [10, 4], [0, 0])
    for n in range(11, 40):  # the adaptive plan changes after every batch
        progress.plan([0, 1], [n, 4], [0, 0])
    progress.plan([0, 1, 2], [40, 4, 2], [0, 0, 0])  # a new level is always announced
    for _ in range(4):
        progress.advance(1, 1)
    progress.note("hello")
    progress.stop()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "[mlmc] started"
    plan_lines = [line for line in lines if "plan:" in line]
    assert plan_lines == ["[mlmc] plan: samples per level L0: 10, L1: 4",
                          "[mlmc] plan: samples per level L0: 40, L1: 4, L2: 2"]
    level_lines = [line for line in lines if "level 1:" in line]
    assert level_lines[0].startswith("[mlmc] level 1: 1/4 samples") and "eta" not in level_lines[0]
    assert level_lines[-1].startswith("[mlmc] level 1: 4/4 samples")  # where the level ended is always printed
    assert len(level_lines) == 2
    assert "[mlmc] hello" in lines and lines[-1].startswith("[mlmc] done in")


def test_samples_counted_by_a_plan_and_not_advanced_reach_both_progresses():
    """A rerun's last round came from the store, which advances nothing: it ended at "level 1: 7/11 samples"."""
    from rich.console import Console

    stream = io.StringIO()
    plain = PlainProgress(stream, interval=3600)
    rich = RichProgress(console=Console(file=io.StringIO(), force_terminal=False))
    for progress in (plain, rich):
        progress.start("mlmc")
        progress.plan([1], [7], [0])
        progress.advance(1, 7)
        progress.plan([1], [11], [7])  # the plan grows
        progress.plan([1], [11], [11])  # the batch of the last round: its 4 samples came from the store
        progress.plan([1], [11], [9])  # a count below what is done changes nothing
        if progress is rich:
            assert [(task.completed, task.total) for task in rich._bars.tasks] == [(11, 11)]
        progress.stop()
    level_lines = [line for line in stream.getvalue().splitlines() if "level 1:" in line]
    assert level_lines[-1].startswith("[mlmc] level 1: 11/11 samples")


@pytest.mark.parametrize("is_complete", [True, False])
def test_rich_bars_of_an_interrupted_run_say_that_it_stopped(is_complete):
    """The bars froze where an interrupted run stopped and said nothing, as if it were still going (the plain
    lines said "stopped after")."""
    from rich.console import Console

    out = io.StringIO()
    progress = RichProgress(console=Console(file=out, force_terminal=False, width=120))
    progress.start("mlmc tol 0.2")
    progress.plan([0], [10], [0])
    progress.advance(0, 3)
    progress.stop(is_complete=is_complete)
    stopped = [line for line in out.getvalue().splitlines() if "stopped after" in line]
    assert stopped == ([] if is_complete else ["[mlmc tol 0.2] stopped after 0s"])


def test_a_plan_that_grows_with_every_batch_is_not_a_line_per_batch():
    # Adaptive MLMC raises a level's plan after each batch, and each batch reaches it: the log said "18/18",
    # "21/21", ... one line per batch, each reading as done. Within an interval: the first line and the last.
    stream = io.StringIO()
    progress = PlainProgress(stream, interval=3600)
    progress.start("mlmc")
    done = 0
    progress.plan([0, 1, 2], [0, 0, 0], [0, 0, 0])  # level 2: one the plan leaves out, never sampled
    for planned in range(3, 30, 3):
        progress.plan([0, 1], [planned, 2], [done, 0])
        progress.advance(0, planned - done)
        done = planned
    progress.advance(1, 2)
    progress.stop(is_complete=False)
    lines = stream.getvalue().splitlines()
    level_lines = [line for line in lines if "] level " in line]
    assert [line.split(",")[0] for line in level_lines] == [
        "[mlmc] level 0: 3/3 samples", "[mlmc] level 1: 2/2 samples", "[mlmc] level 0: 27/27 samples"]
    assert lines[-1].startswith("[mlmc] stopped after")


def test_the_plan_a_run_ends_with_is_printed_if_a_change_went_unsaid():
    # mc printed "plan: samples per level L3: 232", then "level 3: 225/225 samples": the plan had shrunk within
    # the interval and no line said so.
    stream = io.StringIO()
    progress = PlainProgress(stream, interval=3600)
    progress.start("mc")
    progress.plan([3], [10], [0])
    progress.advance(3, 10)
    progress.plan([3], [232], [10])
    progress.plan([3], [225], [10])
    progress.advance(3, 215)
    progress.stop()
    lines = stream.getvalue().splitlines()
    plans = [line for line in lines if "plan:" in line]
    assert plans == ["[mc] plan: samples per level L3: 10", "[mc] plan: samples per level L3: 225"]
    assert lines.index(plans[-1]) < lines.index(next(line for line in lines if "225/225" in line))
    stream = io.StringIO()
    progress = PlainProgress(stream, interval=3600)
    progress.start("mc")
    progress.plan([3], [10], [0])
    progress.advance(3, 10)
    progress.stop()
    assert sum("plan:" in line for line in stream.getvalue().splitlines()) == 1  # nothing unsaid: no repeat


def test_make_progress_picks_plain_for_pipes_and_nothing_when_quiet():
    assert isinstance(make_progress(stream=io.StringIO()), PlainProgress)
    assert type(make_progress(is_quiet=True)) is Progress


def test_no_eta_until_the_rate_means_something(monkeypatch):
    """The first sample carries the start-up: no ETA from it, a right one from the samples after it."""
    clock = [1000.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: clock[0])
    stream = io.StringIO()
    progress = PlainProgress(stream, interval=0)
    progress.start("mlmc")
    progress.plan([0], [100], [0])
    clock[0] += 30.0  # start-up: 30 s before the first sample
    progress.advance(0, 1)
    for _ in range(ETA_MIN_SAMPLES):
        clock[0] += 0.1  # then 0.1 s per sample: too soon for an ETA
        progress.advance(0, 1)
    lines = [line for line in stream.getvalue().splitlines() if "level 0:" in line]
    assert lines and not any("eta" in line for line in lines)
    while clock[0] < 1030.0 + ETA_MIN_SECONDS + 1:
        clock[0] += 0.1
        progress.advance(0, 1)
    last = stream.getvalue().splitlines()[-1]
    done = int(last.split("level 0: ")[1].split("/")[0])
    assert "eta" in last
    eta = last.rsplit("eta ", 1)[1]
    assert eta == format_duration((100 - done) * 0.1, clock=True)  # from the steady rate, not the start-up


def test_interrupted_task_does_not_say_done():
    stream = io.StringIO()
    progress = PlainProgress(stream)
    progress.start("mlmc")
    progress.stop(is_complete=False)
    assert "done" not in stream.getvalue() and "stopped after" in stream.getvalue().splitlines()[-1]


def test_rich_eta_column_waits_for_a_steady_rate(monkeypatch):
    from rich.progress import Progress as Bars

    clock = [0.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: clock[0])
    column = progress_module._EtaColumn()
    bars = Bars(column, auto_refresh=False, disable=True)
    task_id = bars.add_task("level 0", total=100, completed=0, done_at_start=0)
    task = bars.tasks[0]
    assert str(column.render(task)) == ""
    clock[0] = 30.0  # the first sample carries 30 s of start-up
    bars.update(task_id, completed=1)
    assert str(column.render(task)) == ""
    for n in range(2, 2 + ETA_MIN_SAMPLES):
        clock[0] += 0.1
        bars.update(task_id, completed=n)
        assert str(column.render(task)) == ""  # too few samples / seconds yet
    while clock[0] < 30.0 + ETA_MIN_SECONDS + 0.5:
        clock[0] += 0.1
        bars.update(task_id, completed=task.completed + 1)
    text = str(column.render(task))
    assert text == "eta " + format_duration((100 - task.completed) * 0.1, clock=True)


@pytest.mark.parametrize("seconds, options, text", [
    (0.0966, {}, "0.0966 s"),
    (0.0966, {"digits": 2}, "0.097 s"),
    (100.4, {"digits": 2}, "100 s"),  # not 1e+02 s
    (119.6, {"digits": 2}, "120 s"),
    (150.0, {}, "2.5 min"),
    (6600.0, {"digits": 2}, "110 min"),
    (7 * 24 * 3600.0, {}, "168 h"),
    (3600 * 123456.0, {"digits": 2}, "120000 h"),
    (3600 * 1.53e9, {}, "1.53e+09 h"),  # not 1530000000 h (a plan at its cap)
    (math.inf, {}, "forever"),
    (None, {}, "-"),
    (math.nan, {}, "-"),
    (12.4, {"clock": True}, "12s"),
    (65.0, {"clock": True}, "1m05s"),
    (3725.0, {"clock": True}, "1h02m"),
])
def test_one_duration_format_for_every_printed_time(seconds, options, text):
    assert format_duration(seconds, **options) == text


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: PlainProgress("log.txt"), "stream"),  # a file name: AttributeError at the run's first line
        (lambda: PlainProgress(interval="5"), "interval"),  # TypeError in the middle of a run
        (lambda: PlainProgress(interval=-1), "interval"),
        (lambda: PlainProgress(interval=math.nan), "interval"),
        (lambda: PlainProgress(interval=True), "interval"),
        (lambda: RichProgress(console=io.StringIO()), "console"),
    ],
)
def test_progress_settings_are_checked_when_made(make, field):
    with pytest.raises(InvalidParameterError) as caught:
        make()
    assert caught.value.name == field


def test_a_progress_of_a_stream_and_interval_prints_there():
    stream = io.StringIO()
    progress = PlainProgress(stream, interval=np.float64(0.5))
    progress.start("run")
    assert stream.getvalue() == "[run] started\n"
