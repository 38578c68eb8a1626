"""The pipeline joins config, sampler, estimators and store: determinism, resume, units."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rough_uq.study.config import config_from_dict, load_config
from rough_uq.errors import ConfigError, EstimationError, InvalidParameterError, PlanTooLargeError, StudyFileError
from rough_uq.study.executors import Executor, PoolExecutor, SerialExecutor
from rough_uq.multilevel.drivers import PlanUpdated
from rough_uq.multilevel.rates import EXACT_RATE
from rough_uq.study.pipeline import (
    Study,
    StudySampler,
    build_model,
    check_target_budget,
    create_study,
    forecast_run,
    merge_shards,
    missing_samples,
    cdf_request,
    open_existing_study,
    parse_tolerances,
    run_estimation,
    run_id,
    run_screening,
    run_sweep,
    run_target,
)
from rough_uq.study.pipeline.estimation import _events
from rough_uq.study.progress import Progress
from rough_uq.study.records import read_run_records, read_screening_record
from rough_uq.problem.sampler import STAGE_SCREENING, compute_batch, is_coupled_stage, modelled_cost, run_stage

from rough_uq.problem.loads import AbsoluteLoad, RelativeLoad
from rough_uq.study.store import MemoryStore
from tests.study_configs import tiny_config

MLMC_STAGE = run_stage("mlmc", "test")

QUIET = Progress()


def _study(**overrides: object) -> Study:
    config = config_from_dict(tiny_config(**overrides))
    return Study(config, MemoryStore(qoi_names=config.qoi_names))


def _screened(**overrides: object) -> Study:
    study = _study(**overrides)
    run_screening(study, executor=SerialExecutor(), progress=QUIET)
    return study



@pytest.mark.filterwarnings("ignore::rough_uq.multilevel.statistics.EstimationWarning")
def test_a_run_from_a_screening_whose_bias_grows_is_refused_without_a_forecast():
    # Only the CLI's forecast refused it; run_estimation planned with the floor rate 0.5 and ran.
    surface = {"system_size": 1.0, "wavenumbers": {"k_l": 1, "k_r": 2, "k_s": 32}, "hurst": 0.8, "rms_height": 1.0}
    study = _screened(qoi={"clusters": {"tol": 1.0}}, surface=surface)
    assert not read_screening_record(study.store).rates.alpha[0] > 0
    for method in ("mlmc", "mc"):
        with pytest.raises(EstimationError, match=r"^the bias of clusters \(alpha = .*\) does not decrease"):
            run_estimation(study, method=method, tol=np.array([1.0]), executor=SerialExecutor(), progress=QUIET)
    assert not read_run_records(study.store)


def test_a_forecast_capped_at_the_largest_count_is_refused_as_needing_more():
    # "needs about 4.5e+15 samples": the planners' cap, not the need (PlanTooLargeError says "more than").
    from rough_uq.study.pipeline.planning import _check_budget
    from rough_uq.study.records import Forecast

    def forecast(counts):
        return Forecast(finest_level=1, grid=64, n_samples=counts, modelled_cost=1e20, cpu_seconds=1e20,
                        wall_seconds=1e20, memory_bytes=1)

    for counts, amount in (((2**52, 3), "more than 4.5e+15"), ((2 * 10**7, 3), "about 2e+07")):
        with pytest.raises(EstimationError, match=rf"^--tol contact_area=1e-09 needs {re.escape(amount)} samples \("):
            _check_budget(("contact_area",), np.array([1e-9]), forecast(counts), None)


def test_a_qoi_that_never_changes_says_so_instead_of_asking_for_more_samples():
    # Far past full contact the area is 100 % in every sample: more levels or samples would not help.
    study = _study(load={"relative": 1.0e6})
    with pytest.raises(EstimationError, match="contact_area took one value in every sample of every level") as info:
        run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert "screen more levels" not in str(info.value)
    # The refused screening's samples are stored: a run from them is refused too (it "met" 100 % +- 0 while
    # a column exact beside others was made screenable).
    with pytest.raises(EstimationError, match="contact_area took one value in every sample of every level"):
        run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET)


def test_a_load_that_touches_one_node_says_so_and_to_change_the_load_too():
    # One node in contact in every sample: one value per level (one node's area), another on each grid. The beta
    # fit said "cannot fit beta ... levels with Var(Q_l - Q_l-1) = 0" and asked for more levels or samples only,
    # where at 1e-9 only a larger load helps (at 3e-5 finer grids do: both are said).
    study = _study(load={"relative": 1.0e-9}, qoi={"contact_area": {}, "clusters": {}})
    with pytest.raises(EstimationError) as info:
        run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert str(info.value) == (
        "contact_area, clusters took one value in every sample of each level, which only the grid changes (at this "
        "load, e.g. a single node in contact on every grid sampled): no variance to fit; screen more levels "
        "(screening.levels) or more samples (screening.samples), or change the load"
    )

def test_a_column_exact_on_grids_that_truncate_the_spectrum_gets_a_caveat():
    # Full contact at the second load on grids 6, 12, 24 (k_s = 12 needs a grid above 24): planned as exact,
    # with the caveat that a finer grid may differ.
    surface = {"system_size": 1.0, "wavenumbers": {"k_l": 1, "k_r": 2, "k_s": 12}, "hurst": 0.8, "rms_height": 1.0}
    study = _study(surface=surface, grid={"coarsest": 6, "max_level": 2}, load={"relative": [0.2, 1.0e6]})
    outcome = run_screening(study, executor=SerialExecutor(), progress=QUIET)
    exact = study.config.qoi_names.index("contact_area@1000000.0")
    assert outcome.rates.alpha[exact] == EXACT_RATE
    (caveat,) = [d.message for d in outcome.record.diagnostics if "do not resolve the surface" in d.message]
    assert caveat.startswith("contact_area@1000000.0: every level difference is 0 on the screened grids up to 24^2")


def test_model_units_and_load():
    config = config_from_dict(
        tiny_config(
            surface={"system_size": 2.0, "wavenumbers": {"k_l": 1, "k_r": 2, "k_s": 8}, "hurst": 0.8,
                     "rms_height": 1.0},
            material={"e_star": 3.0},
            qoi={"contact_area": {"unit": "percent"}, "clusters": {"unit": "per_area", "connectivity": 8},
                 "mean_gap": {}},
        )
    )
    model = build_model(config)
    assert model.qoi_scales == (100.0, 0.25, 1.0)
    assert model.connectivity == 8
    assert model.mean_pressure == pytest.approx(0.2 * 3.0 * model.spectrum.rms_slope, rel=1e-14)
    absolute = build_model(config_from_dict(tiny_config(load={"absolute": 0.05})))
    assert absolute.mean_pressure == 0.05


#: Loads no solve takes, the config field that names them, and the line of the check they fail.
REFUSED_LOADS = {
    "relative 1e200": ({"relative": 1e200}, "load.relative", "2.2e-298, 1e+15]"),
    "absolute 1e-320": ({"absolute": 1e-320}, "load.absolute", "2.2e-298, 1e+15]"),
    "curve": ({"relative": [0.1, 1e200]}, "load.relative.1", "2.2e-298, 1e+15]"),
    "pressure overflows": ({"relative": 1e308}, "load.relative", "the finest grid's 32^2 nodes is finite"),
}


@pytest.mark.parametrize(("load", "field", "text"), REFUSED_LOADS.values(), ids=REFUSED_LOADS.keys())
def test_the_model_of_a_config_refuses_a_load_no_solve_takes(load, field, text):
    # build_model took them, and only the CLI checked them: a Python caller of create_study started a study of them.
    from rough_uq.problem.loads import checked_mean_pressures

    config = config_from_dict(tiny_config(load=load))
    with pytest.raises(InvalidParameterError) as caught:
        build_model(config)
    assert caught.value.name == field and text in caught.value.allowed
    model = build_model(config_from_dict(tiny_config()))
    kind = RelativeLoad if config.load.kind == "relative" else AbsoluteLoad
    loads = tuple(kind(value) for value in config.load.values)
    with pytest.raises(InvalidParameterError) as same:  # ContactProblem's check, word for word
        checked_mean_pressures(loads, spectrum=model.spectrum, e_star=model.e_star, finest=config.grid.finest)
    assert str(caught.value) == str(same.value)


def test_the_model_of_a_config_file_names_the_file_in_its_refusal():
    """The CLI passed no source: `roughuq screen bad.yaml` said which field, not which file (load_config does)."""
    from rough_uq.errors import ConfigError

    config = config_from_dict(tiny_config(load={"relative": 1e200}))
    with pytest.raises(InvalidParameterError) as plain:
        build_model(config)
    with pytest.raises(ConfigError) as named:
        build_model(config, source="runs/bad.yaml")
    assert str(named.value) == f"runs/bad.yaml: {plain.value}"
    assert isinstance(named.value.__cause__, InvalidParameterError) and named.value.__cause__.name == "load.relative"
    assert build_model(config_from_dict(tiny_config()), source="good.yaml") == build_model(
        config_from_dict(tiny_config()))


def test_a_study_created_with_its_model_does_not_build_it_again(tmp_path, monkeypatch):
    from rough_uq.study.pipeline import studies

    config = config_from_dict(tiny_config())
    model = build_model(config)
    monkeypatch.setattr(studies, "build_model", lambda config: pytest.fail("built again"))
    with create_study(config, tmp_path / "s.h5", model=model) as study:
        assert study.model is model


def test_a_refused_config_creates_no_study_file_and_leaves_none_open(tmp_path):
    from rough_uq.study.config import config_hash, resolved_yaml
    from rough_uq.study.store import open_study

    bad = config_from_dict(tiny_config(load={"relative": 1e200}))
    path = tmp_path / "study.h5"
    with pytest.raises(InvalidParameterError, match="^load.relative: got 1e[+]200; allowed: a dimensionless load"):
        create_study(bad, path)
    assert list(tmp_path.iterdir()) == []
    # A file written before loads were checked: opening it refuses the load, and lets go of the file.
    header = dict(config_text=resolved_yaml(bad), config_hash=config_hash(bad), qoi_names=bad.qoi_names,
                  code_version="0")
    open_study(path, create=True, **header).close()
    for writable in (True, False):
        with pytest.raises(InvalidParameterError, match="^load.relative: got 1e[+]200"):
            open_existing_study(path, writable=writable)
    open_study(path, create=False, **header).close()  # not locked by the refused open


def test_a_study_from_before_the_corrected_area_is_refused_naming_the_estimator(tmp_path):
    import yaml

    from rough_uq.study.config import resolved_yaml
    from rough_uq.study.store import open_study

    config = config_from_dict(tiny_config())
    legacy = yaml.safe_load(resolved_yaml(config))
    del legacy["qoi"]["contact_area"]["estimator"]  # written before the option existed: node counts
    path = tmp_path / "study.h5"
    open_study(path, create=True, config_text=yaml.safe_dump(legacy, sort_keys=False), config_hash="0" * 64,
               qoi_names=config.qoi_names, code_version="0").close()
    for refuse in (lambda: open_existing_study(path, config=config), lambda: create_study(config, path)):
        with pytest.raises(StudyFileError, match="another config") as info:
            refuse()
        assert "differs in qoi.contact_area.estimator: nodes in the file, corrected in this config" in str(info.value)
    # A stored config this version cannot read: still refused, by its hash, naming no settings.
    unreadable = tmp_path / "unreadable.h5"
    open_study(unreadable, create=True, config_text="surface: [", config_hash="0" * 64, qoi_names=config.qoi_names,
               code_version="0").close()
    with pytest.raises(StudyFileError, match="another config") as info:
        create_study(config, unreadable)
    assert "differs" not in str(info.value)


def test_sample_does_not_depend_on_its_batch():
    model = build_model(config_from_dict(tiny_config()))
    together = compute_batch(model, stage=MLMC_STAGE, level=2, indices=[0, 1, 2, 3])
    alone = compute_batch(model, stage=MLMC_STAGE, level=2, indices=[2])
    np.testing.assert_array_equal(alone.fine[0], together.fine[2])
    np.testing.assert_array_equal(alone.coarse[0], together.coarse[2])
    np.testing.assert_array_equal(alone.n_iter[0], together.n_iter[2])
    other_stage = compute_batch(model, stage=STAGE_SCREENING, level=2, indices=[2])
    assert not np.array_equal(other_stage.fine, alone.fine)


def test_coupled_coarse_value_is_a_level_below_sample_in_distribution():
    # The coarse QoI of a level-1 sample and the fine QoI of a level-0 sample come from
    # surfaces with the same distribution: their means agree within statistical error.
    model = build_model(config_from_dict(tiny_config()))
    n = 60
    level1 = compute_batch(model, stage=MLMC_STAGE, level=1, indices=np.arange(n))
    level0 = compute_batch(model, stage=MLMC_STAGE, level=0, indices=np.arange(n))
    difference = level1.coarse[:, 0].mean() - level0.fine[:, 0].mean()
    se = math.sqrt(level1.coarse[:, 0].var(ddof=1) / n + level0.fine[:, 0].var(ddof=1) / n)
    assert abs(difference) < 4 * se
    assert np.all(level0.coarse == 0) and np.all(level0.n_iter[:, 1] == 0)


def test_screening_stores_every_sample_and_resumes_without_recomputing():
    study = _study()
    first = run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert first.record.n_computed == 3 * 8
    for level in range(3):
        assert list(study.store.sample_indices(level=level, stage=STAGE_SCREENING)) == list(range(8))
    again = run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert again.record.n_computed == 0
    assert again.record.statistics == replace(first.record.statistics,
                                              mean_seconds=again.record.statistics.mean_seconds)
    assert read_screening_record(study.store) == again.record  # what is stored is what was returned
    rates = first.record.rates
    assert all(np.isfinite(rates.alpha)) and np.isfinite(rates.gamma)
    assert [p.tol[0] for p in first.record.predictions] == [4.0, 2.0, 1.0, 0.5, 0.25]


def test_mlmc_same_config_same_numbers_and_seed_matters():
    records = []
    for seed in (2026, 2026, 7):
        study = _screened(seed=seed)
        records.append(run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(),
                                      progress=QUIET))
    a, b, c = records
    assert a.status == "finished"
    a, b, c = a.outcome, b.outcome, c.outcome
    assert a.estimate == b.estimate and a.n_samples == b.n_samples and a.cost == b.cost
    assert a.estimate != c.estimate
    assert a.stat_error[0] > 0 and a.cost > 0 and a.seconds > 0


def test_a_rerun_that_computes_nothing_keeps_the_elapsed_time_of_the_run():
    study = _screened()
    for run in (
        lambda: run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET),
        lambda: run_target(study, target="variance", tol=np.array([4.0]), executor=SerialExecutor(), progress=QUIET),
    ):
        first, again = run().outcome, run().outcome
        assert first.n_computed > 0 and again.n_computed == 0
        assert again.elapsed == first.elapsed and again.estimate == first.estimate


def test_a_rerun_that_extends_a_finished_run_adds_its_time_to_the_first():
    # `mc --max-cost 40` (8.68 s), then the same run without the budget: its elapsed time was the rerun's 5.05 s
    # alone, against 21.6 CPU-seconds of samples on two workers.
    import time

    study = _study()
    budget = 1.2 * 4 * float(modelled_cost(study.model, 1, np.zeros((1, 2)))[0])  # as the budget test above

    def run(max_cost):
        return run_estimation(study, method="mc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET,
                              level=1, max_cost=max_cost)

    first = run(budget)
    assert first.status == "finished" and first.outcome.stop_reason == "max_cost"
    # A first command of 1000 s, so that the sum cannot be mistaken for the rerun's own time.
    study.store.write_run(first.run_id, replace(first, outcome=replace(first.outcome, elapsed=1000.0)).to_json())
    started = time.monotonic()
    again = run(None)
    took = time.monotonic() - started
    assert again.run_id == first.run_id and again.outcome.n_computed > 0 and again.outcome.tol_met
    assert 1000.0 < again.outcome.elapsed <= 1000.0 + took


def test_a_resumed_run_counts_the_stored_samples_of_a_batch_that_computes_the_rest():
    # Interrupted at 416 samples stored, the rerun's progress began at "level 3: 411/827": a batch's stored samples
    # counted only once the batch was done.
    import io

    from rough_uq.study.progress import PlainProgress

    study = _study(estimation={"initial_samples": 10, "batch_size": 10})
    tol, estimation = np.array([2.0]), study.config.estimation
    key = run_id("mc", study.config.qoi_names, tol, estimation.theta, 1, richardson=estimation.richardson)
    StudySampler(study, stage=run_stage("mc", key), executor=SerialExecutor(), progress=QUIET).compute(1, np.arange(6))
    out = io.StringIO()
    record = run_estimation(study, method="mc", tol=tol, executor=SerialExecutor(),
                            progress=PlainProgress(out, interval=0.0), level=1)
    assert record.outcome.n_computed == sum(record.outcome.n_samples) - 6
    counts = [int(n) for n in re.findall(r"level 1: ([0-9]+)/", out.getvalue())]
    assert counts[0] >= 6 and counts == sorted(counts), out.getvalue()


def _raising(failure: BaseException):
    def driver(*args: object, **kwargs: object) -> None:
        raise failure

    return driver


def test_a_rerun_that_fails_leaves_the_finished_record_as_it_was(monkeypatch):
    from rough_uq.study.pipeline import estimation, target_runs

    study = _screened()
    modules = {"_follow": estimation, "_follow_target": target_runs}
    runs = {
        "_follow": lambda: run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(),
                                          progress=QUIET),
        "_follow_target": lambda: run_target(study, target="variance", tol=np.array([4.0]),
                                             executor=SerialExecutor(), progress=QUIET),
    }
    for driver, run in runs.items():
        finished = run()
        for failure in (RuntimeError("a crash"), KeyboardInterrupt(), EstimationError("refused")):
            with monkeypatch.context() as patch:
                patch.setattr(modules[driver], driver, _raising(failure))
                with pytest.raises(type(failure)):
                    run()
            (stored,) = [record for record in read_run_records(study.store) if record.run_id == finished.run_id]
            assert stored == finished, (driver, failure)


def test_pool_and_serial_store_identical_samples():
    serial = _screened()
    pooled = _study()
    with PoolExecutor(2) as pool:
        run_screening(pooled, executor=pool, progress=QUIET)
        pooled_record = run_estimation(pooled, method="mlmc", tol=np.array([2.0]), executor=pool, progress=QUIET)
    serial_record = run_estimation(serial, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(),
                                   progress=QUIET)
    assert pooled_record.outcome.estimate == serial_record.outcome.estimate
    assert pooled_record.outcome.n_samples == serial_record.outcome.n_samples
    for stage in (STAGE_SCREENING, pooled_record.stage):
        for level in range(3):
            x = serial.store.read_samples(level=level, stage=stage)
            y = pooled.store.read_samples(level=level, stage=stage)
            np.testing.assert_array_equal(x.indices, y.indices)
            np.testing.assert_array_equal(x.fine, y.fine)
            np.testing.assert_array_equal(x.coarse, y.coarse)
            np.testing.assert_array_equal(x.n_iter, y.n_iter)


class _Interrupting(Executor):
    """Serial executor that raises ``failure`` (Ctrl-C's KeyboardInterrupt by default) after ``n_items`` work items."""

    def __init__(self, n_items: int, failure: BaseException | None = None) -> None:
        self.left = n_items
        self.failure = KeyboardInterrupt() if failure is None else failure

    def run(self, model, items):
        for item in SerialExecutor().run(model, items):
            if self.left == 0:
                raise self.failure
            self.left -= 1
            yield item


@pytest.mark.parametrize("n_items", [0, 5, 17])
def test_interrupted_mlmc_resumes_to_the_uninterrupted_result(n_items):
    reference = run_estimation(_screened(), method="mlmc", tol=np.array([1.0]), executor=SerialExecutor(),
                               progress=QUIET)
    study = _screened()
    with pytest.raises(KeyboardInterrupt):
        run_estimation(study, method="mlmc", tol=np.array([1.0]), executor=_Interrupting(n_items), progress=QUIET)
    stage = run_stage("mlmc", "mlmc_contact_area-1_theta-0.5")
    stored = sum(study.store.sample_indices(level=level, stage=stage).size for level in study.store.levels())
    assert stored == n_items  # every completed sample was kept
    (run,) = study.store.read_runs()
    assert run["status"] == "interrupted"
    resumed = run_estimation(study, method="mlmc", tol=np.array([1.0]), executor=SerialExecutor(), progress=QUIET)
    assert resumed.outcome.n_computed == sum(reference.outcome.n_samples) - n_items
    for key in ("estimate", "stat_error", "bias_estimate", "n_samples", "cost"):
        assert getattr(resumed.outcome, key) == getattr(reference.outcome, key), key
    (run,) = study.store.read_runs()
    assert run["status"] == "finished"


def test_a_run_stopped_by_any_failure_is_recorded_interrupted_and_the_failure_kept(monkeypatch):
    study = _screened()
    with pytest.raises(RuntimeError, match="a worker died"):
        crashing = _Interrupting(3, RuntimeError("a worker died"))
        run_estimation(study, method="mlmc", tol=np.array([1.0]), executor=crashing, progress=QUIET)
    (run,) = study.store.read_runs()
    assert run["status"] == "interrupted"  # not "running": no process computes it any more
    # The record's write failing too (e.g. the disk full) must not replace the interrupt that stopped the run.
    study = _screened()
    writes = {"n": 0}
    original = type(study.store).write_run

    def write_run(self, run_id, record):
        writes["n"] += 1
        if record.get("status") == "interrupted":
            raise OSError("no space left on device")
        return original(self, run_id, record)

    monkeypatch.setattr(type(study.store), "write_run", write_run)
    with pytest.raises(KeyboardInterrupt):
        run_estimation(study, method="mlmc", tol=np.array([1.0]), executor=_Interrupting(3), progress=QUIET)
    assert writes["n"] == 2  # running, then the failed interrupted


def test_a_mean_run_the_estimator_refuses_is_recorded_as_refused(monkeypatch):
    from rough_uq.errors import EstimationError
    from rough_uq.study.pipeline import estimation

    def refusing(*args, **kwargs):
        raise EstimationError("a plan of 2e+11 samples, more than max_samples = 10000000: loosen the tolerance")
        yield

    study = _screened()
    monkeypatch.setattr(estimation, "iter_mlmc", refusing)
    with pytest.raises(EstimationError, match="max_samples"):
        run_estimation(study, method="mlmc", tol=np.array([1.0]), executor=SerialExecutor(), progress=QUIET)
    (run,) = read_run_records(study.store)
    assert run.status == "refused" and run.reason.startswith("a plan of 2e+11 samples") and run.outcome is None


@pytest.mark.parametrize("method", ["mlmc", "mc"])
def test_a_run_refuses_a_plan_beyond_any_budget_that_its_own_samples_make(monkeypatch, method):
    # The forecast checks the first plan only: on a study in full contact (a mean gap at rounding level), mc --tol
    # at a tolerance the screening called cheap re-planned 2.7e7 samples from its own and began to draw them.
    from rough_uq.multilevel.drivers import PlanUpdated
    from rough_uq.study.pipeline import estimation

    drawn = []

    def replanning(sampler, **kwargs):
        yield PlanUpdated(levels=np.array([0, 1]), n_planned=np.array([10, 2]), n_done=np.zeros(2, int),
                          reason="initial")
        yield PlanUpdated(levels=np.array([0, 1]), n_planned=np.array([27_000_000, 2]), n_done=np.array([10, 2]),
                          reason="variance")
        drawn.append(True)

    study = _screened()
    monkeypatch.setattr(estimation, "iter_mlmc" if method == "mlmc" else "iter_mc", replanning)
    with pytest.raises(PlanTooLargeError, match=r"--tol contact_area=1 needs about 2\.7e\+07 samples .*loosen --tol"):
        run_estimation(study, method=method, tol=np.array([1.0]), executor=SerialExecutor(), progress=QUIET)
    assert not drawn
    (run,) = read_run_records(study.store)
    assert run.status == "refused" and run.outcome is None


def test_a_target_run_refused_on_the_way_names_the_option_the_user_gave():
    # The driver says "tol 1e-06 needs about ...: loosen the tolerance"; the user typed --tol-var or --tol-cdf.
    study = _study(qoi={"contact_area": {"unit": "percent"}, "mean_gap": {}})
    with pytest.raises(EstimationError) as info:
        run_target(study, target="variance", tol=np.array([1e-6, 1e-3]), executor=SerialExecutor(), progress=QUIET)
    text = str(info.value)
    assert text.startswith("--tol-var contact_area=1e-06, mean_gap=0.001 needs more than ")
    # max_samples is an argument of the Python API, no option of roughuq's: the limit is named as the forecast does.
    assert text.endswith("more than the 1e+07 samples a roughuq run may plan: loosen --tol-var")
    assert "max_samples" not in text and "tol 1e-06" not in text
    # Still the driver's refusal, with its numbers: worded from them, not from the driver's message.
    assert isinstance(info.value, PlanTooLargeError) and info.value.tol == (1e-6, 1e-3)
    # Levels planned at the planners' cap (2^52): the need is larger, and the counts are written compactly.
    assert max(info.value.n_planned) == 2**52
    counts = " ".join(str(n) if n < 10**7 else f"{n:.3g}" for n in info.value.n_planned)
    assert f"more than {info.value.total:.3g} samples (N_l {counts})" in text
    request = cdf_request(study.config, column="contact_area", thresholds=np.linspace(10.0, 40.0, 31))
    with pytest.raises(EstimationError) as info:
        run_target(study, target="cdf", tol=np.array([1e-5]), request=request, executor=SerialExecutor(),
                   progress=QUIET)
    assert str(info.value).startswith("--tol-cdf 1e-05 needs about ") and str(info.value).endswith("loosen --tol-cdf")
    runs = read_run_records(study.store)
    assert sorted(run.reason.split(" needs")[0] for run in runs) == ["--tol-cdf 1e-05",
                                                                      "--tol-var contact_area=1e-06, mean_gap=0.001"]
    assert all(run.status == "refused" for run in runs)


def test_a_target_run_passes_on_other_refusals_of_the_driver_as_they_are(monkeypatch):
    # Only the driver's PlanTooLargeError is reworded; a message that merely reads like one is not parsed.
    from rough_uq.study.pipeline import target_runs

    def refusing(*args, **kwargs):
        raise EstimationError("tol 1e-06 needs about 3 samples: loosen the tolerance")

    study = _study()
    monkeypatch.setattr(target_runs, "estimate_target", refusing)
    with pytest.raises(EstimationError) as info:
        run_target(study, target="variance", tol=np.array([1e-6]), executor=SerialExecutor(), progress=QUIET)
    assert str(info.value) == "tol 1e-06 needs about 3 samples: loosen the tolerance"
    assert not isinstance(info.value, PlanTooLargeError)
    (run,) = read_run_records(study.store)
    assert run.status == "refused" and run.reason == str(info.value)


def _initial_cost_floor(study: Study) -> float:
    """Modelled cost of a target run's initial samples (4 on each of levels 0..2) if no solve iterated."""
    return 4 * sum(float(modelled_cost(study.model, level, np.zeros((1, 2)))[0]) for level in range(3))


@pytest.mark.parametrize(("max_cost", "named"), [(None, "estimation.max_cost 1e-09"), (2e-9, "--max-cost 2e-09")])
@pytest.mark.parametrize("target", ["variance", "cdf"])
def test_a_target_budget_below_its_initial_samples_is_refused_before_any_sample(max_cost, named, target):
    # The first batch of level 0 was drawn whatever the budget, and the run, stopped there, claimed --tol-var 60 met.
    study = _study(estimation={"initial_samples": 4, "batch_size": 4, "max_cost": 1e-9})
    request = cdf_request(study.config, column="contact_area", thresholds=np.linspace(0.0, 60.0, 13))
    with pytest.raises(EstimationError) as info:
        run_target(study, target=target, tol=np.array([60.0 if target == "variance" else 0.3]),
                   request=None if target == "variance" else request, executor=SerialExecutor(), progress=QUIET,
                   max_cost=max_cost)
    text, option = str(info.value), named.split()[0]
    assert text.startswith(f"{named} is too small for the initial samples of levels 0..2 (4 each), which cost at "
                           f"least {_initial_cost_floor(study):.3g} reference seconds")
    assert text.endswith(f"raise {option} (or lower estimation.initial_samples)")
    assert study.store.read_runs() == [] and study.store.levels() == []  # nothing computed, nothing recorded
    with pytest.raises(EstimationError, match=f"^{named} is too small "):
        check_target_budget(study.config, max_cost=max_cost)  # the check alone, e.g. before a study file exists
    check_target_budget(study.config, max_cost=1.01 * _initial_cost_floor(study))


def test_a_target_run_that_its_budget_stops_before_the_bias_is_estimated_does_not_meet_its_tolerance():
    # Just above the least cost of the initial samples: level 0 (drawn first, whatever it costs) takes
    # the budget. Its statistical error is far below --tol-var 60, and the run claimed the tolerance met.
    study = _study()
    record = run_target(study, target="variance", tol=np.array([60.0]), executor=SerialExecutor(), progress=QUIET,
                        max_cost=1.01 * _initial_cost_floor(study))
    outcome = record.outcome
    assert record.status == "finished" and outcome.stop_reason == "max_cost" and outcome.levels == (0,)
    assert outcome.stat_error[0] < 60.0 and outcome.bias_estimate == (0.0,)
    assert not outcome.is_bias_estimated and not outcome.tol_met
    from rough_uq.report.summary import format_run

    lines = format_run(record, study.config.qoi_names, {"contact_area": "%"})
    assert lines[0] == "variance contact_area=60: NOT MET (max_cost)"
    assert lines[1].startswith("  stopped at --max-cost before the levels its bias estimate needs were sampled;")
    assert lines[2].endswith(f"(stat. error {outcome.stat_error[0]:.2g} <= tol 60, bias not estimated)")


def test_a_study_builds_its_model_once(tmp_path, monkeypatch):
    # The spectrum's set-up grows like k_s^2 (seconds at k_s in the thousands); create_study built the model
    # twice and a target run's budget check a third time.
    from rough_uq.study.pipeline import planning, studies

    calls = []
    real = studies.build_model
    counting = lambda config, **named: calls.append(1) or real(config, **named)  # noqa: E731
    monkeypatch.setattr(studies, "build_model", counting)
    monkeypatch.setattr(planning, "build_model", counting)  # the budget check's
    config = config_from_dict(tiny_config())
    with create_study(config, tmp_path / "s.h5") as study:
        assert len(calls) == 1
        check_target_budget(study.config, max_cost=1e6, model=study.model)
        assert len(calls) == 1


def test_a_plain_mc_run_stopped_by_its_budget_is_not_said_to_miss_bias_levels():
    # Plain MC never estimates a bias: its budget stop is just that (the report blamed the bias levels).
    from rough_uq.report.summary import format_run

    study = _study()
    # Above the least cost of the 4 initial samples (a budget below it is refused before any sample), below their
    # cost with the solves' iterations: the run stops once a probe of two samples shows the rest unaffordable.
    budget = 1.2 * 4 * float(modelled_cost(study.model, 1, np.zeros((1, 2)))[0])
    record = run_estimation(study, method="mc", tol=np.array([0.01]), executor=SerialExecutor(), progress=QUIET,
                            level=1, max_cost=budget)
    outcome = record.outcome
    assert outcome.stop_reason == "max_cost" and not outcome.is_bias_estimated and not outcome.tol_met
    lines = format_run(record, study.config.qoi_names, {"contact_area": "%"})
    assert lines[0].endswith(": NOT MET (max_cost)")
    assert lines[1].startswith("  stopped at --max-cost; level 1, N "), lines[1]
    # Its statistical error against the share sqrt(1 - theta) tol that it had to meet ("<= tol 0.043" beside NOT MET).
    share = 0.01 * math.sqrt(0.5)
    assert lines[2].endswith(f"(stat. error {outcome.stat_error[0]:.2g} > {share:.2g}, its share of tol 0.01, "
                             "bias not estimated)"), lines[2]


def test_a_target_run_passes_other_refusals_on_as_they_are(monkeypatch):
    from rough_uq.study.pipeline import target_runs

    def refusing(*args, **kwargs):
        raise EstimationError("sampler returned a negative or non-finite cost on level 1")

    study = _study()
    monkeypatch.setattr(target_runs, "estimate_target", refusing)
    with pytest.raises(EstimationError, match="^sampler returned a negative or non-finite cost on level 1$"):
        run_target(study, target="variance", tol=np.array([60.0]), executor=SerialExecutor(), progress=QUIET)


def test_every_run_has_its_own_random_stage():
    study = _screened()
    loose = run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET)
    tight = run_estimation(study, method="mlmc", tol=np.array([0.5]), executor=SerialExecutor(), progress=QUIET)
    mc = run_estimation(study, method="mc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET)
    stages = {STAGE_SCREENING, loose.stage, tight.stage, mc.stage}
    assert len(stages) == 4
    assert is_coupled_stage(loose.stage) and is_coupled_stage(tight.stage) and not is_coupled_stage(mc.stage)
    assert tight.outcome.n_computed == sum(tight.outcome.n_samples)  # nothing shared with the looser run
    assert len(study.store.read_runs()) == 3
    for level in range(3):
        first = study.store.read_samples(level=level, stage=loose.stage).fine
        second = study.store.read_samples(level=level, stage=tight.stage).fine
        assert not np.array_equal(first[:3], second[:3])


def test_mc_runs_uncoupled_on_the_planned_level():
    study = _screened()
    record = run_estimation(study, method="mc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET)
    (level,) = record.outcome.levels
    assert level == record.level
    batch = study.store.read_samples(level=level, stage=record.stage)
    assert batch.n_samples == record.outcome.n_samples[0]
    assert np.all(batch.coarse == 0) and np.all(batch.n_iter[:, 1] == 0)
    assert record.outcome.is_bias_estimated


def test_missing_samples_shrinks_as_samples_are_stored():
    study = _screened()
    work = missing_samples(study, method="mlmc", tol=np.array([1.0]))
    before = work.missing
    assert sorted(before) == [0, 1, 2] and work.n_missing == sum(i.size for i in before.values())
    assert all(list(indices) == list(range(indices.size)) and indices.size > 0 for indices in before.values())
    # Store exactly what the plan asks for: the next plan starts where it ended.
    for level, indices in before.items():
        study.store.append_samples(compute_batch(study.model, stage=work.stage, level=level, indices=indices))
    after = missing_samples(study, method="mlmc", tol=np.array([1.0])).missing
    for level, indices in after.items():
        assert indices.size == 0 or indices[0] >= before[level].size
    record = run_estimation(study, method="mlmc", tol=np.array([1.0]), executor=SerialExecutor(), progress=QUIET)
    assert record.stage == work.stage
    assert missing_samples(study, method="mlmc", tol=np.array([1.0])).n_missing == 0
    # The run computed only what was not stored (the first plan may ask for more than the run ends up using).
    stored = [before[level].size for level in record.outcome.levels]
    assert record.outcome.n_computed == sum(max(0, n - s) for n, s in zip(record.outcome.n_samples, stored))


def test_estimation_needs_a_screening():
    with pytest.raises(StudyFileError, match="roughuq screen"):
        run_estimation(_study(), method="mlmc", tol=np.array([1.0]), executor=SerialExecutor(), progress=QUIET)


def test_non_converged_solves_are_retried_flagged_and_reported():
    study = _study(solver={"tol": 1e-14, "max_iter": 1})
    outcome = run_screening(study, executor=SerialExecutor(), progress=QUIET)
    batch = study.store.read_samples(level=2, stage=STAGE_SCREENING)
    assert not batch.converged[:, 0].any()
    assert np.all(batch.n_iter[:, 0] == 1 + 10)  # max_iter, then the retry with 10 x max_iter
    assert outcome.record.n_not_converged == 3 * 8
    assert np.all(np.isfinite(batch.fine))


@pytest.mark.parametrize("probabilities", [(0.5, 0.5), (0.05, 0.5, 5e-1), [0.9, 0.1, 0.9]])
def test_a_cdf_request_refuses_a_probability_given_twice(probabilities):
    # The CLI refused --probabilities 0.5,0.5; a Python caller got two rows of one quantile.
    config = config_from_dict(tiny_config())
    with pytest.raises(InvalidParameterError, match="given twice") as info:
        cdf_request(config, column="contact_area", thresholds=[10.0, 20.0, 30.0], probabilities=probabilities)
    assert info.value.name == "--probabilities" and "distinct" in str(info.value)


@pytest.mark.parametrize("probabilities", [(), (0.0, 0.5), (0.5, 1.0), (float("nan"),), ("0.5",), "0.5", (True,), 0.5])
def test_a_cdf_request_refuses_what_is_not_probabilities_naming_the_option(probabilities):
    config = config_from_dict(tiny_config())
    with pytest.raises(InvalidParameterError) as info:
        cdf_request(config, column="contact_area", thresholds=[10.0, 20.0, 30.0], probabilities=probabilities)
    assert info.value.name == "--probabilities"


def test_a_cdf_request_keeps_the_probabilities_in_the_order_given():
    config = config_from_dict(tiny_config())
    request = cdf_request(config, column="contact_area", thresholds=[10.0, 20.0], probabilities=(0.5, 0.05, 0.95))
    assert request.probabilities == (0.5, 0.05, 0.95)
    assert cdf_request(config, column=None, thresholds=[10.0, 20.0]).probabilities == (0.05, 0.5, 0.95)


def test_a_load_curve_gives_a_column_its_own_thresholds_in_the_config():
    # estimation.distribution took QoI names only: every load's column used one grid, which misses the samples of the
    # others (contact areas of 4 % and 20 %), and `--tol-cdf --qoi contact_area@0.1` drew every sample, then ended
    # NOT MET (thresholds_miss_samples); the column's own key was refused as "not a QoI of this study".
    grids = {"contact_area": {"thresholds": {"start": 3, "stop": 7, "count": 9}},
             "contact_area@0.10": {"thresholds": {"start": 15, "stop": 26, "count": 12}, "probabilities": [0.5]}}
    config = config_from_dict(tiny_config(load={"relative": [0.02, 0.1]}, estimation={"distribution": grids}))
    own = cdf_request(config, column="contact_area@0.1")
    assert own.thresholds.tolist() == list(np.linspace(15, 26, 12)) and own.probabilities == (0.5,)
    other = cdf_request(config, column="contact_area@0.02")
    assert other.thresholds.tolist() == list(np.linspace(3, 7, 9)) and other.probabilities == (0.05, 0.5, 0.95)
    # Each setting from the first entry that gives it: the column's probabilities with its QoI's thresholds.
    config = config_from_dict(tiny_config(load={"relative": [0.02, 0.1]}, estimation={"distribution": {
        "contact_area": {"thresholds": {"start": 3, "stop": 7, "count": 9}, "probabilities": [0.1, 0.9]},
        "contact_area@0.1": {"probabilities": [0.5]}}}))
    own = cdf_request(config, column="contact_area@0.1")
    assert own.thresholds.tolist() == list(np.linspace(3, 7, 9)) and own.probabilities == (0.5,)
    assert cdf_request(config, column="contact_area@0.02").probabilities == (0.1, 0.9)
    with pytest.raises(ConfigError, match="estimation.distribution.contact_area@0.1: a second key for "
                                          "contact_area@0.1 .*one key per column \\(contact_area@0.10 is the first"):
        config_from_dict(tiny_config(load={"relative": [0.02, 0.1]}, estimation={"distribution": {
            **grids, "contact_area@0.1": grids["contact_area"]}}))
    grids["contact_area@0.3"] = grids.pop("contact_area@0.10")  # no such load
    with pytest.raises(ConfigError, match="estimation.distribution.contact_area@0.3: not a QoI or load column of this "
                                          "study .*one load's column: contact_area@0.02, contact_area@0.1"):
        config_from_dict(tiny_config(load={"relative": [0.02, 0.1]}, estimation={"distribution": grids}))
    with pytest.raises(ConfigError, match="estimation.distribution.contact_area@0.1: not a QoI of this study"):
        config_from_dict(tiny_config(estimation={"distribution": {"contact_area@0.1": grids["contact_area"]}}))


def test_parse_tolerances():
    single = config_from_dict(tiny_config())
    assert parse_tolerances(["0.3"], single).tolist() == [0.3]
    assert parse_tolerances(None, single).tolist() == [2.0]
    assert parse_tolerances(["contact_area=0.1"], single).tolist() == [0.1]
    two = config_from_dict(tiny_config(qoi={"contact_area": {"tol": 1.0}, "clusters": {}}))
    assert parse_tolerances(["clusters=2", "contact_area=0.5"], two).tolist() == [0.5, 2.0]
    assert parse_tolerances(["clusters=2,contact_area=0.5"], two).tolist() == [0.5, 2.0]
    with pytest.raises(InvalidParameterError, match="clusters=EPS"):
        parse_tolerances(None, two)
    with pytest.raises(InvalidParameterError, match="NAME=EPS pairs"):
        parse_tolerances(["0.5"], two)
    with pytest.raises(InvalidParameterError, match="a QoI of this study"):
        parse_tolerances(["area=0.5"], two)
    for bad in ("-1", "0", "nan", "inf", "abc"):
        with pytest.raises(InvalidParameterError, match="--tol"):
            parse_tolerances([bad], single)


@pytest.mark.parametrize("values", [[""], ["0.2,"], [" , "], ["contact_area=0.2,,"], ["=0.2"], [" =0.2"]])
@pytest.mark.parametrize("option", ["--tol", "--tol-var"])
def test_an_empty_tolerance_item_or_one_without_a_name_is_refused_naming_option_and_value(values, option):
    # Empty items were skipped: [""] fell back to the config's tolerance, "=0.2" was read as a bare 0.2.
    config = config_from_dict(tiny_config())
    with pytest.raises(InvalidParameterError) as info:
        parse_tolerances(values, config, option=option, use_config=option == "--tol")
    assert info.value.name == option and info.value.value == values[0]
    assert "no empty item" in str(info.value)


def test_a_sweep_refuses_an_empty_tolerance_item_before_writing_anything(tmp_path):
    from rough_uq.study.config import sweep_configs

    configs = sweep_configs(config_from_dict(tiny_config()), key="seed", values=["1", "2"])
    with pytest.raises(InvalidParameterError, match="no empty item"):
        run_sweep(configs, key="seed", directory=tmp_path / "sweep", tol=["5,"], level=0, executor=SerialExecutor(),
                  progress=QUIET)
    assert not (tmp_path / "sweep").exists()


@pytest.mark.parametrize("tol", [["0.5"], None], ids=["--tol", "the config's"])
def test_a_sweep_refuses_studies_that_give_a_qoi_in_different_units(tmp_path, tol):
    """One tolerance, 0.5, was 0.5 percentage points in one study and half the nominal area in the other."""
    from rough_uq.study.config import sweep_configs

    key = "qoi.contact_area.unit"
    configs = sweep_configs(config_from_dict(tiny_config()), key=key, values=["percent", "fraction"])
    with pytest.raises(InvalidParameterError) as info:
        run_sweep(configs, key=key, directory=tmp_path / "sweep", tol=tol, level=0, executor=SerialExecutor(),
                  progress=QUIET)
    assert info.value.name == "--set" and info.value.value == f"{key}=percent,fraction"
    assert "contact_area would be in % (value percent) and in fraction (value fraction)" in info.value.allowed
    assert not (tmp_path / "sweep").exists()


def test_a_sweep_of_a_qoi_tolerance_refuses_a_tol_for_that_qoi_but_not_for_another(tmp_path):
    """--tol overrode every swept qoi.contact_area.tol: two files, one study, one tolerance."""
    from rough_uq.study.config import sweep_configs

    key = "qoi.contact_area.tol"
    qoi = {"contact_area": {"unit": "percent", "tol": 2.0}, "mean_gap": {"tol": 0.5}}
    configs = sweep_configs(config_from_dict(tiny_config(qoi=qoi)), key=key, values=["4", "8"])
    options = dict(key=key, directory=tmp_path / "sweep", level=0, executor=SerialExecutor(), progress=QUIET)
    with pytest.raises(InvalidParameterError) as info:
        run_sweep(configs, tol=["mean_gap=0.5", "contact_area=3"], **options)
    assert info.value.name == "--tol" and "every study would run contact_area=3 " in info.value.allowed
    assert not (tmp_path / "sweep").exists()
    rows = run_sweep(configs, tol=["mean_gap=0.5"], **options)  # the swept QoI at its swept tolerances
    assert [list(row.run.tol) for row in rows] == [[4.0, 0.5], [8.0, 0.5]]


def test_study_file_roundtrip_and_mismatch(tmp_path):
    config = config_from_dict(tiny_config())
    path = tmp_path / "study.h5"
    with create_study(config, path) as study:
        run_screening(study, executor=SerialExecutor(), progress=QUIET)
    with open_existing_study(path) as study:
        assert study.config == config
        record = run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET)
    with open_existing_study(path, writable=False) as study:
        (run,) = study.store.read_runs()
        assert run["estimate"] == list(record.outcome.estimate)
        assert read_run_records(study.store) == [record]
    other = config_from_dict(tiny_config(seed=1))
    with pytest.raises(StudyFileError, match="another config"):
        open_existing_study(path, config=other)
    with pytest.raises(StudyFileError):
        create_study(other, path)
    # Estimation settings and tolerances do not change samples: the same study accepts them.
    relaxed = config_from_dict(tiny_config(estimation={"theta": 0.3}))
    with open_existing_study(path, config=relaxed) as study:
        assert study.config.estimation.theta == 0.3
    with pytest.raises(StudyFileError, match="does not exist"):
        open_existing_study(tmp_path / "missing.h5")


def _tamper_qoi_names(path: Path, names: list[str]) -> None:
    """Other QoI names, with the header checksum that goes with them (as a faulty writer would leave them: names
    altered alone are refused by the checksum, test_store_damaged)."""
    import h5py

    from rough_uq.study.store import header_checksum

    with h5py.File(path, "r+") as f:
        del f["qoi_names"]
        f.create_dataset("qoi_names", data=names, dtype=h5py.string_dtype())
        f.attrs["header_checksum"] = header_checksum(f["config_yaml"].asstr()[()], names)


def test_a_study_whose_qoi_names_are_not_its_configs_columns_is_refused_as_damaged(tmp_path):
    config = config_from_dict(tiny_config())
    path = tmp_path / "study.h5"
    create_study(config, path).close()
    _tamper_qoi_names(path, ["foo", "bar"])
    before = path.read_bytes()
    openers = [lambda: open_existing_study(path, writable=False), lambda: open_existing_study(path),
               lambda: open_existing_study(path, config=config), lambda: create_study(config, path)]
    for opener in openers:
        with pytest.raises(StudyFileError, match=r"damaged study file \(qoi_names \['foo', 'bar'\]") as info:
            opener()
        assert str(path) in str(info.value) and "contact_area" in str(info.value)
    assert path.read_bytes() == before


def test_merging_a_shard_with_other_qoi_names_says_what_differs(tmp_path):
    config = config_from_dict(tiny_config())
    path, shard = tmp_path / "study.h5", tmp_path / "shard.h5"
    create_study(config, shard).close()
    _tamper_qoi_names(shard, ["foo", "bar"])
    with create_study(config, path) as study:
        with pytest.raises(StudyFileError, match=r"other QoI columns \(foo, bar; this study: contact_area\)") as info:
            merge_shards(study, [shard])
    assert "another study" not in str(info.value) and "nothing was merged" in str(info.value)


def test_merging_the_study_into_itself_is_refused_by_any_path(tmp_path, monkeypatch):
    config = config_from_dict(tiny_config())
    path = tmp_path / "study.h5"
    (tmp_path / "link.h5").symlink_to(path)
    monkeypatch.chdir(tmp_path)
    with create_study(config, path) as study:
        study.store.append_samples(compute_batch(study.model, stage=STAGE_SCREENING, level=0, indices=np.arange(2)))
        before = path.read_bytes()
        for same in (path, "study.h5", "./study.h5", tmp_path / "link.h5"):
            with pytest.raises(StudyFileError, match=r"is the study file .* itself \(.*\); nothing was merged"):
                merge_shards(study, [same])
    assert path.read_bytes() == before


def test_another_configs_study_is_refused_naming_the_options_of_the_command(tmp_path):
    config, other = config_from_dict(tiny_config()), config_from_dict(tiny_config(seed=1))
    path = tmp_path / "study.h5"
    create_study(config, path).close()
    with pytest.raises(StudyFileError, match="another config") as screen:
        create_study(other, path)
    with pytest.raises(StudyFileError, match="another config") as mlmc:
        open_existing_study(path, config=other)
    assert "another --out file" in str(screen.value)  # roughuq screen CONFIG --out
    assert "--config" in str(mlmc.value) and "another --study file" in str(mlmc.value)
    assert "--out" not in str(mlmc.value)
    # Both name the setting that differs, with its two values.
    for refusal in (screen, mlmc):
        assert "differs in seed: 2026 in the file, 1 in this config" in str(refusal.value)


def test_another_configs_refusals_name_the_differing_settings_and_how_many_more(tmp_path):
    config = config_from_dict(tiny_config())
    path, shard = tmp_path / "study.h5", tmp_path / "shard.h5"
    create_study(config, path).close()
    surface = {**tiny_config()["surface"], "hurst": 0.6, "rms_height": 2.0}
    changes = {"seed": 5, "surface": surface, "load": {"absolute": 0.5}, "grid": {"coarsest": 16, "max_level": 2}}
    other = config_from_dict(tiny_config(**changes))
    with pytest.raises(StudyFileError, match="another config") as info:
        open_existing_study(path, config=other)
    message = str(info.value)
    assert "grid.coarsest: 8 in the file, 16 in this config" in message
    assert "load.absolute: unset in the file, 0.5 in this config" in message
    assert "load.relative: 0.2 in the file, unset in this config" in message
    assert "seed: 2026 in the file, 5 in this config" in message
    assert "; and 2 more setting(s)" in message  # surface.hurst and surface.rms_height
    assert "surface.hurst" not in message
    # A shard of another config names them too, as the shard's values against the study's.
    create_study(config_from_dict(tiny_config(seed=5)), shard).close()
    with create_study(config, path) as study, pytest.raises(StudyFileError, match="another study") as merge:
        merge_shards(study, [shard])
    assert "differs in seed: 5 in the shard, 2026 in this study" in str(merge.value)


def test_a_sweep_refuses_another_configs_study_before_writing_any_config(tmp_path):
    from rough_uq.study.config import sweep_configs

    base = config_from_dict(tiny_config())
    configs = sweep_configs(base, key="surface.system_size", values=["1", "2"])
    directory = tmp_path / "sweep"
    first = directory / Path(configs[0][1].output.path).name
    second = directory / Path(configs[1][1].output.path).name
    create_study(config_from_dict(tiny_config(seed=1)), second).close()  # value 2: a study of another seed
    second.with_suffix(".yaml").write_text("the config of that study\n")
    with pytest.raises(StudyFileError, match="another config") as info:
        run_sweep(configs, key="surface.system_size", directory=directory, tol=["5"], level=0,
                  executor=SerialExecutor(), progress=QUIET)
    assert "--dir" in str(info.value) and "--out" not in str(info.value) and "--study" not in str(info.value)
    assert second.with_suffix(".yaml").read_text() == "the config of that study\n"
    assert not first.exists() and not first.with_suffix(".yaml").exists()


def test_screening_again_with_more_levels_extends_the_study(tmp_path):
    path = tmp_path / "study.h5"
    grid = {"coarsest": 8, "max_level": 3}
    first = config_from_dict(tiny_config(grid=grid, screening={"levels": 3, "samples": 6}))
    with create_study(first, path) as study:
        run_screening(study, executor=SerialExecutor(), progress=QUIET)
    more = config_from_dict(tiny_config(grid=grid, screening={"levels": 4, "samples": 8}))
    with create_study(more, path) as study:  # same samples, same study
        outcome = run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert outcome.record.n_computed == 4 * 8 - 3 * 6
    with open_existing_study(path) as study:  # its stored config still says 3 levels
        assert study.config.screening.levels == 3
        record = run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(),
                                progress=QUIET)
    assert record.predicted.finest_level >= 0
    assert record.screening_rates.levels_gamma == (1, 2, 3)  # the rates come from the four screened levels


