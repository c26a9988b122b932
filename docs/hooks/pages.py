"""MkDocs hook: Sphinx markup in the pages converted; a page that would show roles or raw TeX warns.

The pages' Markdown gets the conversion the docstrings get (``sphinx_roles.py``, a griffe
extension): ``:class:`~torchcage.Cage``` and the other roles become code spans linked to the API
page where the object is documented there (absolute targets: a page has no Python scope),
``:math:`` and ``.. math::`` become arithmatex maths; fenced code blocks are left alone.
Then any page that would still show markup is a build warning, and
``mkdocs build --strict`` turns these warnings into a failed build, so the problems the docs
once had (maths shown as raw ``\\[ ... \\]`` because no renderer loaded, ``:class:`` and
``:meth:`` roles shown as text on the API page) cannot come back unnoticed:

- a page with maths (arithmatex's ``.arithmatex`` elements) while ``mkdocs.yml`` loads no KaTeX;
- TeX delimiters (``$$``, ``\\[``, ``\\(``), ``.. math::`` or a Sphinx role (``:class:`` ...)
  left in a page's text outside code and outside the maths elements.

The browser test (``tests/test_docs_render.py``) checks what a reader sees after KaTeX ran.
"""

from __future__ import annotations

import importlib.util
import logging
import re
from pathlib import Path
from typing import Any

log = logging.getLogger("mkdocs.hooks.torchcage_docs")

_spec = importlib.util.spec_from_file_location(
    "torchcage_docs_sphinx_roles", Path(__file__).with_name("sphinx_roles.py")
)
assert _spec is not None and _spec.loader is not None
sphinx_roles = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sphinx_roles)

_FENCE = re.compile(r"^([ \t]*)(`{3,}|~{3,}).*?^\1\2[ \t]*$", re.S | re.M)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Convert the Sphinx roles and maths of a page's Markdown (outside fenced code)."""

    def convert(text: str) -> str:
        return sphinx_roles.convert_math(sphinx_roles.convert_roles(text, lambda target: target.lstrip(".")))

    out, end = [], 0
    for fence in _FENCE.finditer(markdown):
        out += [convert(markdown[end : fence.start()]), fence.group()]
        end = fence.end()
    return "".join([*out, convert(markdown[end:])])


_ROLE_TEXT = re.compile(r":(?:py:)?(?:func|meth|class|attr|mod|data|exc|obj|const|math):(?=<code>|`)")
_SKIPPED = re.compile(
    r"<(pre|code|script|style)\b[^>]*>.*?</\1>|<(span|div) class=\"arithmatex\">.*?</\2>", re.S | re.I
)
_BLOCKS = re.compile(r"<(pre|script|style)\b[^>]*>.*?</\1>", re.S | re.I)
_CODE = re.compile(r"<code\b[^>]*>.*?</code>", re.S | re.I)
_RAW_TEX = re.compile(r"\$\$|\\\[|\\\]|\\\(|\\\)|\.\. math::")


def on_page_content(html: str, page: Any, config: Any, files: Any) -> str:
    """Warn about maths without a renderer and about markup left as text (``--strict`` fails)."""
    name = page.file.src_uri
    if 'class="arithmatex"' in html and not any("katex" in str(js).lower() for js in config.extra_javascript):
        log.warning("%s has maths but mkdocs.yml loads no KaTeX (extra_javascript): it would show raw TeX", name)
    outside_code = _CODE.sub("<code></code>", _BLOCKS.sub(" ", html))  # a role shown in code is fine
    roles = _ROLE_TEXT.findall(outside_code)
    if roles:
        log.warning("%s shows %d Sphinx role(s) as text, e.g. %r", name, len(roles), roles[0])
    text = _SKIPPED.sub(" ", html)
    raw = _RAW_TEX.search(text)
    if raw:
        context = re.sub(r"\s+", " ", text[max(0, raw.start() - 60) : raw.end() + 60])
        log.warning("%s shows raw TeX %r outside the maths elements: ...%s...", name, raw.group(), context)
    return html
