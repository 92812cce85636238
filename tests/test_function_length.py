"""No function of the product is longer than 80 lines (issue 27): a longer one is split into pieces that each
read as one step. Counted from the ``def`` line to the function's last line, docstring and comments included;
tests are left out."""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("synth", "agv_protocol", "service", "edge_client", "agv_fe")
MAX_FUNCTION_LINES = 80


def long_functions(source: str, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int]]:
    """Every function (methods and nested ones too) of ``source`` longer than ``limit`` lines: (name, lines)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            assert node.end_lineno is not None
            lines = node.end_lineno - node.lineno + 1
            if lines > limit:
                out.append((node.name, lines))
    return out


def _method(name: str, body_lines: int) -> str:
    body = "\n".join(f"        x{i} = {i}" for i in range(body_lines))
    return f"class A:\n    async def {name}(self):\n{body}\n"


def test_the_length_check_finds_a_function_over_the_limit_and_only_that():
    assert long_functions(_method("long", 80)) == [("long", 81)]
    assert long_functions(_method("at_the_limit", 79)) == []
    nested = "def f():\n" + textwrap.indent(_method("inner", 80), "    ")
    assert long_functions(nested) == [("f", 83), ("inner", 81)]


def test_no_function_of_the_product_is_over_80_lines():
    found = [
        f"{path.relative_to(ROOT)}: {name} ({lines} lines)"
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
        for name, lines in long_functions(path.read_text())
    ]
    assert found == []
