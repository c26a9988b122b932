"""Sphinx markup in docstrings, turned into what the mkdocs site renders (a griffe extension).

The docstrings use Sphinx's cross-reference roles (``:class:`~torchcage.Cage```, ``:meth:``,
``:func:``, ``:attr:``, ``:mod:``, ``:data:``, ``:exc:``, ``:obj:``, ``:const:``, with or without
the ``py:`` domain) and its maths (``:math:`...``` and ``.. math::`` blocks); Markdown shows them
as literal text. Before mkdocstrings parses a docstring this extension rewrites

- a role into a code span wrapped in an optional autorefs cross-reference (a link to the object's
  anchor on the API page when the object is documented there, plain code otherwise), the target
  resolved in the docstring owner's scope as Python would (``with_vertices`` in a method of
  ``Cage`` is ``Cage.with_vertices``); Sphinx's forms are kept: ``~`` shows the last component,
  ``!`` suppresses the link, ``title <target>`` gives the text, functions and methods get ``()``;
- ``:math:`x``` into ``\\(x\\)`` and a ``.. math::`` block into ``$$ ... $$`` blocks (one per
  equation), which pymdownx.arithmatex turns into the elements KaTeX typesets.

The source files are untouched: new docstrings are converted too. ``mkdocs.yml`` loads it as an
extension of the mkdocstrings Python handler; ``docs/hooks/pages.py`` fails a strict build if any
role or raw TeX still reaches a page.
"""

from __future__ import annotations

import html
import re
from collections.abc import Callable

from griffe import Extension, GriffeLoader, Module, Object

ROLES = ("func", "meth", "class", "attr", "mod", "data", "exc", "obj", "const")
"""The Python-domain cross-reference roles converted (``:py:class:`` as well as ``:class:``)."""

_ROLE = re.compile(r":(?:py:)?(?P<role>" + "|".join(ROLES) + r"):`(?P<body>[^`]+)`")
_MATH_ROLE = re.compile(r":math:`(?P<tex>[^`]+)`")
_MATH_DIRECTIVE = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*(?P<rest>.*)$")
_EXPLICIT_TITLE = re.compile(r"^(?P<title>.+?)\s*<(?P<target>[^<>]+)>$")

Resolver = Callable[[str], "str | None"]
"""Maps a role's target (as written, ``~``/``!`` stripped) to a full dotted path, or ``None``."""


def convert_roles(text: str, resolve: Resolver) -> str:
    """Replace the Sphinx cross-reference roles in ``text`` by autorefs code spans.

    Args:
        text: Docstring text.
        resolve: Maps a target such as ``Cage.with_vertices`` or ``.checks`` to the full dotted
            path of the object (``torchcage.cage.Cage.with_vertices``), or ``None`` if unknown.

    Returns:
        The text with every role replaced: ``<autoref identifier="path" optional><code>title</code></autoref>``
        (autorefs links it when ``path`` is documented on the site, else shows the code) or a
        bare ``<code>title</code>`` for ``!target`` and unresolvable targets.
    """

    def replace(match: re.Match[str]) -> str:
        role, body = match["role"], match["body"].strip()
        explicit = _EXPLICIT_TITLE.match(body)
        if explicit:
            title, target = explicit["title"], explicit["target"].strip()
        else:
            title, target = None, body
        link = not target.startswith("!")
        target = target.lstrip("!")
        short = target.startswith("~")
        target = target.lstrip("~")
        if title is None:
            title = target.lstrip(".")
            if short:
                title = title.rsplit(".", 1)[-1]
            if role in ("func", "meth"):
                title += "()"
        code = f"<code>{html.escape(title, quote=False)}</code>"
        path = resolve(target) if link else None
        if path is None:
            return code
        return f'<autoref identifier="{html.escape(path)}" optional>{code}</autoref>'

    return _ROLE.sub(replace, text)


def convert_math(text: str) -> str:
    """Replace ``:math:`x``` by ``\\(x\\)`` and ``.. math::`` blocks by ``$$`` blocks.

    A directive's content is the following lines indented deeper than it (and any text on its
    own line); blank lines separate equations, each becoming one ``$$`` block at the directive's
    indentation with blank lines around it (arithmatex reads a block only at a block start).
    Option lines (``:label:``, ``:nowrap:``) are dropped.
    """
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        match = _MATH_DIRECTIVE.match(lines[i])
        if match is None:
            out.append(lines[i])
            i += 1
            continue
        indent = match["indent"]
        body: list[str] = [match["rest"]] if match["rest"].strip() else []
        i += 1
        while i < len(lines) and (not lines[i].strip() or _width(lines[i]) > len(indent)):
            body.append(lines[i])
            i += 1
        while body and not body[-1].strip():  # trailing blank lines belong to the text after
            body.pop()
            i -= 1
        equations: list[list[str]] = [[]]
        for line in body:
            stripped = line.strip()
            if not stripped:
                if equations[-1]:
                    equations.append([])
            elif not (re.match(r"^:\w+:", stripped) and not equations[-1] and len(equations) == 1):
                equations[-1].append(stripped)
        if out and out[-1].strip():
            out.append("")
        for k, equation in enumerate(e for e in equations if e):
            if k:
                out.append("")
            out.extend([indent + "$$", *(indent + line for line in equation), indent + "$$"])
        if i < len(lines) and lines[i].strip():
            out.append("")
    return _MATH_ROLE.sub(lambda m: r"\(" + m["tex"] + r"\)", "\n".join(out))


def _width(line: str) -> int:
    return len(line) - len(line.lstrip())


def scope_resolver(obj: Object, loader: GriffeLoader | None = None) -> Resolver:
    """A resolver for the roles of ``obj``'s docstring, following Python's scoping.

    ``a.b.c`` is tried as an absolute path first; a leading dot (``.checks``) is relative to the
    package of ``obj``'s module; otherwise the first component is looked up in ``obj``'s scope
    and its parents' (members and imports), the rest appended. ``None`` when nothing matches.
    """

    def exists(path: str) -> bool:
        if loader is None:
            return False
        try:
            loader.modules_collection[path]
        except Exception:
            return False
        return True

    def resolve(target: str) -> str | None:
        if target.startswith("."):
            module = obj if obj.is_module else obj.module
            package = module.path if module.is_package else module.path.rsplit(".", 1)[0]
            path = package + target
            return path if exists(path) else None
        if "." in target and exists(target):
            return target
        first, _, rest = target.partition(".")
        try:
            base = obj.resolve(first)
        except Exception:
            return None
        return f"{base}.{rest}" if rest else base

    return resolve


class SphinxMarkup(Extension):
    """Converts the roles and maths of every docstring once griffe has loaded the package."""

    def on_object(self, *, obj: Object, loader: GriffeLoader, **kwargs: object) -> None:
        convert_docstring(obj, loader)

    def on_package(self, *, pkg: Module, loader: GriffeLoader, **kwargs: object) -> None:
        convert_docstring(pkg, loader)  # (griffe's on_object covers the package's members only)


def convert_docstring(obj: Object, loader: GriffeLoader | None = None) -> None:
    """Convert ``obj``'s docstring in place (roles resolved in its scope, then the maths)."""
    docstring = obj.docstring
    if docstring is None or (":" not in docstring.value and ".. math::" not in docstring.value):
        return
    value = convert_math(convert_roles(docstring.value, scope_resolver(obj, loader)))
    if value != docstring.value:
        docstring.value = value
        docstring.__dict__.pop("parsed", None)  # a cached parse of the old text
