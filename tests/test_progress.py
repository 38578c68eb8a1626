"""Plain progress for logs: line-buffered, throttled, with ETA."""

from __future__ import annotations

import io

from rough_uq.progress import PlainProgress, Progress, make_progress


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
    assert level_lines[0].startswith("[mlmc] level 1: 1/4 samples") and "eta" in level_lines[0]
    assert level_lines[-1].startswith("[mlmc] level 1: 4/4 samples")  # completion is always printed
    assert len(level_lines) == 2
    assert "[mlmc] hello" in lines and lines[-1].startswith("[mlmc] done in")


def test_make_progress_picks_plain_for_pipes_and_nothing_when_quiet():
    assert isinstance(make_progress(stream=io.StringIO()), PlainProgress)
    assert type(make_progress(is_quiet=True)) is Progress