def test_a_study_too_shallow_to_screen_is_refused_before_any_sample_naming_grid_max_level():
    # grid.max_level 1 (valid for runs without a screening): levels 0..1 were computed, then the rates failed.
    study = _study(grid={"coarsest": 8, "max_level": 1})
    with pytest.raises(InvalidParameterError) as info:
        run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert info.value.name == "grid.max_level" and info.value.value == 1
    assert "a screening needs levels 0..2" in str(info.value) and "mlmc --tol-var" in str(info.value)
    assert study.store.levels() == []
    shallow = _study(grid={"coarsest": 8, "max_level": 0})
    with pytest.raises(InvalidParameterError) as info:  # was min_finest_level, a name of the core
        run_target(shallow, target="variance", tol=np.array([60.0]), executor=SerialExecutor(), progress=QUIET)
    assert info.value.name == "grid.max_level" and "variance and cdf runs" in str(info.value)


def test_screening_without_decaying_bias_keeps_its_table_and_says_why(monkeypatch):
    from rough_uq.errors import InvalidParameterError as Invalid
    from rough_uq.study.pipeline import screening

    def no_decay(**kwargs):
        raise Invalid("alpha", -0.9, "alpha > 0: the bias does not decay with the level")

    monkeypatch.setattr(screening, "plan", no_decay)
    outcome = run_screening(_study(), executor=SerialExecutor(), progress=QUIET)
    assert outcome.record.predictions == ()
    (why,) = [d for d in outcome.record.diagnostics if d.kind == "prediction"]
    assert "no cost prediction" in why.message and "screening.levels" in why.message


