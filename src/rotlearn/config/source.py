"""A component's arguments, read from its source without importing it.

`parameters(target)` lists a constructor's arguments and defaults from the syntax tree of the
module that defines it, following re-exports and a class's `**kwargs` to its bases. That takes
milliseconds where importing would load torch and Lightning (seconds), so `rotlearn.config`
answers an unknown key, option or data folder at once, and a value whose annotation names only
`typing` and annotated-types constructs (`rotlearn.config.checks`).
"""

from __future__ import annotations

import ast
import importlib.util
import sys
from functools import cache
from pathlib import Path
from typing import Any, NamedTuple

__all__ = [
    "MISSING",
    "NOT_LITERAL",
    "Parameter",
    "class_attribute",
    "is_marked",
    "marked",
    "parameters",
    "provides",
    "typing_names",
]

MISSING = "???"  # OmegaConf's mark of a value still to set: a required argument
NOT_LITERAL = object()  # a default that is no literal (`device=torch.device("cpu")`)
TYPING = ("typing", "typing_extensions", "collections.abc", "annotated_types", "pathlib")


class Parameter(NamedTuple):
    name: str
    default: Any  # MISSING where required, NOT_LITERAL where its source is no literal
    owner: str  # the dotted class or function whose signature declares it
    annotation: str | None  # its source text (None: unannotated)


@cache
def _module(name: str) -> tuple[ast.Module, bool] | None:
    """The syntax tree of module `name` and whether it is a package, not importing it."""
    path = getattr(sys.modules.get(name), "__file__", None)
    top, *rest = name.split(".")
    spec = importlib.util.find_spec(top) if path is None else None
    for base in (spec.submodule_search_locations or []) if spec else []:
        files = (Path(base, *rest, "__init__.py"), Path(base, *rest).with_suffix(".py"))
        path = path or next((f for f in files if f.is_file()), None)
    return (ast.parse(Path(path).read_bytes()), Path(path).name == "__init__.py") if path else None


def _body(statements: list[ast.stmt]):
    """Module-level statements, those inside `if` and `try` blocks included."""
    for stmt in statements:
        yield stmt
        if isinstance(stmt, ast.If | ast.Try):
            handlers = [s for handler in getattr(stmt, "handlers", []) for s in handler.body]
            yield from _body([*stmt.body, *stmt.orelse, *handlers])


def _source(module: str, package: bool, stmt: ast.ImportFrom) -> str:
    """The module a `from ... import` in `module` reads from."""
    parts = module.split(".")
    parts = parts[: len(parts) - stmt.level + package] if stmt.level else []
    return ".".join([*parts, *([stmt.module] if stmt.module else [])])


@cache
def _find(name: str, depth: int = 0) -> tuple[str, ast.AST] | None:
    """(module, node) defining the dotted `name`: a class, a function or an assigned value (the
    last binding in its module), following `from x import name`."""
    module, _, attr = name.rpartition(".")
    found = _module(module) if module and depth < 16 else None
    tree, package = found or (None, False)
    found = None
    for stmt in _body(tree.body) if tree else ():
        if isinstance(stmt, ast.ClassDef | ast.FunctionDef) and stmt.name == attr:
            found = (module, stmt)
        elif isinstance(stmt, ast.Assign) and any(
            getattr(t, "id", 0) == attr for t in stmt.targets
        ):
            found = (module, stmt.value)
        elif isinstance(stmt, ast.ImportFrom):
            for alias in stmt.names:
                if (alias.asname or alias.name) == attr:
                    found = _find(f"{_source(module, package, stmt)}.{alias.name}", depth + 1)
    return found


@cache
def typing_names(module: str) -> dict[str, Any]:
    """The names module `module` imports from `TYPING`'s modules (cheap to import; type checkers'
    imports included), as those define them: enough to read most annotations of its source."""
    names = {}
    for stmt in _body(_module(module)[0].body) if _module(module) else ():
        pairs = []
        if isinstance(stmt, ast.ImportFrom) and stmt.module in TYPING and not stmt.level:
            pairs = [(a.asname or a.name, stmt.module, a.name) for a in stmt.names]
        elif isinstance(stmt, ast.Import):  # import typing as t, import collections.abc
            for alias in (a for a in stmt.names if a.name in TYPING):
                top = alias.name.split(".")[0]
                pairs.append((alias.asname or top, alias.name if alias.asname else top, None))
        for name, source, attr in pairs:
            try:
                found = importlib.import_module(source)
            except ImportError:
                continue
            names[name] = getattr(found, attr, None) if attr else found
    return {name: value for name, value in names.items() if value is not None}


