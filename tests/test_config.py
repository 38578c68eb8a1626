"""The study config: shipped configs load, every defect is named, the hash is canonical."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pydantic
import pytest
import yaml

from rough_uq.study import config as config_module
from rough_uq.study.config import (
    SOLVER_ARRAYS_PER_NODE,
    SolverConfig,
    config_from_dict,
    config_from_stored_text,
    config_from_yaml_text,
    config_differences,
    config_hash,
    load_config,
    memory_warning,
    resolved_yaml,
    solver_memory_bytes,
    sweep_configs,
)
from rough_uq.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "rough_uq" / "study" / "configs"  # package data: `roughuq init NAME`
SHIPPED = sorted(CONFIGS.glob("*.yaml"))
BAD = ROOT / "tests" / "data" / "bad_configs"

# One line per problem: "<field.path>: <what> (got <value>; allowed: <what>)"
LINE = re.compile(r"^\S+: .+ \(got .+; allowed: .+\)$")


def _base() -> dict:
    return {
        "schema_version": 1,
        "seed": 7,
        "surface": {
            "system_size": 2.0,
            "wavelengths": {"lambda_l": 1.0, "lambda_r": 1.0, "lambda_s": 1 / 64},
            "hurst": 0.8,
            "rms_height": 1.0,
        },
        "material": {"e_star": 1.0},
        "load": {"relative": 0.1},
        "qoi": {"contact_area": {"unit": "percent", "tol": 0.5}},
        "grid": {"coarsest": 256, "max_level": 2},
    }


def _message(data: object) -> str:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data)
    return str(info.value)


# ---------------------------------------------------------------------------
# Shipped configs
# ---------------------------------------------------------------------------


def test_three_configs_are_shipped() -> None:
    assert {p.name for p in SHIPPED} >= {"quickstart.yaml", "classic-area.yaml", "classic-clusters.yaml"}


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_config_loads_and_round_trips(path: Path) -> None:
    config = load_config(path)
    again = config_from_dict(yaml.safe_load(resolved_yaml(config)))
    assert again == config
    assert config_hash(again) == config_hash(config)
    assert resolved_yaml(again) == resolved_yaml(config)


def test_classic_configs_match_the_reference_setting() -> None:
    area = load_config(CONFIGS / "classic-area.yaml")
    assert (area.surface.k_l, area.surface.k_r, area.surface.k_s) == (2.0, 2.0, 128.0)
    assert area.surface.hurst == 0.8 and area.surface.rms_height == 1.0
    assert area.material.e_star == 1.0
    assert (area.load.kind, area.load.value) == ("relative", 0.1)
    assert area.grid.coarsest == 256
    assert area.qoi_names == ("contact_area",) and area.qoi["contact_area"].unit == "percent"

    clusters = load_config(CONFIGS / "classic-clusters.yaml")
    assert clusters.surface.system_size == 3.0
    assert (clusters.surface.k_l, clusters.surface.k_r, clusters.surface.k_s) == (3.0, 3.0, 192.0)
    assert (clusters.grid.coarsest, clusters.grid.max_level) == (96, 5)
    settings = clusters.qoi["clusters"]
    assert (settings.unit, settings.connectivity) == ("per_area", "mean")


def test_defaults_are_filled_in() -> None:
    config = config_from_dict(_base())
    assert config.solver.tol == 1e-7 and config.solver.max_iter == 10000
    assert config.solver.warm_start is True and config.solver.threads == 1
    assert config.grid.projection == "truncation"
    assert config.screening.levels == 3 and config.screening.samples == 20
    assert config.estimation.theta == 0.5 and config.estimation.max_cost is None
    assert config.output.path == "results.h5"
    assert config.grid.n_at(2) == 1024 == config.grid.finest
    text = resolved_yaml(config)
    assert "max_iter: 10000" in text and "wavenumbers" not in text and "absolute" not in text


def test_wavenumbers_and_wavelengths_resolve_alike() -> None:
    data = _base()
    data["surface"].pop("wavelengths")
    data["surface"]["wavenumbers"] = {"k_l": 2, "k_r": 2, "k_s": 128}
    by_k = config_from_dict(data)
    by_lambda = config_from_dict(_base())
    assert (by_k.surface.k_l, by_k.surface.k_r, by_k.surface.k_s) == (2.0, 2.0, 128.0)
    assert (by_lambda.surface.k_l, by_lambda.surface.k_r, by_lambda.surface.k_s) == (2.0, 2.0, 128.0)
    assert config_hash(by_k) == config_hash(by_lambda)


def test_config_is_frozen() -> None:
    config = config_from_dict(_base())
    with pytest.raises(pydantic.ValidationError):
        config.seed = 3  # type: ignore[misc]


def test_qoi_order_is_kept_and_bare_names_allowed(tmp_path: Path) -> None:
    text = yaml.safe_dump(_base(), sort_keys=False).replace(
        "qoi:\n  contact_area:\n    unit: percent\n    tol: 0.5\n",
        "qoi:\n  mean_gap:\n  clusters: {connectivity: 8}\n  contact_area: {unit: fraction}\n",
    )
    path = tmp_path / "study.yaml"
    path.write_text(text)
    config = load_config(path)
    assert config.qoi_names == ("mean_gap", "clusters", "contact_area")
    assert config.qoi["clusters"].unit == "per_area"
    assert list(yaml.safe_load(resolved_yaml(config))["qoi"]) == ["mean_gap", "clusters", "contact_area"]


def test_exponent_without_dot_is_a_number(tmp_path: Path) -> None:
    # YAML 1.1 reads 1e-6 as a string; a user writing it means a number.
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(_base()) + "solver:\n  tol: 1e-6\n  max_iter: 1e3\n")
    config = load_config(path)
    assert config.solver.tol == 1e-6 and config.solver.max_iter == 1000


# ---------------------------------------------------------------------------
# One bad config per defect
# ---------------------------------------------------------------------------

BAD_CASES = {
    "wrong_type": ("grid.coarsest: ", "got 'big'"),
    "unknown_key": ("surface.colour: unknown key", "got 'red'"),
    "hurst_out_of_range": ("surface.hurst: ", "got 1.5"),
    "negative_load": ("load.relative: ", "got -0.1"),
    "unresolved_rolloff": ("grid.coarsest: ", "got 32"),
    "both_spectra": ("surface.wavelengths: ", "got both of wavelengths and wavenumbers"),
    "not_yaml": ("not_yaml.yaml: not valid YAML at line 7", "expected ','"),
    "empty": ("empty.yaml: the file is empty", "got no content"),
    "missing_section": ("material: required section is missing", "got nothing"),
    "wavenumbers_out_of_order": ("surface.wavenumbers: cut-offs are out of order", "got k_l=4, k_r=2, k_s=16"),
    "screening_too_many_levels": ("screening.levels: ", "got 5"),
    "unknown_qoi": ("qoi.area: unknown quantity of interest", "got 'area'"),
    "wrong_schema_version": ("schema_version: ", "got 2"),
    "top_level_list": ("top_level_list.yaml: the top level must be a mapping", "got a list"),
    "duplicate_key": ("duplicate_key.yaml: not valid YAML at line 4", "duplicate key 'seed'"),
    "boolean_key": ("boolean_key.yaml: not valid YAML at line 4, column 1", "found the key on, which YAML reads as "
                    "true; keys are field names"),
    "octal_seed": ("octal_seed.yaml: not valid YAML at line 3", "found 012345, which YAML reads as an octal number "
                   "(5349); write it without the leading zero"),
}


def test_every_bad_config_file_has_a_case() -> None:
    assert {p.stem for p in BAD.glob("*.yaml")} == set(BAD_CASES)


@pytest.mark.parametrize("name", sorted(BAD_CASES))
def test_bad_config_names_field_and_value(name: str) -> None:
    path_part, value_part = BAD_CASES[name]
    with pytest.raises(ConfigError) as info:
        load_config(BAD / f"{name}.yaml")
    lines = str(info.value).splitlines()
    assert len(lines) == 1, lines
    assert path_part in lines[0] and value_part in lines[0]
    assert LINE.match(lines[0]), lines[0]
    assert info.value.problems == tuple(lines)


def test_unresolved_rolloff_message_explains_nyquist() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(BAD / "unresolved_rolloff.yaml")
    assert "Nyquist wave number is n_0/2 = 16" in str(info.value)
    assert "k_r = 20" in str(info.value)
    assert ">= 42" in str(info.value)


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")


def test_a_study_file_given_as_config_is_named_as_one(tmp_path: Path) -> None:
    # It said "cannot be read: 'utf-8' codec can't decode byte 0x89 in position 0" (roughuq screen s.h5).
    study = tmp_path / "s.h5"
    study.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)) * 4)
    with pytest.raises(ConfigError, match=r"s\.h5: is an HDF5 file \(a study file\?\), not a YAML config .*--study"):
        load_config(study)
    binary = tmp_path / "b.yaml"
    binary.write_bytes(b"\xff\xfe not text")
    with pytest.raises(ConfigError, match="b.yaml: cannot be read: 'utf-8' codec"):
        load_config(binary)


def test_one_line_per_problem() -> None:
    data = _base()
    data["surface"]["hurst"] = -1
    data["material"]["e_star"] = 0
    data["grid"]["projection"] = "spline"
    data["qoi"] = {"clusters": {"connectivity": 6, "bogus": 1}}
    lines = _message(data).splitlines()
    assert len(lines) == 5, lines
    assert all(LINE.match(line) for line in lines), lines
    starts = sorted(line.split(":")[0] for line in lines)
    assert starts == [
        "grid.projection",
        "material.e_star",
        "qoi.clusters.bogus",
        "qoi.clusters.connectivity",
        "surface.hurst",
    ]


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda d: d["load"].update(absolute=0.01), "load.relative: give the load exactly once"),
        (lambda d: d["load"].clear(), "got neither of relative and absolute"),
        (lambda d: d["grid"].update(coarsest=255), "grid.coarsest: must be even (got 255"),
        (lambda d: d["grid"].update(projection="injection"), "grid.projection: injection needs"),
        (lambda d: d.update(seed=True), "seed: must be a number, not a boolean (got True"),
        # lax pydantic would read a quoted number as the number
        (lambda d: d["surface"].update(hurst="0.8"), "surface.hurst: must be a number, not a string (remove"),
        (lambda d: d["grid"].update(coarsest="64"), "grid.coarsest: must be a number, not a string"),
        # grids beyond 65536 were "valid", then overflowed in the memory estimate (max_level 1000)
        (lambda d: d["grid"].update(max_level=1000), "grid.max_level: makes the finest grid 256 * 2**1000 larger"),
        (lambda d: d["grid"].update(coarsest=256, max_level=9), "integer with coarsest * 2**max_level <= 65536"),
        # a coarsest grid too large on its own was blamed on max_level
        (lambda d: d["grid"].update(coarsest=1_000_000), "grid.coarsest: larger than the largest grid, 65536 (got"),
        (lambda d: d["surface"].update(rms_height=float("nan")), "surface.rms_height: must be a finite number"),
        (lambda d: d.update(qoi={}), "qoi: at least one quantity of interest"),
        (lambda d: d.update(qoi={"area_above": {}}), "qoi.area_above.critical_pressure: required field is missing"),
        (lambda d: d.update(qoi={"mean_gap": 3}), "qoi.mean_gap: must be a mapping (got 3"),
        (lambda d: d.update(material=5), "material: must be a mapping (got 5"),
        (lambda d: d.update(estimation={"theta": 1.0}), "estimation.theta: must be less than 1"),
        (
            lambda d: d["qoi"]["contact_area"].update(estimator="exact"),
            "qoi.contact_area.estimator: must be 'corrected' or 'nodes' (got 'exact'",
        ),
        (lambda d: d.update(solver={"warm_start": "maybe"}), "solver.warm_start: "),
        # lax pydantic would read these as booleans
        (lambda d: d.update(solver={"warm_start": "yes"}), "solver.warm_start: must be true or false (got 'yes'"),
        (lambda d: d.update(estimation={"richardson": 1}), "estimation.richardson: must be true or false (got 1"),
        (
            lambda d: d["surface"].update(wavelengths={"lambda_l": 1 / 1.2, "lambda_r": 1 / 1.25, "lambda_s": 1 / 1.3}),
            "no non-zero integer wave vector",
        ),
    ],
)
def test_more_defects(change, expected: str) -> None:
    data = _base()
    change(data)
    assert expected in _message(data)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        # The user wrote no quotes: there are none to remove.
        ("tol: abc", "solver.tol: must be a number, not a string (got 'abc'"),
        ("tol: nan", "solver.tol: must be a number, not a string (got 'nan'"),
        ("tol: '0.5'", "solver.tol: must be a number, not a string (remove the quotes) (got '0.5'"),
        ('tol: " 1e-7"', "solver.tol: must be a number, not a string (remove the quotes) (got ' 1e-7'"),
        # pydantic wrote the bound as 0.00000000000001
        ("tol: 0", "solver.tol: must be greater than or equal to 1e-14 (got 0;"),
        ("tol: 2", "solver.tol: must be less than or equal to 0.01 (got 2;"),
        ("max_iter: 0", "solver.max_iter: must be greater than or equal to 1 (got 0;"),
    ],
)
def test_a_bad_number_in_a_yaml_file_is_told_as_written(line: str, expected: str) -> None:
    text = yaml.safe_dump(_base(), sort_keys=False) + f"solver:\n  {line}\n"
    with pytest.raises(ConfigError) as info:
        config_from_yaml_text(text)
    message = str(info.value)
    assert expected in message, message
    assert ("remove the quotes" in message) == ("'" in line or '"' in line), message
    assert "0.0000" not in message


def test_memory_is_a_run_time_warning_not_a_validation_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    assert solver_memory_bytes(1024) == 20 * 8 * 1024**2
    # Pretend the machine has just enough memory for one 512 x 512 solve.
    monkeypatch.setattr(config_module, "machine_memory_bytes", lambda: solver_memory_bytes(512))
    data = _base()
    data["grid"] = {"coarsest": 256, "max_level": 2}  # finest 1024 x 1024: four times too much
    config = config_from_dict(data)  # a cluster config validates on a laptop
    assert memory_warning(config, 1) is None
    text = memory_warning(config, 2)
    assert text.startswith("level 2 (grid 1024 x 1024) needs about 160 MiB per solve")
    assert "this machine has 40 MiB" in text and "stay at level <= 1 (a smaller grid.max_level)" in text
    # A caller that cannot go below level 2 (a screening needs levels 0..2) is told of the coarsest grid instead:
    # the screen advised "stay at level <= 1 (a smaller screening.levels)", which the config then refused.
    assert "use a smaller grid.coarsest" in memory_warning(config, 2, lower_with="a smaller screening.levels",
                                                           least_level=2)
    assert "stay at level <= 1 (a smaller screening.levels)" in memory_warning(
        config, 2, lower_with="a smaller screening.levels", least_level=1)
    # Two workers on level 1 need two solves at once; one fits.
    text = memory_warning(config, 1, n_workers=2, lower_with="unused")
    assert "x 2 workers = 80 MiB" in text and "use --workers 1" in text and "unused" not in text
    assert memory_warning(config, 0, n_workers=4) is None
    # Not even the coarsest grid fits.
    monkeypatch.setattr(config_module, "machine_memory_bytes", lambda: solver_memory_bytes(128))
    assert "use a smaller grid.coarsest" in memory_warning(config, 0)
    # Unknown machine memory: nothing to say.
    monkeypatch.setattr(config_module, "machine_memory_bytes", lambda: None)
    assert memory_warning(config, 2, n_workers=64) is None


def _cli(*args: str, expect: tuple[int, ...] = (0,)):
    from click.testing import CliRunner

    from rough_uq.cli import main

    result = CliRunner().invoke(main, list(args))
    assert result.exit_code in expect, (result.output, result.stderr, result.exception)
    return result


def _memory_warnings(result) -> list[str]:
    return [line for line in result.stderr.splitlines() if line.startswith("warning: level")]


def test_commands_warn_before_computing_levels_beyond_the_machine(tmp_path, monkeypatch) -> None:
    from tests.study_configs import tiny_config, write_config

    monkeypatch.chdir(tmp_path)
    path = str(write_config(tmp_path / "tiny.yaml", tiny_config()))  # grids 8, 16, 32; screens levels 0..2
    monkeypatch.setattr(config_module, "machine_memory_bytes", lambda: solver_memory_bytes(16))
    checked = _cli("validate", path)
    assert checked.stderr == "" and ": valid" in checked.stdout
    assert ("(finest solve about 0.16 MiB per worker, beyond the some 200 MiB a process takes to start; this machine "
            "has 0.039 MiB, too little for it)") in checked.stdout

    (line,) = _memory_warnings(_cli("screen", path, "--workers", "1", "--quiet"))
    assert line == (
        f"warning: level 2 (grid 32 x 32) needs about 0.156 MiB per solve ({SOLVER_ARRAYS_PER_NODE} float64 arrays "
        "of n^2), but this machine has 0.0391 MiB: use a smaller grid.coarsest, or run on a machine with more "
        "memory"
    )
    # --plan said nothing of it: the run warned only when it started (the plans of shards for other machines too).
    (line,) = _memory_warnings(_cli("mc", "--level", "2", "--plan"))
    assert "grid 32 x 32" in line and "(a smaller --level)" in line
    (line,) = _memory_warnings(_cli("mlmc", "--plan"))  # mlmc samples levels 0..2 whatever its tolerance
    assert "grid 32 x 32" in line and "use a smaller grid.coarsest" in line and "--tol" not in line
    (line,) = _memory_warnings(_cli("mc", "--level", "2", "--workers", "1", "--quiet", expect=(0, 3)))
    assert "grid 32 x 32" in line and "(a smaller --level)" in line
    (line,) = _memory_warnings(_cli("sample", "--stage", "screening", "--level", "2", "--indices", "8:9",
                                    "--out", "shard.h5", "--workers", "1", "--quiet"))
    assert "grid 32 x 32" in line and "this machine has 0.0391 MiB" in line
    assert not _memory_warnings(_cli("sample", "--stage", "screening", "--level", "1", "--indices", "8:9",
                                     "--out", "shard1.h5", "--workers", "1", "--quiet"))

    # Not even the coarsest grid fits: every run warns, whatever level it plans.
    monkeypatch.setattr(config_module, "machine_memory_bytes", lambda: solver_memory_bytes(8) // 2)
    lines = _memory_warnings(_cli("mlmc", "--workers", "1", "--quiet", expect=(0, 3)))
    assert lines and all("use a smaller grid.coarsest" in line for line in lines)
    levels = [int(line.split()[2]) for line in lines]
    assert levels == sorted(set(levels))  # once per level, as the run adds levels

    # Enough memory for one solve of level 2 but not for two at once.
    monkeypatch.setattr(config_module, "machine_memory_bytes", lambda: solver_memory_bytes(32) * 3 // 2)
    (line,) = _memory_warnings(_cli("sample", "--stage", "screening", "--level", "2", "--indices", "9:11",
                                    "--out", "shard2.h5", "--workers", "2", "--quiet"))
    assert "x 2 workers = 0.312 MiB" in line and "use --workers 1" in line


# ---------------------------------------------------------------------------
# Hash
# ---------------------------------------------------------------------------


def test_hash_is_stable_and_tracks_physics_only() -> None:
    reference = config_hash(config_from_dict(_base()))
    assert re.fullmatch(r"[0-9a-f]{64}", reference)
    assert config_hash(config_from_dict(_base())) == reference

    def hash_with(change) -> str:
        data = _base()
        change(data)
        return config_hash(config_from_dict(data))

    assert hash_with(lambda d: d.update(output={"path": "elsewhere/other.h5"})) == reference
    assert hash_with(lambda d: d.update(solver={"threads": 4})) == reference
    assert hash_with(lambda d: d.update(solver={"tol": 1e-7})) == reference  # a default spelled out
    assert hash_with(lambda d: d["surface"].update(hurst=0.7)) != reference
    assert hash_with(lambda d: d.update(seed=8)) != reference
    assert hash_with(lambda d: d["load"].update(relative=0.2)) != reference
    assert hash_with(lambda d: d.update(solver={"tol": 1e-8})) != reference
    assert hash_with(lambda d: d["grid"].update(projection="truncation")) == reference
    # Per-run settings leave every stored sample valid.
    assert hash_with(lambda d: d.update(estimation={"theta": 0.3, "batch_size": 3})) == reference
    assert hash_with(lambda d: d.update(screening={"levels": 3, "samples": 50})) == reference
    assert hash_with(lambda d: d["qoi"]["contact_area"].update(tol=0.05)) == reference
    assert hash_with(lambda d: d["qoi"]["contact_area"].update(unit="fraction")) != reference


#: Changes of _base(): (what, the keys config_differences must name). Keys not hashed name none.
_CHANGES = [
    (lambda d: d["surface"].update(hurst=0.7), ["surface.hurst"]),
    (lambda d: d.update(seed=8), ["seed"]),
    (lambda d: d.update(load={"absolute": 0.5}), ["load.absolute", "load.relative"]),
    (lambda d: d["grid"].update(max_level=3), ["grid.max_level"]),
    (lambda d: d["surface"].update(wavelengths={"lambda_l": 1.0, "lambda_r": 0.5, "lambda_s": 1 / 64}),
     ["surface.wavenumbers.k_r"]),
    (lambda d: d["qoi"].update(mean_gap={}), ["qoi"]),
    (lambda d: d["qoi"]["contact_area"].update(unit="fraction"), ["qoi.contact_area.unit"]),
    (lambda d: d.setdefault("solver", {}).update(tol=1e-8), ["solver.tol"]),
    (lambda d: d.setdefault("solver", {}).update(threads=2), []),
    (lambda d: d.setdefault("estimation", {}).update(theta=0.3), []),
    (lambda d: d["qoi"]["contact_area"].update(tol=0.05), []),
]


def test_config_differences_name_what_changes_the_hash() -> None:
    # Random combinations of the changes above (seeded): the differences are exactly the changed hashed keys,
    # with both values, and there are none exactly when the hashes agree.
    rng = np.random.default_rng(2026)
    reference = config_from_dict(_base())
    for _ in range(40):
        chosen = rng.choice(len(_CHANGES), size=rng.integers(1, 4), replace=False)
        data = _base()
        for index in chosen:
            _CHANGES[index][0](data)
        other = config_from_dict(data)
        differences = config_differences(reference, other)
        expected = {key for index in chosen for key in _CHANGES[index][1]}
        assert sorted(key for key, _, _ in differences) == sorted(expected)
        assert (not differences) == (config_hash(other) == config_hash(reference))
        for key, ours, theirs in differences:
            assert ours != theirs
    (difference,) = config_differences(reference, config_from_dict({**_base(), "seed": 8}))
    assert difference == ("seed", 7, 8)


def test_config_differences_name_a_new_qoi_order() -> None:
    first, second = _base(), _base()
    first["qoi"] = {"contact_area": {}, "mean_gap": {}}
    second["qoi"] = {"mean_gap": {}, "contact_area": {}}
    differences = config_differences(config_from_dict(first), config_from_dict(second))
    assert differences == [("qoi (column order)", ["contact_area", "mean_gap"], ["mean_gap", "contact_area"])]
    # Other QoIs come first, before any setting (a refusal names only the first four).
    third = {**_base(), "seed": 8, "material": {"e_star": 2.0}}
    third["qoi"] = {"contact_area": {}, "clusters": {}}
    keys = [key for key, _, _ in config_differences(config_from_dict(first), config_from_dict(third))]
    assert keys[0] == "qoi" and {"seed", "material.e_star"} <= set(keys[1:])


def test_config_from_yaml_text_roundtrips_resolved_yaml() -> None:
    config = config_from_dict(_base())
    assert config_from_yaml_text(resolved_yaml(config), source="study.h5") == config
    with pytest.raises(ConfigError, match="study.h5: not valid YAML"):
        config_from_yaml_text("a: [", source="study.h5")


def test_hash_depends_on_qoi_order() -> None:
    first = _base()
    first["qoi"] = {"contact_area": {}, "mean_gap": {}}
    second = _base()
    second["qoi"] = {"mean_gap": {}, "contact_area": {}}
    assert config_hash(config_from_dict(first)) != config_hash(config_from_dict(second))


def test_every_number_field_states_its_unit() -> None:
    words = ("unit", "dimensionless", "count", "seconds", "periods per box", "seed", "fraction", "percent")
    models = [
        obj
        for obj in vars(config_module).values()
        if isinstance(obj, type) and issubclass(obj, pydantic.BaseModel) and obj.__module__ == config_module.__name__
    ]
    assert len(models) >= 15
    n_checked = 0
    for model in models:
        for name, info in model.model_fields.items():
            if info.exclude:
                continue
            assert info.description, f"{model.__name__}.{name} has no description"
            if "float" in repr(info.annotation) or "int" in repr(info.annotation):
                n_checked += 1
                assert any(w in info.description.lower() for w in words), f"{model.__name__}.{name}: {info.description}"
    assert n_checked >= 20


def test_contact_area_estimator_defaults_to_corrected_and_changes_the_hash() -> None:
    data = _base()
    config = config_from_dict(data)
    assert config.qoi["contact_area"].estimator == "corrected"
    assert yaml.safe_load(resolved_yaml(config))["qoi"]["contact_area"]["estimator"] == "corrected"
    data["qoi"]["contact_area"]["estimator"] = "nodes"
    nodes = config_from_dict(data)
    assert nodes.qoi["contact_area"].estimator == "nodes"
    # Different numbers, different samples: a study file of one is refused for the other.
    assert config_hash(nodes) != config_hash(config)


def test_a_stored_config_without_estimator_was_a_node_count() -> None:
    config = config_from_dict(_base())
    text = resolved_yaml(config)
    assert config_from_stored_text(text) == config  # written by this code: read back as it is
    old = yaml.safe_load(text)
    del old["qoi"]["contact_area"]["estimator"]  # written before the option existed
    old_text = yaml.safe_dump(old, sort_keys=False)
    assert config_from_stored_text(old_text).qoi["contact_area"].estimator == "nodes"
    assert config_from_yaml_text(old_text).qoi["contact_area"].estimator == "corrected"  # a user's config file


def test_richardson_is_an_opt_in_estimation_setting() -> None:
    data = _base()
    config = config_from_dict(data)
    assert config.estimation.richardson is False
    data["estimation"] = {"richardson": True}
    extrapolated = config_from_dict(data)
    assert extrapolated.estimation.richardson is True
    # An estimation setting: the samples stay valid, so the study file is the same.
    assert config_hash(extrapolated) == config_hash(config)
    data["estimation"] = {"richardson": "sometimes"}
    assert "estimation.richardson: " in _message(data)


def test_solver_defaults_agree_in_the_config_the_public_problem_and_the_model():
    # One default per setting, whichever door a study comes in by.
    from rough_uq.problem.contact import ContactProblem
    from rough_uq.problem.sampler import ContactModel

    model = {item.name: item.default for item in dataclasses.fields(ContactModel)}
    problem = {item.name: item.default for item in dataclasses.fields(ContactProblem)}
    solver = SolverConfig()
    assert model["tol"] == problem["solver_tol"] == solver.tol
    for name in ("max_iter", "warm_start", "threads"):
        assert model[name] == problem[name] == getattr(solver, name), name


def test_sweep_values_are_read_as_the_config_file_reads_them() -> None:
    # 1e-8 is a number in a config file (not a string, as plain YAML 1.1 has it); a sweep reads it alike.
    config = config_from_dict(_base())
    configs = sweep_configs(config, key="solver.tol", values=["1e-8", "2.5e-9"])
    assert [c.solver.tol for _, c in configs] == [1e-8, 2.5e-9]
    with pytest.raises(ConfigError, match="solver.tol: must be a number, not a string"):
        sweep_configs(config, key="solver.tol", values=["tight"])


def test_a_swept_null_is_the_config_file_s_null_and_a_leading_zero_is_refused() -> None:
    # null was kept as the text 'null': "estimation.max_cost: must be a number, not a string (got 'null'; allowed:
    # number > 0 or null)"; 012 would be the octal 10 of YAML 1.1.
    config = config_from_dict(_base())
    configs = sweep_configs(config, key="estimation.max_cost", values=["1", "null"])
    assert [c.estimation.max_cost for _, c in configs] == [1, None]
    with pytest.raises(ConfigError, match=r"^--set seed=012: found 012, which YAML reads as an octal number \(10\)"):
        sweep_configs(config, key="seed", values=["1", "012"])


def test_a_swept_value_is_named_in_its_file_by_the_full_key_and_the_value_text():
    # The folder of a sweep is sweep-<full key>; the file names carry the full key too.
    config = config_from_dict({**_base(), "output": {"path": "runs.v2/results"}})
    names = [c.output.path for _, c in sweep_configs(config, key="solver.tol", values=["1e-8", " 2.5e-9 "])]
    assert names == ["runs.v2/results-solver.tol-1e-8.h5", "runs.v2/results-solver.tol-2.5e-9.h5"]
    (_, swept), = sweep_configs(config_from_dict(_base()), key="qoi.contact_area.tol", values=["0.25"])
    assert swept.output.path == "results-qoi.contact_area.tol-0.25.h5"


@pytest.mark.parametrize("value", ["0.1/2", "../0.1", "0.1\\x", "a\x00", "0.1 0.2", "'0.1'", "", "  "])
def test_a_swept_value_that_is_no_safe_file_name_part_is_refused_naming_set(value):
    # "0.1/2" became the path results-hurst-0.1/2.h5, a space an awkward name, NUL a YAML traceback.
    with pytest.raises(ConfigError) as info:
        sweep_configs(config_from_dict(_base()), key="surface.hurst", values=["0.7", value])
    line = str(info.value)
    assert line.startswith("--set surface.hurst=") and f"got {value!r}" in line and "file name" in line


@pytest.mark.parametrize("values", [["0.01", "0.01"], ["0.01", " 0.01"], ["true", "True"], ["1e-3", "1E-3"]])
def test_two_swept_values_that_would_share_a_file_name_are_refused(values):
    with pytest.raises(ConfigError, match=r"^--set: got .*; allowed: distinct values: .* is the same as") as info:
        sweep_configs(config_from_dict(_base()), key="solver.warm_start" if values[0] == "true" else "solver.tol",
                      values=values)
    assert "both would be the study file" in str(info.value)


@pytest.mark.parametrize(("key", "values", "twin"), [
    ("load.relative", ["0.1", "1e-1"], "1e-1 is the same as 0.1"),
    ("load.relative", ["0.2", "0.10", "0.1"], "0.1 is the same as 0.10"),
    ("surface.system_size", ["1", "2", "2.0"], "2.0 is the same as 2"),
])
def test_two_swept_values_that_make_one_study_are_refused(key, values, twin):
    # Only the CLI refused them: a Python caller of sweep_configs / run_sweep computed the same study twice.
    with pytest.raises(ConfigError, match=r"^--set: got .*; allowed: distinct values: ") as info:
        sweep_configs(config_from_dict(_base()), key=key, values=values)
    line = str(info.value)
    assert f"got {key + '=' + ','.join(values)!r}" in line
    assert line.endswith(f"distinct values: {twin} (one study, which would be computed twice)")
    assert len(sweep_configs(config_from_dict(_base()), key=key, values=values[:-1])) == len(values) - 1


def test_the_largest_grid_is_the_problem_layers():
    from rough_uq.problem.contact import MAX_GRID

    assert config_module.MAX_GRID == MAX_GRID
    data = _base()
    data["grid"] = {"coarsest": 256, "max_level": 8}  # 65536, the largest
    assert config_from_dict(data).grid.finest == MAX_GRID


def test_screening_levels_below_three_are_refused_saying_why(tmp_path, monkeypatch) -> None:
    # screening.levels: 2 was accepted, and `roughuq screen` computed levels 0 and 1 only to fail fitting the rates.
    from tests.study_configs import tiny_config, write_config

    data = _base()
    data["screening"] = {"levels": 2}
    line = _message(data)
    assert line.startswith("screening.levels: ") and "got 2" in line and "integer >= 3" in line
    assert "fitted on levels 1..levels-1, two at least" in line
    monkeypatch.chdir(tmp_path)
    path = write_config(tmp_path / "tiny.yaml", tiny_config(screening={"levels": 2, "samples": 4}))
    result = _cli("screen", str(path), "--workers", "1", "--quiet", expect=(2,))
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: ") and "screening.levels" in line and "integer >= 3" in line
    assert not (tmp_path / "results.h5").exists()  # refused before any sample


@pytest.mark.parametrize("max_level", [0, 1])
def test_a_study_too_shallow_to_screen_is_a_valid_config_for_runs_without_a_screening(max_level) -> None:
    # With grid.max_level 1 the default screening.levels 3 made the config invalid; 0 had no valid config at all.
    data = _base()
    data["grid"] = {"coarsest": 256, "max_level": max_level}
    assert config_from_dict(data).screening.levels == 3
    data["grid"] = {"coarsest": 256, "max_level": 2}
    data["screening"] = {"levels": 4}
    assert "screening.levels: cannot screen more levels than exist (levels 0..2)" in _message(data)


def test_a_stored_config_of_two_screening_levels_is_read_as_three() -> None:
    # Written before 3 levels were required; such a screening never finished, and screening is not hashed.
    config = config_from_dict(_base())
    stored = resolved_yaml(config).replace("levels: 3", "levels: 2")
    assert "levels: 2" in stored
    read = config_from_stored_text(stored)
    assert read.screening.levels == 3 and config_hash(read) == config_hash(config)


def test_the_most_thresholds_of_the_config_and_the_command_line_agree() -> None:
    from rough_uq import cli

    assert config_module.MAX_THRESHOLDS == cli.MAX_THRESHOLDS == 10_000


def test_a_stored_config_of_values_refused_since_is_still_read() -> None:
    # initial_samples above 10^7 and an output.path with a control character passed validate before: a study file
    # written then must still open (its report, its runs), reading them as the runs could take them.
    config = config_from_dict(_base())
    stored = resolved_yaml(config)
    assert "initial_samples: 10\n" in stored and "path: results.h5\n" in stored
    stored = stored.replace("initial_samples: 10\n", "initial_samples: 100000000\n").replace(
        "path: results.h5\n", 'path: "a\\e[31mb.h5"\n')
    read = config_from_stored_text(stored)
    assert read.estimation.initial_samples == 10_000_000 and read.output.path == "a\\x1b[31mb.h5"
    assert config_hash(read) == config_hash(config)
    for grid in ({"start": -1e308, "stop": 1e308, "count": 5}, {"start": 1e-320, "stop": 2e-320, "count": 10_000}):
        data = _base()
        data.setdefault("estimation", {})["distribution"] = {"contact_area": {"thresholds": grid}}
        text = yaml.safe_dump(data)
        with pytest.raises(ConfigError, match="thresholds"):
            config_from_dict(yaml.safe_load(text))
        # Every cdf run on such a grid failed: read as none, so that runs ask for --thresholds.
        assert config_from_stored_text(text).estimation.distribution["contact_area"].thresholds is None


def test_the_fewest_screened_levels_are_the_problem_layers() -> None:
    from rough_uq.problem.runs import MIN_SCREENED_LEVELS

    assert config_module.MIN_SCREENED_LEVELS == MIN_SCREENED_LEVELS == 3


def test_a_config_larger_than_the_cap_is_refused_before_it_is_read_whole(tmp_path, monkeypatch):
    # /dev/zero was read until the kernel killed the process (23 GB in 4 s).
    monkeypatch.setattr(config_module, "MAX_CONFIG_BYTES", 4096)
    path = tmp_path / "big.yaml"
    path.write_text(yaml.safe_dump(_base()) + "#" * 5000 + "\n")
    with pytest.raises(ConfigError, match=r"big\.yaml: larger than .*at most 4096 bytes"):
        load_config(path)
    path.write_text(yaml.safe_dump(_base()))
    assert load_config(path).seed == 7


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero")
def test_dev_zero_is_refused_by_its_size():
    with pytest.raises(ConfigError, match=r"^/dev/zero: larger than 1 MiB"):
        load_config("/dev/zero")


@pytest.mark.parametrize("depth", [1000, 5000])
def test_yaml_nested_too_deeply_is_a_config_error(tmp_path, depth):
    # PyYAML recurses per level: a RecursionError traceback.
    path = tmp_path / "deep.yaml"
    path.write_text("a: " + "[" * depth + "]" * depth + "\n")
    with pytest.raises(ConfigError, match=r"deep\.yaml: not valid YAML: nested too deeply"):
        load_config(path)
    with pytest.raises(ConfigError, match=r"nested too deeply"):
        config_from_stored_text(path.read_text())


def test_schema_version_true_is_not_version_1():
    assert "schema_version: must be a number, not a boolean" in _message({**_base(), "schema_version": True})


@pytest.mark.parametrize("path", [".", "..", "runs/", "a/..", "study/."])
def test_an_output_path_that_names_a_directory_is_refused(path):
    text = _message({**_base(), "output": {"path": path}})
    assert f"output.path: names a directory, not a file (got {path!r}" in text


@pytest.mark.parametrize("path", ["a\x1b[31mb.h5", "runs\n.h5", "x\t.h5", "del\x7f.h5", "csi\x9b31m.h5",
                                  "results\u202e5h.txt", "isolate\u2066.h5"])
def test_an_output_path_with_a_control_character_is_refused(path):
    # `validate` showed "a\e[31mb.h5" as "ab.h5" (the terminal ate the escape) and screen wrote it as typed.
    text = _message({**_base(), "output": {"path": path}})
    assert "output.path: contains the control character " in text and "allowed: a non-empty file path" in text


def test_an_output_path_in_the_home_directory_is_expanded(tmp_path, monkeypatch):
    # `output.path: ~/runs/x.h5` made a directory named `~` in the working directory.
    monkeypatch.setenv("HOME", str(tmp_path))
    config = config_from_dict({**_base(), "output": {"path": "~/runs/x.h5"}})
    assert config.output.path == str(tmp_path / "runs" / "x.h5")


@pytest.mark.parametrize("grid, field, words", [
    ({"start": -1e308, "stop": 1e308, "count": 5}, "stop", "stop - start exceeds the largest float"),
    ({"start": 1e-320, "stop": 2e-320, "count": 10_000}, "count", "are not distinct numbers"),
], ids=["span beyond the floats", "subnormal neighbours"])
def test_a_threshold_grid_floats_cannot_hold_is_refused(grid, field, words):
    # validate passed both; the cdf run then said "--thresholds: got None" of the first.
    text = _message({**_base(), "estimation": {"distribution": {"contact_area": {"thresholds": grid}}}})
    assert f"estimation.distribution.contact_area.thresholds.{field}: " in text and words in text, text


def test_colon_separated_numbers_stay_text_not_base_60_integers(tmp_path):
    # YAML 1.1 read `thresholds: 15:25:41` (the --thresholds form) as 55541: "must be a mapping (got 55541)".
    from tests.study_configs import tiny_config, write_config

    path = write_config(tmp_path / "c.yaml", tiny_config())
    text = path.read_text()
    grid = "estimation:\n  distribution:\n    contact_area:\n      thresholds: 15:25:41\n"
    path.write_text(text.replace("estimation:\n", grid, 1))
    with pytest.raises(ConfigError, match=r"thresholds: must be a mapping \(got '15:25:41'; "):
        load_config(path)
    path.write_text(text.replace("seed: 2026", "seed: 1:30"))
    with pytest.raises(ConfigError, match=r"seed: must be a number, not a string \(got '1:30'; "):
        load_config(path)
    path.write_text(text.replace("seed: 2026", "seed: 0x1f"))  # YAML 1.1's other integers are kept
    assert load_config(path).seed == 31


def test_an_empty_config_path_is_named_as_such():
    # It said ": config file not found (got '' ...)", a file name missing in front of the colon.
    with pytest.raises(ConfigError, match=r"^config file: got ''; allowed: a non-empty path of a YAML file$"):
        load_config("")


@pytest.mark.parametrize("samples", [10**11, 4_000_000])
def test_a_screening_over_the_planned_sample_cap_is_refused(tmp_path, samples):
    # `validate` accepted samples: 100000000000 and `screen` then failed allocating 745 GiB for its progress.
    from tests.study_configs import tiny_config, write_config

    path = write_config(tmp_path / "huge.yaml", tiny_config(screening={"levels": 3, "samples": samples}))
    expected = (f"huge.yaml: screening.samples: a screening of {3 * samples:,} samples (3 levels) exceeds the "
                f"10,000,000 samples any run may plan (got {samples}; allowed: integer in 2..3333333)")
    with pytest.raises(ConfigError, match=re.escape(expected)):
        load_config(path)
    fine = tiny_config(screening={"levels": 3, "samples": 3_333_333})
    assert load_config(write_config(tmp_path / "fine.yaml", fine))


def test_screening_levels_beyond_the_grid_are_the_one_error_not_a_sample_bound_of_2_to_0():
    # levels: 10**30 also refused screening.samples: 20 with "allowed: integer in 2..0".
    text = _message({**_base(), "screening": {"levels": 10**30, "samples": 20}})
    assert "screening.levels: cannot screen more levels than exist" in text
    assert "screening.samples" not in text


@pytest.mark.parametrize("value", [10**7 + 1, 1e15, 1e29])
def test_initial_samples_beyond_any_plan_are_refused_by_the_config(value):
    # `validate` passed 1e15 (the runs refused it later) and said of 1e29 "unable to parse input string as an
    # integer, exceeded maximum size".
    text = _message({**_base(), "estimation": {"initial_samples": value}})
    assert "estimation.initial_samples: " in text and "allowed: integer in 2..10000000 " in text
    assert "parse" not in text and "input" not in text.lower()


@pytest.mark.parametrize("distribution, where, allowed", [
    ({"contact_area": {"probabilities": [0.5, "x"]}}, "contact_area.probabilities.1",
     "a non-empty list of distinct numbers in (0, 1)"),
    ({"contact_area": 5}, "contact_area", "a mapping with keys thresholds, probabilities"),
], ids=["list element", "named section"])
def test_refused_distribution_fields_say_what_is_allowed(distribution, where, allowed):
    # Both said "allowed: see the documentation".
    config = _base()
    config.setdefault("estimation", {})["distribution"] = distribution
    text = _message(config)
    assert f"estimation.distribution.{where}: " in text and f"; allowed: {allowed})" in text, text


@pytest.mark.parametrize("field, value, what", [
    (("schema_version",), 10**30, "is far beyond any integer allowed here"),
    (("seed",), [1], "must be an integer"),
    (("seed",), 0.5, "must be an integer, not a number with a fractional part"),
    (("surface", "hurst"), [1], "must be a number"),
    (("output", "path"), 1.5, "must be text"),
    (("estimation", "distribution"), {"contact_area": {"probabilities": 0.5}}, "must be a list"),
    (("estimation", "distribution"), {"contact_area": {"probabilities": []}}, "must not be empty"),
], ids=["huge integer", "list for integer", "fraction for integer", "list for number", "number for path",
        "number for list", "empty list"])
def test_pydantic_type_errors_are_said_in_the_words_of_a_config(field, value, what):
    # They said "Input should be a valid tuple", "valid string", "unable to parse input string".
    config = _base()
    section = config
    for key in field[:-1]:
        section = section.setdefault(key, {})
    section[field[-1]] = value
    text = _message(config)
    assert f": {what} (got " in text, text
    assert "valid" not in text and "parse" not in text, text


@pytest.mark.parametrize("qoi", [{"contact_area": {}}, {"clusters": {}}, {"mean_gap": {}}, {"max_pressure": {}},
                                 {"area_above": {"critical_pressure": 0.1}}], ids=lambda q: next(iter(q)))
@pytest.mark.parametrize("tol", [1e-200, 1e200])
def test_every_qoi_tolerance_lies_in_the_range_the_runs_take(tmp_path, qoi, tol):
    # qoi.max_pressure.tol took 1e-200, which the run refused later naming neither the field nor the file.
    from tests.study_configs import tiny_config, write_config

    name = next(iter(qoi))
    path = write_config(tmp_path / "q.yaml", tiny_config(qoi={name: {**qoi[name], "tol": tol}}))
    with pytest.raises(ConfigError, match=rf"q.yaml: qoi.{name}.tol: .*allowed: number in \[1e-140, 1e\+140\]"):
        load_config(path)


@pytest.mark.parametrize(("key", "kind"), [("[a, b]", "list"), ("{a: 1}", "dict")])
def test_a_complex_yaml_key_is_refused_as_malformed(key, kind) -> None:
    # `key in seen` of the duplicate check raised TypeError: unhashable type (a traceback from `roughuq validate`).
    text = yaml.safe_dump(_base(), sort_keys=False) + f"? {key}\n: 1\n"
    with pytest.raises(ConfigError, match=f"found a {kind} as a key; keys are field names"):
        config_from_yaml_text(text)


def test_an_output_path_with_a_nul_character_is_refused() -> None:
    # Accepted by `validate`; `screen` then ended in "ValueError: embedded null byte".
    data = _base()
    data["output"] = {"path": "a\0b.h5"}
    with pytest.raises(ConfigError, match=r"output\.path: contains a NUL character"):
        config_from_dict(data)


def test_nested_yaml_aliases_under_an_unknown_key_are_refused_at_once() -> None:
    # Ten aliases of ten (10^9 elements from 1 KB): the message built the whole repr before cutting it to 80
    # characters (minutes, and memory); a bounded repr names the key at once.
    lines = ["bogus:", "  a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"  a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 10)]
    text = yaml.safe_dump(_base(), sort_keys=False) + "\n".join(lines) + "\n"
    with pytest.raises(ConfigError, match=r"bogus: unknown key \(got a mapping \{") as info:
        config_from_yaml_text(text)
    assert len(str(info.value)) < 400