@pytest.mark.parametrize("tol, kept", [(3e-140, 3), (8e139, 4), (1.0, 5)], ids=["near 1e-140", "near 1e140", "inside"])
def test_a_tol_near_the_edge_of_the_range_keeps_the_rows_runs_take(tol, kept):
    # tol 2e-140: its 1/4 row failed, the table lost the rows after it, and the warning said "tol: got
    # array([5.e-141])... screen more levels".
    from rough_uq.study.pipeline.screening import PREDICTION_FACTORS

    outcome = run_screening(_study(qoi={"contact_area": {"unit": "percent", "tol": tol}}),
                            executor=SerialExecutor(), progress=QUIET)
    rows = [prediction.tol[0] for prediction in outcome.record.predictions]
    assert rows == pytest.approx([tol * f for f in PREDICTION_FACTORS if 1e-140 <= tol * f <= 1e140], rel=1e-12)
    assert len(rows) == kept
    notes = [d.message for d in outcome.record.diagnostics if d.kind == "prediction"]
    assert notes == ([] if kept == 5 else [notes[0]])
    assert all("times the tolerance: a tolerance beyond [1e-140, 1e+140]" in note for note in notes)
    assert not any("array" in note or "screen more levels" in note for note in notes)


def test_the_forecast_plans_the_samples_the_run_starts_with():
    # The quickstart's screening drops level 0 at these tolerances (its 32^2 samples cost more than they
    # save): the forecast printed before the run must plan what the run then plans, level 0 dropped too.
    config = load_config(Path(__file__).parents[1] / "rough_uq" / "study" / "configs" / "quickstart.yaml")
    study = Study(config, MemoryStore(qoi_names=config.qoi_names))
    run_screening(study, executor=SerialExecutor(), progress=Progress())
    dropped = 0
    for eps in (0.25, 0.3, 0.5):  # 0.1: refused (the screening predicts a bias of 0.16 on 512^2)
        tol = np.array([eps])
        forecast = forecast_run(study, method="mlmc", tol=tol)
        key = run_id("mlmc", config.qoi_names, tol, config.estimation.theta, None,
                     richardson=config.estimation.richardson)
        sampler = StudySampler(study, stage=run_stage("mlmc", key), executor=SerialExecutor(), progress=Progress())
        events, _ = _events(study, method="mlmc", tol=tol, sampler=sampler, max_cost=None)
        initial = next(iter(events))  # the run's plan before its first sample
        assert isinstance(initial, PlanUpdated) and initial.reason == "initial"
        planned = [int(n) for n in initial.n_planned]
        assert planned[: len(forecast.n_samples)] == list(forecast.n_samples), eps
        assert not any(planned[len(forecast.n_samples):])
        dropped += forecast.n_samples[0] == 0
    assert dropped  # the case this test is about occurred


