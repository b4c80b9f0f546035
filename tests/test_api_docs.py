"""The public surface (`keo_service.__all__`) stays documented as its reference promises
(ARCHITECTURE.md, "The public surface"): every class, function and public method has a
docstring with the Google-style sections that apply: `Args:` when it takes parameters (each
one named), then `Returns:` (or `Yields:`) when it gives something back, `Raises:` when its
own body raises, and for a class whose instances are data (a msgspec Struct, a dataclass) each
field named under `Attributes:` or documented by a docstring under the field. A method without
parameters may say what it gives in its summary, as a property does.

A name added to `__all__` without these fails here, so the reference cannot fall behind."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import textwrap
from collections.abc import Callable, Iterator
from typing import Any

import msgspec
import pytest

import keo_service

SKIP_PARAMS = {"self", "cls"}


def _section(doc: str, name: str) -> str | None:
    """The text of one Google-style section (`Args:` ...), up to the next section or the end."""
    match = re.search(rf"^(\s*){name}:\s*$", doc, flags=re.MULTILINE)
    if match is None:
        return None
    indent = len(match.group(1))
    lines = []
    for line in doc[match.end() :].splitlines()[1:]:
        if line.strip() and len(line) - len(line.lstrip()) <= indent:
            break
        lines.append(line)
    return "\n".join(lines)


def _names_in(section: str) -> set[str]:
    """The entries of a section: `name:` or `**name:` at the start of a line."""
    return set(re.findall(r"^\s*\**(\w+)(?:\s*\([^)]*\))?:", section, flags=re.MULTILINE))


def _parameters(func: Callable[..., Any]) -> list[str]:
    return [p for p in inspect.signature(func).parameters if p not in SKIP_PARAMS]


def _gives_back(func: Callable[..., Any]) -> bool:
    ret = inspect.signature(func).return_annotation
    return ret not in (None, "None", inspect.Signature.empty)


def _raises_itself(func: Callable[..., Any]) -> bool:
    """Whether the function's own body (not a nested function's) has a `raise` with an
    exception; a bare `raise` passes on what came in."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    body = tree.body[0]
    assert isinstance(body, ast.FunctionDef | ast.AsyncFunctionDef)
    todo: list[ast.AST] = list(body.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda | ast.ClassDef):
            continue  # its raises are its own
        if isinstance(node, ast.Raise) and node.exc is not None:
            return True
        todo.extend(ast.iter_child_nodes(node))
    return False


def _function_problems(where: str, func: Callable[..., Any]) -> list[str]:
    doc = inspect.cleandoc(func.__doc__ or "")
    if not doc:
        return [f"{where}: no docstring"]
    problems = []
    params = _parameters(func)
    if params:
        args = _section(doc, "Args")
        if args is None:
            problems.append(f"{where}: takes {params} but has no Args: section")
        else:
            missing = [p.lstrip("*") for p in params if p.lstrip("*") not in _names_in(args)]
            if missing:
                problems.append(f"{where}: Args: does not name {missing}")
    generator = inspect.isgeneratorfunction(func) or inspect.isasyncgenfunction(func)
    documented = _section(doc, "Returns") is not None or (
        generator and _section(doc, "Yields") is not None
    )
    if params and _gives_back(func) and not documented:
        problems.append(f"{where}: returns a value but has no Returns: section")
    if _raises_itself(func) and _section(doc, "Raises") is None:
        problems.append(f"{where}: raises but has no Raises: section")
    return problems


def _attribute_docstrings(cls: type) -> set[str]:
    """Fields documented by a string right under them (PEP 257's attribute docstrings)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0]
    assert isinstance(body, ast.ClassDef)
    out = set()
    for stmt, after in zip(body.body, body.body[1:], strict=False):
        if (
            isinstance(stmt, ast.AnnAssign)
            and isinstance(stmt.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            out.add(stmt.target.id)
    return out


def _fields(cls: type) -> list[str] | None:
    """The fields of a data class (msgspec Struct or dataclass), None for other classes."""
    if issubclass(cls, msgspec.Struct):
        return [f for f in cls.__struct_fields__ if f != "type"]
    if dataclasses.is_dataclass(cls):
        return [f.name for f in dataclasses.fields(cls)]
    return None


def _documented_fields(cls: type) -> set[str]:
    doc = inspect.cleandoc(cls.__doc__ or "")
    names = _attribute_docstrings(cls)
    for section in ("Attributes", "Args"):
        text = _section(doc, section)
        if text is not None:
            names |= _names_in(text)
    return names


def _constructor_problems(name: str, cls: type, doc: str) -> list[str]:
    """A class with a constructor of keo's own names its parameters under `Args:` (or, for a
    record, `Attributes:`)."""
    init = next((vars(k)["__init__"] for k in cls.__mro__ if "__init__" in vars(k)), None)
    if init is None or not getattr(init, "__module__", "").startswith("keo_service"):
        return []
    params = [p.lstrip("*") for p in _parameters(init)]
    if not params:
        return []
    sections = [_section(doc, s) for s in ("Args", "Attributes")]
    if sections == [None, None]:
        return [f"{name}: its constructor takes {params} but it has no Args:"]
    named = set().union(*(_names_in(s) for s in sections if s is not None))
    missing = [p for p in params if p not in named]
    return [f"{name}: Args: does not name {missing}"] if missing else []


def _own_members(cls: type) -> Iterator[tuple[str, Any]]:
    """The public methods and properties keo defines on the class or its keo bases."""
    for name in sorted(dir(cls)):
        if name.startswith("_"):
            continue
        owner = next(k for k in cls.__mro__ if name in vars(k))
        if not owner.__module__.startswith("keo_service"):
            continue
        yield name, vars(owner)[name]


def _class_problems(name: str, cls: type) -> list[str]:
    doc = inspect.cleandoc(cls.__doc__ or "")
    if not doc:
        return [f"{name}: no docstring"]
    problems = []
    fields = _fields(cls)
    if fields is not None:
        missing = [f for f in fields if f not in _documented_fields(cls)]
        if missing:
            problems.append(f"{name}: fields not documented (Attributes: or below each): {missing}")
    else:
        problems += _constructor_problems(name, cls, doc)
    for member, value in _own_members(cls):
        where = f"{name}.{member}"
        if isinstance(value, property):
            if not (value.fget and value.fget.__doc__):
                problems.append(f"{where}: no docstring")
            continue
        func = value.__func__ if isinstance(value, classmethod | staticmethod) else value
        if callable(func):
            problems += _function_problems(where, func)
    return problems


@pytest.mark.parametrize("name", keo_service.__all__)
def test_public_name_is_documented(name):
    obj = getattr(keo_service, name)
    check = _class_problems if inspect.isclass(obj) else _function_problems
    problems = check(name, obj)
    assert not problems, "\n".join(problems)


def test_the_check_can_fail():
    """An undocumented function and a data class with a field nobody describes are caught."""

    def bare(path: str) -> int:
        """Reads a thing."""
        if not path:
            raise ValueError(path)
        return 1

    @dataclasses.dataclass
    class Half:
        """Data.

        Attributes:
            a: metres.
        """

        a: float
        b: float

    problems = _function_problems("bare", bare)
    assert any("Args:" in p for p in problems)
    assert any("Returns:" in p for p in problems)
    assert any("Raises:" in p for p in problems)
    assert _documented_fields(Half) == {"a"}
