"""The documentation site as a reader sees it: the maths typeset, no Sphinx roles.

The site is built once (``mkdocs build --strict`` into a temporary folder, as CI builds it),
served from 127.0.0.1 and opened in headless Chromium with every other host unresolvable (the
site must work offline: KaTeX and its fonts are vendored). On every page with maths, after the
page's scripts ran: each maths element was typeset by KaTeX (no ``.katex-error``), its fonts
loaded, and the visible text (rendered maths, code and scripts aside) holds no TeX: no ``$$``,
``\\[``, ``\\(``, ``.. math::`` or ``\\command``. No page shows a Sphinx role (``:class:``,
``:meth:``, ...) and the API page's cross-references lead to anchors on it.

Without the docs tools (``pip install -e '.[docs]'``) or Chromium the browser tests skip, with
the reason; the conversion of the docstrings' markup is also tested alone (griffe only).
``TORCHCAGE_DOCS_SCREENSHOTS=folder`` keeps a screenshot of each page checked.
"""

from __future__ import annotations

import functools
import http.server
import importlib.util
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from browser import Browser, BrowserError, find_chromium
from support import REPO

DOCS = REPO / "docs"
HOOKS = DOCS / "hooks"
CHROMIUM = find_chromium()
_SOURCE_MATH = re.compile(r"\$\$|\\\[|\\\(|\.\. math::|:math:`")
ROLE_TEXT = re.compile(r":(?:py:)?(?:func|meth|class|attr|mod|data|exc|obj|const|math):")
# TeX a reader should never see: delimiters, a directive, a control word (\frac, \nabla, ...)
RAW_TEX = re.compile(r"\$\$|\\[\[\]()]|\.\. math::|\\[A-Za-z]{2,}")


