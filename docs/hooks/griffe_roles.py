"""Griffe extension for the API reference: reST docstrings read as Markdown, and a Parameters section everywhere.

The library's docstrings are written for Sphinx (``:class:`~a.b.C```, ``:func:`f```, ``::`` literal
blocks, ``#:`` attribute comments) while mkdocstrings renders Markdown with Google-style sections.
Loaded by mkdocstrings-python (``extensions:`` in mkdocs.yml), this extension changes, lazily, when a
docstring is first parsed for rendering (by then every documented package is loaded):

* **roles become cross-references.** ``:class:`~reach.value_function.ValueFunction``` becomes an
  mkdocs-autorefs reference titled ``ValueFunction``; a relative target (``:func:`load_value_function```,
  ``:meth:`validate```, ``:meth:`ControlAffineSystem.config```) is resolved in the docstring's scope:
  the class, its module, the module's imports and the enclosing packages' exports, as Python would.
  The reference is *optional*: a target that no page renders (a private helper, the standard
  library) shows as plain code instead of failing the strict build. A target that cannot be resolved
  at all is plain code from the start. ``:role:`title <target>``` and ``!`` (no link) are honoured.
* **literal blocks**: a paragraph ending in ``::`` before an indented block ends in ``:`` (``text ::``
  and a lone ``::`` vanish), as Sphinx prints them; the block itself already is a Markdown code block.
* **parameters**: a public function or method (and a class, for its ``__init__``) whose docstring has
  no Parameters/Args section gets one built from its signature: name, annotation and default. One
  that documents some parameters gets the others appended.
* **each object documented once**, where it is defined: a name that a module imports (a package's
  re-exports, ``import x as x``, a compatibility module's names) is not rendered again on that
  module, unless it comes from a private module (then the re-export is its only place).
* **attribute comments**: a module or class attribute without a docstring takes its Sphinx ``#:``
  comment (the lines right above it, or one at the end of its line) as its docstring, so that it is
  rendered and ``:data:`` references to it resolve.

``double backticks`` need nothing: Markdown reads them as inline code.
"""

from __future__ import annotations

import importlib.util
import re
from functools import cached_property
from typing import Any

from griffe import (
    Alias,
    Docstring,
    DocstringParameter,
    DocstringSectionKind,
    DocstringSectionParameters,
    Extension,
    Object,
    ParameterKind,
)

ROLE = re.compile(r"(?<![\w`]):(?:py:)?(?P<role>[a-z]+):`(?P<body>[^`]+)`(?!`)")
TITLED = re.compile(r"^(?P<title>.*?)\s*<(?P<target>[^<>]+)>$", re.S)
PYTHON_ROLES = {"class", "func", "meth", "mod", "attr", "data", "exc", "obj", "const", "type"}
FENCE = re.compile(r"^\s*(```|~~~)")
SELF_NAMES = {"self", "cls"}


def _first_line_code(text: str) -> str:
    text = " ".join(text.split())
    return f"`{text}`" if "`" not in text else f"``{text}``"


def _lookup(obj: Object | Alias, path: str) -> tuple[str, bool | None]:
    """``path``'s canonical form, and whether it exists (``None``: its package is not loaded, so unknown)."""
    collection = obj.modules_collection
    top = path.split(".", 1)[0]
    if top not in collection.members:
        return path, None
    try:
        target = collection[path]
    except KeyError:
        return path, False
    except Exception:  # an alias whose target is not loaded (yet): keep the path, autorefs resolves aliases
        return path, None
    try:
        return target.canonical_path, True
    except Exception:
        return path, True


