"""Samples kept with a problem: a Python run interrupted by Ctrl-C and made again goes on where it stopped."""

from __future__ import annotations

import numpy as np
import pytest

import rough_uq
import rough_uq.problem.contact as contact_module
from rough_uq.problem.batch import LevelBatch
from rough_uq.problem.kept import KeptSamples
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
    assert f"interrupted after {stop_after} samples computed; they are kept with the problem" in note
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


def test_a_replaced_problem_and_an_equal_problem_keep_their_own_samples(computed):
    problem = _problem()
    rough_uq.mc(problem, tol=2.0, level=0)
    n_first = len(computed)
    rough_uq.mc(_problem(), tol=2.0, level=0)  # equal, not the same object: its own (empty) store
    assert len(computed) == 2 * n_first
    assert _problem() == problem
