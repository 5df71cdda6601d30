"""A griffe extension (mkdocs.yml, mkdocstrings' ``extensions``): the docstrings' reST markup
rendered as Markdown, so that the API reference shows formulas and links.

The library's docstrings are prose in Sphinx's markup, with Google-style ``Args:`` /
``Returns:`` sections in places. Before griffe parses them, this rewrites

* ``:math:`x``` into ``\\(x\\)`` and ``.. math::`` directives into ``$$`` blocks
  (``pymdownx.arithmatex``, rendered by MathJax);
* ``:func:``, ``:class:``, ``:meth:``, ``:attr:``, ``:data:``, ``:mod:``, ``:obj:`` and
  ``:exc:`` roles into optional cross-references (a link where the target is documented,
  plain code where it is not: private helpers, other libraries), their targets resolved
  the way Sphinx does (the object's own class and module first, ``~`` for the last
  component as the title);
* reST definition lists (a term, its definition indented below it) into bullet lists;
* reST simple tables (``=====  =====`` borders) into Markdown tables;
* a paragraph's closing ``::`` (a literal block follows) into ``:``;

and gives an attribute without a docstring the ``#:`` comment above it (Sphinx's
convention, used for the module constants and the ``eqx.Module`` fields).

The source files are not touched: only the text that mkdocstrings renders.
"""

from __future__ import annotations

import re
from html import escape

import griffe

_MATH_ROLE = re.compile(r":math:`([^`]+)`")
_XREF_ROLE = re.compile(r":(?:py:)?(func|class|meth|attr|data|mod|obj|exc|const):`([^`]+)`")
_EXPLICIT_TITLE = re.compile(r"^(.*?)\s*<([^<>]+)>$", re.DOTALL)
_DIRECTIVE = re.compile(r"^(\s*)\.\. math::\s*(.*)$")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


_BORDER = re.compile(r"^\s*=+(\s+=+)+\s*$")


def _simple_tables(text: str) -> str:
    """reST simple tables (a border, the header, a border, the rows, a border; a row whose
    first cell is empty continues the one above) as Markdown tables."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        if not _BORDER.match(lines[i]):
            out.append(lines[i])
            i += 1
            continue
        border = lines[i]
        spans = [m.span() for m in re.finditer(r"=+", border)]
        pad = border[: spans[0][0]]
        # The column boundaries: each column runs to the start of the next one.
        starts = [a for a, _ in spans]
        ends = [*starts[1:], None]
        rows: list[list[str]] = []
        header_rows = None
        i += 1
        while i < len(lines):
            line = lines[i]
            if _BORDER.match(line):
                if header_rows is None:
                    header_rows = len(rows)
                    i += 1
                    continue
                i += 1
                break
            if not line.strip():
                i += 1
                continue
            cells = [
                line[a:b].strip() if b is not None else line[a:].strip()
                for a, b in zip(starts, ends, strict=True)
            ]
            if rows and not cells[0]:
                rows[-1] = [
                    f"{old} {new}".strip() for old, new in zip(rows[-1], cells, strict=True)
                ]
            else:
                rows.append(cells)
            i += 1
        header_rows = header_rows or 0
        header = (
            [" ".join(c).strip() for c in zip(*rows[:header_rows], strict=True)]
            if header_rows
            else [""] * len(starts)
        )
        body = rows[header_rows:]
        if out and out[-1].strip():
            out.append("")
        out.append(pad + "| " + " | ".join(header) + " |")
        out.append(pad + "|" + "---|" * len(starts))
        out.extend(
            pad + "| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in body
        )
        if i < len(lines) and lines[i].strip():
            out.append("")
    return "\n".join(out)


def _math_blocks(text: str) -> str:
    """``.. math::`` directives (content on the directive's line or in the indented block
    after it) as ``$$`` blocks at the directive's indentation, set off by blank lines; blank
    lines inside the block separate equations, as in Sphinx."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = _DIRECTIVE.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        pad, first = m.group(1), m.group(2)
        base = len(pad)
        groups: list[list[str]] = [[first.strip()] if first.strip() else []]
        i += 1
        while i < len(lines):
            line = lines[i]
            if line.strip():
                if _indent(line) <= base:
                    break
                groups[-1].append(line.strip())
                i += 1
                continue
            # Blank lines: the directive goes on only if an indented line follows.
            j = i
            while j < len(lines) and not lines[j].strip():
                j += 1
            if j < len(lines) and _indent(lines[j]) > base:
                if groups[-1]:
                    groups.append([])
                i = j
                continue
            break
        if out and out[-1].strip():
            out.append("")
        for n, body in enumerate(g for g in groups if g):
            joined = "".join(body)
            if ("&" in joined or "\\\\" in joined) and "\\begin" not in joined:
                # Several aligned lines: Sphinx sets them in a split environment.
                body = ["\\begin{aligned}", *body, "\\end{aligned}"]
            if n:
                out.append("")
            out.append(f"{pad}$$")
            out.extend(f"{pad}{b}" for b in body)
            out.append(f"{pad}$$")
        if i < len(lines) and lines[i].strip():
            out.append("")
    return "\n".join(out)