def _importable(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def _scope(obj: Object | Alias) -> Object | Alias:
    """Where names in ``obj``'s docstring are looked up first: itself for a module or class, else its parent."""
    if obj.is_module or obj.is_class or obj.parent is None:
        return obj
    return obj.parent


def resolve(obj: Object | Alias, target: str) -> str | None:
    """The identifier that ``target`` (a role's target in ``obj``'s docstring) names, or ``None``."""
    target = target.strip().lstrip(".").removesuffix("()")
    if not target or not re.fullmatch(r"[A-Za-z_][\w.]*", target):
        return None
    first, _, rest = target.partition(".")
    scope = _scope(obj)
    base = None
    # 1. the docstring's scope: class members (inherited ones too), the module's names and imports,
    #    then the enclosing packages' (Object.resolve walks up the parents)
    if scope.is_class:
        try:
            member = scope.all_members.get(first)
        except Exception:
            member = None
        if member is not None:
            base = member.target_path if member.is_alias else member.path
    if base is None:
        try:
            base = scope.resolve(first)
        except Exception:
            base = None
    # 2. an absolute path: a loaded or importable top-level package
    if base is None and (first in obj.modules_collection.members or _importable(first)):
        base = first
    if base is not None:
        path = f"{base}.{rest}" if rest else base
        path, exists = _lookup(obj, path)
        if exists is False:
            # the name resolved to something that has no such member: try it as an absolute path
            path, exists = _lookup(obj, target)
        if exists is not False:
            return path
    # 3. out of scope (a method of another class, a stale path): the one loaded object so named
    return _unique(obj, target)


_INDEX: dict[int, tuple[tuple[str, ...], dict[str, list[str]]]] = {}


def _unique(obj: Object | Alias, target: str) -> str | None:
    """The path of the only object (not an alias) of the loaded packages whose path ends with ``target``."""
    collection = obj.modules_collection
    loaded = tuple(sorted(collection.members))
    cached = _INDEX.get(id(collection))
    if cached is None or cached[0] != loaded:
        index: dict[str, list[str]] = {}
        stack = [module for module in collection.members.values() if not module.is_alias]
        while stack:
            current = stack.pop()
            for member in current.members.values():
                if member.is_alias:
                    continue
                index.setdefault(member.name, []).append(member.path)
                if member.is_module or member.is_class:
                    stack.append(member)
        cached = _INDEX[id(collection)] = (loaded, index)
    last = target.rsplit(".", 1)[-1]
    candidates = [path for path in cached[1].get(last, []) if path == target or path.endswith(f".{target}")]
    return candidates[0] if len(candidates) == 1 else None


def _role(obj: Object | Alias, match: re.Match) -> str:
    role, body = match["role"], match["body"]
    titled = TITLED.match(body)
    title, target = (titled["title"], titled["target"]) if titled else (None, body)
    target = target.strip()
    no_link = target.startswith("!")
    target = target.lstrip("!")
    if title is None:
        shown = target.lstrip("~.")
        title = shown.rsplit(".", 1)[-1] if target.startswith("~") else shown
    code = _first_line_code(title)
    if no_link or role not in PYTHON_ROLES:
        return code
    identifier = resolve(obj, target.lstrip("~"))
    if identifier is None:
        return code
    return f'<autoref identifier="{identifier}" optional>{code}</autoref>'


def _literal_blocks(lines: list[str]) -> list[str]:
    """reST ``text::`` before an indented block: ``text:`` (``text ::`` and a lone ``::`` drop the colons)."""
    out = []
    for i, line in enumerate(lines):
        following = lines[i + 1] if i + 1 < len(lines) else ""
        if line.rstrip().endswith("::") and not following.strip():
            stripped = line.rstrip()
            if stripped.strip() == "::":
                continue
            line = stripped[:-3] if stripped.endswith(" ::") else stripped[:-1]
        out.append(line)
    return out


def to_markdown(text: str, obj: Object | Alias) -> str:
    """``text`` (a reST-flavoured docstring of ``obj``) as the Markdown that mkdocstrings expects."""
    lines = text.split("\n")
    out: list[str] = []
    chunk: list[str] = []
    in_fence = False

    def flush() -> None:
        if chunk:
            joined = "\n".join(_literal_blocks(chunk))
            out.append(ROLE.sub(lambda m: _role(obj, m), joined))
            chunk.clear()

    for line in lines:
        if FENCE.match(line):
            if not in_fence:
                flush()
            in_fence = not in_fence
            out.append(line)
        elif in_fence:
            out.append(line)
        else:
            chunk.append(line)
    flush()
    return "\n".join(out)


def _parameter_name(parameter: Any) -> str:
    if parameter.kind is ParameterKind.var_positional:
        return f"*{parameter.name}"
    if parameter.kind is ParameterKind.var_keyword:
        return f"**{parameter.name}"
    return parameter.name


def _signature_parameters(obj: Object | Alias) -> list[Any]:
    """The parameters that a Parameters section of ``obj``'s docstring should list (none: no section)."""
    name = obj.name
    if obj.is_function:
        if (name.startswith("_") and name != "__init__") or "property" in obj.labels or obj.overloads:
            return []
        if name == "__init__" and obj.parent is not None and not obj.parent.is_class:
            return []
        parameters = list(obj.parameters)
    elif obj.is_class:
        if name.startswith("_"):
            return []
        init = obj.members.get("__init__")
        if init is not None and not init.is_alias and init.docstring is not None:
            return []  # the __init__ docstring (merged into the class's) gets the section
        try:
            parameters = list(obj.parameters)
        except Exception:
            return []
    else:
        return []
    in_class = obj.is_class or (obj.parent is not None and obj.parent.is_class)
    if parameters and in_class and parameters[0].name in SELF_NAMES:
        parameters = parameters[1:]
    return parameters


def add_parameters(sections: list[Any], obj: Object | Alias) -> None:
    """Add a Parameters section built from ``obj``'s signature to ``sections``, or complete the one there."""
    parameters = _signature_parameters(obj)
    if not parameters:
        return
    existing = next((s for s in sections if s.kind is DocstringSectionKind.parameters), None)
    documented = {p.name.lstrip("*") for p in existing.value} if existing is not None else set()
    items = [
        DocstringParameter(_parameter_name(p), description="", annotation=p.annotation, value=p.default)
        for p in parameters
        if p.name not in documented
    ]
    if not items:
        return
    if existing is not None:
        existing.value.extend(items)
        return
    index = 0
    leading = (DocstringSectionKind.text, DocstringSectionKind.admonition)
    while index < len(sections) and sections[index].kind in leading:
        index += 1
    sections.insert(index, DocstringSectionParameters(items))


class MarkdownDocstring(Docstring):
    """A docstring turned into Markdown (roles, literal blocks) and completed (parameters) when first parsed."""

    add_parameters = True

    @cached_property
    def parsed(self) -> list[Any]:  # type: ignore[override]
        if self.parent is not None:
            self.value = to_markdown(self.value, self.parent)
        sections = self.parse()
        if self.add_parameters and self.parent is not None:
            add_parameters(sections, self.parent)
        return sections


def _attribute_comment(attr: Object) -> str | None:
    """The Sphinx ``#:`` comment of an attribute: the lines right above it, or one at the end of its line."""
    try:
        lines = attr.lines_collection[attr.filepath]
    except Exception:
        return None
    if not attr.lineno or attr.lineno > len(lines):
        return None
    own = lines[attr.lineno - 1]
    if "#:" in own:
        return own.split("#:", 1)[1].strip() or None
    comment = []
    index = attr.lineno - 2
    while index >= 0 and lines[index].strip().startswith("#:"):
        comment.insert(0, lines[index].strip()[2:].strip())
        index -= 1
    return "\n".join(comment) or None


class ReSTDocstrings(Extension):
    """Make every docstring of a loaded package a :class:`MarkdownDocstring` (see this module's docstring).

    Options (``extensions: [{docs/hooks/griffe_roles.py: {parameters: false}}]``): ``parameters``
    (add Parameters sections), ``attribute_comments`` (read ``#:`` comments), ``hide_imports``
    (render imported names only where they are defined); all default to true.
    """

    def __init__(self, parameters: bool = True, attribute_comments: bool = True, hide_imports: bool = True) -> None:
        super().__init__()
        self.parameters = parameters
        self.attribute_comments = attribute_comments
        self.hide_imports = hide_imports

    def on_package(self, *, pkg: Object, loader: Any, **kwargs: Any) -> None:
        self._convert(pkg, loader, set())

    @staticmethod
    def _hide_import(alias: Alias) -> None:
        """Render an imported name only where it is defined (unless that is a private module)."""
        if alias.inherited or alias.parent is None or not alias.parent.is_module:
            return
        modules = alias.target_path.split(".")[:-1]
        if any(part.startswith("_") for part in modules):
            return
        alias.public = False

    def _convert(self, obj: Object, loader: Any, seen: set[int]) -> None:
        if id(obj) in seen:
            return
        seen.add(id(obj))
        if obj.docstring is None and obj.is_attribute and self.attribute_comments:
            comment = _attribute_comment(obj)
            if comment:
                obj.docstring = Docstring(
                    comment,
                    lineno=obj.lineno,
                    endlineno=obj.lineno,
                    parent=obj,
                    parser=loader.docstring_parser,
                    parser_options=loader.docstring_options,
                )
        if obj.docstring is not None and not isinstance(obj.docstring, MarkdownDocstring):
            obj.docstring.__dict__.pop("parsed", None)
            obj.docstring.__class__ = MarkdownDocstring
            obj.docstring.add_parameters = self.parameters
        for member in list(obj.members.values()):
            if not member.is_alias:
                self._convert(member, loader, seen)
            elif self.hide_imports:
                self._hide_import(member)
