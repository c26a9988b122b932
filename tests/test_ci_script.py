"""CI's script finds the papers' data by the README's rule only: ``../shared/data``
beside the checkout, or ``$TORCHCAGE_DATA``; no machine's absolute path."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

CI = Path(__file__).resolve().parents[1] / ".ci" / "run"


def _data_block() -> str:
    """The lines of .ci/run that set TORCHCAGE_DATA (from the `if` to its `fi`)."""
    text = CI.read_text()
    m = re.search(r"^if \[ -z \"\$\{TORCHCAGE_DATA:-\}\" \].*?^fi$", text, flags=re.S | re.M)
    assert m, "the TORCHCAGE_DATA block of .ci/run"
    return m.group(0)


def test_no_absolute_data_path() -> None:
    text = CI.read_text()
    assert "/work/" not in text and "../shared/data" in text
    assert not re.search(r"TORCHCAGE_DATA=/", text)


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_a_clone_elsewhere_finds_the_data_beside_it(tmp_path) -> None:
    clone, data = tmp_path / "somewhere" / "clone", tmp_path / "somewhere" / "shared" / "data"
    clone.mkdir(parents=True)
    data.mkdir(parents=True)
    env = {k: v for k, v in os.environ.items() if k != "TORCHCAGE_DATA"}
    script = _data_block() + '\necho "$TORCHCAGE_DATA"\n'
    out = subprocess.run(["bash", "-c", script], cwd=clone, env=env, capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()) == data.resolve()
    # an explicit $TORCHCAGE_DATA wins
    out = subprocess.run(["bash", "-c", script], cwd=clone, env={**env, "TORCHCAGE_DATA": "/elsewhere"},
                         capture_output=True, text=True, check=True)  # fmt: skip
    assert out.stdout.strip() == "/elsewhere"
    # none beside it: left unset (its tests skip)
    shutil.rmtree(data)
    out = subprocess.run(["bash", "-c", script], cwd=clone, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("sed") is None, reason="needs bash and sed")
def test_ci_tests_the_oldest_declared_torch() -> None:
    """CI's floor step installs the lower bound of pyproject.toml's torch requirement, read from
    the file by the script's own line; the range also admits the local 2.13.0."""
    tomllib = pytest.importorskip("tomllib")
    from packaging.requirements import Requirement
    from packaging.version import Version

    root = CI.parents[1]
    deps = tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]
    (req,) = [Requirement(d) for d in deps if Requirement(d).name == "torch"]
    (lower,) = [s.version for s in req.specifier if s.operator == ">="]
    assert Version(lower) in req.specifier and Version("2.13.0") in req.specifier
    text = CI.read_text()
    (line,) = [ln for ln in text.splitlines() if ln.startswith('floor="$(')]
    out = subprocess.run(["bash", "-c", line + '\necho "$floor"'], cwd=root, capture_output=True, text=True, check=True)
    assert Version(out.stdout.strip()) == Version(lower)
    # the step installs that torch with the project in one pip call, checks it, and runs the default tier
    step = text[text.index(line) :]
    assert '. "$floor_dir/venv/bin/activate"' in step
    assert 'python -m pip install --quiet "torch==$floor" -e ".[test,docs]"' in step
    assert "python -m pytest -q" in step and "|| true" not in step