_SECTION = re.compile(
    r"^\s*(Args|Arguments|Parameters|Params|Other Parameters|Keyword Args|Keyword Arguments|"
    r"Returns?|Yields?|Receives?|Raises|Warns|Attributes|Methods|Functions|Classes|Modules|"
    r"Examples?|Notes?|Warnings?|Todo|References|See Also):\s*$"
)
_LIST_ITEM = re.compile(r"^\s*([-*+]|\d+[.)]|\|)\s")


def _definition_lists(text: str) -> str:
    """reST definition lists as Markdown bullets: a term line followed by lines indented
    deeper becomes ``- term`` with its definition as the item's continuation. Google-style
    sections, lists, tables, math and code blocks are left alone."""
    lines = text.split("\n")
    out: list[str] = []
    section_indent: int | None = None
    in_math = False
    for k, line in enumerate(lines):
        stripped = line.strip()
        if stripped == "$$":
            in_math = not in_math
        if in_math or stripped == "$$" or not stripped:
            out.append(line)
            continue
        ind = _indent(line)
        if section_indent is not None:
            if ind > section_indent:
                out.append(line)
                continue
            section_indent = None
        if _SECTION.match(line):
            section_indent = ind
            out.append(line)
            continue
        nxt = lines[k + 1] if k + 1 < len(lines) else ""
        prev = out[-1] if out else ""
        is_term = (
            nxt.strip()
            and _indent(nxt) >= ind + 2
            and (not prev.strip() or _indent(prev) > ind or prev.lstrip().startswith("- "))
            and not _LIST_ITEM.match(line)
        )
        if is_term:
            out.append(" " * ind + "- " + stripped)
        else:
            out.append(line)
    return "\n".join(out)


def _comment_doc(obj: griffe.Object) -> str | None:
    """The ``#:`` comment lines right above an attribute's first line, without the marks."""
    try:
        lines = obj.lines_collection[obj.filepath]
    except (KeyError, TypeError, AttributeError):
        return None
    if not obj.lineno or obj.lineno > len(lines):
        return None
    found: list[str] = []
    i = obj.lineno - 2  # the line above, 0-based
    while i >= 0 and lines[i].lstrip().startswith("#:"):
        found.append(lines[i].lstrip()[2:].strip())
        i -= 1
    return "\n".join(reversed(found)) or None


class RstToMarkdown(griffe.Extension):
    """Rewrite every docstring of the loaded package (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        self._collection = loader.modules_collection
        self._walk(pkg, seen=set())

    if not hasattr(griffe.Extension, "on_package"):  # griffe < 1.14 names the event so
        on_package_loaded = on_package

    def _walk(self, obj: griffe.Object, seen: set[str]) -> None:
        if obj.path in seen:
            return
        seen.add(obj.path)
        if obj.docstring is None and obj.is_attribute:
            comment = _comment_doc(obj)
            if comment:
                obj.docstring = griffe.Docstring(comment, parent=obj, lineno=obj.lineno)
        if obj.docstring is not None:
            obj.docstring.value = self._convert(obj.docstring.value, obj)
        for member in list(obj.members.values()):
            if not member.is_alias:
                self._walk(member, seen)

    def _convert(self, text: str, obj: griffe.Object) -> str:
        text = _simple_tables(text)
        text = _math_blocks(text)
        text = _definition_lists(text)
        text = _MATH_ROLE.sub(lambda m: r"\(" + " ".join(m.group(1).split()) + r"\)", text)
        text = _XREF_ROLE.sub(lambda m: self._xref(m.group(1), m.group(2), obj), text)
        # reST literal blocks: "...::" closing a paragraph; the indented block after it is
        # a code block in Markdown as well.
        text = re.sub(r"(?<=[^\s:])::$", ":", text, flags=re.MULTILINE)
        return text

    def _xref(self, role: str, content: str, obj: griffe.Object) -> str:
        content = " ".join(content.split())
        explicit = _EXPLICIT_TITLE.match(content)
        if explicit:
            title, target = explicit.group(1), explicit.group(2)
        else:
            target = content
            title = None
        short = target.startswith("~")
        target = target.lstrip("~!.")
        if title is None:
            title = target.rsplit(".", 1)[-1] if short else target
        identifier = self._resolve(target, obj)
        if role in ("func", "meth") and not title.endswith(")"):
            title += "()"
        return (
            f'<autoref identifier="{escape(identifier)}" optional>'
            f"<code>{escape(title)}</code></autoref>"
        )

    def _resolve(self, target: str, obj: griffe.Object) -> str:
        """The documented path of ``target`` as seen from ``obj``: ``obj``'s class, its
        module and the modules above it first, then the name as given."""
        scopes = []
        scope = obj
        while scope is not None:
            if scope.is_class or scope.is_module:
                scopes.append(scope.path)
            scope = scope.parent
        for candidate in [f"{s}.{target}" for s in scopes] + [target]:
            found = self._lookup(candidate)
            if found is not None:
                return found
        return target

    def _lookup(self, path: str) -> str | None:
        try:
            found = self._collection.get_member(path)
        except (
            KeyError,
            ValueError,
            AttributeError,
            griffe.AliasResolutionError,
            griffe.CyclicAliasError,
        ):
            return None
        if found.is_alias:
            try:
                return found.final_target.path
            except (griffe.AliasResolutionError, griffe.CyclicAliasError):
                return None
        return found.path
