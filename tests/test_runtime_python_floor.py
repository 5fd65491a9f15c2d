"""vo_runtime stays within Python 3.8 (JetPack 5's Python; pyproject's requires-python), checked statically.

This machine has only Python 3.11, so the check reads the sources: the 3.8 grammar, annotations that are never
evaluated (PEP 585/604 forms such as ``list[int]`` or ``X | None`` fail at import on 3.8 otherwise), and no
standard-library names that arrived later.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FLOOR = (3, 8)
SOURCES = sorted((REPO / "vo_runtime").rglob("*.py"))
# Methods that do not exist on 3.8, and module members / modules that arrived later (with the version).
LATER_METHODS = {"removeprefix": "3.9", "removesuffix": "3.9", "is_relative_to": "3.9", "bit_count": "3.10"}
LATER_MEMBERS = {("functools", "cache"): "3.9", ("math", "lcm"): "3.9", ("itertools", "pairwise"): "3.10",
                 ("typing", "TypeAlias"): "3.10", ("typing", "ParamSpec"): "3.10", ("typing", "Self"): "3.11",
                 ("asyncio", "to_thread"): "3.9", ("datetime", "UTC"): "3.11"}
LATER_MODULES = {"tomllib": "3.11", "zoneinfo": "3.9", "graphlib": "3.9"}
LATER_KEYWORDS = {("dataclass", "slots"): "3.10", ("dataclass", "kw_only"): "3.10", ("zip", "strict"): "3.10"}
BUILTIN_GENERICS = {"list", "dict", "tuple", "set", "frozenset", "type"}


def test_requires_python_states_the_floor() -> None:
    text = (REPO / "pyproject.toml").read_text()
    assert re.search(r'requires-python = ">=3\.8"', text)


def _annotation_nodes(tree: ast.AST) -> set[int]:
    """ids of every node inside an annotation (never evaluated under ``from __future__ import annotations``)."""
    inside: set[int] = set()
    for node in ast.walk(tree):
        annotations = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            arguments = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
            arguments += [a for a in (node.args.vararg, node.args.kwarg) if a is not None]
            annotations = [a.annotation for a in arguments if a.annotation is not None]
            annotations += [node.returns] if node.returns is not None else []
        elif isinstance(node, ast.AnnAssign):
            annotations = [node.annotation]
        for annotation in annotations:
            inside.update(id(n) for n in ast.walk(annotation))
    return inside


def _name_of(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def problems_in(source: str) -> list[str]:
    """What in ``source`` would not run on Python 3.8."""
    try:
        tree = ast.parse(source, feature_version=FLOOR)
    except SyntaxError as exc:
        return [f"line {exc.lineno}: not 3.8 grammar ({exc.msg})"]
    found = []
    deferred = any(isinstance(n, ast.ImportFrom) and n.module == "__future__" and any(a.name == "annotations" for a in n.names)
                   for n in tree.body)
    annotated = _annotation_nodes(tree)
    if annotated and not deferred:
        found.append("annotations without `from __future__ import annotations`")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            version = LATER_METHODS.get(node.attr) or LATER_MEMBERS.get((_name_of(node.value), node.attr))
            if version:
                found.append(f"line {node.lineno}: .{node.attr} needs Python {version}")
        if isinstance(node, ast.Import):
            for alias in node.names:
                version = LATER_MODULES.get(alias.name.split(".")[0])
                if version:
                    found.append(f"line {node.lineno}: {alias.name} needs Python {version}")
        if isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:
                version = LATER_MODULES.get(node.module.split(".")[0]) or LATER_MEMBERS.get((node.module, alias.name))
                if version:
                    found.append(f"line {node.lineno}: {node.module}.{alias.name} needs Python {version}")
        if isinstance(node, ast.Call):
            for keyword in node.keywords:
                version = LATER_KEYWORDS.get((_name_of(node.func), keyword.arg))
                if version:
                    found.append(f"line {node.lineno}: {_name_of(node.func)}({keyword.arg}=) needs Python {version}")
        if id(node) in annotated:
            continue
        if isinstance(node, ast.Subscript) and _name_of(node.value) in BUILTIN_GENERICS and isinstance(node.value, ast.Name):
            found.append(f"line {node.lineno}: {node.value.id}[...] evaluated at run time needs Python 3.9")
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr) and any(
                isinstance(side, ast.Constant) and side.value is None for side in (node.left, node.right)):
            found.append(f"line {node.lineno}: `X | None` evaluated at run time needs Python 3.10")
    return found


@pytest.mark.parametrize("path", SOURCES, ids=[str(p.relative_to(REPO)) for p in SOURCES])
def test_runtime_source_runs_on_the_floor(path: Path) -> None:
    assert problems_in(path.read_text()) == []


@pytest.mark.parametrize("snippet, problem", [
    ("match x:\n    case 1:\n        pass\n", "not 3.8 grammar"),
    ("def f(a: list[int]) -> None:\n    pass\n", "annotations without"),
    ("from __future__ import annotations\nAlias = dict[str, int]\n", "dict[...] evaluated"),
    ("from __future__ import annotations\nok = isinstance(1, int | None)\n", "`X | None`"),
    ("name = 'a_b'.removeprefix('a_')\n", ".removeprefix needs Python 3.9"),
    ("from functools import cache\n", "functools.cache needs Python 3.9"),
    ("import tomllib\n", "tomllib needs Python 3.11"),
    ("import math\nn = math.lcm(2, 3)\n", ".lcm needs Python 3.9"),
    ("pairs = list(zip([1], [2], strict=True))\n", "zip(strict=)"),
])
def test_the_floor_check_catches_what_3_8_cannot_run(snippet: str, problem: str) -> None:
    assert any(problem in line for line in problems_in(snippet)), problems_in(snippet)
    fine = "from __future__ import annotations\n\ndef f(a: list[int] | None) -> dict[str, int]:\n    return {}\n"
    assert problems_in(fine) == []