def test_the_run_record_predicts_seconds_from_the_screening_time_per_modelled_cost():
    study = _screened()
    record = run_estimation(study, method="mlmc", tol=np.array([2.0]), executor=SerialExecutor(), progress=QUIET)
    per_cost = read_screening_record(study.store).seconds_per_cost
    assert per_cost > 0 and per_cost != 1.0
    predicted = record.predicted
    assert predicted.mlmc_seconds == pytest.approx(predicted.mlmc_cost * per_cost)
    assert predicted.mc_seconds == pytest.approx(predicted.mc_cost * per_cost)


def test_the_stored_warnings_of_a_run_name_the_qois():
    # A two-QoI run stored "mlmc: level 1: Var(Q_l - Q_l-1) >= Var(Q_l) for QoI [0] (ratio 2.91); ...".
    study = _screened(qoi={"contact_area": {"unit": "percent", "tol": 2.0}, "mean_gap": {"tol": 0.1}})
    run_estimation(study, method="mlmc", tol=np.array([2.0, 0.1]), executor=SerialExecutor(), progress=QUIET)
    (run,) = read_run_records(study.store)
    warnings = [d.to_json() for d in run.outcome.diagnostics]
    assert any(w.startswith("mlmc: level 1: Var(Q_l - Q_l-1) >= Var(Q_l) for contact_area (ratio ") for w in warnings)
    assert not any("QoI [" in w for w in warnings), warnings


