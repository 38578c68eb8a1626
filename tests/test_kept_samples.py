"""Samples kept with a problem: a Python run interrupted by Ctrl-C and made again goes on where it stopped."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

import rough_uq
import rough_uq.problem.contact as contact_module
from rough_uq.problem.batch import LevelBatch
from rough_uq.problem.kept import MAX_GAP, KeptSamples
from rough_uq.study.progress import Progress


def _problem(**overrides: object) -> rough_uq.ContactProblem:
    """A problem on grids 16, 32, 64 whose runs take about a second."""
    spectrum = rough_uq.SurfaceSpectrum(system_size=1.0, k_l=1, k_r=2, k_s=8, hurst=0.8, rms_height=1.0)
    options = dict(load=rough_uq.RelativeLoad(0.2), qoi=["contact_area", "mean_gap"], coarsest=16, max_level=2,
                   seed=7)
    return rough_uq.ContactProblem(spectrum, **(options | overrides))


class InterruptAfter(Progress):
    """Ctrl-C after ``n`` samples are done."""

    def __init__(self, n: int) -> None:
        self.n, self.done = n, 0

    def advance(self, level: int, n: int) -> None:
        self.done += n
        if self.done >= self.n:
            raise KeyboardInterrupt


@pytest.fixture
def computed(monkeypatch):
    """The sample indices computed, per level, as (level, index) pairs in order."""
    pairs: list[tuple[int, int]] = []
    compute = contact_module.compute_batch

    def counted(model, *, stage, level, indices):
        pairs.extend((level, int(i)) for i in indices)
        return compute(model, stage=stage, level=level, indices=indices)

    monkeypatch.setattr(contact_module, "compute_batch", counted)
    return pairs


RUNS = {
    "mlmc": lambda problem, **options: rough_uq.mlmc(problem, tol=0.6, **options),
    "mc": lambda problem, **options: rough_uq.mc(problem, tol=0.6, level=1, **options),
    "variance": lambda problem, **options: rough_uq.variance(problem, tol=100.0, **options),
}


@pytest.mark.parametrize("method", sorted(RUNS))
@pytest.mark.parametrize("stop_after", [1, 17, 40])
def test_an_interrupted_run_made_again_computes_only_the_missing_samples_and_gives_the_same_result(
    method, stop_after, computed
):
    # An interrupted run kept nothing: made again, it started from sample 0 (2629 samples again in the audit).
    run = RUNS[method]
    whole = run(_problem())
    uninterrupted = sorted(computed)
    computed.clear()
    problem = _problem()
    with pytest.raises(KeyboardInterrupt) as caught:
        run(problem, progress=InterruptAfter(stop_after))
    before = list(computed)
    assert len(before) == stop_after  # one sample at a time with a progress reporter
    note = caught.value.__notes__[-1]
    assert f"interrupted; the {stop_after} samples it computed are kept with the problem" in note
    again = run(problem)
    assert sorted(computed) == uninterrupted  # each sample computed once over both calls, none twice
    assert repr(again) == repr(whole)
    assert np.array_equal(again.estimate, whole.estimate) and np.array_equal(again.n_samples, whole.n_samples)
    computed.clear()
    assert repr(run(problem)) == repr(whole) and computed == []  # a third call: every sample kept


def _batch(stage: int, level: int, indices: list[int], rng: np.random.Generator) -> LevelBatch:
    n = len(indices)
    return LevelBatch(level=level, stage=stage, indices=np.array(indices, dtype=np.int64),
                      fine=rng.normal(size=(n, 3)), coarse=rng.normal(size=(n, 3)), cost=rng.uniform(size=n),
                      n_iter=rng.integers(1, 99, size=(n, 2)), converged=rng.random((n, 2)) < 0.9)


@pytest.mark.parametrize("seed", range(20))
def test_kept_samples_give_back_exactly_the_rows_added_in_the_order_asked(seed):
    rng = np.random.default_rng(seed)
    kept, added = KeptSamples(), {}
    for _ in range(int(rng.integers(1, 30))):
        stage, level = int(rng.integers(0, 3)), int(rng.integers(0, 3))
        indices = rng.choice(200, size=int(rng.integers(0, 12)), replace=False).tolist()
        batch = _batch(stage, level, indices, rng)
        kept.add(batch)
        for row, index in enumerate(indices):
            added[stage, level, index] = [getattr(batch, name)[row] for name in ("fine", "coarse", "cost", "n_iter",
                                                                                  "converged")]
    assert len(kept) == len(added)
    for stage in range(3):
        for level in range(3):
            asked = rng.permutation(260)[: int(rng.integers(0, 260))].astype(np.int64)
            given, missing = kept.split(stage, level, asked)
            expected = [index for index in asked.tolist() if (stage, level, index) in added]
            assert missing.tolist() == [index for index in asked.tolist() if (stage, level, index) not in added]
            if given is None:
                assert expected == []
                continue
            assert given.indices.tolist() == expected and (given.stage, given.level) == (stage, level)
            for row, index in enumerate(expected):
                for name, value in zip(("fine", "coarse", "cost", "n_iter", "converged"), added[stage, level, index]):
                    assert np.array_equal(getattr(given, name)[row], value)


def test_an_equal_problem_keeps_its_own_samples(computed):
    problem = _problem()
    rough_uq.mc(problem, tol=2.0, level=0)
    n_first = len(computed)
    rough_uq.mc(_problem(), tol=2.0, level=0)  # equal, not the same object: its own (empty) store
    assert len(computed) == 2 * n_first
    assert _problem() == problem


def test_a_run_without_progress_goes_on_from_its_last_completed_batch(computed):
    # Without a progress reporter a batch is one computation: an interrupt loses the batch in flight only.
    whole = RUNS["mc"](_problem())
    computed.clear()
    problem, calls = _problem(), []
    compute = contact_module.compute_batch

    def interrupt_third(model, **item):
        calls.append(item["indices"].size)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return compute(model, **item)

    contact_module.compute_batch = interrupt_third
    try:
        with pytest.raises(KeyboardInterrupt) as caught:
            RUNS["mc"](problem)
    finally:
        contact_module.compute_batch = compute
    kept = sum(calls[:2])
    assert f"the {kept} samples it computed are kept" in caught.value.__notes__[-1] and len(problem._kept) == kept
    computed.clear()
    assert repr(RUNS["mc"](problem)) == repr(whole)
    assert len(computed) == int(whole.n_samples.sum()) - kept


def test_a_screening_is_kept_too(computed):
    problem = _problem()
    first = rough_uq.screen(problem, levels=3, samples=5)
    computed.clear()
    again = rough_uq.screen(problem, levels=3, samples=5)
    assert computed == [] and np.array_equal(again.statistics.mean_fine, first.statistics.mean_fine)


def test_replaced_and_unpickled_problems_start_with_no_samples(computed):
    problem = _problem()
    rough_uq.mc(problem, tol=2.0, level=0)
    n_first = len(computed)
    for other in (dataclasses.replace(problem, max_level=1), pickle.loads(pickle.dumps(problem))):
        computed.clear()
        rough_uq.mc(other, tol=2.0, level=0)
        assert len(computed) == n_first, other  # computed again: nothing carried over
    # A pickle leaves the samples behind: it does not grow with the runs (another version would serve them).
    assert len(pickle.dumps(problem)) == len(pickle.dumps(_problem()))


def test_a_sample_far_beyond_those_kept_is_computed_not_kept():
    # sampler.batch(0, [2**40]) computed the sample, then asked for a 1 TiB array to keep it.
    rng = np.random.default_rng(3)
    kept = KeptSamples()
    kept.add(_batch(0, 1, [0, 1, 2], rng))
    far = 4 * (3 + 2) + MAX_GAP  # the first index out of reach with 3 kept and a batch of 2
    kept.add(_batch(0, 1, [far, 2**40], rng))
    assert len(kept) == 3
    given, missing = kept.split(0, 1, np.array([2, far, 2**40], dtype=np.int64))
    assert given.indices.tolist() == [2] and missing.tolist() == [far, 2**40]
    kept.add(_batch(0, 1, [MAX_GAP], rng))  # within reach: kept
    assert len(kept) == 4


def test_a_run_inside_an_except_block_reports_its_end_as_complete():
    # The end was decided on sys.exc_info(), which inside an except block is the exception being handled:
    # a run made there (a retry after an EstimationError) was reported "stopped", not "done".
    stops = []

    class Recorded(Progress):
        def stop(self, *, is_complete=True):
            stops.append(is_complete)

    try:
        raise ValueError("a failed attempt")
    except ValueError:
        rough_uq.mc(_problem(), tol=2.0, level=0, progress=Recorded())
    assert stops == [True]


def test_the_note_counts_only_samples_kept_when_the_interrupt_lands_while_one_is_kept(monkeypatch):
    # n_computed was counted before KeptSamples.add: a Ctrl-C inside add() made the note count a sample not kept.
    calls = []
    add = KeptSamples.add

    def interrupted_third(kept, batch):
        calls.append(batch.n_samples)
        if len(calls) == 3:
            raise KeyboardInterrupt
        add(kept, batch)

    monkeypatch.setattr(KeptSamples, "add", interrupted_third)
    problem = _problem()
    with pytest.raises(KeyboardInterrupt) as caught:
        RUNS["mc"](problem, progress=Progress())
    assert f"the {len(problem._kept)} samples it computed" in caught.value.__notes__[-1] and len(problem._kept) == 2


def test_a_progress_interrupted_while_it_starts_is_stopped():
    # A Ctrl-C inside RichProgress.start() (before the run's try) left rich's live display running.
    events = []

    class SlowStart(Progress):
        def start(self, title):
            events.append("start")
            raise KeyboardInterrupt

        def stop(self, *, is_complete=True):
            events.append(("stop", is_complete))

    with pytest.raises(KeyboardInterrupt):
        RUNS["mc"](_problem(), progress=SlowStart())
    assert events == ["start", ("stop", False)]


def test_a_ctrl_c_while_the_kernels_warm_up_takes_effect_once_they_are_loaded(monkeypatch):
    # A Ctrl-C while numba registered its implementations (a process's first solve) broke every later solve of
    # the process (RuntimeError: generator raised StopIteration): the warm-up now defers it.
    import signal
    import threading

    import rough_uq.problem.sampler as sampler_module

    done = []
    compute = sampler_module.compute_batch

    def interrupted(model, **item):
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)  # delivered while the warm-up solves
        batch = compute(model, **item)
        done.append(batch.n_samples)
        return batch

    monkeypatch.setattr(sampler_module, "compute_batch", interrupted)
    with pytest.raises(KeyboardInterrupt):
        sampler_module.warm_up(_problem().model)
    assert done == [1]  # the warm-up's sample was solved whole before the interrupt took effect


def test_the_note_of_a_second_interrupt_counts_that_calls_samples():
    # It counted what that call computed, but the README said the samples kept (the problem's, 9 here).
    problem = _problem()
    for stop_after, computed_here in ((5, 5), (9, 4)):  # the second call is given 5 back, then computes 4
        with pytest.raises(KeyboardInterrupt) as caught:
            RUNS["mlmc"](problem, progress=InterruptAfter(stop_after))
        assert f"the {computed_here} samples it computed are kept" in caught.value.__notes__[-1]
    assert len(problem._kept) == 9
