"""What a component takes, read from its source code without importing it.

`parameters("rotlearn.data.KittiOdometryDataModule")` lists a constructor's arguments and their
defaults from the syntax tree (`ast`) of the module that defines it: re-exports (`from x import
Y`) are followed to the definition, and a class whose `__init__` passes `**kwargs` on also takes
its bases' arguments (the first definition of a name wins), as Python passes them. Reading a
component this way takes milliseconds where importing it would load torch and Lightning (5 s on a
2-core machine), so a command line with an unknown key, option or data folder is answered at once
(`rotlearn.config.checks`); the annotations, with their constraints, are read from the imported
objects afterwards. Only rotlearn's code and the libraries its configs name are read; nothing is
executed.
"""

from __future__ import annotations

import ast
import importlib.util
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

__all__ = ["MISSING", "Parameter", "class_attribute", "is_marked", "marked", "parameters"]

MISSING = "???"  # OmegaConf's mark of a value the config must still set: a required argument
MARK = "config_target"  # the decorator of rotlearn's components (`rotlearn.trust.config_target`)


@dataclass(frozen=True)
class Parameter:
    """A constructor argument: `default` is MISSING for a required one, `owner` the dotted name of
    the function (or class) whose signature declares it."""

    name: str
    default: Any
    owner: str


@dataclass(frozen=True)
class _Found:
    name: str  # dotted name of the definition
    node: ast.AST  # ClassDef, FunctionDef, or an assigned expression
    module: str


@cache
def _module_file(module: str) -> Path | None:
    """The source file of `module`, located without importing it (nor its packages)."""
    loaded = sys.modules.get(module)
    if loaded is not None:
        return Path(loaded.__file__) if getattr(loaded, "__file__", None) else None
    top, *rest = module.split(".")
    spec = importlib.util.find_spec(top)
    if spec is None or spec.origin is None and not spec.submodule_search_locations:
        return None
    if not rest:
        return Path(spec.origin) if spec.origin else None
    for base in spec.submodule_search_locations or ():
        path = Path(base, *rest)
        for candidate in (path / "__init__.py", path.with_suffix(".py")):
            if candidate.is_file():
                return candidate
    return None


@cache
def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_bytes(), str(path))


def _statements(body: list[ast.stmt]) -> Iterator[ast.stmt]:
    """Module-level statements, those inside `if` and `try` blocks included."""
    for stmt in body:
        yield stmt
        if isinstance(stmt, ast.If | ast.Try):
            handlers = [s for h in getattr(stmt, "handlers", ()) for s in h.body]
            yield from _statements([*stmt.body, *stmt.orelse, *handlers])


def _source_module(module: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{node.module}" if node.module else package


def _dotted(module: str, expr: ast.expr) -> str | None:
    """The dotted name that `expr` (a name or attribute, as written in `module`) refers to."""
    if isinstance(expr, ast.Attribute):
        base = _dotted(module, expr.value)
        return f"{base}.{expr.attr}" if base else None
    if not isinstance(expr, ast.Name):
        return None
    path = _module_file(module)
    for stmt in _statements(_tree(path).body) if path else ():
        for alias in getattr(stmt, "names", ()) if isinstance(stmt, ast.Import | ast.ImportFrom) else ():
            if (alias.asname or alias.name.split(".")[0]) != expr.id:
                continue
            if isinstance(stmt, ast.Import):
                return alias.name if alias.asname else expr.id
            return f"{_source_module(module, path, stmt)}.{alias.name}"
    return f"{module}.{expr.id}"


@cache
def _find(name: str, depth: int = 0) -> _Found | None:
    """The definition of the dotted `name`: a class, function or assigned value (the last one in
    its module), following `from x import name` to where it is defined."""
    module, _, attr = name.rpartition(".")
    path = _module_file(module) if module and depth < 16 else None
    found = None
    for stmt in _statements(_tree(path).body) if path else ():
        if isinstance(stmt, ast.ClassDef | ast.FunctionDef) and stmt.name == attr:
            found = _Found(name, stmt, module)
        elif isinstance(stmt, ast.Assign | ast.AnnAssign) and stmt.value is not None:
            targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]
            if any(isinstance(t, ast.Name) and t.id == attr for t in targets):
                found = _Found(name, stmt.value, module)
        elif isinstance(stmt, ast.ImportFrom):
            for alias in stmt.names:
                if (alias.asname or alias.name) == attr:
                    source = f"{_source_module(module, path, stmt)}.{alias.name}"
                    found = _find(source, depth + 1) if source != name else None
    return found