def test_a_variance_run_names_the_columns_of_its_warnings(monkeypatch):
    # A negative variance estimate of a study's --tol-var run was stored as "variance of QoI [0]: ...".
    from rough_uq.study.pipeline import target_runs

    seen = []
    real = target_runs.estimate_target

    def spy(*args, **kwargs):
        seen.append(kwargs.get("qoi_names"))
        return real(*args, **kwargs)

    monkeypatch.setattr(target_runs, "estimate_target", spy)
    study = _study()
    run_target(study, target="variance", tol=np.array([60.0]), executor=SerialExecutor(), progress=QUIET,
               max_cost=1.01 * _initial_cost_floor(study))
    assert seen == [study.config.qoi_names] == [("contact_area",)]


def test_the_screening_checks_name_the_qois(monkeypatch):
    # The coupling warning of a five-QoI screening said "for QoI [4]": the screening passed no names.
    from rough_uq.study.pipeline import screening

    seen = []

    def recording(statistics, **options):
        seen.append(options.get("names"))
        return ()

    monkeypatch.setattr(screening, "diagnose", recording)
    study = _study(qoi={"contact_area": {"unit": "percent", "tol": 2.0}, "mean_gap": {"tol": 0.1}})
    run_screening(study, executor=SerialExecutor(), progress=QUIET)
    assert seen == [study.config.qoi_names] and len(study.config.qoi_names) == 2