def _load(name: str):
    """A module of docs/hooks (they import griffe: skip without the docs tools)."""
    pytest.importorskip("griffe", reason="the docs tools are needed (pip install -e '.[docs]')")
    spec = importlib.util.spec_from_file_location(f"torchcage_docs_{name}", HOOKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def math_pages() -> list[str]:
    """The pages whose Markdown has maths, and the API page (the docstrings' maths and roles)."""
    pages = {p.name for p in DOCS.glob("*.md") if _SOURCE_MATH.search(p.read_text())}
    return sorted(pages | {"api.md"})


def url_of(page: str) -> str:
    return "" if page == "index.md" else page[: -len(".md")] + "/"


# ---------------------------------------------------------------------------------------------
# the conversion alone (griffe, no mkdocs, no browser)


def test_roles_become_code_linked_where_resolved():
    roles = _load("sphinx_roles")
    known = {"Cage": "torchcage.cage.Cage", "with_vertices": "torchcage.cage.Cage.with_vertices"}

    def resolve(target: str) -> str | None:
        first, _, rest = target.partition(".")
        if target.startswith("torchcage."):
            return target
        return known.get(first) and ".".join(filter(None, [known[first], rest]))

    text = (
        "A :class:`~torchcage.Cage`, :py:class:`Cage`, :meth:`with_vertices`, :func:`!raw`, "
        ":attr:`the vertices <Cage.vertices>`, :mod:`torch.nn` and ``:class:`literal```."
    )
    out = roles.convert_roles(text, resolve)
    assert '<autoref identifier="torchcage.Cage" optional><code>Cage</code></autoref>' in out
    assert '<autoref identifier="torchcage.cage.Cage" optional><code>Cage</code></autoref>' in out
    assert '<autoref identifier="torchcage.cage.Cage.with_vertices" optional><code>with_vertices()</code>' in out
    assert ", <code>raw()</code>," in out  # "!": never a link
    assert '<autoref identifier="torchcage.cage.Cage.vertices" optional><code>the vertices</code>' in out
    assert "<code>torch.nn</code> and" in out and "torch.nn" not in out.split("<code>torch.nn</code>")[0]
    assert not ROLE_TEXT.search(out.replace("``:class:`literal```", ""))


def test_math_markup_becomes_arithmatex_input():
    roles = _load("sphinx_roles")
    text = "Energy :math:`\\int |\\nabla w|^2` is\n\n    .. math::\n        a = b,\n\n        c = d\n    after\ntail"
    out = roles.convert_math(text)
    assert "\\(\\int |\\nabla w|^2\\)" in out and ":math:" not in out and ".. math::" not in out
    # one $$ block per equation, at the directive's indentation, blank lines around
    assert "\n\n    $$\n    a = b,\n    $$\n\n    $$\n    c = d\n    $$\n\n    after\ntail" in out
    assert roles.convert_math("x\n.. math:: e = mc^2\n") == "x\n\n$$\ne = mc^2\n$$\n"


def test_griffe_extension_resolves_in_the_docstring_scope(tmp_path):
    griffe = pytest.importorskip("griffe", reason="the docs tools are needed (pip install -e '.[docs]')")
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(
        '"""Use :class:`~pkg.core.Thing` or :func:`.core.make`."""\nfrom .core import Thing\n'
    )
    (pkg / "core.py").write_text(
        "class Thing:\n"
        '    """A thing; see :meth:`grow` and :class:`Thing`, not :class:`Missing`."""\n'
        "    def grow(self):\n"
        '        """Grow (:attr:`size`), as :func:`make` does.\n\n        .. math::\n            s = 2 s\n        """\n'
        "    size = 1\n\n"
        "def make():\n"
        '    """Make a :class:`Thing`."""\n'
    )
    loader = griffe.GriffeLoader(
        search_paths=[str(tmp_path)], extensions=griffe.load_extensions(str(HOOKS / "sphinx_roles.py"))
    )
    root = loader.load("pkg")
    loader.resolve_aliases()
    doc = {p: root[p].docstring.value for p in ("core.Thing", "core.Thing.grow", "core.make")}
    assert 'identifier="pkg.core.Thing.grow" optional><code>grow()</code>' in doc["core.Thing"]
    assert 'identifier="pkg.core.Thing" optional><code>Thing</code>' in doc["core.Thing"]
    assert "not <code>Missing</code>" in doc["core.Thing"]
    assert 'identifier="pkg.core.Thing.size"' in doc["core.Thing.grow"]
    assert 'identifier="pkg.core.make" optional><code>make()</code>' in doc["core.Thing.grow"]
    assert "$$\ns = 2 s\n$$" in doc["core.Thing.grow"]
    assert 'identifier="pkg.core.Thing" optional' in doc["core.make"]
    assert 'identifier="pkg.core.make"' in root.docstring.value and ">core.make()<" in root.docstring.value
    for text in [root.docstring.value, *doc.values()]:
        assert not ROLE_TEXT.search(text) and ".. math::" not in text


def test_the_hook_converts_pages_and_warns_about_leftovers(caplog):
    pages = _load("pages")
    page = SimpleNamespace(file=SimpleNamespace(src_uri="x.md"))
    markdown = "See :meth:`~torchcage.Cage.with_vertices`.\n\n```rst\n:class:`Kept` .. math::\n```\n"
    out = pages.on_page_markdown(markdown, page, None, None)
    assert '<autoref identifier="torchcage.Cage.with_vertices" optional><code>with_vertices()</code>' in out
    assert out.endswith("```rst\n:class:`Kept` .. math::\n```\n")  # fenced code untouched

    with_katex = SimpleNamespace(extra_javascript=["vendor/katex/katex.min.js"])
    clean = [
        '<p>a <code>\\(x\\) $$</code></p><div class="arithmatex">\\[ \\frac{1}{2} \\]</div>',
        '<pre><code>:class:`X` \\[</code></pre><p>text <span class="arithmatex">\\(a\\)</span></p>',
    ]
    for html in clean:
        caplog.clear()
        assert pages.on_page_content(html, page, with_katex, None) == html
        assert not caplog.records, caplog.text
    leftovers = {
        '<div class="arithmatex">\\[ x \\]</div>': "no KaTeX",  # (with no script loaded)
        "<p>see :class:<code>Cage</code></p>": "Sphinx role",
        "<p>energy $$ e = 1 $$</p>": "raw TeX",
        "<p>\\( x \\)</p>": "raw TeX",
        "<p>.. math::\n    x</p>": "raw TeX",
    }
    for html, message in leftovers.items():
        caplog.clear()
        config = SimpleNamespace(extra_javascript=[]) if message == "no KaTeX" else with_katex
        pages.on_page_content(html, page, config, None)
        assert [r for r in caplog.records if r.levelname == "WARNING" and message in r.getMessage()], html


def test_the_site_loads_the_vendored_katex():
    config = (REPO / "mkdocs.yml").read_text()
    assets = re.findall(r"^\s+- (\S+\.(?:js|css))$", config, re.M)
    assert "vendor/katex/katex.min.js" in assets and "vendor/katex/katex.min.css" in assets
    for asset in assets:
        assert (DOCS / asset).is_file(), asset
    assert "MIT License" in (DOCS / "vendor/katex/LICENSE").read_text()
    css = (DOCS / "vendor/katex/katex.min.css").read_text()
    fonts = re.findall(r"url\((fonts/[^)]+)\)", css)
    assert fonts and all((DOCS / "vendor/katex" / f).is_file() for f in fonts)
    assert not re.search(r"https?://", css)


# ---------------------------------------------------------------------------------------------
# the built site in Chromium


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    pytest.importorskip("mkdocs", reason="the docs tools are needed (pip install -e '.[docs]')")
    pytest.importorskip("mkdocstrings", reason="the docs tools are needed (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    build = [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(out)]
    done = subprocess.run(build, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{done.stdout}\n{done.stderr}"
    return out


@pytest.fixture(scope="module")
def served(site):
    handler = functools.partial(_QuietHandler, directory=str(site))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/"
    httpd.shutdown()
    httpd.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def browser():
    if CHROMIUM is None:
        pytest.skip("no Chromium on PATH (apt-get install chromium)")
    pytest.importorskip(
        "websocket", reason="websocket-client is needed to drive the browser (pip install -e '.[test]')"
    )
    try:  # offline: no host but the site's resolves
        b = Browser(CHROMIUM, extra_args=("--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",))
    except BrowserError as err:  # pragma: no cover - a broken install
        pytest.skip(f"chromium does not start here: {err}")
    with b:
        yield b


# what the page shows once its scripts ran: the maths elements and KaTeX's output, the text with
# the typeset maths, code and scripts hidden, the internal links
READ_PAGE = r"""
(async () => {
  const typeset = () => [...document.querySelectorAll('.arithmatex')]
    .every(e => e.querySelector('.katex, .katex-error'));
  for (let k = 0; k < 100 && !typeset(); k++) await new Promise(r => setTimeout(r, 50));
  await document.fonts.ready;
  const article = document.querySelector('article') || document.body;
  const hide = document.createElement('style');
  hide.textContent = '.katex, pre, code, script, style {display: none !important}';
  document.head.appendChild(hide);
  const prose = article.innerText;
  hide.remove();
  const maths = [...document.querySelectorAll('.arithmatex')];
  return {
    maths: maths.length,
    typeset: maths.filter(e => e.querySelector('.katex') && !e.querySelector('.katex-error')).length,
    errors: [...document.querySelectorAll('.katex-error')].map(e => e.title || e.textContent).slice(0, 5),
    fonts: [...document.fonts].filter(f => f.family.includes('KaTeX') && f.status === 'loaded').length,
    prose: prose,
    links: [...article.querySelectorAll('a.autorefs-internal')].map(a => [a.textContent, a.getAttribute('href')]),
  };
})()
"""


def read_page(browser: Browser, url: str) -> dict:
    browser.open(url, "document.readyState === 'complete'", timeout=60)
    return browser.evaluate(READ_PAGE)


def _context(text: str, match: re.Match) -> str:
    return " ".join(text[max(0, match.start() - 80) : match.end() + 80].split())


@pytest.mark.parametrize("page", math_pages())
def test_the_maths_is_typeset_and_no_markup_shows(page, site, served, browser):
    start = time.monotonic()
    shown = read_page(browser, served + url_of(page))
    if folder := os.environ.get("TORCHCAGE_DOCS_SCREENSHOTS"):
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / f"{Path(page).stem}.png").write_bytes(browser.screenshot())
    raw = RAW_TEX.search(shown["prose"])
    assert raw is None, f"{page} shows raw TeX {raw.group()!r}: ...{_context(shown['prose'], raw)}..."
    role = ROLE_TEXT.search(shown["prose"])  # (a role quoted in code would be fine)
    assert role is None, f"{page} shows a Sphinx role as text: ...{_context(shown['prose'], role)}..."
    if page != "api.md" or shown["maths"]:
        assert shown["maths"] > 0, f"{page} has maths in its source but none on the page"
        assert shown["typeset"] == shown["maths"], f"{page}: KaTeX typeset {shown['typeset']} of {shown['maths']}"
        assert not shown["errors"], f"{page}: formulas KaTeX cannot parse: {shown['errors']}"
        assert shown["fonts"] > 0, f"{page}: the KaTeX fonts did not load (offline)"
    assert time.monotonic() - start < 30


def test_the_api_page_links_its_cross_references(site, served, browser):
    shown = read_page(browser, served + url_of("api.md"))
    missing = browser.evaluate(
        "[...document.querySelectorAll('article a.autorefs-internal')].map(a => a.getAttribute('href'))"
        ".filter(h => h.startsWith('#') && !document.getElementById(decodeURIComponent(h.slice(1))))"
    )
    assert not missing, f"links to anchors missing from the API page: {missing[:10]}"
    # the roles of functions and methods show as name() (Sphinx's style), linked to their entries
    calls = [(text, href) for text, href in shown["links"] if text.endswith("()")]
    assert calls, "no :func:/:meth: role became a link"
    for text, href in calls:
        assert href.rsplit(".", 1)[-1].rsplit("#", 1)[-1] == text[:-2].rsplit(".", 1)[-1], (text, href)


def test_every_page_with_maths_is_checked(site):
    with_maths = {
        str(p.parent.relative_to(site)) for p in site.rglob("index.html") if 'class="arithmatex"' in p.read_text()
    }
    checked = {url_of(page).rstrip("/") or "." for page in math_pages()}
    assert with_maths and with_maths <= checked, (
        f"pages with maths the browser test does not open: {with_maths - checked}"
    )