def _value(module: str, expr: ast.expr, depth: int = 0) -> Any:
    """A default value: a literal, or a module constant it names (tuples as lists)."""
    try:
        value = ast.literal_eval(expr)
    except ValueError:
        dotted = _dotted(module, expr) if depth < 8 else None
        found = _find(dotted) if dotted else None
        if found is None or not isinstance(found.node, ast.expr):
            raise ValueError(f"{module}: default {ast.unparse(expr)} is not a literal") from None
        return _value(found.module, found.node, depth + 1)
    return list(value) if isinstance(value, tuple) else value


def _bases(found: _Found) -> Iterator[_Found]:
    """A class and its bases, depth first (the order Python's MRO takes for single chains)."""
    yield found
    for base in found.node.bases if isinstance(found.node, ast.ClassDef) else ():
        dotted = _dotted(found.module, base)
        parent = _find(dotted) if dotted else None
        if parent is not None and isinstance(parent.node, ast.ClassDef):
            yield from _bases(parent)


def _signature(found: _Found, function: ast.FunctionDef) -> list[Parameter]:
    args = function.args
    named = [*args.posonlyargs, *args.args]
    defaults = [None] * (len(named) - len(args.defaults)) + list(args.defaults)
    pairs = [*zip(named, defaults, strict=True), *zip(args.kwonlyargs, args.kw_defaults, strict=True)]
    return [
        Parameter(arg.arg, MISSING if default is None else _value(found.module, default), found.name)
        for arg, default in pairs
        if arg.arg not in ("self", "cls")
    ]


@cache
def parameters(target: str, bases: bool = True) -> tuple[tuple[Parameter, ...], bool] | None:
    """The arguments of the function or class `target` (dotted) and whether it still takes other
    keyword arguments (`**kwargs` it does not pass to a base); None where its source is not found.
    `bases`: follow a class's `**kwargs` to its bases (False: its own `__init__` only)."""
    found = _find(target)
    if found is None:
        return None
    if isinstance(found.node, ast.FunctionDef):
        return tuple(_signature(found, found.node)), found.node.args.kwarg is not None
    seen: dict[str, Parameter] = {}
    for cls in _bases(found):
        init = next((s for s in cls.node.body if getattr(s, "name", "") == "__init__"), None)
        if not isinstance(init, ast.FunctionDef):
            continue
        for parameter in _signature(cls, init):
            seen.setdefault(parameter.name, parameter)
        if init.args.kwarg is None or not bases:
            return tuple(seen.values()), init.args.kwarg is not None
    return tuple(seen.values()), True


def class_attribute(target: str, name: str) -> Any:
    """The literal value of a class attribute `name` of `target` or its bases; None if absent."""
    found = _find(target)
    for cls in _bases(found) if found is not None else ():
        for stmt in cls.node.body:
            if isinstance(stmt, ast.Assign) and any(getattr(t, "id", "") == name for t in stmt.targets):
                return _value(cls.module, stmt.value)
    return None


def is_marked(target: str) -> bool:
    """Whether `target` is one of rotlearn's components: decorated with `@config_target`."""
    found = _find(target)
    decorators = getattr(found.node, "decorator_list", ()) if found is not None else ()
    return any(getattr(d, "id", getattr(d, "attr", "")) == MARK for d in decorators)


@cache
def marked(package: str = "rotlearn") -> tuple[str, ...]:
    """The dotted names of every component marked `@config_target` in `package`'s modules."""
    root = _module_file(package)
    found = []
    for path in sorted(root.parent.rglob("*.py")) if root else ():
        if f"@{MARK}" not in path.read_text(encoding="utf-8"):
            continue
        parts = path.relative_to(root.parent).with_suffix("").parts
        module = ".".join((package, *parts)).removesuffix(".__init__")
        found += [
            f"{module}.{stmt.name}"
            for stmt in _tree(path).body
            if isinstance(stmt, ast.ClassDef | ast.FunctionDef) and is_marked(f"{module}.{stmt.name}")
        ]
    return tuple(found)