def test_index_ranges_and_shards_cover_the_missing_indices_exactly_once():
    from rough_uq.study.pipeline import WorkPlan, index_ranges

    rng = np.random.default_rng(44)
    assert index_ranges([]) == [] and index_ranges([7]) == [(7, 8)]
    assert index_ranges([0, 1, 2, 5, 6, 9]) == [(0, 3), (5, 7), (9, 10)]
    last = np.iinfo(np.int64).max  # `sample --indices` takes it; the range's end is one past it, no int64 wrap
    assert index_ranges([last - 1, last]) == [(last - 1, last + 1)]
    for _ in range(200):
        missing = {level: np.flatnonzero(rng.random(int(rng.integers(0, 60))) < rng.random())
                   for level in range(int(rng.integers(1, 4)))}
        for level, indices in missing.items():
            ranges = index_ranges(indices)
            assert np.array_equal(np.concatenate([np.arange(a, b) for a, b in ranges] or [[]]), indices)
            assert all(b < c for (_, b), (c, _) in zip(ranges, ranges[1:]))  # runs are maximal and in order
        size = int(rng.integers(1, 8))
        shards = WorkPlan("run", 3, missing).shards(size)
        assert all(0 < stop - start <= size for _, start, stop in shards)
        for level, indices in missing.items():
            covered = [i for lv, start, stop in shards if lv == level for i in range(start, stop)]
            assert covered == indices.tolist()


def test_a_refused_command_keeps_a_new_study_file_another_process_holds(tmp_path):
    # Two `screen`s on one new study: the one refused as "locked" removed the file the other had just created and
    # held ("unused"), and the other then failed on a file gone (3 of 25 races). The other process's study is
    # stood in for by a writer of this process (flock locks clash between two opens of the lock file).
    from rough_uq.study.pipeline.studies import removed_if_left_unused
    from rough_uq.study.store import open_study

    path = tmp_path / "results.h5"
    with pytest.raises(StudyFileError, match="is locked by a running process"):
        with removed_if_left_unused(path):
            holder = open_study(path, config_text="x: 1\n", config_hash="h", qoi_names=["contact_area"],
                                code_version="test")
            open_study(path, config_text="x: 1\n", config_hash="h", qoi_names=["contact_area"], code_version="test")
    assert path.is_file()
    holder.close()
    with pytest.raises(RuntimeError):  # once free, a file the block created and left unused is removed, as before
        with removed_if_left_unused(tmp_path / "other.h5"):
            open_study(tmp_path / "other.h5", config_text="x: 1\n", config_hash="h", qoi_names=["contact_area"],
                       code_version="test").close()
            raise RuntimeError("refused")
    assert not (tmp_path / "other.h5").exists()
