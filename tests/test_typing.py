"""py.typed ships with the package, so that type checkers read torchcage's
annotations; CI's `mypy` step (pyproject's [tool.mypy]) checks tests/typing_check.py against them."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_py_typed_is_in_the_package_and_its_package_data() -> None:
    marker = importlib.resources.files("torchcage").joinpath("py.typed")
    assert marker.is_file()
    tomllib = pytest.importorskip("tomllib")  # (Python >= 3.11)
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in config["tool"]["setuptools"]["package-data"]["torchcage"]
    # and the wheel's package discovery includes the top package that holds it
    assert any(p == "torchcage*" for p in config["tool"]["setuptools"]["packages"]["find"]["include"])


def test_type_check_is_configured_on_the_public_api() -> None:
    """The mypy step checks the file of public-API assertions and the facades; every file it names exists."""
    tomllib = pytest.importorskip("tomllib")
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    mypy = config["tool"]["mypy"]
    assert "tests/typing_check.py" in mypy["files"] and "torchcage/__init__.py" in mypy["files"]
    assert all((ROOT / f).is_file() for f in mypy["files"])
    assert any(dep.startswith("mypy") for dep in config["project"]["optional-dependencies"]["test"])
    assert "mypy" in (ROOT / ".ci" / "run").read_text()
