"""Every ``python`` code block of the README and the docs runs: the blocks of
one page run in order in one namespace, in a temporary working directory."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest
from support import REPO

PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def blocks(page: Path) -> list[str]:
    return _BLOCK.findall(page.read_text())


@pytest.mark.parametrize("page", [p for p in PAGES if blocks(p)], ids=lambda p: p.name)
def test_code_blocks_run(page: Path, tmp_path, monkeypatch) -> None:
    if page.name == "image.md":
        pytest.importorskip("kornia")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"docs_{page.stem}"}
    for k, code in enumerate(blocks(page)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                exec(compile(code, f"{page.name}[block {k}]", "exec"), namespace)
            except Exception as err:  # the page and block in the failure
                raise AssertionError(f"{page.name}, code block {k} fails: {err!r}\n{code}") from err


def test_every_page_is_checked() -> None:
    assert sum(len(blocks(p)) for p in PAGES) >= 12
