"""`roughuq init`: the shipped configs are package data, written to the working directory on request."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from importlib.resources import files
from pathlib import Path

import pytest
from click.testing import CliRunner

from rough_uq.cli import SHIPPED_CONFIGS, main
from rough_uq.study.config import load_config

ROOT = Path(__file__).resolve().parent.parent


def run(*args: str, expect: int = 0) -> object:
    result = CliRunner().invoke(main, list(args))
    assert result.exit_code == expect, (result.output, result.stderr, result.exception)
    return result


def test_the_three_configs_are_shipped_as_package_data():
    assert SHIPPED_CONFIGS == ("quickstart", "classic-area", "classic-clusters")
    shipped = files("rough_uq.study").joinpath("configs")
    assert sorted(entry.name for entry in shipped.iterdir() if entry.name.endswith(".yaml")) == sorted(
        f"{name}.yaml" for name in SHIPPED_CONFIGS
    )
    assert not list((ROOT / "configs").glob("*.yaml"))  # one copy, inside the package


@pytest.mark.parametrize("name", SHIPPED_CONFIGS)
def test_init_writes_a_valid_config_to_the_working_directory(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = run("init", name)
    target = tmp_path / f"{name}.yaml"
    assert f"roughuq screen {name}.yaml" in result.stdout
    assert target.read_text() == files("rough_uq.study").joinpath("configs", f"{name}.yaml").read_text()
    config = load_config(target)
    assert config.schema_version == 1
    assert ": valid" in run("validate", str(target)).stdout


def test_init_refuses_to_overwrite_unless_forced(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    target = tmp_path / "mine.yaml"
    target.write_text("my edits\n")
    result = run("init", "quickstart", "--out", str(target), expect=2)
    assert result.stderr.startswith("error: ") and "--force" in result.stderr
    assert target.read_text() == "my edits\n"
    run("init", "quickstart", "--out", str(target), "--force")
    assert load_config(target).qoi_names == ("contact_area",)
    assert not (tmp_path / "quickstart.yaml").exists()  # --out, not the default name


def test_init_takes_quiet_like_the_other_commands(tmp_path, monkeypatch):
    # `roughuq init -q` was "No such option: -q" in scripts that pass -q to every command.
    monkeypatch.chdir(tmp_path)
    for args in (("init", "quickstart", "-q"), ("init", "quickstart", "--quiet")):  # written, then unchanged
        result = run(*args)
        assert result.stdout == "" and (tmp_path / "quickstart.yaml").exists()
    assert "quickstart" in run("init", "--list", "-q").stdout  # the list is the result
    assert "already exists" in run("init", "classic-area", "--out", "quickstart.yaml", "-q", expect=2).stderr


def test_init_again_on_the_unchanged_config_goes_on(tmp_path, monkeypatch):
    # The README's quick start, `roughuq init quickstart && roughuq screen ...`, run twice in one directory.
    monkeypatch.chdir(tmp_path)
    run("init", "quickstart")
    before = (tmp_path / "quickstart.yaml").stat().st_mtime_ns
    result = run("init", "quickstart")
    assert "already the shipped quickstart config, unchanged" in result.stdout
    assert "roughuq screen quickstart.yaml" in result.stdout
    assert (tmp_path / "quickstart.yaml").stat().st_mtime_ns == before  # not rewritten
    # Edited, or another shipped config under that name: refused as before, the file kept.
    for text in ("my edits\n", files("rough_uq.study").joinpath("configs", "classic-area.yaml").read_text()):
        (tmp_path / "quickstart.yaml").write_text(text)
        result = run("init", "quickstart", expect=2)
        assert "already exists" in result.stderr and "--force" in result.stderr
        assert (tmp_path / "quickstart.yaml").read_text() == text


def test_unknown_name_exits_2_with_the_list(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for args in (("init", "classic_area"), ("init",)):
        result = run(*args, expect=2)
        assert result.stderr.startswith("error: NAME: ")
        assert all(name in result.stderr for name in SHIPPED_CONFIGS)
        assert "Traceback" not in result.output
    assert not list(tmp_path.iterdir())


def test_list_names_every_shipped_config_with_its_first_comment():
    lines = run("init", "--list").stdout.splitlines()
    assert [line.split(":")[0] for line in lines] == list(SHIPPED_CONFIGS)
    assert all(len(line.split(": ", 1)[1]) > 10 for line in lines)


def test_list_with_a_name_or_out_is_refused(tmp_path, monkeypatch):
    # `init quickstart --list` listed every config and wrote nothing, without a word about the name
    monkeypatch.chdir(tmp_path)
    for args, given in ((("quickstart",), "NAME quickstart"), (("--out", "x.yaml"), "--out x.yaml")):
        result = run("init", *args, "--list", expect=2)
        expected = f"error: --list lists the shipped configs and writes none: give it alone (got {given})\n"
        assert result.stderr == expected
    assert not list(tmp_path.iterdir())


def test_solve_demo_uses_the_packaged_quickstart(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    output = run("solve").stdout
    assert f"grid {load_config(files('rough_uq.study') / 'configs' / 'quickstart.yaml').grid.coarsest} x" in output


def test_an_installed_package_finds_its_configs(tmp_path):
    """Build the package as an install would (setuptools build_py, what a wheel holds), away from the source tree."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "rough_uq", source / "rough_uq", ignore=shutil.ignore_patterns("__pycache__"))
    installed = tmp_path / "installed"
    subprocess.run(
        [sys.executable, "-W", "ignore", "-c", "from setuptools import setup; setup()", "-q", "build_py",
         "--build-lib", str(installed)],
        cwd=source, check=True, capture_output=True,
    )
    shutil.rmtree(source)
    work = tmp_path / "work"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(installed)}
    script = (
        "import rough_uq, sys; from rough_uq.cli import main; "
        f"assert rough_uq.__file__.startswith({str(installed)!r}), rough_uq.__file__; main()"
    )
    done = subprocess.run([sys.executable, "-c", script, "init", "classic-area"], cwd=work, env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert load_config(work / "classic-area.yaml").surface.system_size == 2.0