def _value(module: str, expr: ast.expr) -> Any:
    """A default: a literal (a tuple as a list), the module constant it names, or NOT_LITERAL."""
    try:
        value = ast.literal_eval(expr)
    except ValueError:
        found = _find(f"{module}.{ast.unparse(expr)}")
        return _value(*found) if found and isinstance(found[1], ast.expr) else NOT_LITERAL
    return list(value) if isinstance(value, tuple) else value


def _classes(module: str, node: ast.AST):
    """(module, class) of a class and of its bases (named or imported in its module), depth
    first."""
    if isinstance(node, ast.ClassDef):
        yield module, node
        for base in node.bases:
            yield from _classes(*(_find(f"{module}.{ast.unparse(base)}") or ("", None)))


@cache
def parameters(target: str, bases: bool = True) -> tuple[tuple[Parameter, ...], bool] | None:
    """The arguments of the class or function `target` (dotted) and whether it takes other
    keyword arguments too (`**kwargs` not passed on to a base); None where its source is not
    found. `bases=False`: a class's own `__init__` only."""
    if (found := _find(target)) is None:
        return None
    module, node = found
    inits = [(f"{m}.{c.name}", m, f) for m, c in _classes(module, node) for f in c.body
             if isinstance(f, ast.FunctionDef) and f.name == "__init__"]  # fmt: skip
    if isinstance(node, ast.FunctionDef):
        inits = [(target, module, node)]
    params: dict[str, Parameter] = {}
    for owner, module, function in inits:
        args = function.args
        named = [*args.posonlyargs, *args.args, *args.kwonlyargs]
        defaults = [None] * (len(named) - len(args.kwonlyargs) - len(args.defaults))
        for arg, default in zip(named, [*defaults, *args.defaults, *args.kw_defaults], strict=True):
            value = MISSING if default is None else _value(module, default)
            if arg.arg not in ("self", "cls"):
                text = ast.unparse(arg.annotation) if arg.annotation else None
                params.setdefault(arg.arg, Parameter(arg.arg, value, owner, text))
        if args.kwarg is None or not bases:
            return tuple(params.values()), args.kwarg is not None
    return tuple(params.values()), True


def class_attribute(target: str, name: str) -> Any:
    """The literal value of class attribute `name` of `target` (or of a base); None if absent."""
    for module, cls in _classes(*(_find(target) or ("", None))):
        for stmt in cls.body:
            if isinstance(stmt, ast.Assign) and any(
                getattr(t, "id", 0) == name for t in stmt.targets
            ):
                return _value(module, stmt.value)
    return None


def provides(target: str, protocol: str) -> bool:
    """Whether class `target` (or a base) defines every method of the class `protocol` (both
    dotted); True where either source is not found (the class is then left to its own checks)."""
    found, wanted = _find(target), _find(protocol)
    if found is None or wanted is None or not isinstance(wanted[1], ast.ClassDef):
        return True
    methods = {
        f.name for _, c in _classes(*found) for f in c.body if isinstance(f, ast.FunctionDef)
    }
    return all(f.name in methods for f in wanted[1].body if isinstance(f, ast.FunctionDef))


def is_marked(target: str) -> bool:
    """Whether `target` is a rotlearn component: decorated with `@config_target`."""
    node = (_find(target) or ("", None))[1]
    return any(
        getattr(d, "id", None) == "config_target" for d in getattr(node, "decorator_list", [])
    )


@cache
def marked() -> tuple[str, ...]:
    """Every component marked `@config_target` in rotlearn's modules (dotted, where defined)."""
    root = Path(importlib.util.find_spec("rotlearn").origin).parent
    names = []
    for path in sorted(root.rglob("*.py")):
        if "@config_target" in path.read_text(encoding="utf-8"):
            parts = ("rotlearn", *path.relative_to(root).with_suffix("").parts)
            module = ".".join(parts).removesuffix(".__init__")
            defined = [getattr(s, "name", "") for s in _module(module)[0].body]
            names += [f"{module}.{n}" for n in defined if n and is_marked(f"{module}.{n}")]
    return tuple(names)
